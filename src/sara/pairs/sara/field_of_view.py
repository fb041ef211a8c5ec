"""The images' field of view, where it is known, and the spanning tree it calls for.

With a wide lens a short baseline still fixes the relative pose well, so the tree of the most
overlapping pairs pays; with a long lens (or a turntable, whose focal length the images cannot
tell) it does not, and the paper's weight, which prefers wider baselines, is kept. Nor where the
views move along their optical axes (a drive, a walk straight ahead): there the overlap hardly
falls as the baseline grows, so the most overlapping pairs are the shortest steps, whose points
are triangulated at the smallest angles.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ... import colmap
from ...io.scores import PairScores
from ...scoring import focal
from .. import PairContext

#: a known field of view at least this wide (degrees, across the larger image side) makes the
#: spanning tree of the most overlapping pairs (`score.tree_overlap=auto`; see `resolve_tree_overlap`).
#: Measured: at 31-33 degrees (half-size centre crops of Strecha scenes) and
#: at 58 that tree gains or both pass; at 27 (bm-moldGoldCape) it costs 0.004 AUC@1, at 16 (quarter
#: crops) 0.16-0.40
WIDE_FIELD_OF_VIEW_DEG = 30.0

#: the accepted candidates' median |cosine| between the baseline and the optical axis at or above
#: which the views move along their axes (`axial_motion`): baselines within 26 degrees of it. Measured:
#: kitti-seq1 and the five stand-ins made from it 0.9998-0.9999, the other seven shared scenes and
#: seventeen stand-ins 0.09-0.62 (lab/notes/CAPTURES.md, section 37)
FORWARD_AXIAL_COSINE = 0.9
#: fewest accepted candidates with a pose for `axial_motion` to say anything
MIN_AXIAL_PAIRS = 5


def resolve_tree_overlap(ctx: PairContext, axial: float | None = None) -> tuple[str, float | None]:
    """The overlap the spanning tree ranks by (`ScoreConfig.tree_overlap`), and the images' known
    field of view (None where unknown).

    ``auto`` takes ``all`` (the inliers among all mutual matches: trees of the nearest, most
    overlapping views) when the images' field of view is known and at least WIDE_FIELD_OF_VIEW_DEG
    and the views do not move along their optical axes (`axial`, from `axial_motion`, under
    FORWARD_AXIAL_COSINE), else ``best`` (the paper's weight, which prefers wider baselines). With a
    wide lens a short baseline still fixes the relative pose well; with a long lens (or a turntable,
    whose focal length the images cannot tell) it does not, and the trees of the nearest views lost
    up to 0.4 AUC@1 on long-lens crops. Moving straight ahead, the nearest views are the shortest
    steps: on kitti-seq1 with its calibration (82 degrees), its images, a dashcam stand-in and its
    video, ``best`` was higher in seven of nine runs (AUC@1 +0.011 on the mean, inside the naming
    band of 0.032), lower in one.
    """
    mode = ctx.conf.score.tree_overlap
    fov = known_field_of_view(ctx.db_path, ctx.names, ctx.focal_estimate, ctx.features_path)
    if mode != "auto":
        return mode, fov
    wide = fov is not None and fov >= WIDE_FIELD_OF_VIEW_DEG
    return ("all" if wide and not moving_ahead(axial) else "best"), fov


def moving_ahead(axial: float | None) -> bool:
    """Whether `axial_motion`'s figure says the views move along their optical axes."""
    return axial is not None and axial >= FORWARD_AXIAL_COSINE


def axial_motion(scores: PairScores) -> float | None:
    """How far the views move along their optical axes: the median, over the accepted candidates
    with a pose, of |cosine| between the baseline and the second view's optical axis (1 straight
    ahead, 0 sideways). None with fewer than MIN_AXIAL_PAIRS such candidates (or scores written
    before the direction was recorded)."""
    direction = np.asarray(scores.direction, dtype=np.float64)[np.asarray(scores.accepted, dtype=bool)]
    known = direction[np.all(np.isfinite(direction), axis=1)]
    if len(known) < MIN_AXIAL_PAIRS:
        return None
    return float(np.median(np.abs(known[:, 2]) / np.maximum(np.linalg.norm(known, axis=1), 1e-12)))


def known_field_of_view(db_path: Path, names: list[str], focal_estimate: dict[str, Any] | None = None,
                        features_path: Path | None = None) -> float | None:
    """The median field of view (degrees, larger image side) of `names`, over the images whose
    focal length is known: from EXIF or `extract.camera_params` (the camera's prior focal length),
    or a sound estimate from the images (`focal_estimate`, the extract stage's). None
    when it is known for fewer than half of them.

    Features extracted by sara 0.1 before the estimate's soundness was recorded get it estimated
    again from `features_path` (a few seconds), so a resumed run chooses as a new one does."""
    cameras = colmap.cameras_by_image(db_path)
    estimate = focal_estimate or {}
    if estimate.get("estimated_px") and "sound" not in estimate and features_path is not None:
        estimate = _estimate_again(cameras, features_path, names, estimate) or {}
    estimated = estimate.get("estimated_px") if estimate.get("sound") else None
    fovs = []
    for name in names:
        camera = cameras.get(name)
        if camera is None or camera.is_fisheye():  # not a pinhole's angle; its prior may be the guess (match)
            continue
        if camera.has_prior_focal_length:
            fovs.append(focal.field_of_view_deg(float(camera.mean_focal_length()), camera.width, camera.height))
        elif estimated:  # only ever for one shared camera
            fovs.append(focal.field_of_view_deg(float(estimated), camera.width, camera.height))
    if not names or 2 * len(fovs) < len(names):
        return None
    return float(np.median(fovs))


def _estimate_again(cameras: dict[str, Any], features_path: Path, names: list[str], recorded: dict) -> dict | None:
    """The focal estimate's length and soundness, from the features, for one camera shared by all images."""
    shared = {camera.camera_id: camera for camera in cameras.values()}
    if len(shared) != 1 or not Path(features_path).is_file():
        return None
    camera = next(iter(shared.values()))
    found = focal.estimate_from_features(Path(features_path), names, camera.width, camera.height,
                                         float(recorded.get("prior_px") or camera.mean_focal_length()))
    return {"estimated_px": found.focal_px, "sound": found.sound} if found is not None else None
