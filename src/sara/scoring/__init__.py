"""The pre-matching scorer: `twoview` holds the pure geometry, `scorer` scores candidate pairs.

The names most callers need are re-exported here.
"""

from ..descriptors import l2_normalize as normalize_descriptors
from ..descriptors import mutual_matches_from_similarity, mutual_nearest_neighbours
from ..io.scores import CSV_COLUMNS, PairScores, read_scores_csv, write_scores_csv
from .journal import ScoreJournal
from .scorer import (
    REASONS,
    PairScore,
    ViewFeatures,
    load_views,
    pair_weight,
    rejection_reason,
    score_pair,
    score_pairs,
    tree_weights,
)
from .twoview import (
    FOCAL_SCALES,
    RelativePose,
    estimate_homography,
    estimate_relative_pose,
    explained_by_rotation,
    inlier_parallax_deg,
    rotation_focal_scale,
    rotation_residuals,
    sampson_errors,
    triangulation_angles_deg,
)

__all__ = [
    "FOCAL_SCALES",
    "CSV_COLUMNS", "REASONS", "PairScore", "PairScores", "RelativePose", "ScoreJournal", "ViewFeatures",
    "estimate_homography",
    "estimate_relative_pose", "explained_by_rotation", "inlier_parallax_deg", "load_views",
    "mutual_matches_from_similarity", "mutual_nearest_neighbours", "normalize_descriptors", "pair_weight",
    "read_scores_csv", "rejection_reason", "rotation_focal_scale", "rotation_residuals", "sampson_errors",
    "score_pair", "score_pairs", "tree_weights", "triangulation_angles_deg", "write_scores_csv",
]
