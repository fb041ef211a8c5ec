"""Nearest-neighbour matching of any descriptors (uint8 SIFT or float), with COLMAP's tests.

Descriptors are compared by the angle between their L2-normalised vectors, as COLMAP's SIFT
matcher does (`acos` of the dot product, radians). A match i0 -> i1 is kept when:

- its angle is at most `match.max_distance` (COLMAP's default 0.7 rad, about 40 degrees);
- ratio test: its angle is below `match.max_ratio` times the angle to the second-nearest
  neighbour (in both directions with `cross_check`);
- `match.cross_check`: i0 is also the nearest neighbour of i1 (mutual nearest neighbours).

The mutual nearest neighbours and the normalisation are those of `sara.descriptors`, one
implementation for the scorer and this matcher.
"""

from __future__ import annotations

import numpy as np

from ..config import MatchConfig
from ..descriptors import l2_normalize, mutual_matches_from_similarity
from ..io.h5 import Features


def _second_best(similarity: np.ndarray, axis: int) -> np.ndarray:
    """The second-largest similarity along `axis` (-1 when there is none: any ratio passes)."""
    n = similarity.shape[axis]
    if n < 2:
        shape = similarity.shape[1 - axis]
        return np.full(shape, -1.0, np.float32)
    return np.take(np.partition(similarity, n - 2, axis=axis), n - 2, axis=axis)


def _angles(similarity: np.ndarray) -> np.ndarray:
    return np.arccos(np.clip(similarity, -1.0, 1.0))


def match_descriptors(
    desc0: np.ndarray, desc1: np.ndarray, *, max_ratio: float, max_distance: float, cross_check: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest neighbours of (N0, D) and (N1, D) descriptors that pass the tests of the module docstring.

    Returns:
        matches: (K, 2) int32 indices (i0, i1).
        similarity: (K,) float32 cosine similarity of each match, in decreasing order.
    """
    if np.ndim(desc0) != 2 or np.ndim(desc1) != 2:
        raise ValueError(f"descriptors must be (N, D), got shapes {np.shape(desc0)} and {np.shape(desc1)}")
    d0, d1 = l2_normalize(desc0), l2_normalize(desc1)
    if d0.shape[1] != d1.shape[1]:
        raise ValueError(f"descriptor sizes differ: {d0.shape[1]} and {d1.shape[1]}")
    if len(d0) == 0 or len(d1) == 0:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
    sim = d0 @ d1.T
    if cross_check:
        matches, values = mutual_matches_from_similarity(sim)
    else:
        best1 = sim.argmax(axis=1)
        values = sim[np.arange(len(sim)), best1]
        order = np.lexsort((np.arange(len(sim)), -values))
        matches = np.stack([order, best1[order]], axis=1).astype(np.int32)
        values = values[order].astype(np.float32)
    angle = _angles(values)
    keep = (angle <= max_distance) & (angle < max_ratio * _angles(_second_best(sim[matches[:, 0]], axis=1)))
    if cross_check:
        keep &= angle < max_ratio * _angles(_second_best(sim[:, matches[:, 1]], axis=0))
    return matches[keep], values[keep]


class NearestNeighbourMatcher:
    """Nearest neighbours with a ratio test, an angle threshold and an optional cross-check."""

    name = "nearest"

    def __init__(self, conf: MatchConfig) -> None:
        if not 0 < conf.max_ratio <= 1:
            raise ValueError(f"match.max_ratio must be in (0, 1], got {conf.max_ratio}")
        if not conf.max_distance > 0:
            raise ValueError(f"match.max_distance must be > 0 (radians), got {conf.max_distance}")
        self.max_ratio = conf.max_ratio
        self.max_distance = conf.max_distance
        self.cross_check = conf.cross_check

    def match(self, feats0: Features, feats1: Features) -> tuple[np.ndarray, np.ndarray]:
        """(K, 2) int32 indices and (K,) float32 cosine similarities (larger is better)."""
        return match_descriptors(feats0.descriptors, feats1.descriptors, max_ratio=self.max_ratio,
                                 max_distance=self.max_distance, cross_check=self.cross_check)


def make(conf: MatchConfig, features: str) -> NearestNeighbourMatcher:
    """The nearest-neighbour matcher; it works for the descriptors of any `features` backend."""
    return NearestNeighbourMatcher(conf)
