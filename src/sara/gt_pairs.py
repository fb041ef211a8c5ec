"""Which image pairs truly overlap, judged from ground-truth poses (for measurements, not the pipeline).

A pair's overlap count is the number of mutual-nearest-neighbour SIFT matches (between each image's
`num_keypoints` largest-scale keypoints) whose Sampson distance to the ground-truth epipolar
geometry is below `max_epipolar_px` pixels.

Conventions: poses are `cam_from_world` (x_cam = R @ X + t); pixel coordinates are COLMAP's (centre
of the top-left pixel at (0.5, 0.5)). `features.h5` keypoints use hloc's convention and are
converted with `colmap.hloc_to_colmap_keypoints` (+0.5). The fundamental matrix F maps image 1 to
image 2: x2^T F x1 = 0 for homogeneous pixel coordinates.
"""

from __future__ import annotations

import hashlib
import itertools
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import colmap
from .descriptors import l2_normalize, mutual_nearest_neighbours
from .io import fingerprint, read_json, write_json_atomic
from .io.h5 import read_features
from .scoring.twoview import sampson_distance, skew

logger = logging.getLogger(__name__)

DEFAULT_MIN_MATCHES = 30
Pair = tuple[str, str]


@dataclass(frozen=True)
class GtView:
    K: np.ndarray  # (3, 3) float64 calibration, COLMAP pixels
    R: np.ndarray  # (3, 3) float64 cam_from_world rotation
    t: np.ndarray  # (3,) float64 cam_from_world translation
    size: tuple[int, int]  # (width, height) of the gt camera, pixels


def fundamental_from_poses(view1: GtView, view2: GtView) -> np.ndarray:
    """(3, 3) F with x2^T F x1 = 0 for homogeneous pixels x1 in view 1 and x2 in view 2."""
    r_rel = view2.R @ view1.R.T
    t_rel = view2.t - r_rel @ view1.t
    essential = skew(t_rel) @ r_rel
    return np.linalg.inv(view2.K).T @ essential @ np.linalg.inv(view1.K)


def read_gt_views(gt_dir: Path) -> dict[str, GtView]:
    """name -> GtView from a COLMAP model folder (PINHOLE cameras expected; others use their K)."""
    views = colmap.cameras_and_poses(gt_dir)
    return {name: GtView(K=K, R=R, t=t, size=size) for name, (K, R, t, size) in views.items()}


def _load_matching_features(features_path: Path, name: str, view: GtView,
                            num_keypoints: int) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (N, 2) in COLMAP pixels of the gt camera, descriptors (N, 128) float32 unit rows."""
    feats = read_features(features_path, name, top_k=num_keypoints)
    xy = colmap.hloc_to_colmap_keypoints(feats.keypoints).astype(np.float64)
    width, height = feats.image_size
    if (width, height) != view.size:  # images and gt at different resolutions: scale the pixels
        xy = xy * np.array([view.size[0] / width, view.size[1] / height])
    return xy, l2_normalize(feats.descriptors, axis=1)


def count_consistent_matches(xy1: np.ndarray, desc1: np.ndarray, xy2: np.ndarray, desc2: np.ndarray,
                             F: np.ndarray, max_epipolar_px: float) -> int:
    """Number of mutual-NN matches whose Sampson distance to F is below `max_epipolar_px`."""
    matches, _ = mutual_nearest_neighbours(desc1, desc2)
    if len(matches) == 0:
        return 0
    dist = sampson_distance(F, xy1[matches[:, 0]], xy2[matches[:, 1]])
    return int((dist < max_epipolar_px).sum())


def _cache_key(gt_dir: Path, features_path: Path, names: Sequence[str], num_keypoints: int,
               max_epipolar_px: float) -> str:
    digest = hashlib.sha256()
    for fname in ("cameras.txt", "images.txt", "cameras.bin", "images.bin"):
        if (Path(gt_dir) / fname).exists():
            digest.update((Path(gt_dir) / fname).read_bytes())
    stat = Path(features_path).stat()
    return fingerprint({"gt": digest.hexdigest(), "features": [stat.st_size, stat.st_mtime_ns],
                        "names": list(names), "num_keypoints": num_keypoints, "max_px": max_epipolar_px})


def gt_overlap_counts(gt_dir: Path, features_path: Path, names: Sequence[str], *, num_keypoints: int = 2048,
                      max_epipolar_px: float = 2.0, cache_dir: Path | None = None,
                      progress: bool = True) -> dict[Pair, int]:
    """(name_i, name_j) -> number of gt-consistent mutual-NN matches, for every pair of `names`.

    Keys follow the order of `names` (name_i before name_j). With `cache_dir`, results are stored
    as JSON keyed by the gt files, the features file, the names and the settings, and reused.
    """
    names = list(names)
    cache_path = None
    if cache_dir is not None:
        key = _cache_key(gt_dir, features_path, names, num_keypoints, max_epipolar_px)
        cache_path = Path(cache_dir) / f"{Path(gt_dir).resolve().parent.name}-{key}.json"
        if cache_path.exists():
            return {(a, b): int(n) for a, b, n in read_json(cache_path)["counts"]}
    views = read_gt_views(gt_dir)
    missing = [n for n in names if n not in views]
    if missing:
        raise ValueError(f"{len(missing)} images have no ground-truth pose in {gt_dir}, e.g. {missing[0]!r}")
    loaded = [_load_matching_features(features_path, n, views[n], num_keypoints) for n in names]
    counts: dict[Pair, int] = {}
    all_pairs = list(itertools.combinations(range(len(names)), 2))
    for i, j in tqdm(all_pairs, desc="gt overlaps", unit="pair", disable=not progress):
        F = fundamental_from_poses(views[names[i]], views[names[j]])
        counts[(names[i], names[j])] = count_consistent_matches(*loaded[i], *loaded[j], F, max_epipolar_px)
    if cache_path is not None:
        write_json_atomic(cache_path, {"gt_dir": str(gt_dir), "num_keypoints": num_keypoints,
                                       "max_epipolar_px": max_epipolar_px,
                                       "counts": [[a, b, n] for (a, b), n in counts.items()]})
    return counts


def overlapping_pairs(counts: dict[Pair, int], min_matches: int = DEFAULT_MIN_MATCHES) -> set[Pair]:
    """Pairs with at least `min_matches` gt-consistent matches."""
    return {pair for pair, n in counts.items() if n >= min_matches}


def strong_pairs(counts: dict[Pair, int], min_matches: int = DEFAULT_MIN_MATCHES,
                 fraction: float = 0.5) -> set[Pair]:
    """The top `fraction` of the overlapping pairs by gt-consistent match count (ties kept together)."""
    values = sorted((n for n in counts.values() if n >= min_matches), reverse=True)
    if not values:
        return set()
    cutoff = values[max(0, int(np.ceil(fraction * len(values))) - 1)]
    return {pair for pair, n in counts.items() if n >= max(cutoff, min_matches)}


def canonical(pairs: Iterable[Pair], order: Sequence[str]) -> set[Pair]:
    """Pairs with their names put in the order of `order` (so sets from different sources compare)."""
    rank = {n: i for i, n in enumerate(order)}
    return {(a, b) if rank[a] < rank[b] else (b, a) for a, b in pairs}
