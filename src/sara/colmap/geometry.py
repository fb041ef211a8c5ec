"""Pixel conventions and camera geometry.

COLMAP puts the centre of the top-left pixel at (0.5, 0.5); hloc's HDF5 files put it at (0, 0).
Every conversion between the two goes through the pair of functions here.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import pycolmap


@dataclass(frozen=True)
class CameraInfo:
    """A camera of the database as sara sees it: COLMAP's model name, the image size in pixels and
    the parameters in COLMAP's order; `has_prior_focal_length`: the focal length came from EXIF
    or `extract.camera_params`, not from COLMAP's guess."""

    camera_id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]
    has_prior_focal_length: bool

    @classmethod
    def of(cls, camera: pycolmap.Camera) -> CameraInfo:
        return cls(int(camera.camera_id), camera.model.name, int(camera.width), int(camera.height),
                   tuple(float(v) for v in camera.params), bool(camera.has_prior_focal_length))

    def mean_focal_length(self) -> float:
        """The mean of the focal lengths along x and y, in pixels."""
        return mean_focal_px(self)

    def is_fisheye(self) -> bool:
        """Whether the model is one of COLMAP's fisheye models (OPENCV_FISHEYE, ...): the pinhole's
        field of view and focal-length estimates do not hold for it."""
        return bool(_pycolmap_camera(self).is_perspective_fisheye())


@functools.lru_cache(maxsize=64)
def _pycolmap_camera(camera: CameraInfo) -> pycolmap.Camera:
    return pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height, params=list(camera.params))


def colmap_to_hloc_keypoints(xy: np.ndarray) -> np.ndarray:
    """(N, 2) keypoints in COLMAP's convention -> hloc's (pixel centre at integer coordinates)."""
    return np.asarray(xy, dtype=np.float32) - 0.5


def hloc_to_colmap_keypoints(xy: np.ndarray) -> np.ndarray:
    """(N, 2) keypoints in hloc's convention -> COLMAP's (top-left pixel centre at (0.5, 0.5))."""
    return np.asarray(xy, dtype=np.float32) + 0.5


def image_to_normalized(camera: CameraInfo, xy_colmap: np.ndarray) -> np.ndarray:
    """(N, 2) pixels in COLMAP's convention -> (N, 2) normalized camera coordinates (undistorted)."""
    if len(xy_colmap) == 0:
        return np.zeros((0, 2))
    points = _pycolmap_camera(camera).cam_from_img(np.asarray(xy_colmap, dtype=np.float64))
    return np.asarray(points, dtype=np.float64)[:, :2]


def mean_focal_px(camera: CameraInfo) -> float:
    """The mean of a camera's focal lengths along x and y, in pixels."""
    pycolmap_camera = _pycolmap_camera(camera)
    return float(np.mean([pycolmap_camera.focal_length_x, pycolmap_camera.focal_length_y]))
