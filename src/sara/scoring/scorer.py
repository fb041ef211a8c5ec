"""The pre-matching scorer: a cheap two-view geometry per candidate pair.

For a pair of images, the scorer

1. matches the top-M keypoints of each image (largest scale first) by mutual nearest neighbours
   of their L2-normalised descriptors and keeps the best ``num_matches`` by similarity;
2. runs a short, seeded 5-point RANSAC for the essential matrix (poselib) on those matches;
3. triangulates the inliers (midpoint method) with the recovered relative pose and takes the
   parallax ``P`` as the median triangulation angle of the points in front of both cameras;
   but ``P = 0`` when a pure rotation (allowing for a wrong focal length) fits the inliers about
   as well as the essential matrix: then the 5-point pose is degenerate and its baseline spurious.

The triangulation angle is the angle at the 3D point between the rays to the two camera centres,
so the relative rotation does not count: a pure rotation or a near-duplicate pair has ``P ~ 0``.
From the inlier count and ``P`` come the overlap ``O = num_inliers / sqrt(N_i N_j)`` and the
weight ``w = O^alpha * g(P)^beta``, ``g(P) = min(P, sat) / sat``.

Frames: ``R, t`` is ``cam1_from_cam0`` (``x_cam1 = R x_cam0 + t``); normalised camera
coordinates are ``(x / z, y / z)`` of the point in the camera frame (undistorted).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from .. import colmap
from ..config import ScoreConfig
from ..descriptors import mutual_nearest_neighbours
from ..io.h5 import Features, read_features
from ..io.scores import PairScores
from .twoview import estimate_relative_pose, inlier_parallax_deg

logger = logging.getLogger(__name__)

#: Why a pair is rejected, in the order the conditions are checked ("" when accepted).
REASONS = ("no_model", "few_inliers", "low_overlap", "low_parallax")


# ----------------------------------------------------------------------------------------
# One pair
# ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ViewFeatures:
    """What the scorer needs of one image (its top-M keypoints).

    Attributes:
        descriptors: (M, D) uint8 or float, as stored; normalised when matched.
        points_norm: (M, 2) float64 normalised, undistorted camera coordinates.
        focal_px: mean focal length in pixels (converts the pixel threshold).
    """

    descriptors: np.ndarray
    points_norm: np.ndarray
    focal_px: float

    def __post_init__(self) -> None:
        if len(self.descriptors) != len(self.points_norm):
            raise ValueError(
                f"{len(self.descriptors)} descriptors but {len(self.points_norm)} keypoints"
            )

    @property
    def num_keypoints(self) -> int:
        return len(self.points_norm)

    @classmethod
    def from_features(cls, feats: Features, camera: Any) -> ViewFeatures:
        """From hloc-convention features and the image's pycolmap camera."""
        xy = colmap.hloc_to_colmap_keypoints(feats.keypoints)
        return cls(
            descriptors=np.asarray(feats.descriptors),
            points_norm=colmap.image_to_normalized(camera, xy),
            focal_px=colmap.mean_focal_px(camera),
        )


@dataclass(frozen=True)
class PairScore:
    """The score of one pair; see :func:`score_pair`."""

    num_matches: int
    num_inliers: int
    overlap: float
    parallax_deg: float
    weight: float
    accepted: bool
    reason: str  # one of REASONS, "" when accepted


def pair_weight(overlap: float, parallax_deg: float, conf: ScoreConfig) -> float:
    """``w = O^alpha * g(P)^beta`` with ``g(P) = min(P, sat) / sat``."""
    saturated = min(max(parallax_deg, 0.0), conf.parallax_saturation_deg) / conf.parallax_saturation_deg
    return float(max(overlap, 0.0) ** conf.alpha * saturated**conf.beta)


def rejection_reason(
    found_model: bool, num_inliers: int, overlap: float, parallax_deg: float, conf: ScoreConfig
) -> str:
    """The first failed condition of :data:`REASONS`, or "" when the pair is accepted."""
    if not found_model:
        return "no_model"
    if num_inliers < conf.min_inliers:
        return "few_inliers"
    if overlap < conf.min_overlap:
        return "low_overlap"
    if parallax_deg < conf.min_parallax_deg:
        return "low_parallax"
    return ""


