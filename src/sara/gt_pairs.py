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
from .io.h5 import read_features
from .io import fingerprint, read_json, write_json_atomic

logger = logging.getLogger(__name__)

DEFAULT_MIN_MATCHES = 30
Pair = tuple[str, str]


@dataclass(frozen=True)
class GtView:
    K: np.ndarray  # (3, 3) float64 calibration, COLMAP pixels
    R: np.ndarray  # (3, 3) float64 cam_from_world rotation
    t: np.ndarray  # (3,) float64 cam_from_world translation
    size: tuple[int, int]  # (width, height) of the gt camera, pixels


def skew(v: np.ndarray) -> np.ndarray:
    """(3,) -> (3, 3) cross-product matrix: skew(a) @ b == cross(a, b)."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def fundamental_from_poses(view1: GtView, view2: GtView) -> np.ndarray:
    """(3, 3) F with x2^T F x1 = 0 for homogeneous pixels x1 in view 1 and x2 in view 2."""
    r_rel = view2.R @ view1.R.T
    t_rel = view2.t - r_rel @ view1.t
    essential = skew(t_rel) @ r_rel
    return np.linalg.inv(view2.K).T @ essential @ np.linalg.inv(view1.K)


def sampson_distance_px(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """(N,) Sampson distance (pixels: the square root of the Sampson error) of matches x1 <-> x2.

    x1, x2: (N, 2) pixel coordinates in views 1 and 2; F maps view 1 to view 2.
    """
    h1 = np.concatenate([np.asarray(x1, np.float64), np.ones((len(x1), 1))], axis=1)
    h2 = np.concatenate([np.asarray(x2, np.float64), np.ones((len(x2), 1))], axis=1)
    f_x1 = h1 @ F.T  # rows: F @ x1
    ft_x2 = h2 @ F  # rows: F^T @ x2
    numerator = np.einsum("ij,ij->i", h2, f_x1) ** 2
    denominator = f_x1[:, 0] ** 2 + f_x1[:, 1] ** 2 + ft_x2[:, 0] ** 2 + ft_x2[:, 1] ** 2
    return np.sqrt(numerator / np.maximum(denominator, 1e-300))


def mutual_nearest_neighbors(desc1: np.ndarray, desc2: np.ndarray) -> np.ndarray:
    """(M, 2) int64 index pairs (i, j) where desc1[i] and desc2[j] are each other's nearest neighbour.

    desc1, desc2: (N1, D), (N2, D) float32 rows with unit norm (similarity = dot product).
    """
    if len(desc1) == 0 or len(desc2) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    sim = desc1 @ desc2.T
    nn12 = np.argmax(sim, axis=1)
    nn21 = np.argmax(sim, axis=0)
    idx1 = np.flatnonzero(nn21[nn12] == np.arange(len(desc1)))
    return np.stack([idx1, nn12[idx1]], axis=1).astype(np.int64)


def read_gt_views(gt_dir: Path) -> dict[str, GtView]:
    """name -> GtView from a COLMAP model folder (PINHOLE cameras expected; others use their K)."""
    rec = colmap.read_model(gt_dir)
    views = {}
    for image in rec.images.values():
        cam = rec.cameras[image.camera_id]
        pose = image.cam_from_world()
        views[image.name] = GtView(
            K=np.asarray(cam.calibration_matrix(), dtype=np.float64),
            R=np.asarray(pose.rotation.matrix(), dtype=np.float64),
            t=np.asarray(pose.translation, dtype=np.float64).reshape(3),
            size=(int(cam.width), int(cam.height)),
        )
    return views


def _load_matching_features(features_path: Path, name: str, view: GtView,
                            num_keypoints: int) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (N, 2) in COLMAP pixels of the gt camera, descriptors (N, 128) float32 unit rows."""
    feats = read_features(features_path, name, top_k=num_keypoints)
    xy = colmap.hloc_to_colmap_keypoints(feats.keypoints).astype(np.float64)
    width, height = feats.image_size
    if (width, height) != view.size:  # images and gt at different resolutions: scale the pixels
        xy = xy * np.array([view.size[0] / width, view.size[1] / height])
    desc = np.asarray(feats.descriptors, dtype=np.float32)
    desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
    return xy, desc


def count_consistent_matches(xy1: np.ndarray, desc1: np.ndarray, xy2: np.ndarray, desc2: np.ndarray,
                             F: np.ndarray, max_epipolar_px: float) -> int:
    """Number of mutual-NN matches whose Sampson distance to F is below `max_epipolar_px`."""
    matches = mutual_nearest_neighbors(desc1, desc2)
    if len(matches) == 0:
        return 0
    dist = sampson_distance_px(F, xy1[matches[:, 0]], xy2[matches[:, 1]])
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
