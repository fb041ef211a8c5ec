"""Pair selection on the scored candidate graph: `spanning` (maximum spanning forest, components,
tree paths) and `augment` (loops, anchors, weak views, and `select_pairs` that runs them all)."""

from .ambiguity import INCONSISTENT, CycleCheck, inconsistent_pairs, mark_inconsistent
from .augment import (
    ROLES,
    SELECTED_ROLES,
    Selection,
    capped_budgets,
    loop_gain,
    loop_length_thresholds,
    select_pairs,
    weak_views,
)
from .spanning import (
    RootedForest,
    connected_components,
    maximum_spanning_forest,
    tree_path_lengths,
)

__all__ = [
    "INCONSISTENT", "CycleCheck", "inconsistent_pairs", "mark_inconsistent",
    "ROLES", "SELECTED_ROLES", "RootedForest", "Selection", "capped_budgets", "connected_components", "loop_gain",
    "loop_length_thresholds", "maximum_spanning_forest", "select_pairs", "tree_path_lengths", "weak_views",
]
