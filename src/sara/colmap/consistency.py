"""Does a model agree with the verified pairs between its own views?

A verified pair holds matches that fit one relative pose (geometric verification). Once both of
its views are in a model, the model's relative pose predicts where those matches must lie: on each
other's epipolar lines. A model that is right places the inlier matches of its pairs within about
a pixel of them; a pair whose matches lie, at the median, further off than the mapper's own
reprojection threshold (4 px) contradicts the model.

Why this is worth checking: on the 1,000-image synthetic street the incremental mapper sometimes
builds a first model that is bent where the walk passes a place twice (median view rotation error
1.2-3.5 degrees against 0.08 for a good model from the same matches, under another random seed).
Its reprojection error stays low because the contradicting pairs' matches never join a track, so
the mapper cannot see the bend, but 37-54 of its 1,700-2,000 pairs contradicted it where the
good models from the same matches contradicted none (lab/notes/SCALE.md).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

#: a pair whose inlier matches lie, at the median, further than this from the model's epipolar lines
#: contradicts the model (COLMAP's mapper filters observations at 4 px of reprojection error)
CONTRADICTION_PX = 4.0


@dataclass(frozen=True)
class Agreement:
    """How a model agrees with the verified pairs between its views."""

    checked: int  # verified pairs with both views in the model
    contradicted: list[tuple[str, str]] = field(default_factory=list)  # pairs off by more than CONTRADICTION_PX

    @property
    def share(self) -> float:
        return len(self.contradicted) / self.checked if self.checked else 0.0

    def most_contradicted_view(self) -> str | None:
        """The view in the most contradicting pairs (the first by name among equals), None without any:
        where a bent model's seam is."""
        counts = Counter(view for pair in self.contradicted for view in pair)
        return min(counts, key=lambda view: (-counts[view], view)) if counts else None


def model_agreement(model: Path, db_path: Path, *, min_num_inliers: int = 15,
                    max_error_px: float = CONTRADICTION_PX) -> Agreement:
    """How the COLMAP model in the folder `model` agrees with the verified pairs of `db_path` (`agreement`)."""
    return agreement(pycolmap.Reconstruction(str(model)), db_path, min_num_inliers=min_num_inliers,
                     max_error_px=max_error_px)


def agreement(rec: pycolmap.Reconstruction, db_path: Path, *, min_num_inliers: int = 15,
              max_error_px: float = CONTRADICTION_PX) -> Agreement:
    """Check every verified pair of `db_path` (at least `min_num_inliers` inliers) whose two views
    `rec` holds: the median epipolar (Sampson) distance of its inlier matches under the model's
    relative pose, in pixels of the two cameras' mean focal length."""
    posed = {im.name: im for im in rec.images.values() if im.has_pose}
    normalized: dict[int, np.ndarray] = {}
    checked, contradicted = 0, []
    with pycolmap.Database.open(str(db_path)) as db:
        names = {im.image_id: im.name for im in db.read_all_images()}
        pair_ids, geometries = db.read_two_view_geometries()
        for pair_id, geometry in zip(pair_ids, geometries):
            id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
            im1, im2 = posed.get(names[id1]), posed.get(names[id2])
            matches = geometry.inlier_matches
            if im1 is None or im2 is None or len(matches) < min_num_inliers:
                continue
            for db_id, im in ((id1, im1), (id2, im2)):
                if db_id not in normalized:
                    normalized[db_id] = rec.cameras[im.camera_id].cam_from_img(
                        db.read_keypoints(db_id)[:, :2].astype(np.float64))
            error = _sampson(_essential(im1, im2), normalized[id1][matches[:, 0]], normalized[id2][matches[:, 1]])
            cam1, cam2 = rec.cameras[im1.camera_id], rec.cameras[im2.camera_id]
            focal = (cam1.mean_focal_length() + cam2.mean_focal_length()) / 2
            checked += 1
            if np.median(error) * focal > max_error_px:
                contradicted.append((im1.name, im2.name))
    return Agreement(checked, contradicted)


def _essential(im1: pycolmap.Image, im2: pycolmap.Image) -> np.ndarray:
    rel = im2.cam_from_world() * im1.cam_from_world().inverse()
    t = rel.translation / max(np.linalg.norm(rel.translation), 1e-12)
    cross = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return cross @ rel.rotation.matrix()


def _sampson(essential: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distance of normalized points x1 -> x2 under `essential` (normalized units)."""
    h1, h2 = np.c_[x1, np.ones(len(x1))], np.c_[x2, np.ones(len(x2))]
    ex1, etx2 = h1 @ essential.T, h2 @ essential
    num = np.sum(h2 * ex1, axis=1) ** 2
    den = ex1[:, 0] ** 2 + ex1[:, 1] ** 2 + etx2[:, 0] ** 2 + etx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-30))
