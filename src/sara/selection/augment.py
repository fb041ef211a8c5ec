"""Pair selection on the candidate graph: a maximum spanning forest plus budgeted augmentation.

Images are nodes and scored candidate pairs are edges. Each candidate has a weight
``w = O^a * g(P)^b`` (overlap ``O``, a function of the parallax ``P``), computed by the
pre-matching scorer. Pairs are chosen in four stages, each under its own budget:

1. ``tree``: a maximum spanning forest of the accepted candidates (Kruskal). It keeps every
   connected component of the accepted graph connected with the strongest pairs available.
2. ``loop``: multi-scale loop consolidation. A non-tree edge ``(i, j)`` closes a cycle of
   ``L + 1`` edges, where ``L`` is the number of tree edges between ``i`` and ``j``. Closing
   cycles of several lengths constrains local structure (short loops) and drift along the
   tree (long loops).
3. ``anchor``: long-baseline anchors, the pairs with the best ``parallax * w``, spread so that
   no view receives more than ``anchor_max_per_view`` of them.
4. ``weak``: weak-view reinforcement: views that are barely attached to the selected graph
   get their best remaining candidates.

The core works on arrays: ``num_images`` and ``edges: (E, 2) int64`` with ``i < j``, unique.
Rejected candidates (``accepted == False``) are never selected. Everything is deterministic:
ties are broken by edge index, then by image index.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..config import GraphConfig
from .spanning import (
    RootedForest,
    _check_graph,
    _check_per_edge,
    connected_components,
    maximum_spanning_forest,
    take_capped_per_view,
)

logger = logging.getLogger(__name__)

ROLES = ("tree", "loop", "anchor", "weak", "unselected", "rejected")
"""Every role a candidate edge can have in a :class:`Selection`, selected ones first."""

SELECTED_ROLES = ("tree", "loop", "anchor", "weak")


# ----------------------------------------------------------------------------------------
# Augmentation
# ----------------------------------------------------------------------------------------


def loop_length_thresholds(diameter: int, conf: GraphConfig) -> tuple[int, int]:
    """``(s1, s2)`` in tree edges: short loops have L <= s1, long ones L > s2."""
    s1 = max(conf.loop_min_short_len, math.ceil(conf.loop_short_frac * diameter))
    s2 = max(s1 + 1, math.ceil(conf.loop_long_frac * diameter))
    return s1, s2


def loop_gain(path_length: np.ndarray, long_threshold: int) -> np.ndarray:
    """``gamma(L) = min(1, log(1 + L) / log(1 + s2))``: grows with L, 1 from ``L = s2`` on."""
    gain = np.log1p(np.asarray(path_length, dtype=np.float64)) / math.log1p(long_threshold)
    return np.minimum(1.0, gain)


def _split_budget(budget: int, fractions: tuple[float, ...]) -> np.ndarray:
    """Integer shares of ``budget`` proportional to ``fractions`` (largest remainder)."""
    raw = budget * np.asarray(fractions, dtype=np.float64) / np.sum(fractions)
    shares = np.floor(raw).astype(np.int64)
    by_remainder = np.lexsort((np.arange(len(raw)), -(raw - shares)))
    shares[by_remainder[: budget - shares.sum()]] += 1
    return shares


def _ranked(candidates: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Positions into ``candidates`` by score descending, then edge index ascending."""
    return np.lexsort((candidates, -score))


def _add_loops(
    role: np.ndarray, edges: np.ndarray, weight: np.ndarray, forest: RootedForest,
    budget: int, conf: GraphConfig,
) -> None:
    """Mark up to ``budget`` unselected accepted edges "loop": best ``w * gamma(L)`` per scale."""
    candidates = np.flatnonzero(role == "unselected")
    length = forest.path_lengths(edges[candidates])
    candidates, length = candidates[np.isfinite(length)], length[np.isfinite(length)]
    s1, s2 = loop_length_thresholds(forest.diameter(), conf)
    score = weight[candidates] * loop_gain(length, s2)
    scale = np.where(length <= s1, 0, np.where(length <= s2, 1, 2))
    order = _ranked(candidates, score)
    taken = np.zeros(len(candidates), dtype=bool)
    for s, share in enumerate(_split_budget(budget, conf.loop_scale_fractions)):
        taken[order[scale[order] == s][:share]] = True
    # What a scale could not use goes to the best remaining loops of any scale.
    leftover = budget - int(taken.sum())
    taken[order[~taken[order]][:leftover]] = True
    role[candidates[taken]] = "loop"
    logger.debug(
        "loops: s1=%d s2=%d, %d short, %d medium, %d long",
        s1, s2, *(int(np.sum(taken & (scale == s))) for s in range(3)),
    )


