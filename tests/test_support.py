"""Pairs added before the first mapping for weakly matched views (`sara.pairs.sara.support`)."""

from pathlib import Path
from types import SimpleNamespace

from sara.config import PipelineConfig, make_config
from sara.pairs.sara import rounds as sara_source
from sara.pairs.sara.support import support_pairs, view_inliers

HEADER = "name0,name1,num_matches,num_inliers,overlap,parallax_deg,weight,accepted,reason,role\n"


def _scores(path: Path, rows) -> Path:
    """rows: (name0, name1, weight, accepted, role)."""
    path.write_text(HEADER + "".join(
        f"{a},{b},50,40,0.1,5,{w},{'true' if ok else 'false'},{'' if ok else 'few_inliers'},{role}\n"
        for a, b, w, ok, role in rows))
    return path


def test_view_inliers_sums_the_verified_matches_of_each_view():
    inliers = {("a", "b"): 100, ("b", "c"): 40}
    assert view_inliers(["a", "b", "c", "d"], [("b", "a"), ("b", "c"), ("c", "d")], inliers) == \
        {"a": 100, "b": 140, "c": 40, "d": 0}


def test_weakest_views_first_best_accepted_candidates_within_the_limits(tmp_path: Path):
    scores = _scores(tmp_path / "scores.csv", [
        ("a", "b", 0.9, True, "tree"), ("b", "c", 0.8, True, "tree"),
        ("a", "c", 0.5, True, "unselected"), ("c", "d", 0.7, True, "unselected"),
        ("c", "e", 0.6, True, "unselected"), ("c", "f", 0.99, False, "rejected"),
        ("a", "d", 0.4, True, "unselected"), ("a", "e", 0.3, True, "unselected"),
    ])
    pairs = [("a", "b"), ("b", "c")]
    support = {"a": 150, "b": 900, "c": 50, "d": 0, "e": 0, "f": 0}
    # weakest first: d, e, f (no pair yet), then c, then a. d: c-d (0.7); e: c-e (0.6), c now has
    # two; f: only a rejected candidate; c: served; a: a-c (0.5)
    extra = support_pairs(scores, pairs, support, min_inliers=200, per_view=1, room=10)
    assert extra == sorted([("c", "d"), ("c", "e"), ("a", "c")])
    assert support_pairs(scores, pairs, support, min_inliers=200, per_view=1, room=1) == [("c", "d")]
    # `order` ranks the weak views (the set is still `support`'s): a first takes its best, a-c
    order = {"a": 0, "b": 0, "c": 5, "d": 9, "e": 9, "f": 9}
    assert support_pairs(scores, pairs, support, min_inliers=200, per_view=1, room=1, order=order) == [("a", "c")]
    assert support_pairs(scores, pairs, {**support, "a": 900}, min_inliers=200, per_view=1, room=1,
                         order=order) == [("c", "d")]
    assert support_pairs(scores, pairs, support, min_inliers=200, per_view=1, room=2) == [("c", "d"), ("c", "e")]
    assert support_pairs(scores, pairs, support, min_inliers=200, per_view=3, room=10) == \
        [("a", "c"), ("a", "d"), ("a", "e"), ("c", "d"), ("c", "e")]
    assert support_pairs(scores, pairs, {"a": 900, "b": 900, "c": 900}, min_inliers=200, per_view=3, room=10) == []
    assert support_pairs(scores, pairs, support, min_inliers=200, per_view=0, room=10) == []


def test_the_source_adds_support_pairs_once_per_selection(tmp_path: Path, monkeypatch):
    _scores(tmp_path / "scores.csv", [
        ("a", "b", 0.9, True, "tree"), ("b", "c", 0.8, True, "tree"), ("a", "c", 0.5, True, "unselected")])
    inliers = {("a", "b"): 1000, ("b", "c"): 60}  # c is weak; d-h have no candidate
    monkeypatch.setattr(sara_source.colmap, "verified_inliers", lambda db, min_num_inliers: dict(inliers))
    monkeypatch.setattr(sara_source.colmap, "match_counts", lambda db: dict(inliers))
    names = ["a", "b", "c", "d", "e", "f", "g", "h"]  # the cap of all rounds leaves room for 5 more pairs
    ctx = SimpleNamespace(names=names, out_dir=tmp_path, conf=PipelineConfig(), max_round_pairs=None)
    pairs = [("a", "b"), ("b", "c")]
    extra = sara_source.before_mapping(ctx, pairs, tmp_path / "database.db")
    assert extra == [("a", "c")]
    # interrupted before they were matched: the same pairs; once matched: none, whatever the matches say
    assert sara_source.before_mapping(ctx, pairs, tmp_path / "database.db") == [("a", "c")]
    inliers[("a", "c")] = 0
    assert sara_source.before_mapping(ctx, pairs + extra, tmp_path / "database.db") == []
    conf_off = make_config(overrides={"rounds.support_min_view_inliers": 0})
    off = SimpleNamespace(names=ctx.names, out_dir=tmp_path, conf=conf_off, max_round_pairs=None)
    assert sara_source.before_mapping(off, pairs, tmp_path / "database.db") == []


def test_from_the_size_set_the_round_before_mapping_fills_up_to_the_cap(tmp_path: Path, monkeypatch):
    rows = [("a", "b", 0.9, True, "tree"), ("b", "c", 0.8, True, "tree"), ("c", "d", 0.7, True, "tree"),
            ("a", "c", 0.5, True, "unselected"), ("b", "d", 0.6, True, "unselected"),
            ("a", "d", 0.4, True, "unselected"), ("a", "e", 0.95, False, "rejected")]
    _scores(tmp_path / "scores.csv", rows)
    inliers = {("a", "b"): 1000, ("b", "c"): 1000, ("c", "d"): 1000}  # no weak view: no support pairs
    monkeypatch.setattr(sara_source.colmap, "verified_inliers", lambda db, min_num_inliers: dict(inliers))
    monkeypatch.setattr(sara_source.colmap, "match_counts", lambda db: dict(inliers))
    names = ["a", "b", "c", "d", "e"]  # the overrides below make the cap 1 pair per image: 5
    pairs = [("a", "b"), ("b", "c"), ("c", "d")]

    def ctx(**overrides):
        conf = make_config(overrides={"budget.max_pairs_fraction": 1.0, "budget.max_pairs_per_image": 1.0,
                                      **overrides})
        return SimpleNamespace(names=names, out_dir=tmp_path, conf=conf, max_round_pairs=None)

    # off by default, and nothing below the size set (the room stays for the pose-guided round)
    assert sara_source.before_mapping(ctx(), pairs, tmp_path / "database.db") == []
    assert sara_source.before_mapping(ctx(**{"rounds.fill_before_map_images": 6}), pairs,
                                      tmp_path / "database.db") == []
    # from the size: the best remaining accepted candidates by weight, up to the cap of 5 pairs
    filled = sara_source.before_mapping(ctx(**{"rounds.fill_before_map_images": 5}), pairs, tmp_path / "database.db")
    assert filled == [("a", "c"), ("b", "d")]
    record = sara_source.records.read_record(tmp_path, sara_source.SUPPORT_STAGE)
    assert record["info"]["num_fill"] == 2
    # once matched, none again; 0 turns it off at any size
    assert sara_source.before_mapping(ctx(**{"rounds.fill_before_map_images": 5}), pairs + filled,
                                      tmp_path / "database.db") == []
    assert sara_source.before_mapping(ctx(**{"rounds.fill_before_map_images": 0}), pairs,
                                      tmp_path / "database.db") == []
