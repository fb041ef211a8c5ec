from pathlib import Path

import pytest

from sara.config import MapConfig
from sara.pairs.sara.repair import fill_pairs, left_out_views, neighbour_pairs, repair_pairs


def _scores(path: Path, rows):
    header = "name0,name1,num_matches,num_inliers,overlap,parallax_deg,weight,accepted,reason,role\n"
    path.write_text(header + "".join(f"{a},{b},50,{n},0.01,5,0.01,false,{r},rejected\n" for a, b, n, r in rows))
    return path


def test_left_out_views_only_in_main_component():
    names = ["a", "b", "c", "d", "x", "y"]
    pairs = [("a", "b"), ("b", "c"), ("c", "d"), ("x", "y")]  # x, y: another scene
    assert left_out_views(names, pairs, main={"a", "b"}) == ["c", "d"]
    assert left_out_views(names, pairs, main=set()) == []


def test_repair_pairs_best_links_into_main(tmp_path: Path):
    scores = _scores(tmp_path / "scores.csv", [
        ("a", "c", 12, "few_inliers"), ("b", "c", 14, "few_inliers"), ("c", "d", 40, ""),
        ("a", "d", 3, "no_model"), ("b", "d", 9, "few_inliers"), ("c", "x", 13, "few_inliers"),
    ])
    extra = repair_pairs(scores, pairs=[("a", "b"), ("c", "d")], main={"a", "b"}, left_out=["c", "d"], per_view=1)
    # c: best link into the main model is b (14); d: a is "no_model", so b (9); never c-d (both left out)
    assert extra == [("b", "c"), ("b", "d")]
    two = repair_pairs(scores, pairs=[("a", "b")], main={"a", "b"}, left_out=["c"], per_view=2)
    assert two == [("a", "c"), ("b", "c")]


def test_repair_pairs_rank_by_the_inliers_among_all_matches(tmp_path: Path):
    # both links of c saturate at the 50 best matches; all mutual matches tell them apart
    path = tmp_path / "scores.csv"
    header = "name0,name1,num_matches,num_inliers,num_inliers_all,overlap,parallax_deg,weight,accepted,reason,role\n"
    path.write_text(header + "a,c,50,50,90,0.05,5,0.05,true,,unselected\n"
                    + "b,c,50,50,400,0.05,5,0.05,true,,unselected\n")
    assert repair_pairs(path, pairs=[("a", "b")], main={"a", "b"}, left_out=["c"], per_view=1) == [("b", "c")]


def test_repair_pairs_rank_by_the_scores_given_again(tmp_path: Path):
    """The round's ratio-tested scores replace the first ones for the pairs they cover, a pair the
    first scoring found no model for included; the others keep their first score."""
    path = _scores(tmp_path / "scores.csv", [
        ("a", "c", 14, "few_inliers"), ("b", "c", 9, "few_inliers"),
        ("a", "d", 3, "no_model"), ("b", "d", 8, "few_inliers"),
    ])
    asked: list = []

    def rescore(pairs):
        asked.append(pairs)
        return {("b", "c"): 60, ("a", "d"): 30}

    extra = repair_pairs(path, pairs=[("a", "b")], main={"a", "b"}, left_out=["c", "d"], per_view=1, rescore=rescore)
    assert extra == [("a", "d"), ("b", "c")]
    assert asked == [[("a", "c"), ("a", "d"), ("b", "c"), ("b", "d")]]  # once, every candidate of the views
    assert repair_pairs(path, pairs=[("a", "b")], main={"a", "b"}, left_out=["c", "d"], per_view=1) == [
        ("a", "c"), ("b", "d")]


def test_repair_pairs_leave_out_candidates_that_would_not_verify(tmp_path: Path):
    """A left-out view whose candidates into the model all count fewer inliers than verification asks
    for gets none of them (the cap's room stays for the fill round); a count that reaches it, first
    or given again, is taken. Where the scorer saw only part of a view's keypoints, its count does
    not hold the pair back."""
    path = _scores(tmp_path / "scores.csv", [
        ("a", "c", 14, "few_inliers"), ("b", "c", 12, "few_inliers"),
        ("a", "d", 9, "few_inliers"), ("b", "d", 40, ""),
        ("a", "e", 3, "no_model"), ("b", "e", 8, "few_inliers"),
    ])
    base = {"pairs": [("a", "b")], "main": {"a", "b"}, "left_out": ["c", "d", "e"], "per_view": 2}
    assert repair_pairs(path, **base, min_inliers=15) == [("b", "d")]
    assert repair_pairs(path, **base, min_inliers=15, rescore=lambda pairs: {("a", "c"): 15, ("b", "d"): 11}) == [
        ("a", "c")]
    assert len(repair_pairs(path, **base)) == 5  # no minimum: every candidate with a model
    # the minimum holds only where the scorer saw every keypoint of both views (here a, b, c)
    assert repair_pairs(path, **base, min_inliers=15, fully_scored={"a", "b", "c"}) == [
        ("a", "d"), ("b", "d"), ("b", "e")]


