from pathlib import Path

from sara.pairs.repair import left_out_views, repair_pairs


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
