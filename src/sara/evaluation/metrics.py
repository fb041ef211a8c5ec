"""Pose and structure metrics on arrays: relative pose errors, pose AUC, similarity alignment.

Conventions used throughout this module:

- Poses are ``cam_from_world``: a world point ``X`` (3,) maps to camera coordinates
  ``x_cam = R_cam_from_world @ X + t_cam_from_world`` (COLMAP convention).
- The camera centre in world coordinates is ``-R_cam_from_world.T @ t_cam_from_world``.
- Images of the estimate and of the ground truth are matched by image NAME.
- Angles are in degrees, pixel errors in pixels (COLMAP's pixel convention), positions in the
  unit of the ground truth unless stated as a percentage of the scene radius.

The ground truth is a COLMAP model folder (text or binary; ``points3D`` may be empty). An
estimate is a list of model folders, one per connected component (``sparse/0``, ``sparse/1``,
...). Metrics that need one model use the largest component (most registered images).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..rotations import angle_between_deg as rotation_angle_deg  # the angle of R_a^T R_b, here under its old name

logger = logging.getLogger(__name__)

DEFAULT_THRESHOLDS_DEG: tuple[float, ...] = (1, 3, 5, 10)
_MIN_NORM = 1e-12  # below this a relative translation has no direction
_UNDEFINED_DIRECTION_ERROR_DEG = 90.0  # expected angle to a random direction


@dataclass(frozen=True)
class Pose:
    """A camera pose, ``cam_from_world``.

    Unpacks like the ``(R, t)`` tuples that :func:`load_poses` returns: ``R, t = pose``.

    Attributes:
        R_cam_from_world: (3, 3) float64 rotation, world frame to camera frame.
        t_cam_from_world: (3,) float64 translation, in camera frame, world units.
    """

    R_cam_from_world: np.ndarray
    t_cam_from_world: np.ndarray

    @property
    def center_world(self) -> np.ndarray:
        """Camera centre in world coordinates, (3,) float64."""
        return -self.R_cam_from_world.T @ self.t_cam_from_world

    def __iter__(self) -> Iterator[np.ndarray]:
        yield self.R_cam_from_world
        yield self.t_cam_from_world


# ----------------------------------------------------------------------------------------------
# Pure cores on arrays


def direction_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in degrees between the directions of (..., 3) vectors ``a`` (estimate), ``b`` (truth).

    A zero-norm ``b`` has no direction to miss: error 0. A zero-norm ``a`` against a non-zero
    ``b`` gets 90 degrees (the expected angle to a random direction). Returns (...,) in [0, 180].
    """
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = np.sum(a * b, axis=-1)
    angle = np.degrees(np.arctan2(cross, dot))
    norm_a, norm_b = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    angle = np.where(norm_a < _MIN_NORM, _UNDEFINED_DIRECTION_ERROR_DEG, angle)
    return np.where(norm_b < _MIN_NORM, 0.0, angle)


#: pairs whose relative poses are computed at a time (`relative_pose_errors`)
BLOCK_PAIRS = 1_000_000


