"""What shapes a synthetic world (`WorldConfig`), the names of its files, and the grid size it walks."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...io import fingerprint

DB_NAME = "database.db"
TRUTH_NAME = "truth.h5"
WORLD_JSON = "world.json"
IMAGES_DIR = "images"  # the ImageSet's root; no image files are written
DESCRIPTOR_DIM = 128
WORLD_VERSION = 2  # bump when the generator changes what it writes

OUTLIER_KEY_BIT = np.uint64(1 << 62)  # keys of outlier descriptors
STYLE_KEY_BIT = np.uint64(1 << 61)  # keys of the repeated (style) descriptors


@dataclass(frozen=True, kw_only=True)
class WorldConfig:
    """Everything that shapes a synthetic world; the same config gives the same files."""

    num_images: int = 1000
    seed: int = 0
    # camera: one PINHOLE camera, true focal
    width: int = 1024
    height: int = 768
    focal_px: float = 900.0
    # city
    block_size_m: float = 50.0
    street_width_m: float = 14.0
    facade_height_m: tuple[float, float] = (10.0, 16.0)
    point_density: float = 10.0  # 3D points per m^2 of facade
    point_size_m: float = 0.06  # median physical size of a point's feature
    point_size_sigma: float = 0.5  # log-normal spread of the size
    repeat_fraction: float = 0.2  # points with a repeated (style) descriptor
    num_styles: int = 24  # facade styles in the city
    style_words: int = 12  # repeated descriptors per style
    repeat_jitter: float = 0.5  # a repeated point's own deviation from its style word (0: identical copies)
    grid_blocks: int = 0  # G; 0: chosen from num_images and visits_per_street
    visits_per_street: float = 1.6
    # walk
    step_m: float = 1.2
    yaw_pattern_deg: tuple[float, ...] = (60.0, 0.0, -60.0, 0.0)  # from the heading, + is left
    yaw_jitter_deg: float = 6.0
    pitch_deg: float = 8.0
    pitch_jitter_deg: float = 3.0
    roll_jitter_deg: float = 2.0
    camera_height_m: float = 1.6
    height_jitter_m: float = 0.1
    lateral_offset_m: float = 2.0  # keep right of the street centre
    lateral_jitter_m: float = 0.5
    heading_smoothing_m: float = 6.0
    # visibility and keypoints
    min_depth_m: float = 0.5
    max_depth_m: float = 35.0
    max_view_angle_deg: float = 75.0
    min_scale_px: float = 1.6
    max_keypoints: int = 4096
    outlier_fraction: float = 0.15
    pixel_noise_px: float = 0.7
    # descriptors
    descriptor_noise: float = 0.7
    view_drift: float = 0.35  # per radian of viewing angle
    scale_drift: float = 0.25  # per unit of log distance

    def __post_init__(self) -> None:
        if self.num_images < 2:
            raise ValueError(f"a world needs at least 2 images, got {self.num_images}")
        if not 0 <= self.outlier_fraction < 1 or not 0 <= self.repeat_fraction <= 1:
            raise ValueError("outlier_fraction must be in [0, 1) and repeat_fraction in [0, 1]")
        if self.street_width_m / 2 <= self.lateral_offset_m + 3 * self.lateral_jitter_m:
            raise ValueError("the camera must stay in the street: lateral_offset_m too large for street_width_m")
        if not self.yaw_pattern_deg:
            raise ValueError("yaw_pattern_deg needs at least one angle")

    @property
    def pitch_m(self) -> float:
        """Distance between neighbouring street centrelines (m)."""
        return self.block_size_m + self.street_width_m

    def camera_params(self) -> list[float]:
        """PINHOLE fx, fy, cx, cy in COLMAP's pixel convention."""
        return [self.focal_px, self.focal_px, self.width / 2, self.height / 2]

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def key(self) -> str:
        return fingerprint({"config": self.to_dict(), "version": WORLD_VERSION})


def features_name() -> str:
    """The features file sara's extract stage would write for its default (SIFT) backend."""
    try:
        from ...config import ExtractConfig
        from ...features import features_file_name
    except ImportError:  # sara before per-backend feature files
        return "features.h5"
    return features_file_name(ExtractConfig())


def grid_blocks(conf: WorldConfig) -> int:
    """G: blocks per side of the walked grid, so that each street is walked about `visits_per_street` times."""
    if conf.grid_blocks > 0:
        return conf.grid_blocks
    walked = conf.num_images * conf.step_m / (conf.pitch_m * conf.visits_per_street)  # streets to cover
    # 2 G (G + 1) streets between the (G + 1)^2 crossings
    return max(1, round((-1 + math.sqrt(1 + 2 * walked)) / 2))


def image_name(index: int) -> str:
    return f"{index:06d}.jpg"

