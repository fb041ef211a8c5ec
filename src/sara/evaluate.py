"""Compare estimated COLMAP models with a ground-truth model.

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
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from .io import write_json_atomic

logger = logging.getLogger(__name__)

DEFAULT_THRESHOLDS_DEG: tuple[float, ...] = (1, 3, 5, 10)
_MODEL_FILES = ("cameras.bin", "cameras.txt")
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
# pycolmap access (kept in these few functions so that an API change is mended here)


def _has_model(model_dir: Path) -> bool:
    return any((model_dir / name).is_file() for name in _MODEL_FILES)


def read_reconstruction(model_dir: Path) -> pycolmap.Reconstruction:
    """Read a COLMAP model folder (binary or text).

    Raises:
        FileNotFoundError: the folder does not exist or holds no COLMAP model.
    """
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise FileNotFoundError(f"Model folder does not exist: {model_dir}")
    if not _has_model(model_dir):
        raise FileNotFoundError(
            f"No COLMAP model in {model_dir}: expected cameras/images/points3D .bin or .txt files"
        )
    try:
        return pycolmap.Reconstruction(model_dir)
    except ValueError as error:  # pycolmap reports missing or unreadable files this way
        raise FileNotFoundError(
            f"Could not read a COLMAP model from {model_dir}: {error}"
        ) from error


def _pose_of_image(image: Any) -> tuple[np.ndarray, np.ndarray]:
    """(R_cam_from_world (3, 3), t_cam_from_world (3,)) float64 of a posed pycolmap Image."""
    cam_from_world = image.cam_from_world()  # a method in pycolmap 4.x, not a property
    rotation = np.asarray(cam_from_world.rotation.matrix(), dtype=np.float64)
    translation = np.asarray(cam_from_world.translation, dtype=np.float64).reshape(3)
    return rotation, translation


def _poses_of(rec: pycolmap.Reconstruction) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name -> (R_cam_from_world (3, 3), t_cam_from_world (3,)) for every image with a pose."""
    return {image.name: _pose_of_image(image) for image in rec.images.values() if image.has_pose}


def _image_reprojection_errors_px(
    rec: pycolmap.Reconstruction, image: Any, point_ids_sorted: np.ndarray, xyz_sorted: np.ndarray
) -> np.ndarray:
    """Reprojection errors (K,) float64 in pixels of the K observations of one posed image.

    Points behind the camera give NaN.
    """
    points2d = image.get_observation_points2D()
    if len(points2d) == 0:
        return np.zeros(0)
    xy_observed = np.array([p.xy for p in points2d], dtype=np.float64).reshape(-1, 2)
    point3d_ids = np.array([p.point3D_id for p in points2d], dtype=np.int64)
    xyz_world = xyz_sorted[np.searchsorted(point_ids_sorted, point3d_ids)]
    rotation, translation = _pose_of_image(image)
    xyz_cam = xyz_world @ rotation.T + translation
    xy_projected = np.asarray(rec.cameras[image.camera_id].img_from_cam(xyz_cam), dtype=np.float64)
    return np.linalg.norm(xy_projected.reshape(-1, 2) - xy_observed, axis=1)


def reprojection_errors_px(rec: pycolmap.Reconstruction) -> np.ndarray:
    """Reprojection error of every observation of every 3D point, in pixels.

    Each 3D point is projected with the pose and camera of every image in its track and compared
    with the observed keypoint. Vectorised per image.

    Returns:
        (M,) float64, one entry per observation (M = total track length); NaN where the point
        lies behind the camera.
    """
    if rec.num_points3D() == 0:
        return np.zeros(0)
    point_ids = np.fromiter(rec.points3D.keys(), dtype=np.int64, count=rec.num_points3D())
    xyz = np.array([point.xyz for point in rec.points3D.values()], dtype=np.float64)
    order = np.argsort(point_ids)
    point_ids_sorted, xyz_sorted = point_ids[order], xyz[order]
    errors = [
        _image_reprojection_errors_px(rec, image, point_ids_sorted, xyz_sorted)
        for image in rec.images.values()
        if image.has_pose
    ]
    return np.concatenate(errors) if errors else np.zeros(0)


# ----------------------------------------------------------------------------------------------
# Pure cores on arrays