def test_the_repair_scores_again_with_the_ratio_test(monkeypatch, tmp_path: Path):
    from types import SimpleNamespace

    from sara import scoring
    from sara.config import make_config
    from sara.pairs.sara import rounds as sara_rounds

    seen = {}

    def fake_score_pairs(pairs, features, db, conf, **kwargs):
        seen["ratio"] = conf.max_descriptor_ratio
        return SimpleNamespace(num_inliers_all=[7 * (k + 1) for k in range(len(pairs))])

    monkeypatch.setattr(scoring, "score_pairs", fake_score_pairs)
    ctx = SimpleNamespace(conf=make_config("sift-offline"), features_path=tmp_path / "f.h5", db_path=tmp_path / "d.db",
                          executor=None, out_dir=tmp_path, progress=False, score_journal=None)
    assert sara_rounds._ratio_rescore(ctx)([("a", "b"), ("a", "c")]) == {("a", "b"): 7, ("a", "c"): 14}
    assert seen["ratio"] == 0.8 and ctx.conf.score.max_descriptor_ratio == 1.0  # the selection's scores: untouched
    ctx.conf = make_config("sift-offline", {"rounds.repair_descriptor_ratio": 1.0})
    assert sara_rounds._ratio_rescore(ctx) is None


def test_a_repair_that_leaves_most_of_its_views_out_is_not_repeated(tmp_path: Path, monkeypatch):
    from types import SimpleNamespace

    from sara.config import PipelineConfig
    from sara.pairs.sara import rounds as sara_source
    monkeypatch.setattr(sara_source, "_fully_scored", lambda ctx, views: set(views))

    registered = {"a", "b", "c"}
    monkeypatch.setattr(sara_source.colmap, "registered_images", lambda model_dir: set(registered))

    def fake_repair(scores, pairs, main, left_out, per_view, **options):
        """The first unmatched link into the model."""
        done = {tuple(sorted(p)) for p in pairs}
        return [next(p for p in (tuple(sorted((m, v))) for m in sorted(main)) if p not in done) for v in left_out]

    monkeypatch.setattr(sara_source, "repair_pairs", fake_repair)
    monkeypatch.setattr(sara_source.colmap, "verified_inliers", lambda db, min_num_inliers: {})  # no neighbours
    monkeypatch.setattr(sara_source, "pose_guided_round", lambda ctx, pairs, model_dir: [("a", "c")])
    pairs = [("a", "b"), ("b", "c"), ("c", "d"), ("d", "e")]
    header = "name0,name1,num_matches,num_inliers,overlap,parallax_deg,weight,accepted,reason,role\n"
    (tmp_path / "scores.csv").write_text(header + "".join(f"{a},{b},50,40,0.1,5,0.1,true,,tree\n" for a, b in pairs))
    ctx = SimpleNamespace(names=["a", "b", "c", "d", "e"], out_dir=tmp_path, conf=PipelineConfig(),
                          max_round_pairs=None, last_round=False, db_path=tmp_path / "database.db")
    model = tmp_path / "sparse" / "0"

    first = sara_source.after_mapping(ctx, pairs, model).pairs
    assert first == [("a", "d"), ("a", "e")]
    registered.add("d")  # the repair registered half of its views: repair again
    second = sara_source.after_mapping(ctx, pairs + first, model).pairs
    assert second == [("b", "e")]
    # e is still out after a repair meant for it: no third repair, the pose-guided pairs instead
    third = sara_source.after_mapping(ctx, pairs + first + second, model).pairs
    assert third == [("a", "c")]
    # and it stays so once the pose-guided pairs are matched
    assert sara_source.after_mapping(ctx, pairs + first + second + third, model).pairs == [("a", "c")]
    # unless another view drops out of the model
    registered.discard("d")
    assert sara_source.after_mapping(ctx, pairs + first + second + third, model).pairs == [("b", "d"), ("c", "e")]
    # a record of another selection does not apply
    rows = "".join(f"{a},{b},50,40,0.1,5,0.1,true,,tree\n" for a, b in pairs[:3])
    (tmp_path / "scores.csv").write_text(header + rows)
    registered.add("d")
    assert sara_source.after_mapping(ctx, pairs + first + second, model).pairs == [("c", "e")]