def _add_anchors(
    role: np.ndarray, edges: np.ndarray, weight: np.ndarray, parallax_deg: np.ndarray,
    budget: int, max_per_view: int,
) -> None:
    """Mark the best ``parallax * w`` unselected accepted edges as "anchor", capped per view."""
    candidates = np.flatnonzero(role == "unselected")
    score = parallax_deg[candidates] * weight[candidates]
    candidates, score = candidates[score > 0], score[score > 0]
    role[take_capped_per_view(candidates[_ranked(candidates, score)], edges, budget, max_per_view)] = "anchor"


def _median_incident_weight(num_images: int, edges: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(N,) float64 median weight of the edges at each image; NaN for images without edges."""
    view = np.concatenate([edges[:, 0], edges[:, 1]])
    w = np.concatenate([weight, weight])
    order = np.lexsort((w, view))
    view, w = view[order], w[order]
    count = np.bincount(view, minlength=num_images)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    has = count > 0
    median = np.full(num_images, np.nan)
    low = start[has] + (count[has] - 1) // 2
    high = start[has] + count[has] // 2
    median[has] = 0.5 * (w[low] + w[high])
    return median


def weak_views(
    num_images: int, edges: np.ndarray, weight: np.ndarray, role: np.ndarray, conf: GraphConfig
) -> np.ndarray:
    """Weak images, weakest first (lowest degree, then lowest median weight, then index).

    A view is weak when its degree in the selected graph is ``<= conf.weak_degree`` or its
    median accepted candidate weight is below the ``conf.weak_quantile`` quantile of all
    views' medians. Only views with at least one accepted candidate are considered.
    """
    selected = np.isin(role, SELECTED_ROLES)
    degree = np.bincount(edges[selected].ravel(), minlength=num_images)
    accepted = role != "rejected"
    median = _median_incident_weight(num_images, edges[accepted], weight[accepted])
    has = ~np.isnan(median)
    weak = has & (degree <= conf.weak_degree)
    if conf.weak_quantile > 0 and has.any():
        weak |= has & (median < np.quantile(median[has], conf.weak_quantile))
    views = np.flatnonzero(weak)
    return views[np.lexsort((views, median[views], degree[views]))]


def _add_weak(
    role: np.ndarray, edges: np.ndarray, weight: np.ndarray, num_images: int,
    budget: int, conf: GraphConfig,
) -> None:
    """Give each weak view up to ``conf.weak_per_view`` of its best unselected candidates."""
    views = weak_views(num_images, edges, weight, role, conf)
    candidates = np.flatnonzero(role == "unselected")
    candidates = candidates[_ranked(candidates, weight[candidates])]
    # Incident candidates of every view, best first (stable sort keeps the ranking).
    ends = np.concatenate([edges[candidates, 0], edges[candidates, 1]])
    incident = np.concatenate([candidates, candidates])
    by_view = np.argsort(ends, kind="stable")
    incident = incident[by_view]
    stop = np.cumsum(np.bincount(ends, minlength=num_images))
    start = stop - np.bincount(ends, minlength=num_images)
    added = 0
    for v in views.tolist():
        own = 0
        for e in incident[start[v]:stop[v]].tolist():
            if added == budget or own == conf.weak_per_view:
                break
            if role[e] == "unselected":
                role[e] = "weak"
                own += 1
                added += 1
        if added == budget:
            break


# ----------------------------------------------------------------------------------------
# Selection
# ----------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Selection:
    """The selected pairs and the role of every candidate.

    Attributes:
        num_images: number of images N.
        edges: (E, 2) int64 candidate pairs, as given.
        edge_index: (K,) int64 indices into ``edges`` of the selected pairs, ascending.
        role: (E,) str, one of :data:`ROLES` per candidate.
        components: (N,) int64 component labels of the accepted candidate graph
            (see :func:`connected_components`); the selected graph has the same components.
        num_components: number of components of the accepted candidate graph.
        budgets: pairs each augmentation was allowed to add ("loop", "anchor", "weak").
    """

    num_images: int
    edges: np.ndarray
    edge_index: np.ndarray
    role: np.ndarray
    components: np.ndarray
    num_components: int
    budgets: dict[str, int] = field(default_factory=dict)

    @property
    def selected_edges(self) -> np.ndarray:
        """(K, 2) int64 selected image pairs."""
        return self.edges[self.edge_index]

    def stats(self) -> dict[str, Any]:
        """JSON-serialisable summary: pairs per role, components, degrees of the selection."""
        selected = self.selected_edges
        degree = np.bincount(selected.ravel(), minlength=self.num_images)
        selected_labels = connected_components(self.num_images, selected)
        return {
            "num_images": int(self.num_images),
            "num_candidates": len(self.edges),
            "num_accepted": int(np.sum(self.role != "rejected")),
            "num_selected": len(self.edge_index),
            "pairs_per_role": {r: int(np.sum(self.role == r)) for r in ROLES},
            "budgets": {k: int(v) for k, v in self.budgets.items()},
            "num_components_accepted": int(self.num_components),
            "num_components_selected": int(selected_labels.max() + 1) if self.num_images else 0,
            "degree_min": int(degree.min()) if self.num_images else 0,
            "degree_median": float(np.median(degree)) if self.num_images else 0.0,
            "degree_max": int(degree.max()) if self.num_images else 0,
            "num_images_degree_0": int(np.sum(degree == 0)),
        }


def capped_budgets(budgets: dict[str, int], room: int) -> dict[str, int]:
    """The augmentation budgets scaled down (floor, in proportion) so that they sum to at most `room`."""
    total = sum(budgets.values())
    if total <= room:
        return dict(budgets)
    return {k: (v * room) // total for k, v in budgets.items()}


def _warn_if_disconnected(components: np.ndarray) -> None:
    sizes = np.bincount(components)
    if len(sizes) <= 1:
        return
    shown = ", ".join(str(s) for s in sizes[:20]) + (", ..." if len(sizes) > 20 else "")
    logger.warning(
        "The accepted candidate graph has %d connected components (sizes: %s); "
        "the selection spans each one separately and will reconstruct as separate models.",
        len(sizes), shown,
    )


def _accepted_weight(name: str, values: np.ndarray, accepted: np.ndarray) -> np.ndarray:
    """(E,) float64 `values`, checked per edge and finite, >= 0 where `accepted`."""
    values = _check_per_edge(name, values, len(accepted)).astype(np.float64)
    if not np.all(np.isfinite(values[accepted])) or np.any(values[accepted] < 0):
        raise ValueError(f"{name} must be finite and >= 0 for accepted pairs")
    return values


def select_pairs(
    num_images: int,
    edges: np.ndarray,
    weight: np.ndarray,
    parallax_deg: np.ndarray,
    accepted: np.ndarray,
    conf: GraphConfig | None = None,
    *,
    max_pairs: int | None = None,
    tree_weight: np.ndarray | None = None,
) -> Selection:
    """Choose the pairs to match: spanning forest, then loops, anchors and weak views.

    Args:
        num_images: number of images N (>= 1).
        edges: (E, 2) int64 candidate pairs, ``i < j``, unique.
        weight: (E,) float64 pair weight ``w``; finite and >= 0 for accepted pairs.
        parallax_deg: (E,) float64 parallax, degrees; finite for accepted pairs.
        accepted: (E,) bool; rejected pairs are never selected.
        conf: budgets and thresholds; defaults to ``GraphConfig()``.
        max_pairs: at most this many pairs in all (the augmentation budgets shrink in proportion;
            the spanning forest is always kept); None: no cap. The caller's pair budget gives it
            (SARA: `sara.pairs.sara.budget`).
        tree_weight: (E,) float64 the weight the spanning forest maximises (finite and >= 0 for
            accepted pairs); None: ``weight``. The augmentation always ranks by ``weight``.
    Returns:
        A :class:`Selection`; the same input always gives the same output.
    """
    conf = GraphConfig() if conf is None else conf
    if num_images < 1:
        raise ValueError(f"num_images must be >= 1, got {num_images}")
    edges = _check_graph(num_images, edges)
    parallax_deg = _check_per_edge("parallax_deg", parallax_deg, len(edges)).astype(np.float64)
    accepted = _check_per_edge("accepted", accepted, len(edges)).astype(bool)
    weight = _accepted_weight("weight", weight, accepted)
    tree_weight = weight if tree_weight is None else _accepted_weight("tree_weight", tree_weight, accepted)
    if not np.all(np.isfinite(parallax_deg[accepted])):
        raise ValueError("parallax_deg must be finite for accepted pairs")

    accepted_index = np.flatnonzero(accepted)
    components = connected_components(num_images, edges[accepted_index])
    _warn_if_disconnected(components)
    role = np.where(accepted, "unselected", "rejected").astype(f"<U{max(map(len, ROLES))}")
    forest_index = maximum_spanning_forest(
        num_images, edges[accepted_index], tree_weight[accepted_index]
    )
    tree = accepted_index[forest_index]
    role[tree] = "tree"

    budgets = conf.budgets(num_images)
    if max_pairs is not None:
        budgets = capped_budgets(budgets, max(0, max_pairs - len(tree)))
    if budgets["loop"] > 0:
        forest = RootedForest.from_edges(num_images, edges[tree])
        _add_loops(role, edges, weight, forest, budgets["loop"], conf)
    if budgets["anchor"] > 0:
        _add_anchors(
            role, edges, weight, parallax_deg, budgets["anchor"],
            conf.anchor_max_per_view,
        )
    if budgets["weak"] > 0:
        _add_weak(role, edges, weight, num_images, budgets["weak"], conf)

    selection = Selection(
        num_images=int(num_images),
        edges=edges,
        edge_index=np.flatnonzero(np.isin(role, SELECTED_ROLES)).astype(np.int64),
        role=role,
        components=components,
        num_components=int(components.max()) + 1,
        budgets=budgets,
    )
    logger.info("Selected pairs: %s", selection.stats()["pairs_per_role"])
    return selection
