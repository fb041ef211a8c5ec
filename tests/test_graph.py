"""Tests of the pair graph: spanning forest, components, tree paths and augmentation."""

from __future__ import annotations

import itertools
import json
import logging

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import minimum_spanning_tree, shortest_path

from sara.config import GraphConfig
from sara.selection import (
    RootedForest,
    connected_components,
    loop_length_thresholds,
    maximum_spanning_forest,
    select_pairs,
    tree_path_lengths,
)

NO_AUGMENTATION = GraphConfig(use_loops=False, use_anchors=False, use_weak=False)


def random_graph(rng: np.random.Generator, num_images: int, density: float) -> np.ndarray:
    """(E, 2) int64 random unique pairs with i < j."""
    pairs = np.array(list(itertools.combinations(range(num_images), 2)), dtype=np.int64)
    return pairs[rng.random(len(pairs)) < density].reshape(-1, 2)


def random_candidates(seed: int) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    num_images = int(rng.integers(2, 40))
    edges = random_graph(rng, num_images, float(rng.uniform(0.05, 0.5)))
    weight = rng.uniform(0.05, 1.0, len(edges))
    parallax_deg = rng.uniform(0.0, 30.0, len(edges))
    accepted = rng.random(len(edges)) < 0.8
    return num_images, edges, weight, parallax_deg, accepted


def num_components(num_images: int, edges: np.ndarray) -> int:
    return int(connected_components(num_images, edges).max()) + 1


def is_forest(num_images: int, edges: np.ndarray) -> bool:
    return len(edges) == num_images - num_components(num_images, edges)


