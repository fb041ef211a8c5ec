"""Local features in HDF5 with hloc's layout.

One group per image name (sub-folders become nested groups), holding
`keypoints` (N, 2) float32 pixels in hloc's convention (centre of the top-left pixel at (0, 0)),
`descriptors` (D, N) (uint8 RootSIFT scaled as COLMAP stores it, or float for learned features),
`scores` (N,) float32 (for SIFT: the keypoint scale in pixels; larger first is a good ranking),
`image_size` (2,) int32 (width, height).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np


@dataclass
class Features:
    keypoints: np.ndarray  # (N, 2) float32, hloc pixel convention
    descriptors: np.ndarray  # (N, D)
    scores: np.ndarray  # (N,) float32
    image_size: tuple[int, int]  # (width, height)


def write_features(h5: h5py.File, name: str, feats: Features) -> None:
    if name in h5:
        del h5[name]
    grp = h5.create_group(name)
    grp.create_dataset("keypoints", data=np.asarray(feats.keypoints, np.float32))
    grp.create_dataset("descriptors", data=np.ascontiguousarray(np.asarray(feats.descriptors).T))
    grp.create_dataset("scores", data=np.asarray(feats.scores, np.float32))
    grp.create_dataset("image_size", data=np.asarray(feats.image_size, np.int32))


def read_features(path: Path, name: str, *, top_k: int | None = None) -> Features:
    """Features of one image; with `top_k`, only the k best by score (in decreasing score order)."""
    with h5py.File(path, "r") as h5:
        if name not in h5:
            raise KeyError(f"image {name!r} has no features in {path}")
        grp = h5[name]
        kp = grp["keypoints"][()]
        desc = grp["descriptors"][()].T
        scores = grp["scores"][()]
        size = tuple(int(v) for v in grp["image_size"][()])
    if top_k is not None and len(scores) > top_k:
        order = np.argsort(-scores, kind="stable")[:top_k]
        kp, desc, scores = kp[order], desc[order], scores[order]
    return Features(kp, desc, scores, size)  # type: ignore[arg-type]


def list_names(path: Path) -> list[str]:
    """Names of all images with features in an HDF5 file (nested groups joined with '/')."""
    names: list[str] = []
    with h5py.File(path, "r") as h5:
        def visit(name: str, obj: object) -> None:
            if isinstance(obj, h5py.Group) and "keypoints" in obj:
                names.append(name)
        h5.visititems(visit)
    return sorted(names)