def _stack_poses(poses: dict, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    rotations = np.stack([np.asarray(Pose(*poses[n]).R_cam_from_world, float) for n in names])
    translations = np.stack([np.asarray(Pose(*poses[n]).t_cam_from_world, float).reshape(3)
                             for n in names])
    return rotations, translations


def _relative_poses(rotations: np.ndarray, translations: np.ndarray,
                    first: np.ndarray, second: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cam_second_from_cam_first for index pairs: R (P, 3, 3), t (P, 3)."""
    R_rel = rotations[second] @ np.swapaxes(rotations[first], -1, -2)
    t_rel = translations[second] - np.einsum("pij,pj->pi", R_rel, translations[first])
    return R_rel, t_rel


def relative_pose_errors(est: dict, gt: dict, names: list[str], *,
                         block_pairs: int = BLOCK_PAIRS) -> tuple[np.ndarray, np.ndarray]:
    """Relative pose errors of every unordered pair of images.

    For each pair (i, j), i < j in the order of ``names`` restricted to names present in both
    ``est`` and ``gt``, the relative pose ``cam_j_from_cam_i`` of the estimate is compared with
    that of the ground truth. Scale-free: only the direction of the relative translation counts.

    Args:
        est: name -> (R_cam_from_world (3, 3), t_cam_from_world (3,)) (or :class:`Pose`).
        gt: the same for the ground truth.
        names: image names; duplicates are ignored.
        block_pairs: pairs computed at a time (the memory: about 600 bytes a pair; all 50 million
            pairs of 10,000 views at once took 17.9 GB).

    Returns:
        rotation errors (P,) float64 in degrees (angle of R_est^T R_gt of the relative rotations)
        and translation errors (P,) float64 in degrees (angle between the relative translation
        directions, see :func:`direction_angle_deg` for zero norms), P = k (k - 1) / 2 for the k
        names present in both, pairs ordered as ``np.triu_indices(k, 1)``.
    """
    common = [n for n in dict.fromkeys(names) if n in est and n in gt]
    if len(common) < 2:
        return np.zeros(0), np.zeros(0)
    poses_est, poses_gt = _stack_poses(est, common), _stack_poses(gt, common)
    rotation, translation = [], []
    for first, second in _pair_blocks(len(common), block_pairs):
        R_est, t_est = _relative_poses(*poses_est, first, second)
        R_gt, t_gt = _relative_poses(*poses_gt, first, second)
        rotation.append(rotation_angle_deg(R_est, R_gt))
        translation.append(direction_angle_deg(t_est, t_gt))
    return np.concatenate(rotation), np.concatenate(translation)


def _pair_blocks(num: int, block_pairs: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """The pairs (i, j), i < j < num, in the order of ``np.triu_indices(num, 1)``, as index arrays of
    whole rows i holding about `block_pairs` pairs each (at least one row)."""
    counts = np.arange(num - 1, 0, -1)  # pairs of row i: num - 1 - i
    before = np.concatenate([[0], np.cumsum(counts)])  # pairs of the rows before row i
    start = 0
    while start < num - 1:
        stop = min(max(start + 1, int(np.searchsorted(before, before[start] + block_pairs, side="right")) - 1), num - 1)
        rows = np.arange(start, stop)
        first = np.repeat(rows, counts[rows])
        offsets = np.arange(len(first)) - np.repeat(before[rows] - before[start], counts[rows])
        yield first, first + 1 + offsets
        start = stop


def pose_auc(
    errors_deg: np.ndarray, thresholds_deg: Sequence[float], num_total: int
) -> list[float]:
    """Area under the recall curve of pose errors, one value per threshold.

    The recall curve is ``r(x) = #{pairs with error <= x} / num_total``; pairs missing from
    ``errors_deg`` (``num_total - len(errors_deg)`` of them) and NaN errors count as failures
    (error = inf). The AUC at threshold T is ``(1 / T) * integral_0^T r(x) dx``, integrated
    exactly; it equals ``sum_i max(0, 1 - e_i / T) / num_total``. (SuperGlue/LightGlue integrate
    a piecewise-linear curve through the sorted errors instead, which differs slightly.)

    Args:
        errors_deg: (P,) errors in degrees, usually max(rotation, translation) error per pair.
        thresholds_deg: positive thresholds in degrees.
        num_total: number of pairs in all, at least P.

    Returns:
        One AUC in [0, 1] per threshold; all 0.0 when ``num_total`` is 0.
    """
    errors = np.asarray(errors_deg, dtype=np.float64).ravel()
    if num_total < errors.size:
        raise ValueError(
            f"num_total ({num_total}) is smaller than the number of errors ({errors.size})"
        )
    if np.any(errors < 0):
        raise ValueError("pose errors must be non-negative")
    if any(t <= 0 for t in thresholds_deg):
        raise ValueError(f"thresholds must be positive, got {list(thresholds_deg)}")
    if num_total == 0:
        return [0.0 for _ in thresholds_deg]
    errors = np.where(np.isnan(errors), np.inf, errors)
    return [float(np.clip(1.0 - errors / t, 0.0, 1.0).sum() / num_total) for t in thresholds_deg]


def umeyama_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity from ``src`` to ``dst`` (Umeyama 1991).

    Minimises ``sum_k || dst_k - (s R src_k + t) ||^2``.

    Args:
        src: (N, 3) points.
        dst: (N, 3) corresponding points; N >= 3, not all collinear.

    Returns:
        scale s (float > 0), rotation R (3, 3) float64 with det +1, translation t (3,) float64.

    Raises:
        ValueError: shapes differ, fewer than 3 points, or the points are collinear.
    """
    src, dst = np.asarray(src, dtype=np.float64), np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"expected two (N, 3) arrays, got {src.shape} and {dst.shape}")
    if src.shape[0] < 3:
        raise ValueError(f"a similarity needs at least 3 points, got {src.shape[0]}")
    mean_src, mean_dst = src.mean(axis=0), dst.mean(axis=0)
    src_c, dst_c = src - mean_src, dst - mean_dst
    covariance = dst_c.T @ src_c / src.shape[0]
    U, singular, Vt = np.linalg.svd(covariance)
    if singular[1] <= 1e-12 * max(singular[0], np.finfo(float).tiny):
        raise ValueError("points are collinear (or coincide): the similarity is not determined")
    signs = np.array([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt))])
    rotation = (U * signs) @ Vt
    variance_src = np.mean(np.sum(src_c**2, axis=1))
    scale = float(np.sum(singular * signs) / variance_src)
    translation = mean_dst - scale * rotation @ mean_src
    return scale, rotation, translation


