"""Local-feature backends: one small Protocol, one file per backend, one registry.

A backend turns one image into keypoints, scores and descriptors. The extract stage
(`sara.extract`) does everything else for every backend alike: it decodes and resizes images,
maps keypoints back to full resolution, writes `features-<backend>.h5` (hloc's layout) and puts
the keypoints into the COLMAP database so that verification and mapping are the same for all.

COLMAP's own SIFT is the one backend that extracts straight into the database (its fastest
path); it implements `extract_to_database` instead of `extract`.

Adding a backend: write `make(conf: ExtractConfig) -> LocalFeatures` in a new module and add one
line to `BACKENDS` (or call `BACKENDS.register(name, make)` from outside, as the tests do).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from ..config import ExtractConfig
from ..registry import Registry


@dataclass(frozen=True)
class Keypoints:
    """What a backend finds in one image.

    Attributes:
        xy: (N, 2) float32 pixel coordinates in the image given to `extract`, hloc's convention
            (the centre of the top-left pixel is (0, 0)).
        scores: (N,) float32, larger is better (detection score, or SIFT's scale).
        descriptors: (N, D) float32 (learned, unit length) or uint8 (SIFT as COLMAP stores it).
    """

    xy: np.ndarray
    scores: np.ndarray
    descriptors: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.xy)
        if np.shape(self.xy) != (n, 2) or len(self.scores) != n or len(self.descriptors) != n:
            raise ValueError(
                f"keypoints {np.shape(self.xy)}, scores {np.shape(self.scores)} and descriptors "
                f"{np.shape(self.descriptors)} do not describe the same N points"
            )


@runtime_checkable
class LocalFeatures(Protocol):
    """A local-feature backend.

    `extract` takes one (H, W, 3) uint8 RGB image, already resized by the stage so that its longer
    side is at most `ExtractConfig.max_image_size`. A backend may also define
    `extract_batch(images: list[np.ndarray]) -> list[Keypoints]` (used in chunks when present), and a
    `device` attribute when it runs on an accelerator: the stage then calls it in the driver process
    instead of loading it in every worker (`sara.execute.for_device`).
    """

    name: str

    def extract(self, image: np.ndarray) -> Keypoints: ...


FeatureFactory = Callable[[ExtractConfig], LocalFeatures]

BACKENDS: Registry[FeatureFactory] = Registry("local-feature backend", {
    "sift": "sara.features.sift:make",
    "aliked-n16": "sara.features.learned:make",
    "aliked-n16rot": "sara.features.learned:make",
    "aliked-n32": "sara.features.learned:make",
    "disk": "sara.features.learned:make",
    "xfeat": "sara.features.learned:make",
})


def make_backend(conf: ExtractConfig) -> LocalFeatures:
    """The backend `conf.backend`, built from its settings (weights are loaded here)."""
    return BACKENDS.get(conf.backend)(conf)


#: backends whose `scores` are each keypoint's scale in pixels (SIFT), not a detection score
SCALE_SCORES = frozenset({"sift"})


def scores_are_scales(backend: str) -> bool:
    """Whether the features of `backend` carry each keypoint's scale as its score (the track
    extension then also tests scales, `sara.colmap.tracks.TrackExtension.scale_quantile`)."""
    return backend in SCALE_SCORES


def features_file_name(conf: ExtractConfig) -> str:
    """`features-<backend>.h5`: switching backends never reuses or overwrites another's file."""
    return f"features-{conf.backend}.h5"