def test_neighbour_pairs_link_the_registered_neighbours_of_a_left_out_view(tmp_path: Path):
    """v is matched to a, b and c in the model and still out: pairs among a, b, c, best weight first."""
    path = tmp_path / "scores.csv"
    header = "name0,name1,num_matches,num_inliers,overlap,parallax_deg,weight,accepted,reason,role\n"
    rows = [("a", "b", 0.3, "true"), ("a", "c", 0.8, "true"), ("b", "c", 0.5, "true"), ("c", "d", 0.9, "true"),
            ("a", "v", 0.9, "true"), ("b", "d", 0.99, "false")]
    path.write_text(header + "".join(f"{a},{b},50,40,0.1,5,{w},{ok},,unselected\n" for a, b, w, ok in rows))
    linked = {("a", "v"): 120, ("b", "v"): 90, ("c", "v"): 60, ("d", "v"): 40, ("a", "d"): 300}
    main = {"a", "b", "c"}  # d is matched to v but not in the model; a-b is already matched
    near = neighbour_pairs(path, [("a", "b")], main, ["v"], linked, per_view=3)
    assert near == {"v": [("a", "c"), ("b", "c")]}
    assert neighbour_pairs(path, [("a", "b")], main, ["v"], linked, per_view=1) == {"v": [("a", "c")]}
    # a view with no neighbour in the model gets none; a pair goes to the first view that names it
    assert neighbour_pairs(path, [], main, ["d", "v", "w"], {**linked, ("b", "w"): 50, ("c", "w"): 50},
                           per_view=3) == {"d": [], "v": [("a", "c"), ("b", "c"), ("a", "b")], "w": []}


def test_the_repair_takes_one_pair_of_each_kind_per_view_in_turn(tmp_path: Path, monkeypatch):
    from types import SimpleNamespace

    from sara.config import make_config
    from sara.pairs.sara import rounds as sara_source
    monkeypatch.setattr(sara_source, "_fully_scored", lambda ctx, views: set(views))

    own = {"v": [("m1", "v"), ("m2", "v")], "w": [("m1", "w")]}
    near = {"v": [("m1", "m2"), ("m2", "m3")], "w": [("m3", "m4")]}
    monkeypatch.setattr(sara_source, "repair_pairs", lambda *a, **k: sorted(p for ps in own.values() for p in ps))
    monkeypatch.setattr(sara_source, "neighbour_pairs", lambda *a, **k: near)
    monkeypatch.setattr(sara_source.colmap, "verified_inliers", lambda db, min_num_inliers: {})
    names = ["m1", "m2", "m3", "m4", "v", "w"]
    pairs = [("m1", "m2"), ("m2", "m3"), ("m3", "m4"), ("m4", "v"), ("m4", "w")]  # the cap (6 pairs) leaves 1

    def repair(room_per_image: float):
        conf = make_config(overrides={"budget.max_pairs_per_image": room_per_image, "budget.max_pairs_fraction": 1.0})
        ctx = SimpleNamespace(names=names, out_dir=tmp_path, conf=conf, max_round_pairs=None, last_round=False,
                              db_path=tmp_path / "database.db")
        return sara_source._repair_round(ctx, pairs, {"m1", "m2", "m3", "m4"}, ["v", "w"])

    # room: at least 2 per left-out view (4): v's first of each kind, then w's
    assert repair(1.0) == sorted([("m1", "v"), ("m1", "m2"), ("m1", "w"), ("m3", "m4")])
    # with room for all: every pair of both kinds
    assert repair(9.0) == sorted([("m1", "v"), ("m2", "v"), ("m1", "w"), ("m1", "m2"), ("m2", "m3"), ("m3", "m4")])