def score_pair(view0: ViewFeatures, view1: ViewFeatures, conf: ScoreConfig, *, seed: int = 0) -> PairScore:
    """Score one pair: mutual NN, short RANSAC, parallax, overlap, weight.

    ``num_inliers`` counts the RANSAC inliers; ``parallax_deg`` is :func:`inlier_parallax_deg`;
    ``overlap`` is ``num_inliers / sqrt(N0 * N1)`` with N the keypoints used (at most M per image).
    The same views, settings and seed always give the same score.
    """
    matches, _ = mutual_nearest_neighbours(view0.descriptors, view1.descriptors, conf.num_matches)
    x0, x1 = view0.points_norm[matches[:, 0]], view1.points_norm[matches[:, 1]]
    max_error = conf.ransac_max_error_px * 2.0 / (view0.focal_px + view1.focal_px)
    pose = estimate_relative_pose(x0, x1, max_error=max_error, iterations=conf.ransac_iterations, seed=seed)
    num_inliers, parallax_deg = 0, 0.0
    if pose is not None:
        num_inliers = int(pose.inliers.sum())
        parallax_deg = inlier_parallax_deg(
            pose, x0[pose.inliers], x1[pose.inliers], max_error=max_error,
            iterations=conf.ransac_iterations, seed=seed,
        )
    denom = math.sqrt(view0.num_keypoints * view1.num_keypoints)
    overlap = num_inliers / denom if denom > 0 else 0.0
    reason = rejection_reason(pose is not None, num_inliers, overlap, parallax_deg, conf)
    return PairScore(
        num_matches=len(matches), num_inliers=num_inliers, overlap=overlap, parallax_deg=parallax_deg,
        weight=pair_weight(overlap, parallax_deg, conf), accepted=reason == "", reason=reason,
    )


# ----------------------------------------------------------------------------------------
# Many pairs
# ----------------------------------------------------------------------------------------


def load_views(
    names: Iterable[str], features_path: Path, db_path: Path, num_keypoints: int, *, progress: bool = True
) -> dict[str, ViewFeatures]:
    """The top-``num_keypoints`` features of each image, normalised with its database camera."""
    names = sorted(set(names))
    cameras = colmap.cameras_by_image(Path(db_path))
    missing = [n for n in names if n not in cameras]
    if missing:
        raise ValueError(
            f"{len(missing)} images are not in the database {db_path} (e.g. {missing[0]!r}); "
            "score pairs with the database the features were extracted into"
        )
    views = {}
    for name in tqdm(names, desc="load features", unit="img", disable=not progress):
        try:
            feats = read_features(Path(features_path), name, top_k=num_keypoints)
        except KeyError as err:
            raise ValueError(f"image {name!r} has no features in {features_path}") from err
        views[name] = ViewFeatures.from_features(feats, cameras[name])
    return views


def score_pairs(
    pairs: Sequence[tuple[str, str]],
    features_path: Path,
    db_path: Path,
    conf: ScoreConfig,
    *,
    progress: bool = True,
    seed: int = 0,
) -> PairScores:
    """Score candidate pairs in one thread; each image's top-M features are read once.

    Args:
        pairs: (name0, name1) image names; both must have features and a database camera.
        features_path: features.h5 (hloc layout, keypoints in hloc's pixel convention).
        db_path: the COLMAP database with the images' cameras (EXIF focal or COLMAP's prior).
        conf: scorer settings.
        progress: show progress bars.
        seed: RANSAC seed, the same for every pair: a pair's score does not depend on the others.
    Returns:
        The scores, in the order of ``pairs``.
    """
    pairs = [(str(a), str(b)) for a, b in pairs]
    same = [a for a, b in pairs if a == b]
    if same:
        raise ValueError(f"a pair of an image with itself: {same[0]!r}")
    views = load_views(
        (n for p in pairs for n in p), features_path, db_path, conf.num_keypoints, progress=progress
    )
    start = time.perf_counter()
    results = [
        score_pair(views[name0], views[name1], conf, seed=seed)
        for name0, name1 in tqdm(pairs, desc="score pairs", unit="pair", disable=not progress)
    ]
    scores = PairScores.from_scores(pairs, results)
    _log_summary(scores, time.perf_counter() - start)
    return scores


def _log_summary(scores: PairScores, elapsed_s: float) -> None:
    count = len(scores)
    if count == 0:
        logger.info("score: no pairs")
        return
    rejected = {r: scores.reason.count(r) for r in REASONS if r in scores.reason}
    logger.info(
        "score: %d pairs in %.1f s (%.2f ms per pair); %d accepted, rejected: %s",
        count, elapsed_s, 1e3 * elapsed_s / count, int(scores.accepted.sum()), rejected or "none",
    )
