"""The pose-guided round: covisibility predicted from a model, the choice of pairs, the pair cap."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import pytest

from sara.config import BudgetConfig, RoundsConfig
from sara.pairs.sara.budget import PairBudget
from sara.selection import capped_budgets, select_pairs
from sara.selection.pose_guided import (
    Covisibility,
    choose_pairs,
    covisibility,
    pair_scores,
)

#: the pose-guided round and the pair caps as measured on the shared scenes (off by default until
#: they win on every shared scene)
CAPPED = BudgetConfig(max_pairs_per_image=4.0, max_pairs_fraction=0.25)
POSE_GUIDED_PAIRS_PER_IMAGE = 1.0


def first_round_cap(num_images: int, budget: BudgetConfig, pose_guided_pairs_per_image: float) -> int:
    rounds = RoundsConfig(pose_guided_pairs_per_image=pose_guided_pairs_per_image)
    return PairBudget(num_images, budget, rounds).first_round()


@dataclass(frozen=True)
class Geometry:
    """The fields of `sara.colmap.refine.ModelGeometry` that the core reads."""

    names: list[str]
    rotations: np.ndarray
    translations: np.ndarray
    focal_px: np.ndarray
    principal_px: np.ndarray
    sizes_px: np.ndarray
    points_xyz: np.ndarray
    obs_point: np.ndarray
    obs_view: np.ndarray


def _look_at_origin(center: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world (R, t) of a camera at `center` whose +z axis points at the origin."""
    z = -center / np.linalg.norm(center)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ center


def _geometry(centers: list[list[float]], points: np.ndarray, observations: list[tuple[int, int]]) -> Geometry:
    poses = [_look_at_origin(np.asarray(c, dtype=float)) for c in centers]
    n = len(centers)
    obs = np.asarray(observations, dtype=np.int64).reshape(-1, 2)
    return Geometry(names=[f"v{k}" for k in range(n)], rotations=np.stack([p[0] for p in poses]),
                    translations=np.stack([p[1] for p in poses]), focal_px=np.full(n, 100.0),
                    principal_px=np.full((n, 2), 50.0), sizes_px=np.full((n, 2), 100.0),
                    points_xyz=np.asarray(points, dtype=float), obs_point=obs[:, 0], obs_view=obs[:, 1])


def test_covisibility_counts_projection_angle_and_tracks():
    # views 0 and 1 are 30 degrees apart around the origin, view 2 looks from behind (180 degrees)
    c30 = [10 * np.sin(np.radians(30)), 0.0, -10 * np.cos(np.radians(30))]
    geom = _geometry([[0, 0, -10], c30, [0, 0, 10]],
                     points=np.array([[0, 0, 0], [0.5, 0.2, 0], [0.1, -0.3, 0.2], [40, 0, 0]]),
                     # point 0 in views 0 and 1 (linked); 1 and 2 only in view 0; 3 (far outside) in view 0
                     observations=[(0, 0), (0, 1), (1, 0), (2, 0), (3, 0)])
    cov = covisibility(geom, np.array([[0, 1], [0, 2]]), max_view_angle_deg=45.0)
    # 0 -> 1: points 0, 1, 2 project into view 1 (3 is outside); 1 -> 0: point 0. Mean (3 + 1) / 2
    assert cov.covisible[0] == pytest.approx(2.0)
    assert cov.linked[0] == 1
    assert cov.tri_angle_deg[0] == pytest.approx(30.0, abs=3.0)
    # view 2 sees the points from the opposite side: beyond 45 degrees, nothing covisible
    assert cov.covisible[1] == 0 and cov.linked[1] == 0 and cov.tri_angle_deg[1] == 0
    assert cov.observed.tolist() == [4, 1, 0]
    wide = covisibility(geom, np.array([[0, 2]]), max_view_angle_deg=180.0)
    assert wide.covisible[0] == pytest.approx(1.5)  # points 0, 1, 2 in front of view 2, inside its image


def _cov(covisible, tri_angle_deg, observed) -> Covisibility:
    n = len(covisible)
    return Covisibility(np.asarray(covisible, float), np.zeros(n), np.asarray(tri_angle_deg, float),
                        np.asarray(observed, np.int64))


def test_choose_pairs_ranks_by_predicted_weight_within_budget_and_threshold():
    pairs = np.array([[0, 1], [0, 2], [1, 2], [0, 3]])
    # views 0..3 observe 100, 100, 400, 25 points
    cov = _cov(covisible=[50, 100, 100, 20], tri_angle_deg=[10, 10, 2.5, 40], observed=[100, 100, 400, 25])
    # w = covisible / sqrt(n_i n_j) * sqrt(min(P, 10) / 10): 0.5, 0.5, 0.5 * 0.5, 0.4 * 1
    assert pair_scores(cov, pairs, "weight") == pytest.approx([0.5, 0.5, 0.25, 0.4])
    assert choose_pairs(pairs, cov, 2).tolist() == [0, 1]  # tie broken by index
    assert choose_pairs(pairs, cov, 10, min_covisible=30).tolist() == [0, 1, 2]
    assert choose_pairs(pairs, cov, 0).tolist() == []
    assert choose_pairs(pairs, cov, 2, rule="covisible").tolist() == [1, 2]
    assert pair_scores(cov, pairs, "weight", beta=0.0) == pytest.approx([0.5, 0.5, 0.5, 0.4])
    with pytest.raises(ValueError, match="unknown pose-guided rule"):
        pair_scores(cov, pairs, "nope")