def test_fill_pairs_are_the_best_unmatched_accepted_candidates(tmp_path: Path):
    path = tmp_path / "scores.csv"
    header = "name0,name1,num_matches,num_inliers,overlap,parallax_deg,weight,accepted,reason,role\n"
    path.write_text(header + "a,b,50,40,0.1,5,0.9,true,,tree\n" + "a,c,50,40,0.1,5,0.2,true,,unselected\n"
                    + "b,c,50,40,0.1,5,0.5,true,,unselected\n" + "c,d,50,40,0.1,5,0.7,false,low_parallax,rejected\n"
                    + "b,d,50,40,0.1,5,0.4,true,,unselected\n")
    assert fill_pairs(path, [("a", "b")], room=2) == [("b", "c"), ("b", "d")]  # 0.5, 0.4; never the rejected c-d
    assert fill_pairs(path, [("a", "b")], room=9) == [("a", "c"), ("b", "c"), ("b", "d")]
    assert fill_pairs(path, [("a", "b")], room=0) == []


def test_views_a_repair_left_out_get_the_fill_round_once_then_the_pose_guided_one(tmp_path: Path, monkeypatch):
    """Views a repair could not bring in: the rest of the cap on the best remaining pairs, once."""
    from types import SimpleNamespace

    from sara.config import make_config
    from sara.pairs.sara import rounds as sara_source
    monkeypatch.setattr(sara_source, "_fully_scored", lambda ctx, views: set(views))

    registered = {"a", "b", "c"}
    monkeypatch.setattr(sara_source.colmap, "registered_images", lambda model_dir: set(registered))
    monkeypatch.setattr(sara_source, "_repair_stalled", lambda ctx, key, pairs, left_out: True)
    monkeypatch.setattr(sara_source, "pose_guided_round", lambda ctx, pairs, model_dir: [("a", "c")])
    tree = [("a", "b"), ("b", "c"), ("c", "d"), ("d", "e")]
    others = [("a", "c", 0.3), ("b", "d", 0.6), ("c", "e", 0.5), ("a", "e", 0.1)]
    header = "name0,name1,num_matches,num_inliers,overlap,parallax_deg,weight,accepted,reason,role\n"
    (tmp_path / "scores.csv").write_text(header + "".join(f"{a},{b},50,40,0.1,5,0.9,true,,tree\n" for a, b in tree)
                                         + "".join(f"{a},{b},50,40,0.1,5,{w},true,,unselected\n" for a, b, w in others))
    # a pair cap of 6 pairs for 5 views leaves room for 2 beyond the 4 matched
    conf = make_config(overrides={"budget.max_pairs_per_image": 1.2, "budget.max_pairs_fraction": 1.0})
    ctx = SimpleNamespace(names=["a", "b", "c", "d", "e"], out_dir=tmp_path, conf=conf, max_round_pairs=None,
                          last_round=False, db_path=tmp_path / "database.db")
    monkeypatch.setattr(sara_source.colmap, "verified_inliers", lambda db, min_num_inliers: {})
    model = tmp_path / "sparse" / "0"

    fill = sara_source.after_mapping(ctx, tree, model)
    assert (fill.role, fill.pairs) == ("fill", [("b", "d"), ("c", "e")])  # the best two by weight, within the cap
    # after an interruption before they were matched: the same pairs
    assert sara_source.after_mapping(ctx, tree, model).pairs == fill.pairs
    # once matched, and views still out: not again, the pose-guided round instead
    after = sara_source.after_mapping(ctx, tree + fill.pairs, model)
    assert (after.role, after.pairs) == ("pose-guided", [("a", "c")])
    # with every view in the model there is no fill round
    registered.update({"d", "e"})
    (tmp_path / ".sara" / "fill.json").unlink()
    assert sara_source.after_mapping(ctx, tree, model).role == "pose-guided"
    # a repair that finds no candidate into the model (not stalled) leads to the fill round too
    registered.difference_update({"d", "e"})
    monkeypatch.setattr(sara_source, "_repair_stalled", lambda ctx, key, pairs, left_out: False)
    monkeypatch.setattr(sara_source, "repair_pairs", lambda *args, **kwargs: [])
    assert sara_source.after_mapping(ctx, tree, model).role == "fill"


class _Model:
    def __init__(self, views: int) -> None:
        self.views = views

    def num_reg_images(self) -> int:
        return self.views


