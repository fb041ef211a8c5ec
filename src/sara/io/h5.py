"""Local features in HDF5 with hloc's layout.

One group per image name (sub-folders become nested groups), holding
`keypoints` (N, 2) float32 pixels in hloc's convention (centre of the top-left pixel at (0, 0)),
`descriptors` (D, N) unit-length float (float16 for SIFT, as hloc stores it; the COLMAP database keeps
COLMAP's uint8), any D,
`scores` (N,) float32 (for SIFT: the keypoint scale in pixels; larger first is a good ranking),
`image_size` (2,) int32 (width, height).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from . import DamagedOutputError, atomic_path, ensure_free_space, fingerprint

#: what h5py raises on a damaged file: OSError (truncated), RuntimeError (bad node), KeyError, ValueError
H5_ERRORS = (OSError, RuntimeError, KeyError, ValueError)


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


def has_features(h5: h5py.File, name: str) -> bool:
    """Whether `name` has a complete group (all four datasets) in an open file."""
    grp = h5.get(name)
    return isinstance(grp, h5py.Group) and all(k in grp for k in ("keypoints", "descriptors", "scores", "image_size"))


def read_features(path: Path, name: str, *, top_k: int | None = None) -> Features:
    """Features of one image; with `top_k`, only the k best by score (in decreasing score order)."""
    with h5py.File(path, "r") as h5:
        return _read_group(h5, name, path, top_k)


def read_open(h5: h5py.File, name: str, *, top_k: int | None = None) -> Features:
    """`read_features` from a file already open (one still being written, too)."""
    return _read_group(h5, name, Path(h5.filename), top_k)


def _read_group(h5: h5py.File, name: str, path: Path, top_k: int | None) -> Features:
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


class FeatureCache:
    """Features of a file by image name, read on demand and kept for the most recent images.

    The file is opened once and kept open; at most `capacity` images are held in memory.
    """

    def __init__(self, path: Path, *, capacity: int = 256, top_k: int | None = None) -> None:
        self.path, self.capacity, self.top_k = Path(path), capacity, top_k
        self._h5: h5py.File | None = None
        self._cache: dict[str, Features] = {}

    def get(self, name: str) -> Features:
        if name in self._cache:
            self._cache[name] = self._cache.pop(name)  # most recent last
            return self._cache[name]
        if self._h5 is None:
            self._h5 = h5py.File(self.path, "r")
        feats = _read_group(self._h5, name, self.path, self.top_k)
        self._cache[name] = feats
        if len(self._cache) > self.capacity:
            self._cache.pop(next(iter(self._cache)))
        return feats

    def close(self) -> None:
        if self._h5 is not None:
            self._h5.close()
            self._h5 = None

    def __enter__(self) -> FeatureCache:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def keypoint_counts(path: Path, names: list[str]) -> dict[str, int]:
    """How many keypoints each of `names` has in an HDF5 feature file (read from the dataset's shape)."""
    with h5py.File(path, "r") as h5:
        return {name: int(h5[name]["keypoints"].shape[0]) for name in names}


def groups_holding(h5: h5py.File, dataset: str) -> list[str]:
    """Sorted names of the groups that hold `dataset` (nested groups joined with '/'): image names."""
    names: list[str] = []

    def visit(name: str, obj: object) -> None:
        if isinstance(obj, h5py.Group) and dataset in obj:
            names.append(name)

    h5.visititems(visit)
    return sorted(names)


def list_names(path: Path) -> list[str]:
    """Names of all images with features in an HDF5 file."""
    with h5py.File(path, "r") as h5:
        return groups_holding(h5, "keypoints")


def features_digest(path: Path) -> dict[str, Any] | None:
    """What identifies a features file cheaply: its size, its image names and each one's keypoint
    and descriptor counts (None when the file does not exist).

    Raises DamagedOutputError when HDF5 cannot read it (truncated, overwritten, half written).
    """
    path = Path(path)
    if not path.is_file():
        return None
    try:
        with h5py.File(path, "r") as h5:
            names = groups_holding(h5, "keypoints")
            counts = [(n, int(h5[n]["keypoints"].shape[0]), int(h5[n]["descriptors"].shape[-1])) for n in names]
    except H5_ERRORS as exc:
        raise DamagedOutputError(f"{path} is damaged ({_first_line(exc)})") from None
    return {"size": path.stat().st_size, "num_images": len(names),
            "num_keypoints": sum(c[1] for c in counts), "digest": fingerprint(counts)}


def _first_line(exc: BaseException) -> str:
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


# ---------------------------------------------------------------------------------------------
# Global descriptors, hloc's layout: one group per image holding `global_descriptor` (D,)
# ---------------------------------------------------------------------------------------------


def write_global(path: Path, names: list[str], desc: np.ndarray, attrs: dict[str, str]) -> None:
    """Write global descriptors atomically: one group per name, root attributes `attrs`."""
    desc = np.asarray(desc, dtype=np.float32)
    ensure_free_space(Path(path).parent, 2 * desc.nbytes + 4096 * len(names))  # HDF5 crashes on a full disk
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as h5:
            for name, row in zip(names, desc):
                h5.create_group(name).create_dataset("global_descriptor", data=row)
            for key, value in attrs.items():
                h5.attrs[key] = value


def read_global(path: Path) -> tuple[list[str], np.ndarray]:
    """Image names (sorted) and their (N, D) float32 global descriptors."""
    with h5py.File(path, "r") as h5:
        names = groups_holding(h5, "global_descriptor")
        desc = np.stack([h5[n]["global_descriptor"][()] for n in names]) if names else np.zeros((0, 0))
    return names, desc.astype(np.float32, copy=False)


def stored_attribute(path: Path, key: str) -> str | None:
    """A root attribute of an h5 file, or None when the file is absent or damaged."""
    if not Path(path).exists():
        return None
    try:
        with h5py.File(path, "r") as h5:
            value = h5.attrs.get(key)
    except OSError:
        return None
    return value.decode() if isinstance(value, bytes) else value