def test_choose_pairs_limits_the_pairs_of_each_view():
    pairs = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]])
    # weights (one view set, no parallax cap): 0.9, 0.8, 0.7, 0.6, 0.5
    cov = _cov(covisible=[90, 80, 70, 60, 50], tri_angle_deg=[10] * 5, observed=[100] * 4)
    assert choose_pairs(pairs, cov, 5).tolist() == [0, 1, 2, 3, 4]
    # view 0 is full after two pairs: (0, 3) is skipped, then view 2 is full after (1, 2)
    assert choose_pairs(pairs, cov, 5, max_per_view=2).tolist() == [0, 1, 3]
    assert choose_pairs(pairs, cov, 2, max_per_view=2).tolist() == [0, 1]
    assert choose_pairs(pairs, cov, 5, max_per_view=1).tolist() == [0, 4]


def test_choose_pairs_skips_pairs_with_nothing_covisible():
    pairs = np.array([[0, 1], [0, 2], [1, 2]])
    cov = _cov(covisible=[50, 0, 50], tri_angle_deg=[5, 0, 0], observed=[100, 100, 100])
    assert choose_pairs(pairs, cov, 3).tolist() == [0]  # no angle: no weight either


@pytest.mark.parametrize(("num_images", "cap"), [(11, 13), (16, 30), (25, 75), (30, 108), (47, 188), (119, 476),
                                                 (3, 2)])
def test_pair_cap_is_four_per_image_and_a_quarter_of_exhaustive(num_images, cap):
    assert CAPPED.pair_cap(num_images) == cap


def test_first_round_leaves_room_for_the_pose_guided_round():
    conf = CAPPED
    # room beyond the tree: 13 - 10 = 3 on 11 images, of which the round keeps half (1)
    assert first_round_cap(11, conf, POSE_GUIDED_PAIRS_PER_IMAGE) == 13 - 1
    assert first_round_cap(16, conf, POSE_GUIDED_PAIRS_PER_IMAGE) == 30 - 7
    assert first_round_cap(47, conf, POSE_GUIDED_PAIRS_PER_IMAGE) == 188 - 47
    assert first_round_cap(47, CAPPED, 0) == 188
    assert capped_budgets({"loop": 10, "anchor": 4, "weak": 6}, 10) == {"loop": 5, "anchor": 2, "weak": 3}
    assert capped_budgets({"loop": 1, "anchor": 1, "weak": 1}, 10) == {"loop": 1, "anchor": 1, "weak": 1}


def test_select_pairs_respects_max_pairs_but_keeps_the_tree():
    rng = np.random.default_rng(0)
    n = 20
    edges = np.array([(i, j) for i in range(n) for j in range(i + 1, n)], dtype=np.int64)
    weight = rng.uniform(0.01, 1.0, len(edges))
    parallax = rng.uniform(1.0, 20.0, len(edges))
    accepted = np.ones(len(edges), bool)
    free = select_pairs(n, edges, weight, parallax, accepted)
    capped = select_pairs(n, edges, weight, parallax, accepted, max_pairs=25)
    assert len(free.edge_index) > 25 >= len(capped.edge_index) >= n - 1
    assert np.sum(capped.role == "tree") == n - 1
    tiny = select_pairs(n, edges, weight, parallax, accepted, max_pairs=5)
    assert len(tiny.edge_index) == n - 1  # the spanning tree is never cut


def test_densify_keeps_the_first_round_and_caps_at_sixty_percent_of_exhaustive():
    conf = dataclasses.replace(CAPPED, densify=True)
    # no room kept back: densify adds to the usual selection
    assert first_round_cap(11, conf, POSE_GUIDED_PAIRS_PER_IMAGE) == 13
    assert conf.densify_cap(11) == 33  # 60% of 55
    assert conf.densify_cap(47) == 8 * 47


def test_large_models_predict_only_the_pairs_of_nearby_views(monkeypatch):
    """Above MAX_ALL_PAIRS the round predicts each view's NEAREST_VIEWS nearest views only: views
    on a line, all looking along +z except one that looks back; matched pairs stay out."""
    from sara.pairs.sara import pose_guided as round_

    names = [f"v{i:02d}" for i in range(12)]
    centers = np.stack([np.arange(12.0), np.zeros(12), np.zeros(12)], axis=1)
    axes = np.tile([0.0, 0.0, 1.0], (12, 1))
    axes[5] = [0.0, 0.0, -1.0]  # looks away from all the others
    matched = [("v00", "v01")]
    everything = round_.candidate_pairs(names, matched, centers, axes)
    assert len(everything) == 66 - 1  # below the limit: every unmatched pair

    monkeypatch.setattr(round_, "MAX_ALL_PAIRS", 10)
    monkeypatch.setattr(round_, "NEAREST_VIEWS", 2)
    near = {tuple(p) for p in round_.candidate_pairs(names, matched, centers, axes).tolist()}
    assert (0, 1) not in near and (0, 2) in near  # v00's two nearest: v01 (matched) and v02
    assert all(5 not in p for p in near)  # v05 faces the other way: no pair with it
    assert (4, 6) in near and (3, 4) in near and (0, 3) not in near
    assert all(a < b for a, b in near)
    with pytest.raises(ValueError, match="centres"):
        round_.candidate_pairs(names, matched)