# ----------------------------------------------------------------------------------------------
# Metrics of a whole estimate


def median_or_none(values: np.ndarray) -> float | None:
    values = np.asarray(values, dtype=np.float64)
    return float(np.median(values)) if values.size else None


def _auc_key(threshold_deg: float) -> str:
    return f"{threshold_deg:g}"


def failure_metrics(num_images_gt: int, thresholds_deg: Sequence[float]) -> dict[str, Any]:
    """The metrics of an estimate that registered nothing."""
    return {
        "num_images_gt": num_images_gt,
        "num_registered": 0,
        "registered_pct": 0.0,
        "num_registered_any": 0,
        "num_components": 0,
        "num_images_est": 0,
        "num_pairs_gt": num_images_gt * (num_images_gt - 1) // 2,
        "num_pairs_coregistered": 0,
        "rel_rotation_error_median_deg": None,
        "rel_translation_error_median_deg": None,
        "auc": {_auc_key(t): 0.0 for t in thresholds_deg},
        "abs_rotation_error_median_deg": None,
        "position_error_median_pct": None,
        "num_points3d": 0,
        "mean_track_length": None,
        "reproj_error_mean_px": None,
        "reproj_error_median_px": None,
    }


def relative_metrics(est: dict, gt: dict, thresholds_deg: Sequence[float]) -> dict[str, Any]:
    """Relative pose errors over co-registered pairs and AUC over all gt pairs."""
    names = sorted(gt)
    num_pairs_gt = len(names) * (len(names) - 1) // 2
    rot_err, trans_err = relative_pose_errors(est, gt, names)
    aucs = pose_auc(np.maximum(rot_err, trans_err), thresholds_deg, num_pairs_gt)
    return {
        "num_pairs_coregistered": int(rot_err.size),
        "rel_rotation_error_median_deg": median_or_none(rot_err),
        "rel_translation_error_median_deg": median_or_none(trans_err),
        "auc": {_auc_key(t): auc for t, auc in zip(thresholds_deg, aucs)},
    }


def scene_radius(centers: np.ndarray) -> float:
    """Median distance of (N, 3) camera centres to their centroid, in their unit."""
    centers = np.asarray(centers, dtype=np.float64)
    return float(np.median(np.linalg.norm(centers - centers.mean(axis=0), axis=1)))


def absolute_metrics(est: dict, gt: dict) -> dict[str, Any]:
    """Absolute rotation and position errors after aligning est centres to gt centres."""
    result: dict[str, Any] = {
        "abs_rotation_error_median_deg": None,
        "position_error_median_pct": None,
    }
    names = sorted(n for n in gt if n in est)
    if len(names) < 3:
        return result
    R_est, t_est = _stack_poses(est, names)
    R_gt, t_gt = _stack_poses(gt, names)
    centers_est = -np.einsum("nji,nj->ni", R_est, t_est)
    centers_gt = -np.einsum("nji,nj->ni", R_gt, t_gt)
    try:
        scale, R_align, t_align = umeyama_similarity(centers_est, centers_gt)
    except ValueError as error:
        logger.warning("No similarity alignment of the estimate to the ground truth: %s", error)
        return result
    # world_gt = s R_align world_est + t  =>  R_cam_from_world_gt ~ R_cam_from_world_est R_align^T
    rotation_errors = rotation_angle_deg(R_est @ R_align.T, R_gt)
    result["abs_rotation_error_median_deg"] = float(np.median(rotation_errors))
    position_errors = np.linalg.norm(scale * centers_est @ R_align.T + t_align - centers_gt, axis=1)
    all_centers_gt = np.stack([Pose(*pose).center_world for pose in gt.values()])
    radius = scene_radius(all_centers_gt)
    if radius > 0:
        result["position_error_median_pct"] = float(100.0 * np.median(position_errors) / radius)
    else:
        logger.warning("Ground-truth camera centres coincide: no position error in percent")
    return result
