"""Two views: COLMAP's SIFT matching and geometric verification of listed pairs, and its RANSAC
fundamental matrix of given correspondences."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pycolmap

from .database import fisheye_focal_priors
from .native import native_errors

logger = logging.getLogger(__name__)

#: the seed of the verification's RANSAC: COLMAP's default (-1) draws from a generator per thread,
#: so a pair's inlier count depended on which thread verified it and what it had done before (two
#: identical runs: 216 against 217, 154 against 156 inliers); with a seed every pair draws the same
VERIFICATION_SEED = 0


def _verification_options(min_num_inliers: int) -> pycolmap.TwoViewGeometryOptions:
    """COLMAP's geometric verification settings: its defaults, `min_num_inliers`, a fixed RANSAC seed."""
    opts = pycolmap.TwoViewGeometryOptions()
    opts.min_num_inliers = min_num_inliers
    opts.ransac.random_seed = VERIFICATION_SEED
    return opts


def _fisheye_priors(db_path: Path) -> None:
    """Before COLMAP verifies pairs: the fisheye cameras' focal lengths made priors (said once per camera)."""
    if marked := fisheye_focal_priors(Path(db_path)):
        logger.info("fisheye camera%s %s: COLMAP takes the focal length guess as a prior, since it verifies "
                    "no pair of a fisheye camera without one; bundle adjustment refines it",
                    "s" if len(marked) > 1 else "", ", ".join(map(str, marked)))


def match_pairs(db_path: Path, pairs_path: Path, *, max_ratio: float, max_distance: float, cross_check: bool,
                min_num_inliers: int, num_threads: int = -1) -> None:
    """COLMAP's SIFT matching and geometric verification of the pairs in a file.

    Pairs already matched in the database are skipped by COLMAP, so this resumes.
    """
    mopts = pycolmap.FeatureMatchingOptions()
    mopts.num_threads = num_threads
    mopts.sift.max_ratio = max_ratio
    mopts.sift.max_distance = max_distance
    mopts.sift.cross_check = cross_check
    vopts = _verification_options(min_num_inliers)
    _fisheye_priors(db_path)
    with native_errors("match the pairs", Path(db_path).parent):
        pycolmap.match_image_pairs(
            str(db_path), matching_options=mopts,
            pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(pairs_path)),
            verification_options=vopts, device=pycolmap.Device.cpu,
        )


def verify_pairs(db_path: Path, pairs_path: Path, *, min_num_inliers: int) -> None:
    """COLMAP's geometric verification of the stored matches of the pairs in a pairs file."""
    _fisheye_priors(db_path)
    with native_errors("verify the matches", Path(db_path).parent):
        pycolmap.verify_matches(str(db_path), str(pairs_path), options=_verification_options(min_num_inliers))


def estimate_fundamental(points0: np.ndarray, points1: np.ndarray, *, max_error_px: float,
                         max_trials: int = 10000, seed: int = 0) -> tuple[np.ndarray, int] | None:
    """COLMAP's LO-RANSAC fundamental matrix of (N, 2) pixel correspondences: (F, number of inliers)
    with x1^T F x0 = 0, or None when it finds none."""
    if len(points0) < 8:
        return None
    options = pycolmap.RANSACOptions()
    options.max_error = max_error_px
    options.max_num_trials = max_trials
    options.random_seed = seed
    result = pycolmap.estimate_fundamental_matrix(np.asarray(points0, dtype=np.float64),
                                                  np.asarray(points1, dtype=np.float64), options)
    if result is None:
        return None
    return np.asarray(result["F"], dtype=np.float64), int(np.sum(result["inlier_mask"]))