def load_poses(model_dir: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Poses of the registered images of a COLMAP model (text or binary).

    Returns:
        name -> (R_cam_from_world (3, 3) float64, t_cam_from_world (3,) float64); images
        without a pose are left out.

    Raises:
        FileNotFoundError: the folder does not exist or holds no model.
    """
    return _poses_of(read_reconstruction(Path(model_dir)))


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angle of the rotation ``R_a^T R_b`` in degrees, for (..., 3, 3) stacks of rotations.

    Uses ``||R_a - R_b||_F = 2 sqrt(2) sin(angle / 2)``, which stays accurate near zero (unlike
    the arccos of the trace). Returns (...,) float64 in [0, 180].
    """
    frobenius = np.linalg.norm(np.asarray(R_a) - np.asarray(R_b), axis=(-2, -1))
    return np.degrees(2.0 * np.arcsin(np.clip(frobenius / (2.0 * math.sqrt(2.0)), 0.0, 1.0)))


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


def relative_pose_errors(est: dict, gt: dict, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Relative pose errors of every unordered pair of images.

    For each pair (i, j), i < j in the order of ``names`` restricted to names present in both
    ``est`` and ``gt``, the relative pose ``cam_j_from_cam_i`` of the estimate is compared with
    that of the ground truth. Scale-free: only the direction of the relative translation counts.

    Args:
        est: name -> (R_cam_from_world (3, 3), t_cam_from_world (3,)) (or :class:`Pose`).
        gt: the same for the ground truth.
        names: image names; duplicates are ignored.

    Returns:
        rotation errors (P,) float64 in degrees (angle of R_est^T R_gt of the relative rotations)
        and translation errors (P,) float64 in degrees (angle between the relative translation
        directions, see :func:`direction_angle_deg` for zero norms), P = k (k - 1) / 2 for the k
        names present in both, pairs ordered as ``np.triu_indices(k, 1)``.
    """
    common = [n for n in dict.fromkeys(names) if n in est and n in gt]
    if len(common) < 2:
        return np.zeros(0), np.zeros(0)
    first, second = np.triu_indices(len(common), 1)
    R_est, t_est = _relative_poses(*_stack_poses(est, common), first, second)
    R_gt, t_gt = _relative_poses(*_stack_poses(gt, common), first, second)
    return rotation_angle_deg(R_est, R_gt), direction_angle_deg(t_est, t_gt)


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


def _median_or_none(values: np.ndarray) -> float | None:
    values = np.asarray(values, dtype=np.float64)
    return float(np.median(values)) if values.size else None


def _auc_key(threshold_deg: float) -> str:
    return f"{threshold_deg:g}"


def _failure_metrics(num_images_gt: int, thresholds_deg: Sequence[float]) -> dict[str, Any]:
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


def _relative_metrics(est: dict, gt: dict, thresholds_deg: Sequence[float]) -> dict[str, Any]:
    """Relative pose errors over co-registered pairs and AUC over all gt pairs."""
    names = sorted(gt)
    num_pairs_gt = len(names) * (len(names) - 1) // 2
    rot_err, trans_err = relative_pose_errors(est, gt, names)
    aucs = pose_auc(np.maximum(rot_err, trans_err), thresholds_deg, num_pairs_gt)
    return {
        "num_pairs_coregistered": int(rot_err.size),
        "rel_rotation_error_median_deg": _median_or_none(rot_err),
        "rel_translation_error_median_deg": _median_or_none(trans_err),
        "auc": {_auc_key(t): auc for t, auc in zip(thresholds_deg, aucs)},
    }


def scene_radius(centers: np.ndarray) -> float:
    """Median distance of (N, 3) camera centres to their centroid, in their unit."""
    centers = np.asarray(centers, dtype=np.float64)
    return float(np.median(np.linalg.norm(centers - centers.mean(axis=0), axis=1)))


def _absolute_metrics(est: dict, gt: dict) -> dict[str, Any]:
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


def _structure_metrics(rec: pycolmap.Reconstruction) -> dict[str, Any]:
    """3D point count, mean track length and reprojection errors of one reconstruction."""
    num_points = rec.num_points3D()
    errors = reprojection_errors_px(rec)
    finite = np.isfinite(errors)
    if not np.all(finite):
        logger.warning("%d of %d observations lie behind their camera; left out of the "
                       "reprojection errors", int(np.sum(~finite)), errors.size)
    errors = errors[finite]
    return {
        "num_points3d": int(num_points),
        "mean_track_length": (
            float(rec.compute_num_observations() / num_points) if num_points else None
        ),
        "reproj_error_mean_px": float(np.mean(errors)) if errors.size else None,
        "reproj_error_median_px": _median_or_none(errors),
    }


def _read_components(model_dirs: Sequence[Path]) -> list[pycolmap.Reconstruction]:
    """Read every model folder that exists; missing or empty ones are skipped with a warning."""
    recs = []
    for model_dir in model_dirs:
        try:
            recs.append(read_reconstruction(Path(model_dir)))
        except FileNotFoundError as error:
            logger.warning("Skipping estimated model: %s", error)
    return recs


def evaluate_models(model_dirs: list[Path] | Path, gt_dir: Path, *,
                    thresholds_deg: Sequence[float] = DEFAULT_THRESHOLDS_DEG) -> dict[str, Any]:
    """Evaluate the components of an estimated reconstruction against the ground truth.

    Args:
        model_dirs: estimated COLMAP model folders (one per component), or one folder. Missing
            folders are skipped; with none left the estimate is scored as a complete failure.
        gt_dir: ground-truth COLMAP model folder (poses of all images).
        thresholds_deg: thresholds of the pose AUC, in degrees.

    Returns:
        A JSON-serialisable dict. Pose metrics use the largest component (most registered
        images): ``num_registered`` / ``registered_pct`` (gt images registered in it),
        ``num_registered_any`` (in any component), ``num_components``, ``num_images_est``
        (registered images of the largest component, gt or not), relative pose error medians
        in degrees over co-registered pairs, ``auc`` {threshold: AUC of max(rot, trans) error
        over all gt pairs}, ``abs_rotation_error_median_deg`` and ``position_error_median_pct``
        (after a similarity alignment of camera centres; None with fewer than 3 images) and
        the structure statistics ``num_points3d``, ``mean_track_length``,
        ``reproj_error_mean_px``, ``reproj_error_median_px``. Missing values are None.

    Raises:
        FileNotFoundError: the ground-truth folder does not exist or holds no model.
    """
    if isinstance(model_dirs, (str, os.PathLike)):
        model_dirs = [Path(model_dirs)]
    gt = load_poses(Path(gt_dir))
    metrics = _failure_metrics(len(gt), thresholds_deg)
    recs = [rec for rec in _read_components(model_dirs) if rec.num_reg_images() > 0]
    if not recs:
        logger.warning("No estimated model with registered images: scored as a failure")
        return metrics
    largest = max(recs, key=lambda rec: (rec.num_reg_images(), rec.num_points3D()))
    est = _poses_of(largest)
    registered_any = set().union(*(_poses_of(rec).keys() for rec in recs)) & gt.keys()
    num_registered = len(est.keys() & gt.keys())
    metrics.update({
        "num_registered": num_registered,
        "registered_pct": 100.0 * num_registered / len(gt) if gt else 0.0,
        "num_registered_any": len(registered_any),
        "num_components": len(recs),
        "num_images_est": len(est),
    })
    metrics.update(_relative_metrics(est, gt, thresholds_deg))
    metrics.update(_absolute_metrics(est, gt))
    metrics.update(_structure_metrics(largest))
    return metrics


# ----------------------------------------------------------------------------------------------
# Presentation and runner


def _format_value(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4f}"
    return str(value)


def format_table(metrics: dict) -> str:
    """Render metrics as a two-column text table; nested dicts become ``auc@<key>`` rows."""
    rows = []
    for key, value in metrics.items():
        if isinstance(value, dict):
            rows.extend((f"{key}@{sub}", _format_value(v)) for sub, v in value.items())
        else:
            rows.append((key, _format_value(value)))
    width_key = max([len("metric")] + [len(key) for key, _ in rows])
    width_value = max([len("value")] + [len(value) for _, value in rows])
    lines = [
        f"{'metric':<{width_key}}  {'value':>{width_value}}",
        f"{'-' * width_key}  {'-' * width_value}",
    ]
    lines += [f"{key:<{width_key}}  {value:>{width_value}}" for key, value in rows]
    return "\n".join(lines)


def find_model_dirs(model_root: Path) -> list[Path]:
    """Component folders under ``model_root``.

    ``model_root`` is either one model folder (holding cameras.bin or cameras.txt) or a folder
    of components (``sparse/0``, ``sparse/1``, ...). Returns [] when it does not exist.
    """
    model_root = Path(model_root)
    if _has_model(model_root):
        return [model_root]
    if not model_root.is_dir():
        return []
    subdirs = [p for p in model_root.iterdir() if p.is_dir() and _has_model(p)]
    numbered = sorted((p for p in subdirs if p.name.isdigit()), key=lambda p: int(p.name))
    return numbered + sorted(p for p in subdirs if not p.name.isdigit())


def run(model_root: Path, gt_dir: Path, out_path: Path | None = None) -> dict:
    """Evaluate every component under ``model_root`` against ``gt_dir``.

    Writes the metrics as JSON to ``out_path`` (atomically) when given, and returns them.
    A missing ``model_root`` evaluates as a failed reconstruction.
    """
    model_dirs = find_model_dirs(Path(model_root))
    logger.debug(
        "Evaluating %d component(s) under %s against %s", len(model_dirs), model_root, gt_dir
    )
    metrics = evaluate_models(model_dirs, Path(gt_dir))
    if out_path is not None:
        write_json_atomic(Path(out_path), metrics)
        logger.debug("Wrote metrics to %s", out_path)
    logger.debug("Evaluation of %s:\n%s", model_root, format_table(metrics))
    return metrics