@pytest.mark.parametrize("continued", [10, 14, 20])
def test_a_repair_round_continues_the_model_and_never_maps_anew(tmp_path: Path, monkeypatch, continued):
    """A repair round continues the model of 10 views; 20 views are joined by verified pairs. Whether
    continuing registered none, some or all of the missing views, the database is mapped once."""
    from sara import mapping

    maps = []

    def fake_map(conf, db_path, images_root, tmp, seed, progress, input_model=None, **kwargs):
        maps.append("continued" if input_model is not None else "scratch")
        return mapping.colmap.MappedModels({0: _Model(continued if input_model is not None else 12)}), 20, 0.1

    monkeypatch.setattr(mapping, "_map", fake_map)
    monkeypatch.setattr(mapping.colmap_refine, "triangulate_new_matches", lambda *args, **kwargs: None)
    monkeypatch.setattr(mapping.colmap, "registered_images", lambda path: {f"v{k}" for k in range(10)})
    monkeypatch.setattr(mapping.colmap, "verified_graph", lambda db_path, min_num_inliers: (30, 20, [20], 100))
    recs, _, _ = mapping._extend(MapConfig(), tmp_path / "db", tmp_path, tmp_path, 0, False, tmp_path / "in", 15)
    assert maps == ["continued"]
    assert recs.largest == continued


def test_after_the_fill_one_more_repair_then_the_pose_guided_round(tmp_path: Path, monkeypatch):
    from types import SimpleNamespace

    from sara.config import make_config
    from sara.pairs.sara import rounds as sara_source
    monkeypatch.setattr(sara_source, "_fully_scored", lambda ctx, views: set(views))

    registered = {"a", "b", "c"}
    monkeypatch.setattr(sara_source.colmap, "registered_images", lambda model_dir: set(registered))
    monkeypatch.setattr(sara_source.colmap, "verified_inliers", lambda db, min_num_inliers: {})
    monkeypatch.setattr(sara_source, "pose_guided_round", lambda ctx, pairs, model_dir: [("a", "c")])
    tree = [("a", "b"), ("b", "c"), ("c", "d"), ("d", "e")]
    others = [("a", "d", 0.3), ("b", "d", 0.6), ("c", "e", 0.5), ("a", "e", 0.1), ("b", "e", 0.2)]
    header = "name0,name1,num_matches,num_inliers,overlap,parallax_deg,weight,accepted,reason,role\n"
    (tmp_path / "scores.csv").write_text(header + "".join(f"{a},{b},50,40,0.1,5,0.9,true,,tree\n" for a, b in tree)
                                         + "".join(f"{a},{b},50,40,0.1,5,{w},true,,unselected\n" for a, b, w in others))
    # a cap of 8 pairs: the tree, a first repair of a-d and a-e, a fill of the best two (b-d, c-e); b-e is left
    conf = make_config(overrides={"budget.max_pairs_per_image": 1.6, "budget.max_pairs_fraction": 1.0,
                                  "rounds.repair_pairs_per_view": 1, "rounds.repair_descriptor_ratio": 1.0})
    ctx = SimpleNamespace(names=["a", "b", "c", "d", "e"], out_dir=tmp_path, conf=conf, max_round_pairs=None,
                          last_round=False, db_path=tmp_path / "database.db")
    model = tmp_path / "sparse" / "0"

    matched = list(tree)
    rounds = [("repair", [("a", "d"), ("a", "e")]), ("fill", [("b", "d"), ("c", "e")]), ("repair", [("b", "e")]),
              ("pose-guided", [("a", "c")])]
    for role, pairs in rounds:  # d and e stay out throughout
        added = sara_source.after_mapping(ctx, matched, model)
        assert (added.role, added.pairs) == (role, pairs)
        matched += added.pairs
    # and the pose-guided pairs once more, never a third repair
    assert sara_source.after_mapping(ctx, matched, model).role == "pose-guided"


def _round_model(out_dir: Path, poses: dict, views: int) -> None:
    """What a round's mapping leaves: a model of the first `views` of `poses` in `sparse/`, recorded
    as the map stage's model of the round's matches."""
    from model_utils import write_text_model
    from sara import mapping
    from sara.io import records

    new = out_dir / ".sara" / "new"
    write_text_model(new / "0", dict(list(poses.items())[:views]))
    mapping.swap_in(new, out_dir / "sparse")
    records.mark_done(out_dir, mapping.STAGE, "matches-after", {"num_registered": views, "num_components": 2,
                                                               "time_s": 2.0},
                      outputs={"sparse": mapping.model_digest(out_dir / "sparse")})


