"""Helpers for tests: hand-built camera poses and COLMAP text models written from numpy arrays.

Poses are ``cam_from_world`` (COLMAP): ``x_cam = R @ X_world + t``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

PoseDict = dict[str, tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class PinholeCamera:
    """A PINHOLE camera: image size in pixels, focal lengths and principal point in pixels."""

    width: int = 640
    height: int = 480
    fx: float = 500.0
    fy: float = 500.0
    cx: float = 320.0
    cy: float = 240.0

    def project(self, xyz_cam: np.ndarray) -> np.ndarray:
        """(N, 3) points in the camera frame -> (N, 2) pixels (COLMAP convention)."""
        xyz_cam = np.atleast_2d(np.asarray(xyz_cam, dtype=np.float64))
        uv = xyz_cam[:, :2] / xyz_cam[:, 2:3]
        return uv * [self.fx, self.fy] + [self.cx, self.cy]


@dataclass(frozen=True)
class Point3D:
    """A 3D point in world coordinates, (3,), and its observations: image name -> pixel (2,)."""

    xyz: np.ndarray
    observations: Mapping[str, np.ndarray]


def rotation_about_axis(axis: Sequence[float], angle_deg: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_deg`` degrees about ``axis``."""
    axis = np.asarray(axis, dtype=np.float64)
    return Rotation.from_rotvec(np.radians(angle_deg) * axis / np.linalg.norm(axis)).as_matrix()


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A random (3, 3) rotation matrix."""
    return Rotation.random(random_state=rng).as_matrix()


def look_at(center: np.ndarray, target: np.ndarray, up: Sequence[float] = (0.0, 0.0, 1.0)
            ) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world (R (3, 3), t (3,)) of a camera at ``center`` looking at ``target``.

    Camera axes follow COLMAP: x right, y down, z forward.
    """
    center, target = np.asarray(center, dtype=np.float64), np.asarray(target, dtype=np.float64)
    z_axis = target - center
    z_axis /= np.linalg.norm(z_axis)
    x_axis = np.cross(z_axis, np.asarray(up, dtype=np.float64))
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    rotation = np.stack([x_axis, y_axis, z_axis])
    return rotation, -rotation @ center


def ring_poses(num_images: int, radius: float = 5.0, seed: int = 0) -> PoseDict:
    """Cameras on a slightly irregular ring around the origin, all looking at it.

    Names are ``0000.jpg``, ``0001.jpg``, ...; centres vary in height so no three are collinear.
    """
    rng = np.random.default_rng(seed)
    poses = {}
    for i in range(num_images):
        angle = 2 * np.pi * i / num_images + rng.uniform(-0.1, 0.1)
        center = [radius * np.cos(angle), radius * np.sin(angle), rng.uniform(-1.0, 1.0)]
        poses[f"{i:04d}.jpg"] = look_at(np.array(center), rng.normal(0.0, 0.2, size=3))
    return poses


def transform_poses(poses: PoseDict, scale: float, rotation: np.ndarray, translation: np.ndarray
                    ) -> PoseDict:
    """The same cameras in the world ``X' = scale * rotation @ X + translation``.

    A camera seeing ``x_cam = R X + t`` sees
    ``scale * x_cam = (R rotation^T) X' + (scale t - R rotation^T translation)``.
    """
    result = {}
    for name, (R, t) in poses.items():
        R_new = R @ rotation.T
        result[name] = (R_new, scale * t - R_new @ translation)
    return result


def camera_center(pose: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """World coordinates (3,) of the centre of a cam_from_world pose."""
    R, t = pose
    return -R.T @ t


def _quaternion_wxyz(rotation: np.ndarray) -> np.ndarray:
    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    return np.array([w, x, y, z])


def write_text_model(model_dir: Path, poses: PoseDict, camera: PinholeCamera = PinholeCamera(),
                     points: Sequence[Point3D] = ()) -> Path:
    """Write a COLMAP text model (cameras.txt, images.txt, points3D.txt) and return its folder.

    One PINHOLE camera per image (like the ground-truth folders), image ids 1, 2, ... in the
    order of ``poses``; each observation of ``points`` becomes a 2D point of its image.
    """
    model_dir = Path(model_dir)
    model_dir.mkdir(parents=True, exist_ok=True)
    names = list(poses)
    image_ids = {name: i + 1 for i, name in enumerate(names)}
    points2d: dict[str, list[tuple[np.ndarray, int]]] = {name: [] for name in names}
    point_lines = []
    for point_id, point in enumerate(points, start=1):
        track = []
        for name, xy in point.observations.items():
            track += [image_ids[name], len(points2d[name])]
            points2d[name].append((np.asarray(xy, dtype=np.float64), point_id))
        xyz = " ".join(repr(float(v)) for v in point.xyz)
        point_lines.append(f"{point_id} {xyz} 128 128 128 0 " + " ".join(map(str, track)))
    camera_lines, image_lines = [], []
    for name in names:
        image_id = image_ids[name]
        camera_lines.append(f"{image_id} PINHOLE {camera.width} {camera.height} "
                            f"{camera.fx!r} {camera.fy!r} {camera.cx!r} {camera.cy!r}")
        R, t = poses[name]
        qvec = " ".join(repr(float(v)) for v in _quaternion_wxyz(R))
        tvec = " ".join(repr(float(v)) for v in t)
        image_lines.append(f"{image_id} {qvec} {tvec} {image_id} {name}")
        image_lines.append(
            " ".join(f"{float(x)!r} {float(y)!r} {pid}" for (x, y), pid in points2d[name])
        )
    (model_dir / "cameras.txt").write_text("\n".join(camera_lines) + "\n")
    (model_dir / "images.txt").write_text("\n".join(image_lines) + "\n")
    (model_dir / "points3D.txt").write_text("\n".join(point_lines) + "\n")
    return model_dir


def synthetic_database(db_path: Path, num_views: int, num_points: int):
    """pycolmap's synthetic scene of `num_views` posed 320x240 views (one camera) and `num_points`
    points, its matches written to `db_path`; returns the true reconstruction (seed 0)."""
    import pycolmap

    pycolmap.set_random_seed(0)
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_cameras_per_rig, opts.num_frames_per_rig = 1, 1, num_views
    opts.num_points3D = num_points
    opts.camera_width, opts.camera_height = 320, 240
    opts.camera_model_id = pycolmap.CameraModelId.SIMPLE_RADIAL
    opts.camera_params = [300.0, 160.0, 120.0, 0.0]
    db = pycolmap.Database.open(str(db_path))
    rec = pycolmap.synthesize_dataset(opts, db)
    db.close()
    return rec
