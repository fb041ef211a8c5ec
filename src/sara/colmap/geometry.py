"""Pixel conventions and camera geometry.

COLMAP puts the centre of the top-left pixel at (0.5, 0.5); hloc's HDF5 files put it at (0, 0).
Every conversion between the two goes through the pair of functions here.
"""

from __future__ import annotations

import numpy as np
import pycolmap


def colmap_to_hloc_keypoints(xy: np.ndarray) -> np.ndarray:
    """(N, 2) keypoints in COLMAP's convention -> hloc's (pixel centre at integer coordinates)."""
    return np.asarray(xy, dtype=np.float32) - 0.5


def hloc_to_colmap_keypoints(xy: np.ndarray) -> np.ndarray:
    """(N, 2) keypoints in hloc's convention -> COLMAP's (top-left pixel centre at (0.5, 0.5))."""
    return np.asarray(xy, dtype=np.float32) + 0.5


def image_to_normalized(camera: pycolmap.Camera, xy_colmap: np.ndarray) -> np.ndarray:
    """(N, 2) pixels in COLMAP's convention -> (N, 2) normalized camera coordinates (undistorted)."""
    if len(xy_colmap) == 0:
        return np.zeros((0, 2))
    return np.asarray(camera.cam_from_img(np.asarray(xy_colmap, dtype=np.float64)), dtype=np.float64)[:, :2]


def mean_focal_px(camera: pycolmap.Camera) -> float:
    """The mean of a camera's focal lengths along x and y, in pixels."""
    return float(np.mean([camera.focal_length_x, camera.focal_length_y]))
