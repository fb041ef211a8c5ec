"""The truth of a world: its poses, and which pairs of images truly overlap."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

import h5py
import numpy as np

from .config import TRUTH_NAME


class Truth:
    """The true poses and observations of a world, for judging selected pairs.

    Two images truly overlap when they observe at least `min_common` common 3D points (their
    keypoints with a 3D point, outliers aside, within the `max_keypoints` kept). Counts are
    computed for the pairs asked, never for all N^2.
    """

    def __init__(self, out_dir: Path, *, min_common: int = 20):
        self.min_common = int(min_common)
        with h5py.File(Path(out_dir) / TRUTH_NAME, "r") as h5:
            self.names = [n.decode() if isinstance(n, bytes) else str(n) for n in h5["names"][()]]
            self.offsets = h5["offsets"][()]
            self.point_ids = h5["point_ids"][()]
            self.R = h5["cam_from_world_R"][()]
            self.t = h5["cam_from_world_t"][()]
            self.centers = h5["centers"][()]
        self.index = {n: i for i, n in enumerate(self.names)}

    def observed(self, image: int | str) -> np.ndarray:
        """Sorted int32 ids of the 3D points an image observes."""
        i = self.index[image] if isinstance(image, str) else int(image)
        return self.point_ids[self.offsets[i]:self.offsets[i + 1]]

    def common_points(self, a: int | str, b: int | str) -> int:
        return int(np.intersect1d(self.observed(a), self.observed(b), assume_unique=True).size)

    def common_counts(self, pairs: Iterable[Sequence[int | str]]) -> np.ndarray:
        """(P,) int64 common 3D points of each pair (names or indices)."""
        return np.array([self.common_points(a, b) for a, b in pairs], dtype=np.int64)

    def overlaps(self, pairs: Iterable[Sequence[int | str]]) -> np.ndarray:
        """(P,) bool: the pair truly overlaps (at least `min_common` common points)."""
        return self.common_counts(pairs) >= self.min_common

    def relative_angle_deg(self, a: int | str, b: int | str) -> float:
        """Angle of the relative rotation between two cameras, degrees."""
        i = self.index[a] if isinstance(a, str) else int(a)
        j = self.index[b] if isinstance(b, str) else int(b)
        rel = self.R[j] @ self.R[i].T
        return float(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1))))