@pytest.mark.parametrize("views_after", [5, 8])
def test_a_round_whose_mapping_holds_fewer_views_keeps_the_model_it_started_from(tmp_path: Path, monkeypatch,
                                                                                 views_after):
    """A round maps its matches again (continuing the model); when the result's main model holds fewer
    views than the model the round started from, that model is put back, as the map stage's model of
    the round's matches (a re-run keeps it). As many views or more: the round's model stays."""
    from types import SimpleNamespace

    from model_utils import ring_poses, write_text_model
    from sara import colmap, mapping
    from sara.config import make_config
    from sara.io import records
    from sara.pairs import Round
    from sara.pipeline import rounds as pipeline_rounds

    out = tmp_path / "out"
    poses = ring_poses(8)
    write_text_model(out / "sparse" / "0", poses)
    records.mark_done(out, mapping.STAGE, "matches-before", {"num_registered": 8, "num_components": 1, "time_s": 1.0},
                      outputs={"sparse": mapping.model_digest(out / "sparse")})
    committed = []

    def mapped_again(conf, db, images, out_dir, *, commit, input_model, **kwargs):
        assert input_model == out_dir / "sparse" / "0"  # the round continues the model
        commit()
        _round_model(out_dir, poses, views_after)

    monkeypatch.setattr(pipeline_rounds.mapping, "run", mapped_again)
    monkeypatch.setattr(pipeline_rounds.match, "commit", lambda *args: committed.append("matches"))
    monkeypatch.setattr(pipeline_rounds.match, "matches_digest", lambda db: "digest")
    monkeypatch.setattr(pipeline_rounds, "_commit_pairs", lambda *args: committed.append("pairs"))
    run = SimpleNamespace(out_dir=out, conf=make_config("sift-offline"), ctx=SimpleNamespace(images_root=tmp_path),
                          progress=False)
    map_s = pipeline_rounds._map_again(run, Round([("a", "b")], "repair"), tmp_path / "work.db", {})
    assert map_s == 2.0 and committed == ["matches", "pairs"]  # the round's matches and pairs stay committed
    record = records.read_record(out, mapping.STAGE)
    assert record["key"] == "matches-after"
    assert record["info"]["num_registered"] == max(views_after, 8)
    assert len(colmap.registered_images(out / "sparse" / "0")) == max(views_after, 8)
    assert record["outputs"]["sparse"] == mapping.model_digest(out / "sparse")  # not seen as damaged on a re-run
    assert not (out / ".sara" / pipeline_rounds.BEFORE_ROUND).exists()


@pytest.mark.parametrize("views_after", [5, 8])
def test_a_run_killed_after_a_rounds_mapping_puts_the_larger_model_back_when_it_resumes(tmp_path: Path, monkeypatch,
                                                                                       views_after):
    """Killed between the round's mapping replacing the model and the comparison with the model the
    round started from: the next run's rounds begin by that comparison (the state at the kill is a
    copy of the output folder taken inside the mapping)."""
    import shutil
    from types import SimpleNamespace

    from model_utils import ring_poses, write_text_model
    from sara import colmap, mapping
    from sara.config import make_config
    from sara.io import records
    from sara.pairs import Round
    from sara.pipeline import rounds as pipeline_rounds

    out, killed = tmp_path / "out", tmp_path / "killed"
    poses = ring_poses(8)
    write_text_model(out / "sparse" / "0", poses)
    records.mark_done(out, mapping.STAGE, "matches-before", {"num_registered": 8, "num_components": 1, "time_s": 1.0},
                      outputs={"sparse": mapping.model_digest(out / "sparse")})

    def mapped_again(conf, db, images, out_dir, *, commit, input_model, **kwargs):
        _round_model(out_dir, poses, views_after)
        shutil.copytree(out_dir, killed)  # the folder as a kill here leaves it

    monkeypatch.setattr(pipeline_rounds.mapping, "run", mapped_again)
    monkeypatch.setattr(pipeline_rounds.match, "matches_digest", lambda db: "digest")
    run = SimpleNamespace(out_dir=out, conf=make_config("sift-offline"), ctx=SimpleNamespace(images_root=tmp_path),
                          progress=False)
    pipeline_rounds._map_again(run, Round([("a", "b")], "repair"), tmp_path / "work.db", {})
    assert len(colmap.registered_images(killed / "sparse" / "0")) == views_after  # the kill left the round's model

    pipeline_rounds.recover(killed)  # what a run does first
    assert len(colmap.registered_images(killed / "sparse" / "0")) == max(views_after, 8)
    record = records.read_record(killed, mapping.STAGE)
    assert record["info"]["num_registered"] == max(views_after, 8)
    assert record["outputs"]["sparse"] == mapping.model_digest(killed / "sparse")
    assert not (killed / ".sara" / pipeline_rounds.BEFORE_ROUND).exists()
    assert not (killed / ".sara" / pipeline_rounds.BEFORE_RECORD).exists()
    assert not list((killed / "sparse").glob("*.json"))


