"""Reading COLMAP models: whether a folder holds one, its registered images, its poses as arrays,
its reprojection errors. Poses are cam_from_world, (R (3, 3), t (3,)) float64: x_cam = R @ X + t.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap


def has_model(model_dir: Path) -> bool:
    """Whether a folder holds a COLMAP model (binary or text)."""
    return any((Path(model_dir) / f"{kind}.{ext}").is_file()
               for kind in ("cameras", "images") for ext in ("bin", "txt"))


def read_model(path: Path) -> pycolmap.Reconstruction:
    """The COLMAP model of a folder, read with no check (`read_reconstruction` checks)."""
    return pycolmap.Reconstruction(str(path))


def read_reconstruction(model_dir: Path) -> pycolmap.Reconstruction:
    """Read a COLMAP model folder (binary or text).

    Raises:
        FileNotFoundError: the folder does not exist or holds no COLMAP model.
    """
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise FileNotFoundError(f"Model folder does not exist: {model_dir}")
    if not has_model(model_dir):
        raise FileNotFoundError(
            f"No COLMAP model in {model_dir}: expected cameras/images/points3D .bin or .txt files"
        )
    try:
        return pycolmap.Reconstruction(model_dir)
    except (ValueError, RuntimeError, LookupError, EOFError) as error:  # missing, cut short, damaged
        raise FileNotFoundError(
            f"Could not read a COLMAP model from {model_dir} (damaged or incomplete: {error})"
        ) from error


def registered_images(model_dir: Path) -> set[str]:
    """Names of the posed images of a model folder (empty when there is no model)."""
    if not has_model(model_dir):
        return set()
    rec = read_model(model_dir)
    return {im.name for im in rec.images.values() if im.has_pose}


def num_registered(rec: pycolmap.Reconstruction) -> int:
    """The number of images with a pose in a model."""
    return int(rec.num_reg_images())


def pose_of_image(image: Any) -> tuple[np.ndarray, np.ndarray]:
    """(R_cam_from_world (3, 3), t_cam_from_world (3,)) float64 of a posed pycolmap Image."""
    cam_from_world = image.cam_from_world()  # a method in pycolmap 4.x, not a property
    rotation = np.asarray(cam_from_world.rotation.matrix(), dtype=np.float64)
    translation = np.asarray(cam_from_world.translation, dtype=np.float64).reshape(3)
    return rotation, translation


def poses_of(rec: pycolmap.Reconstruction) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name -> (R_cam_from_world (3, 3), t_cam_from_world (3,)) for every image with a pose."""
    return {image.name: pose_of_image(image) for image in rec.images.values() if image.has_pose}


def load_poses(model_dir: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Poses of the registered images of a COLMAP model (text or binary).

    Returns:
        name -> (R_cam_from_world (3, 3) float64, t_cam_from_world (3,) float64); images
        without a pose are left out.

    Raises:
        FileNotFoundError: the folder does not exist or holds no model.
    """
    return poses_of(read_reconstruction(Path(model_dir)))


def cameras_and_poses(model_dir: Path) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]]:
    """name -> (K (3, 3), R (3, 3), t (3,), (width, height)) of every posed image of a model (gt models)."""
    rec = read_reconstruction(Path(model_dir))
    out = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        cam = rec.cameras[image.camera_id]
        R, t = pose_of_image(image)
        K = np.asarray(cam.calibration_matrix(), dtype=np.float64)
        out[image.name] = (K, R, t, (int(cam.width), int(cam.height)))
    return out


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
    rotation, translation = pose_of_image(image)
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


def model_structure(rec: pycolmap.Reconstruction) -> tuple[int, int, np.ndarray]:
    """(3D points, observations, reprojection error of every observation in pixels (NaN behind))."""
    return rec.num_points3D(), rec.compute_num_observations(), reprojection_errors_px(rec)


@dataclass(frozen=True)
class ModelSummary:
    """What the evaluation reads of one model: its poses (cam_from_world, by image name), the views
    it registered, its 3D points, their observations and reprojection errors (pixels)."""

    poses: dict[str, tuple[np.ndarray, np.ndarray]]
    num_registered: int
    num_points3d: int
    num_observations: int
    reprojection_errors_px: np.ndarray


def read_summary(model_dir: Path) -> ModelSummary:
    """The summary of a model folder (FileNotFoundError as `read_reconstruction`)."""
    rec = read_reconstruction(model_dir)
    num_points, num_observations, errors = model_structure(rec)
    return ModelSummary(poses_of(rec), num_registered(rec), int(num_points), int(num_observations), errors)
