"""COLMAP's SIFT matcher (ratio test, distance threshold, cross-check) and its geometric
verification, run by COLMAP inside the database: the default and fastest path for SIFT."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import colmap
from ..config import MatchConfig
from ..io.h5 import Features


class ColmapSiftMatcher:
    name = "colmap"
    #: what a call costs for each image it touches, in pairs' matching time: COLMAP builds the
    #: image's search index once per call (fountain-P11, 8,192 keypoints: about 1.6 s an image
    #: against 1.1 s a pair on a loaded CPU); the match stage's time estimate counts it
    image_cost_in_pairs = 1.5

    def __init__(self, conf: MatchConfig) -> None:
        self.conf = conf

    def match(self, feats0: Features, feats1: Features) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError("COLMAP's SIFT matcher runs inside the database (match_in_database)")

    def match_in_database(self, db_path: Path, pairs_path: Path) -> None:
        """Match and verify the pairs of a pairs file; pairs already verified are skipped by COLMAP."""
        conf = self.conf
        colmap.match_pairs(db_path, pairs_path, max_ratio=conf.max_ratio, max_distance=conf.max_distance,
                           cross_check=conf.cross_check, min_num_inliers=conf.min_num_inliers,
                           num_threads=conf.num_threads)


def make(conf: MatchConfig, features: str) -> ColmapSiftMatcher:
    if features != "sift":
        raise ValueError(f"the colmap matcher matches SIFT only, not {features!r} features; "
                         "use -s match.backend=auto (or nearest, lightglue)")
    return ColmapSiftMatcher(conf)
