"""Widening: views cut off from the selected graph get candidates from more neighbours."""

import numpy as np

from sara.io.scores import PairScores, concat_scores
from sara.pairs.sara.source import _widen_schedule, widen_candidates
from sara.retrieval import knn_pairs
from sara.selection import connected_components


def _two_clusters(seed: int = 0) -> np.ndarray:
    """20 descriptors near one direction and 5 near another, plus a bridge view between them."""
    rng = np.random.default_rng(seed)
    a = np.array([1.0, 0.0, 0.0, 0.0]) + 0.05 * rng.standard_normal((20, 4))
    b = np.array([0.0, 1.0, 0.0, 0.0]) + 0.05 * rng.standard_normal((5, 4))
    bridge = np.array([[0.6, 0.8, 0.0, 0.0]])
    return np.concatenate([a, b, bridge]).astype(np.float32)


def test_widen_reaches_the_cut_off_views_and_only_new_pairs():
    desc = _two_clusters()
    edges = knn_pairs(desc, 3)
    # suppose only the pairs inside the big cluster were selected: the others are cut off
    selected = edges[(edges < 20).all(axis=1)]
    labels = connected_components(len(desc), selected)
    assert labels.max() > 0
    new = widen_candidates(desc, edges, labels, 10)
    known = {tuple(e) for e in edges.tolist()}
    assert len(new) > 0
    assert all(i < j for i, j in new.tolist())
    assert not known & {tuple(e) for e in new.tolist()}
    assert len({tuple(e) for e in new.tolist()}) == len(new)
    # every new pair has a cut-off view in it, and some reach the big cluster
    assert all(labels[i] != 0 or labels[j] != 0 for i, j in new.tolist())
    assert any((labels[i] == 0) != (labels[j] == 0) for i, j in new.tolist())
    # at most as many new pairs as candidates already there
    assert len(widen_candidates(desc, edges[:4], labels, 25)) <= 25
    # the same input gives the same pairs
    assert np.array_equal(new, widen_candidates(desc, edges, labels, 10))


def test_widen_nothing_when_one_component():
    desc = _two_clusters()
    edges = knn_pairs(desc, 3)
    labels = np.zeros(len(desc), dtype=np.int64)
    assert widen_candidates(desc, edges, labels, 10).shape == (0, 2)


def test_widen_schedule():
    assert _widen_schedule(0, 100) == []
    assert _widen_schedule(20, 1000) == [20, 80]
    assert _widen_schedule(20, 50) == [20, 49]
    assert _widen_schedule(80, 30) == [29]


def test_concat_scores_keeps_order():
    def make(names, accepted):
        n = len(names)
        return PairScores(name0=[a for a, _ in names], name1=[b for _, b in names],
                          num_matches=np.arange(n), num_inliers=np.arange(n), overlap=np.ones(n),
                          parallax_deg=np.ones(n), weight=np.arange(n, dtype=float),
                          accepted=np.array(accepted, bool), reason=["" if x else "few_inliers" for x in accepted])

    both = concat_scores(make([("a", "b")], [True]), make([("a", "c"), ("b", "c")], [False, True]))
    assert both.name1 == ["b", "c", "c"]
    assert both.weight.tolist() == [0.0, 0.0, 1.0]
    assert both.accepted.tolist() == [True, False, True]
    assert both.reason == ["", "few_inliers", ""]


def _scored(pairs, accepted) -> PairScores:
    n = len(pairs)
    acc = np.array(accepted, bool)
    return PairScores(name0=[a for a, _ in pairs], name1=[b for _, b in pairs], num_matches=np.full(n, 50),
                      num_inliers=np.where(acc, 40, 9), overlap=np.ones(n), parallax_deg=np.full(n, 5.0),
                      weight=acc.astype(float), accepted=acc, reason=["" if x else "few_inliers" for x in acc])


def test_the_rejected_candidates_of_cut_off_views_are_scored_again_with_the_ratio_test(monkeypatch, tmp_path):
    """Only rejected candidates touching a view outside the largest part are scored again, with
    the repair's ratio; those it accepts replace their first scores, the rest are kept."""
    from sara.config import make_config
    from sara.pairs import PairContext
    from sara.pairs.sara import source

    names = ["a", "b", "c", "d"]
    edges = np.array([[0, 1], [1, 2], [0, 3], [2, 3]], dtype=np.int64)
    candidates = [(names[i], names[j]) for i, j in edges]
    first = _scored(candidates, [True, True, False, False])  # view d (3) is cut off
    labels = connected_components(4, edges[first.accepted])
    seen: list = []

    def fake_score(ctx, pairs, score_conf=None, progress=None):
        seen.append((pairs, score_conf.max_descriptor_ratio))
        return _scored(pairs, [p == ("a", "d") for p in pairs])

    monkeypatch.setattr(source, "_score", fake_score)
    ctx = PairContext(names=names, images_root=tmp_path, features_path=tmp_path / "f.h5", db_path=tmp_path / "db",
                      out_dir=tmp_path, conf=make_config("sift-offline", {}))
    scores, accepted = source.rescore_outside(ctx, candidates, edges, labels, first)
    assert seen == [([("a", "d"), ("c", "d")], 0.8)]
    assert accepted == 1
    assert scores.accepted.tolist() == [True, True, True, False] and scores.name1 == ["b", "c", "d", "d"]
    # one part: nothing is scored again; the ratio at 1 turns it off
    assert source.rescore_outside(ctx, candidates, edges, np.zeros(4, np.int64), first) == (first, 0)
    off = PairContext(**{**ctx.__dict__, "conf": make_config("sift-offline", {"rounds.repair_descriptor_ratio": 1.0})})
    assert source.rescore_outside(off, candidates, edges, labels, first) == (first, 0)
    assert len(seen) == 1
