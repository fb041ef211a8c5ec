"""Stage `retrieval`: one global descriptor per image, then cosine kNN proposes candidate pairs.

Backends live behind the small `GlobalDescriptor` Protocol, one file each, in the registry
`DESCRIPTORS`. The default, `vlad`, needs no weights (see `vlad.py`); learned ones read pixels
from the image folder and load local weights (`sara weights`).

`global-<descriptor>.h5` is in hloc's layout: one group per image name holding
`global_descriptor` (D,) float32, L2-normalised; root attributes `fingerprint` (of the image
names, the config fields that shape the descriptors, the seed and the features file),
`descriptor` (backend name) and `config` (JSON).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from ..config import RetrievalConfig
from ..descriptors import l2_normalize, top_k_cosine
from ..io import fingerprint
from ..io.h5 import read_global, stored_attribute, write_global
from ..registry import Registry

logger = logging.getLogger(__name__)


@runtime_checkable
class GlobalDescriptor(Protocol):
    """One global descriptor per image, comparable by cosine similarity."""

    name: str

    def compute(self, features_path: Path, names: Sequence[str], conf: RetrievalConfig, *,
                images_root: Path | None = None, progress: bool = True, seed: int = 0) -> np.ndarray:
        """(N, D) float32 descriptors of `names` (in that order), each row L2-normalised.

        `seed` makes any randomness (codebook sampling, k-means) reproducible; deterministic
        backends ignore it.
        """
        ...


DESCRIPTORS: Registry = Registry("global descriptor", {
    "vlad": "sara.retrieval.vlad:VladDescriptor",
    "bow": "sara.retrieval.vlad:BowDescriptor",
    "dinov2": "sara.retrieval.learned:DinoV2Descriptor",
    "aliked-gem": "sara.retrieval.learned:AlikedGemDescriptor",
})


def get_descriptor(name: str) -> GlobalDescriptor:
    """The backend registered under `name`; an unknown name is a ValueError listing the valid ones."""
    return DESCRIPTORS.get(name)()


def global_file_name(conf: RetrievalConfig) -> str:
    return f"global-{conf.descriptor}.h5"


def knn_pairs(desc: np.ndarray, k: int) -> np.ndarray:
    """Top-k cosine neighbours of every image, as a symmetric union of undirected pairs.

    desc: (N, D) rows (normalised here, so any non-zero scale works). Returns (E, 2) int64 pairs
    with i < j, sorted, unique, no self pairs. Ties go to the lower index. With k >= N - 1 every
    pair is returned.
    """
    if k < 1:
        raise ValueError(f"num_neighbors must be at least 1, got {k}")
    nbrs = top_k_cosine(desc, k)
    if nbrs.shape[1] == 0:
        return np.zeros((0, 2), dtype=np.int64)
    rows = np.repeat(np.arange(len(nbrs)), nbrs.shape[1])
    pairs = np.sort(np.stack([rows, nbrs.reshape(-1)], axis=1), axis=1).astype(np.int64)
    return np.unique(pairs, axis=0)




def _key(conf: RetrievalConfig, features_path: Path, names: Sequence[str], seed: int) -> str:
    """Fingerprint of everything that shapes the descriptors (not the neighbour counts: kNN is cheap)."""
    stat = Path(features_path).stat()
    fields = {k: v for k, v in dataclasses.asdict(conf).items() if k not in ("num_neighbors", "widen_neighbors")}
    return fingerprint({"names": list(names), "conf": fields, "seed": seed,
                        "features": {"size": stat.st_size, "mtime_ns": stat.st_mtime_ns}})


def pairs_from_global(path: Path, num_neighbors: int) -> list[tuple[str, str]]:
    """Candidate pairs (name_i, name_j), i < j in file order: the symmetric kNN union."""
    names, desc = read_global(path)
    return [(names[i], names[j]) for i, j in knn_pairs(desc, num_neighbors)]


def run(conf: RetrievalConfig, features_path: Path, names: Sequence[str], out_dir: Path, *,
        images_root: Path | None = None, overwrite: bool = False, progress: bool = True, seed: int = 0) -> Path:
    """Compute the global descriptors of `names` into `out_dir/global-<descriptor>.h5`; returns its path.

    Rows are stored in sorted name order (read them back with `read_global`), so callers that pass
    the same images in another order share one file. Skipped when the file already holds
    descriptors of the same names, config, seed and features file (its `fingerprint` attribute).
    """
    features_path, out_path = Path(features_path), Path(out_dir) / global_file_name(conf)
    if not features_path.exists():
        raise FileNotFoundError(f"no features file at {features_path}: run the extract stage first")
    if not names:
        raise ValueError("no images to describe")
    backend = get_descriptor(conf.descriptor)
    names = sorted(set(names))  # rows in name order: the same file whatever order callers pass
    key = _key(conf, features_path, names, seed)
    if not overwrite and stored_attribute(out_path, "fingerprint") == key:
        logger.info("retrieval: %s is up to date, skipping", out_path)
        return out_path
    desc = np.asarray(backend.compute(features_path, names, conf, images_root=images_root, progress=progress,
                                     seed=seed))
    if desc.ndim != 2 or len(desc) != len(names):
        raise RuntimeError(f"descriptor {conf.descriptor!r} returned shape {desc.shape} for {len(names)} images")
    write_global(out_path, names, l2_normalize(desc),
                 {"fingerprint": key, "descriptor": conf.descriptor,
                  "config": json.dumps(dataclasses.asdict(conf), sort_keys=True)})
    return out_path