@pytest.mark.parametrize("committed", [False, True])
def test_a_run_killed_inside_a_rounds_mapping_keeps_the_model_it_started_from(tmp_path: Path, monkeypatch, committed):
    """Killed while the round's mapping ran (its record only started): before the round's matches
    were committed, the map stage's record goes back to the earlier one; after, the model the round
    started from is kept as the model of the committed matches."""
    import shutil
    from types import SimpleNamespace

    from model_utils import ring_poses, write_text_model
    from sara import colmap, mapping
    from sara.config import make_config
    from sara.io import records
    from sara.pairs import Round
    from sara.pipeline import rounds as pipeline_rounds

    out, killed = tmp_path / "out", tmp_path / "killed"
    poses = ring_poses(8)
    write_text_model(out / "sparse" / "0", poses)
    records.mark_done(out, mapping.STAGE, "matches-before", {"num_registered": 8, "num_components": 1, "time_s": 1.0},
                      outputs={"sparse": mapping.model_digest(out / "sparse")})
    database = {"matches": "before"}

    def mapped_again(conf, db, images, out_dir, *, commit, input_model, **kwargs):
        records.mark_started(out_dir, mapping.STAGE, "matches-after")
        if committed:
            commit()
        shutil.copytree(out_dir, killed)  # the folder as a kill here leaves it
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline_rounds.mapping, "run", mapped_again)
    monkeypatch.setattr(pipeline_rounds.match, "commit", lambda *args: database.update(matches="after"))
    monkeypatch.setattr(pipeline_rounds, "_commit_pairs", lambda *args: None)
    monkeypatch.setattr(pipeline_rounds.match, "matches_digest", lambda db: database["matches"])
    run = SimpleNamespace(out_dir=out, conf=make_config("sift-offline"), ctx=SimpleNamespace(images_root=tmp_path),
                          progress=False)
    with pytest.raises(KeyboardInterrupt):
        pipeline_rounds._map_again(run, Round([("a", "b")], "repair"), tmp_path / "work.db", {})

    pipeline_rounds.recover(killed)  # what a run does first
    record = records.read_record(killed, mapping.STAGE)
    assert record["done"] is True and record["key"] == ("matches-after" if committed else "matches-before")
    assert record["info"]["num_registered"] == 8
    assert len(colmap.registered_images(killed / "sparse" / "0")) == 8
    assert record["outputs"]["sparse"] == mapping.model_digest(killed / "sparse")
    assert not (killed / ".sara" / pipeline_rounds.BEFORE_ROUND).exists()


def test_fully_scored_views_have_no_more_keypoints_than_the_scorer_uses_and_a_nearest_neighbour_matcher(tmp_path: Path):
    from types import SimpleNamespace

    import h5py
    import numpy as np

    from sara.config import make_config
    from sara.io.h5 import Features, write_features
    from sara.pairs.sara import rounds as sara_rounds

    path = tmp_path / "features.h5"
    with h5py.File(path, "w") as h5:
        for name, num in (("few.png", 200), ("edge.png", 1024), ("many.png", 5000)):
            write_features(h5, name, Features(np.zeros((num, 2), np.float32), np.zeros((num, 128), np.float32),
                                              np.ones(num, np.float32), (640, 480)))
    ctx = SimpleNamespace(features_path=path, conf=make_config("sift-offline"))
    assert ctx.conf.score.num_keypoints == 1024
    assert sara_rounds._fully_scored(ctx, {"few.png", "edge.png", "many.png"}) == {"few.png", "edge.png"}
    # LightGlue finds matches the scorer's nearest neighbours miss: no count holds a pair back
    ctx.conf = make_config("sift-offline", {"extract.backend": "aliked-n16", "match.backend": "auto"})
    assert sara_rounds._fully_scored(ctx, {"few.png", "edge.png", "many.png"}) == set()
    ctx.conf = make_config("sift-offline", {"match.backend": "nearest"})
    assert sara_rounds._fully_scored(ctx, {"few.png", "many.png"}) == {"few.png"}
