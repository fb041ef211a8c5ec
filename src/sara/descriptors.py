"""Primitives on descriptors, one implementation each: normalisation, mutual nearest neighbours,
top-k cosine neighbours by blocks. A leaf: numpy only.
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-12
KNN_BLOCK_ROWS = 1024  # rows of a similarity matrix held at once by `top_k_cosine`


def l2_normalize(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """`x` (uint8 RootSIFT as COLMAP stores it, or float) as float32 scaled to unit L2 norm along
    `axis`; all-zero vectors stay zero. Always a new array."""
    x = np.asarray(x, dtype=np.float32)
    norm = np.linalg.norm(x, axis=axis, keepdims=True)
    return x / np.maximum(norm, _EPS)


def mutual_nearest_neighbours(
    desc0: np.ndarray, desc1: np.ndarray, max_matches: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours by cosine similarity of L2-normalised descriptors.

    Args:
        desc0: (N0, D) descriptors of image 0 (uint8 or float; normalised here).
        desc1: (N1, D) descriptors of image 1.
        max_matches: keep only the best this many matches (all when None).
    Returns:
        See :func:`mutual_matches_from_similarity`.
    """
    d0, d1 = np.asarray(desc0), np.asarray(desc1)
    if d0.ndim != 2 or d1.ndim != 2:
        raise ValueError(f"descriptors must be (N, D), got shapes {d0.shape} and {d1.shape}")
    if d0.shape[1] != d1.shape[1]:
        raise ValueError(f"descriptor sizes differ: {d0.shape[1]} and {d1.shape[1]}")
    return mutual_matches_from_similarity(l2_normalize(d0, axis=1) @ l2_normalize(d1, axis=1).T, max_matches)


def mutual_matches_from_similarity(
    similarity: np.ndarray, max_matches: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours in a similarity matrix (larger is more similar).

    Args:
        similarity: (N0, N1) float, e.g. dot products of unit descriptors.
        max_matches: keep only the best this many matches (all when None).
    Returns:
        matches: (K, 2) int32 indices ``(i0, i1)``; i1 is the nearest neighbour of i0 in image 1
            and i0 the nearest neighbour of i1 in image 0.
        similarity: (K,) float32, in decreasing order; equal similarities are ordered by i0.
            Equal-similarity neighbours resolve to the lowest index.
    """
    sim = np.asarray(similarity)
    if sim.ndim != 2:
        raise ValueError(f"similarity must be (N0, N1), got shape {sim.shape}")
    if max_matches is not None and max_matches < 0:
        raise ValueError(f"max_matches must be >= 0, got {max_matches}")
    if sim.size == 0:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
    best1 = sim.argmax(axis=1)  # nearest neighbour in image 1 of each i0 (first on ties)
    best_sim = sim[np.arange(len(sim)), best1]
    # i0 is also the nearest neighbour of best1[i0] when it reaches that column's maximum.
    # (A column max is cheap; a column argmax of a C-ordered matrix is not.)
    i0 = np.flatnonzero(best_sim >= sim.max(axis=0)[best1])
    # On an exact tie several rows may reach one column's maximum: keep the lowest row.
    i1, first = np.unique(best1[i0], return_index=True)
    i0 = i0[first]
    values = best_sim[i0]
    order = np.lexsort((i0, -values))[:max_matches]
    matches = np.stack([i0[order], i1[order]], axis=1).astype(np.int32)
    return matches, values[order].astype(np.float32)


def descriptor_distance_ratios(similarity: np.ndarray, matches: np.ndarray) -> np.ndarray:
    """Lowe's ratio of each match: its descriptor distance over the distance to the second-best
    candidate, in either image (the larger of the two ratios).

    Args:
        similarity: (N0, N1) dot products of unit descriptors; a distance is ``sqrt(2 - 2 s)``.
        matches: (K, 2) int indices ``(i0, i1)`` of nearest neighbours (e.g. mutual ones).
    Returns:
        (K,) float64 ratios in [0, 1]; 0 where the match is an exact copy, 1 where a second
        candidate is as near (or an image has a single descriptor: no evidence that it is distinct).
    """
    sim = np.asarray(similarity, dtype=np.float64)
    matches = np.asarray(matches).reshape(-1, 2)
    if len(matches) == 0:
        return np.zeros(0)
    i0, i1 = matches[:, 0], matches[:, 1]
    best = sim[i0, i1]

    def second_best(rows: np.ndarray) -> np.ndarray:  # second largest of each row
        if rows.shape[1] < 2:
            return best
        return np.partition(rows, -2, axis=1)[:, -2]

    second = np.maximum(second_best(sim[i0]), second_best(sim[:, i1].T))
    nearest = np.sqrt(np.maximum(2.0 - 2.0 * best, 0.0))
    runner_up = np.sqrt(np.maximum(2.0 - 2.0 * second, 0.0))
    return np.where(runner_up > _EPS, nearest / np.maximum(runner_up, _EPS), 1.0).clip(0.0, 1.0)


def top_k_cosine(desc: np.ndarray, k: int, queries: np.ndarray | None = None) -> np.ndarray:
    """The k most cosine-similar rows of `desc` for each query row (itself excluded), by blocks of
    rows so that memory is O(block * N), never N x N.

    desc: (N, D) rows (normalised here). queries: row indices (default: all). Returns (Q, k') int64
    row indices, best first, k' = min(k, N - 1); ties go to the lower index.
    """
    x = l2_normalize(desc, axis=1)
    rows_all = np.arange(len(x)) if queries is None else np.asarray(queries, dtype=np.int64)
    k = min(k, len(x) - 1)
    if k < 1 or len(rows_all) == 0:
        return np.zeros((len(rows_all), 0), dtype=np.int64)
    out = []
    for start in range(0, len(rows_all), KNN_BLOCK_ROWS):
        rows = rows_all[start:start + KNN_BLOCK_ROWS]
        sim = x[rows] @ x.T
        sim[np.arange(len(rows)), rows] = -np.inf
        best = np.argsort(-sim, axis=1, kind="stable")[:, :k]
        out.append(best.astype(np.int64))
    return np.concatenate(out)