# ----------------------------------------------------------------------------------------
# Spanning forest
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(40))
def test_spanning_forest_weight_matches_scipy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    num_images = int(rng.integers(1, 30))
    edges = random_graph(rng, num_images, float(rng.uniform(0.02, 0.6)))
    weight = rng.uniform(0.1, 1.0, len(edges))
    chosen = maximum_spanning_forest(num_images, edges, weight)

    expected_count = num_images - num_components(num_images, edges)
    assert len(chosen) == expected_count
    assert len(np.unique(chosen)) == len(chosen)
    assert is_forest(num_images, edges[chosen])
    # Same components as the whole graph.
    np.testing.assert_array_equal(
        connected_components(num_images, edges[chosen]), connected_components(num_images, edges)
    )
    # scipy's minimum spanning forest of the negated weights (weights are non-zero).
    graph = coo_matrix((-weight, (edges[:, 0], edges[:, 1])), shape=(num_images, num_images))
    expected = -minimum_spanning_tree(graph).sum()
    assert weight[chosen].sum() == pytest.approx(expected, rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("seed", range(15))
def test_spanning_forest_weight_matches_brute_force(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    num_images = int(rng.integers(2, 7))
    edges = random_graph(rng, num_images, 0.6)[:10]
    # Few distinct values, so ties happen.
    weight = rng.integers(1, 4, len(edges)).astype(np.float64)
    size = num_images - num_components(num_images, edges)
    best = max(
        weight[list(subset)].sum()
        for subset in itertools.combinations(range(len(edges)), size)
        if is_forest(num_images, edges[list(subset)])
    ) if size else 0.0
    chosen = maximum_spanning_forest(num_images, edges, weight)
    assert len(chosen) == size
    assert weight[chosen].sum() == best


def test_spanning_forest_ties_broken_by_edge_index() -> None:
    edges = np.array([[0, 1], [1, 2], [0, 2], [2, 3], [1, 3]])
    weight = np.ones(5)
    np.testing.assert_array_equal(maximum_spanning_forest(4, edges, weight), [0, 1, 3])
    weight = np.array([1.0, 1.0, 2.0, 1.0, 1.0])
    np.testing.assert_array_equal(maximum_spanning_forest(4, edges, weight), [0, 2, 3])


def test_spanning_forest_of_disconnected_graph() -> None:
    # Triangle {0, 1, 2}, pair {3, 4}, isolated 5.
    edges = np.array([[0, 1], [0, 2], [1, 2], [3, 4]])
    weight = np.array([0.5, 0.9, 0.7, 0.1])
    np.testing.assert_array_equal(maximum_spanning_forest(6, edges, weight), [1, 2, 3])
    assert len(maximum_spanning_forest(3, np.zeros((0, 2), np.int64), np.zeros(0))) == 0


@pytest.mark.parametrize(
    "edges",
    [[[1, 0]], [[1, 1]], [[0, 1], [0, 1]], [[0, 5]], [[0.0, 1.0]]],
    ids=["order", "self", "duplicate", "range", "float"],
)
def test_bad_edges_raise(edges: list) -> None:
    with pytest.raises(ValueError):
        maximum_spanning_forest(3, np.array(edges), np.ones(len(edges)))


# ----------------------------------------------------------------------------------------
# Components
# ----------------------------------------------------------------------------------------


def test_connected_components_hand_made() -> None:
    # {0, 5} size 2, {1, 2, 3} size 3, {4} size 1, {6, 7} size 2, {8} size 1.
    edges = np.array([[0, 5], [1, 2], [2, 3], [6, 7]])
    labels = connected_components(9, edges)
    np.testing.assert_array_equal(labels, [1, 0, 0, 0, 3, 1, 2, 2, 4])
    np.testing.assert_array_equal(connected_components(3, np.zeros((0, 2), np.int64)), [0, 1, 2])


# ----------------------------------------------------------------------------------------
# Tree paths
# ----------------------------------------------------------------------------------------


def test_tree_path_lengths_on_path_graph() -> None:
    # Path 3 - 0 - 4 - 1 - 2: the root (image 0) sits inside the path.
    tree = np.array([[0, 3], [0, 4], [1, 4], [1, 2]])
    pairs = np.array([[2, 3], [0, 1], [3, 4], [2, 2], [1, 3], [0, 2]])
    np.testing.assert_array_equal(tree_path_lengths(5, tree, pairs), [4, 2, 2, 0, 3, 3])
    assert RootedForest.from_edges(5, tree).diameter() == 4


def test_tree_path_lengths_on_star() -> None:
    tree = np.array([[0, 5], [1, 5], [2, 5], [3, 5], [4, 5]])
    pairs = np.array([[0, 1], [3, 4], [0, 5], [4, 5]])
    np.testing.assert_array_equal(tree_path_lengths(6, tree, pairs), [2, 2, 1, 1])
    assert RootedForest.from_edges(6, tree).diameter() == 2


def test_tree_path_lengths_across_trees_are_infinite() -> None:
    tree = np.array([[0, 1], [2, 3]])
    pairs = np.array([[0, 1], [1, 2], [0, 4], [2, 3]])
    np.testing.assert_array_equal(tree_path_lengths(5, tree, pairs), [1, np.inf, np.inf, 1])


def test_rooted_forest_rejects_cycles() -> None:
    with pytest.raises(ValueError, match="cycle"):
        RootedForest.from_edges(3, np.array([[0, 1], [1, 2], [0, 2]]))


@pytest.mark.parametrize("seed", range(10))
def test_tree_path_lengths_match_bfs(seed: int) -> None:
    rng = np.random.default_rng(200 + seed)
    num_images = int(rng.integers(2, 300))
    edges = random_graph(rng, num_images, 4.0 / num_images)
    tree = edges[maximum_spanning_forest(num_images, edges, rng.random(len(edges)))]
    graph = coo_matrix((np.ones(len(tree)), (tree[:, 0], tree[:, 1])), (num_images, num_images))
    distance = shortest_path(graph, directed=False, unweighted=True)
    pairs = rng.integers(0, num_images, (500, 2))
    lengths = tree_path_lengths(num_images, tree, pairs)
    np.testing.assert_array_equal(lengths, distance[pairs[:, 0], pairs[:, 1]])
    finite = distance[np.isfinite(distance)]
    assert RootedForest.from_edges(num_images, tree).diameter() == int(finite.max())


# ----------------------------------------------------------------------------------------
# Augmentation invariants
# ----------------------------------------------------------------------------------------


def check_invariants(
    num_images: int, edges: np.ndarray, accepted: np.ndarray, conf: GraphConfig
) -> None:
    weight = np.random.default_rng(num_images).uniform(0.05, 1.0, len(edges))
    parallax_deg = np.random.default_rng(num_images + 1).uniform(0.0, 30.0, len(edges))
    selection = select_pairs(num_images, edges, weight, parallax_deg, accepted, conf)
    index = selection.edge_index
    selected = edges[index]
    # No duplicate or self pairs, nothing rejected.
    assert len(np.unique(index)) == len(index)
    assert np.all(selected[:, 0] < selected[:, 1])
    assert np.all(accepted[index])
    np.testing.assert_array_equal(selection.role == "rejected", ~accepted)
    np.testing.assert_array_equal(np.isin(selection.role, ["unselected", "rejected"]).sum(),
                                  len(edges) - len(index))
    # Each budget respected.
    for role, budget in selection.budgets.items():
        assert np.sum(selection.role == role) <= budget
    # Same components as the accepted graph (connected whenever the accepted graph is).
    accepted_labels = connected_components(num_images, edges[accepted])
    np.testing.assert_array_equal(connected_components(num_images, selected), accepted_labels)
    np.testing.assert_array_equal(selection.components, accepted_labels)
    # The tree is exactly the maximum spanning forest of the accepted candidates.
    accepted_index = np.flatnonzero(accepted)
    forest = accepted_index[maximum_spanning_forest(num_images, edges[accepted], weight[accepted])]
    np.testing.assert_array_equal(np.flatnonzero(selection.role == "tree"), forest)
    stats = selection.stats()
    json.dumps(stats)
    assert stats["num_components_selected"] == stats["num_components_accepted"]
    assert stats["num_selected"] == len(index)


@pytest.mark.parametrize("seed", range(30))
def test_augmentation_invariants_on_random_graphs(seed: int) -> None:
    num_images, edges, _, _, accepted = random_candidates(seed)
    for conf in (
        GraphConfig(),
        GraphConfig(loop_budget_ratio=2.0, anchor_budget_ratio=1.0, weak_budget_ratio=1.0),
        GraphConfig(anchor_max_per_view=2, weak_per_view=3, weak_degree=2, weak_quantile=0.5),
        NO_AUGMENTATION,
    ):
        check_invariants(num_images, edges, accepted, conf)


@pytest.mark.parametrize("seed", range(20))
def test_each_augmentation_alone_adds_only_its_role(seed: int) -> None:
    num_images, edges, weight, parallax_deg, accepted = random_candidates(seed)
    base = select_pairs(num_images, edges, weight, parallax_deg, accepted, NO_AUGMENTATION)
    assert set(base.role.tolist()) <= {"tree", "unselected", "rejected"}
    tree = np.flatnonzero(base.role == "tree")
    np.testing.assert_array_equal(base.edge_index, tree)
    flags = {"loop": "use_loops", "anchor": "use_anchors", "weak": "use_weak"}
    for role, flag in flags.items():
        only = {f: f == flag for f in flags.values()}
        selection = select_pairs(
            num_images, edges, weight, parallax_deg, accepted, GraphConfig(**only)
        )
        assert set(selection.role.tolist()) <= {"tree", role, "unselected", "rejected"}
        np.testing.assert_array_equal(np.flatnonzero(selection.role == "tree"), tree)
    # A budget ratio of 0 disables an augmentation as well.
    zero = GraphConfig(loop_budget_ratio=0, anchor_budget_ratio=0, weak_budget_ratio=0)
    selection = select_pairs(num_images, edges, weight, parallax_deg, accepted, zero)
    np.testing.assert_array_equal(selection.edge_index, tree)


@pytest.mark.parametrize("seed", range(20))
def test_loops_fill_their_budget(seed: int) -> None:
    num_images, edges, weight, parallax_deg, accepted = random_candidates(seed)
    conf = GraphConfig(use_anchors=False, use_weak=False)
    selection = select_pairs(num_images, edges, weight, parallax_deg, accepted, conf)
    available = int(accepted.sum()) - int(np.sum(selection.role == "tree"))
    # Scales lend each other what they cannot use, so the budget is used whenever possible.
    assert np.sum(selection.role == "loop") == min(selection.budgets["loop"], available)


def test_loops_split_across_scales() -> None:
    # Path 0-1-...-9 as the tree (diameter 9): s1 = 3 and s2 = 4.
    path = np.array([[i, i + 1] for i in range(9)])
    chords = np.array([[0, 2], [1, 3], [0, 3], [0, 4], [0, 9], [1, 8]])
    edges = np.concatenate([path, chords])
    weight = np.concatenate([np.full(9, 10.0), [0.9, 0.8, 0.7, 0.3, 0.2, 0.5]])
    accepted = np.ones(len(edges), dtype=bool)
    conf = GraphConfig(use_anchors=False, use_weak=False, loop_budget_ratio=0.3)
    assert loop_length_thresholds(9, conf) == (3, 4)
    selection = select_pairs(10, edges, weight, np.zeros(len(edges)), accepted, conf)
    loops = {tuple(e) for e in edges[selection.role == "loop"].tolist()}
    # Best short (0, 2), the only medium (0, 4), best long (1, 8): not the three heaviest.
    assert loops == {(0, 2), (0, 4), (1, 8)}
    # Without a medium loop its share flows to the best remaining loop of any scale.
    keep = ~np.all(edges == [0, 4], axis=1)
    selection = select_pairs(10, edges[keep], weight[keep], np.zeros(keep.sum()),
                             accepted[keep], conf)
    loops = {tuple(e) for e in edges[keep][selection.role == "loop"].tolist()}
    # Scores w * gamma(L): (0, 3) 0.7 * log(4) / log(5) = 0.60 beats
    # (1, 3) 0.8 * log(3) / log(5) = 0.55.
    assert loops == {(0, 2), (1, 8), (0, 3)}


def test_anchors_spread_over_views() -> None:
    # Hub 0 has the widest baselines to every view; a path 1-2-...-7 is the strong backbone.
    hub = np.array([[0, j] for j in range(1, 8)])
    path = np.array([[j, j + 1] for j in range(1, 7)])
    extra = np.array([[1, 3], [2, 5], [4, 7], [3, 6]])
    edges = np.concatenate([hub, path, extra])
    weight = np.concatenate([np.full(7, 0.2), np.full(6, 1.0), np.full(4, 0.5)])
    parallax_deg = np.concatenate([np.full(7, 40.0), np.full(6, 1.0), [10.0, 9.0, 8.0, 7.0]])
    parallax_deg[:7] += np.arange(7)  # distinct scores on the hub
    accepted = np.ones(len(edges), dtype=bool)
    for max_per_view in (1, 2):
        conf = GraphConfig(use_loops=False, use_weak=False, anchor_budget_ratio=1.0,
                           anchor_max_per_view=max_per_view)
        selection = select_pairs(8, edges, weight, parallax_deg, accepted, conf)
        anchors = edges[selection.role == "anchor"]
        count = np.bincount(anchors.ravel(), minlength=8)
        assert count.max() <= max_per_view
        assert count[0] == max_per_view  # the hub still gets its best anchors
    # Exact picks: the hub's best pair, then the best extras whose views are still free.
    tree = {tuple(e) for e in edges[selection.role == "tree"].tolist()}
    assert (0, 1) in tree  # hub pairs weigh the same: the lowest index joins the tree
    expected = {1: {(0, 7), (1, 3), (2, 5)}, 2: {(0, 7), (0, 6), (1, 3), (2, 5), (4, 7), (3, 6)}}
    for max_per_view, anchors in expected.items():
        conf = GraphConfig(use_loops=False, use_weak=False, anchor_budget_ratio=1.0,
                           anchor_max_per_view=max_per_view)
        selection = select_pairs(8, edges, weight, parallax_deg, accepted, conf)
        assert {tuple(e) for e in edges[selection.role == "anchor"].tolist()} == anchors


@pytest.mark.parametrize("seed", range(20))
def test_anchor_cap_on_random_graphs(seed: int) -> None:
    num_images, edges, weight, parallax_deg, accepted = random_candidates(seed)
    for max_per_view in (1, 2):
        conf = GraphConfig(anchor_budget_ratio=1.0, anchor_max_per_view=max_per_view)
        selection = select_pairs(num_images, edges, weight, parallax_deg, accepted, conf)
        anchors = edges[selection.role == "anchor"]
        assert np.bincount(anchors.ravel(), minlength=num_images).max() <= max_per_view


def weak_case() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    # Tree: 0-1, 1-4, 1-2, 2-3. Leaves 0, 3, 4 have degree 1.
    edges = np.array([[0, 1], [1, 4], [1, 2], [2, 3], [0, 2], [1, 3], [0, 4], [0, 3]])
    weight = np.array([1.0, 0.95, 0.9, 0.8, 0.3, 0.2, 5.0, 0.1])
    accepted = np.array([True, True, True, True, True, True, False, True])
    return edges, weight, accepted


def test_weak_view_of_degree_one_gets_one_extra_edge() -> None:
    edges, weight, accepted = weak_case()
    conf = GraphConfig(use_loops=False, use_anchors=False, weak_quantile=0.0,
                       weak_budget_ratio=1.0)
    selection = select_pairs(5, edges, weight, np.zeros(len(edges)), accepted, conf)
    np.testing.assert_array_equal(np.flatnonzero(selection.role == "tree"), [0, 1, 2, 3])
    weak = {tuple(e) for e in edges[selection.role == "weak"].tolist()}
    # 3 takes its best other candidate (1, 3), 0 takes (0, 2); each gets one only,
    # so (0, 3) is left; 4's only other candidate is rejected.
    assert weak == {(1, 3), (0, 2)}
    assert selection.role[6] == "rejected"
    # Weakest view first (degree, then median weight): with a budget of 1, view 3 wins.
    conf = GraphConfig(use_loops=False, use_anchors=False, weak_quantile=0.0,
                       weak_budget_ratio=0.2)
    selection = select_pairs(5, edges, weight, np.zeros(len(edges)), accepted, conf)
    assert edges[selection.role == "weak"].tolist() == [[1, 3]]
    # Two per view: 3 and 0 also share (0, 3).
    conf = GraphConfig(use_loops=False, use_anchors=False, weak_quantile=0.0,
                       weak_budget_ratio=1.0, weak_per_view=2)
    selection = select_pairs(5, edges, weight, np.zeros(len(edges)), accepted, conf)
    assert {tuple(e) for e in edges[selection.role == "weak"].tolist()} == {
        (1, 3), (0, 3), (0, 2)
    }


def test_weak_view_by_low_median_weight() -> None:
    # Square 0-1-2-3-0 plus diagonal (0, 2); view 3's pairs are all weak.
    edges = np.array([[0, 1], [1, 2], [2, 3], [0, 3], [0, 2], [1, 3]])
    weight = np.array([1.0, 1.0, 0.1, 0.11, 0.9, 0.12])
    accepted = np.ones(len(edges), dtype=bool)
    conf = GraphConfig(use_loops=False, use_anchors=False, weak_degree=0,
                       weak_quantile=0.2, weak_budget_ratio=1.0)
    selection = select_pairs(4, edges, weight, np.zeros(len(edges)), accepted, conf)
    # (0, 2) would close a cycle, so the weak (1, 3) joins the tree; view 3 has degree 1
    # but weak_degree=0, so only its low median weight (0.11) makes it weak.
    assert edges[selection.role == "tree"].tolist() == [[0, 1], [1, 2], [1, 3]]
    assert edges[selection.role == "weak"].tolist() == [[0, 3]]


# ----------------------------------------------------------------------------------------
# Selection
# ----------------------------------------------------------------------------------------


def test_disconnected_accepted_graph_warns_and_spans_each_component(
    caplog: pytest.LogCaptureFixture,
) -> None:
    edges = np.array([[0, 1], [1, 2], [0, 2], [3, 4], [2, 3]])
    weight = np.array([0.5, 0.6, 0.7, 0.8, 0.9])
    accepted = np.array([True, True, True, True, False])
    with caplog.at_level(logging.WARNING, logger="sara.selection.augment"):
        selection = select_pairs(6, edges, weight, np.ones(5), accepted, NO_AUGMENTATION)
    assert "3 connected components (sizes: 3, 2, 1)" in caplog.text
    assert selection.num_components == 3
    np.testing.assert_array_equal(selection.components, [0, 0, 0, 1, 1, 2])
    np.testing.assert_array_equal(selection.edge_index, [1, 2, 3])
    stats = selection.stats()
    assert stats["num_components_selected"] == 3
    assert stats["num_images_degree_0"] == 1
    assert stats["pairs_per_role"] == {
        "tree": 3, "loop": 0, "anchor": 0, "weak": 0, "unselected": 1, "rejected": 1
    }
    assert (stats["degree_min"], stats["degree_median"], stats["degree_max"]) == (0, 1.0, 2)


def test_selection_is_deterministic() -> None:
    num_images, edges, weight, parallax_deg, accepted = random_candidates(7)
    weight = np.round(weight, 1)  # many ties
    first = select_pairs(num_images, edges, weight, parallax_deg, accepted)
    second = select_pairs(num_images, edges.copy(), weight.copy(), parallax_deg.copy(),
                          accepted.copy())
    np.testing.assert_array_equal(first.edge_index, second.edge_index)
    np.testing.assert_array_equal(first.role, second.role)
    assert first.stats() == second.stats()


def test_the_tree_follows_its_own_weight_and_the_loops_the_pair_weight() -> None:
    # Every pair weighs the same by `weight` (the b best matches were all inliers), so alone the
    # tree would be the lowest edge indices: the star around view 0. `tree_weight` (all mutual
    # matches) makes it the path 0-1-2-3; the loop, ranked by `weight`, is then the lowest index.
    edges = np.array(list(itertools.combinations(range(4), 2)), dtype=np.int64)
    weight = np.ones(len(edges))
    parallax_deg = np.full(len(edges), 20.0)
    accepted = np.ones(len(edges), dtype=bool)
    path = np.array([abs(int(i) - int(j)) == 1 for i, j in edges])
    tree_weight = np.where(path, 3.0, 1.0)
    conf = GraphConfig(use_anchors=False, use_weak=False, loop_budget_ratio=0.25)  # one loop at N = 4
    star = select_pairs(4, edges, weight, parallax_deg, accepted, conf)
    assert {tuple(e) for e in edges[star.role == "tree"].tolist()} == {(0, 1), (0, 2), (0, 3)}
    chosen = select_pairs(4, edges, weight, parallax_deg, accepted, conf, tree_weight=tree_weight)
    assert {tuple(e) for e in edges[chosen.role == "tree"].tolist()} == {(0, 1), (1, 2), (2, 3)}
    assert np.count_nonzero(chosen.role == "loop") == 1
    with pytest.raises(ValueError, match="tree_weight"):
        select_pairs(4, edges, weight, parallax_deg, accepted, tree_weight=np.full(len(edges), -1.0))


def test_default_budgets_scale_with_images() -> None:
    assert GraphConfig().budgets(20) == {"loop": 10, "anchor": 3, "weak": 5}
    assert GraphConfig().budgets(7) == {"loop": 4, "anchor": 2, "weak": 2}
    assert GraphConfig(use_anchors=False).budgets(20)["anchor"] == 0


def test_bad_inputs_raise() -> None:
    edges = np.array([[0, 1], [1, 2]])
    with pytest.raises(ValueError, match="weight"):
        select_pairs(3, edges, np.array([1.0, np.nan]), np.ones(2), np.ones(2, bool))
    with pytest.raises(ValueError, match="shape"):
        select_pairs(3, edges, np.ones(3), np.ones(2), np.ones(2, bool))
    with pytest.raises(ValueError):
        GraphConfig(loop_budget_ratio=-1)
    with pytest.raises(TypeError):
        GraphConfig(unknown_key=1)  # type: ignore[call-arg]
