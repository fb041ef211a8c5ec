"""Class 7 of the fault suite: options and commands. An out-of-range option fails when parsed,
naming the option and its valid range (exit 2, nothing read or written); usage errors, `sara
evaluate` on what it cannot score, and too few images each give one line."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from harness import assert_error, assert_kept, assert_ok, best_matched_pair, registered, snapshot, truncate

BAD_VALUES = {
    "--seed -1": (["--seed", "-1"], "--seed", "from 0 to 2147483647"),
    "--seed 2**31": (["--seed", str(2**31)], "seed must be"),
    "--workers -1": (["--workers", "-1"], "--workers", "execute.workers must be an integer >= 0"),
    "zero features": (["-s", "extract.max_num_features=0"], "extract.max_num_features", ">= 1"),
    "negative image size": (["-s", "extract.max_image_size=-5"], "extract.max_image_size", ">= 32"),
    "NaN weight exponent": (["-s", "score.alpha=nan"], "score.alpha", "finite"),
    "infinite weight exponent": (["-s", "score.beta=inf"], "score.beta", "finite"),
    "zero chunk size": (["-s", "match.chunk_size=0"], "match.chunk_size", ">= 1"),
    "zero shard size": (["-s", "execute.shard_size=0"], "execute.shard_size", ">= 1"),
    "zero neighbours": (["-s", "retrieval.num_neighbors=0"], "retrieval.num_neighbors", ">= 1"),
    "ratio above 1": (["-s", "match.max_ratio=1.5"], "match.max_ratio", "(0, 1]"),
    "model of one image": (["-s", "map.min_model_size=1"], "map.min_model_size", ">= 2"),
    "inliers above matches": (["-s", "score.min_inliers=100"], "score.min_inliers", "score.num_matches"),
    "unknown camera model": (["-s", "extract.camera_model=FOO"], "extract.camera_model", "PINHOLE"),
    "camera params not numbers": (["-s", "extract.camera_params=a,b"], "extract.camera_params", "comma-separated"),
    "unknown orientation mode": (["-s", "images.exif_orientation=rotate"], "images.exif_orientation", "ignore, apply"),
    "NaN budget": (["-s", "graph.loop_budget_ratio=nan"], "graph.loop_budget_ratio", "finite"),
    "negative rounds": (["-s", "rounds.repair_rounds=-1"], "rounds.repair_rounds", ">= 0"),
    "unknown device": (["-s", "extract.device=gpu"], "extract.device", "cuda"),
    "zero focal factor": (["-s", "extract.default_focal_length_factor=0"], "default_focal_length_factor", "(0, 100]"),
    "zero inlier ratio": (["-s", "map.abs_pose_min_inlier_ratio=0"], "map.abs_pose_min_inlier_ratio", "(0, 1]"),
    "not a number": (["-s", "score.alpha=abc"], "score.alpha", "not a float"),
    "unknown mapper flag": (["--mapper", "foo"], "--mapper", "invalid choice"),
    "unknown camera mode flag": (["--camera-mode", "x"], "--camera-mode", "invalid choice"),
}


@pytest.mark.parametrize("case", list(BAD_VALUES))
def test_out_of_range_option_fails_at_parse_time(case, finished_run_template, images, run_cli):
    """The message names the option and its valid range; nothing is read or written."""
    args, *fragments = BAD_VALUES[case]
    before = snapshot(finished_run_template)
    result = run_cli("run", images, finished_run_template, "-q", *args)
    assert_error(result, 2, *fragments)
    assert_kept(before, finished_run_template)


@pytest.mark.parametrize("argv,fragment", [
    (["demo", "--num-images", "1"], "--num-images"),
    (["nope"], "invalid choice"),
    (["run"], "required"),
], ids=["demo of one image", "unknown command", "missing arguments"])
def test_usage_errors_are_one_line(argv, fragment, run_cli):
    result = run_cli(*argv)
    assert_error(result, 2, fragment)


@pytest.fixture
def other_scene_gt(synthetic_scene, tmp_path) -> Path:
    """The ground truth with every image renamed: the truth of another scene."""
    gt = Path(shutil.copytree(synthetic_scene[1], tmp_path / "other_gt"))
    text = (gt / "images.txt").read_text()
    for name in sorted(os.listdir(synthetic_scene[0])):
        text = text.replace(name, "other_" + name)
    (gt / "images.txt").write_text(text)
    return gt


EVALUATE = {
    "folder without a model": (lambda t, o, g: (t, g), 2, "holds no COLMAP model"),
    "missing model folder": (lambda t, o, g: (t / "nope", g), 2, "does not exist"),
    "ground truth of another scene": (lambda t, o, g: (o, "OTHER"), 2, "share no image name", "another scene"),
    "missing ground truth": (lambda t, o, g: (o, t / "nope"), 2, "ground truth not found"),
    "damaged model": (lambda t, o, g: (_damaged_model(o), g), 2, "no readable COLMAP model"),
}


def _damaged_model(out: Path) -> Path:
    truncate(out / "sparse" / "0" / "images.bin", 0.5)
    return out


@pytest.mark.parametrize("case", list(EVALUATE))
def test_evaluate_refuses_what_it_cannot_score(case, finished_run, synthetic_scene, other_scene_gt, tmp_path,
                                               run_cli):
    make, code, *fragments = EVALUATE[case]
    model, gt = make(tmp_path / "empty", finished_run, synthetic_scene[1])
    (tmp_path / "empty").mkdir()
    gt = other_scene_gt if gt == "OTHER" else gt
    result = run_cli("evaluate", model, gt)
    assert_error(result, code, *fragments)


def test_evaluate_scores_a_model(finished_run, synthetic_scene, run_cli):
    result = run_cli("evaluate", finished_run, synthetic_scene[1])
    assert_ok(result)
    assert "num_registered" in result.out


def test_run_against_another_scenes_truth_fails_before_any_work(finished_run, images, other_scene_gt, run_cli):
    before = snapshot(finished_run)
    result = run_cli("run", images, finished_run, "-q", "--gt", other_scene_gt)
    assert_error(result, 2, "shares no image name", "another scene")
    assert_kept(before, finished_run)


def test_one_image_is_refused(images, tmp_path, run_cli):
    folder = tmp_path / "one"
    folder.mkdir()
    shutil.copyfile(sorted(images.iterdir())[0], folder / "only.png")
    result = run_cli("run", folder, tmp_path / "out", "-q")
    assert_error(result, 2, "only one usable image", "at least 2")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("mapper", ["incremental", "global"])
def test_two_views_make_a_model(mapper, images, synthetic_scene, finished_run_template, tmp_path, run_cli):
    """Two photos (the pair of the scene with the most inlier matches): COLMAP triangulates only points
    seen in three views or more, so it built no model of two views (exit 5 before); the mapper now maps
    again with the points seen in two, and both views are posed as the truth has them. The global
    mapper builds none of two views either: the incremental one then maps them, with its retries."""
    *two, inliers = best_matched_pair(finished_run_template)
    assert inliers > 100
    folder = tmp_path / "two"
    folder.mkdir()
    for name in two:
        shutil.copyfile(images / name, folder / name)
    result = run_cli("run", folder, tmp_path / "out", "-q", "-s", f"map.mapper={mapper}")
    assert_ok(result)
    assert "points seen in two views only" in result.err
    assert registered(tmp_path / "out") == sorted(two)
    info = json.loads((tmp_path / "out" / ".sara" / "map.json").read_text())["info"]
    assert info["two_view_points"] is True and info["mapper"] == "incremental"
    scored = run_cli("evaluate", tmp_path / "out" / "sparse" / "0", synthetic_scene[1], "--json", tmp_path / "m.json")
    assert_ok(scored)
    assert json.loads((tmp_path / "m.json").read_text())["rel_rotation_error_median_deg"] < 1.0


def test_two_views_that_never_moved_say_why_no_model(images, tmp_path, run_cli):
    """The same photo under two names: thousands of inlier matches and no triangulation angle at all.
    The message says what COLMAP's mapper lacks (the angle), not "too few verified matches"."""
    folder = tmp_path / "two"
    folder.mkdir()
    first = sorted(images.iterdir())[0]
    for name in ("a.png", "b.png"):
        shutil.copyfile(first, folder / name)
    result = run_cli("run", folder, tmp_path / "out", "-q")
    line = assert_error(result, 5, "no model could be built", "inlier matches", "16 degrees", "two views only")
    assert "too few verified matches" not in line
    assert not (tmp_path / "out" / "sparse").exists() and not (tmp_path / "out" / "report.md").exists()


def test_map_with_a_missing_image_folder(finished_run, tmp_path, run_cli):
    before = snapshot(finished_run)
    result = run_cli("map", finished_run, "--images", tmp_path / "gone", "-q")
    assert_error(result, 2, "not found", "--images")
    assert_kept(before, finished_run)


@pytest.mark.parametrize("command", ["match", "map"])
def test_match_or_map_where_extract_never_ran(command, tmp_path, run_cli):
    """An output folder whose extract stage never ran is an earlier stage unfinished: exit 3 for
    both commands, as the exit-code table says (issue 30: `sara match` gave 2)."""
    result = run_cli(command, tmp_path, "-q")
    assert_error(result, 3, "extract stage", "never ran", "sara extract")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command", ["match", "map"])
def test_match_or_map_on_a_missing_folder(command, tmp_path, run_cli):
    result = run_cli(command, tmp_path / "typo", "-q")
    assert_error(result, 2, "output folder not found", "typo")
    assert not (tmp_path / "typo").exists()


@pytest.mark.parametrize("case", ["no name in common", "same names, other pixels", "one image edited"])
def test_map_with_the_images_of_another_scene(case, finished_run, images, tmp_path, run_cli):
    """`sara map OUT --images F` colours the points from F: F must hold the images the features
    were made from (issue 30: it exited 0, with black points or another scene's colours)."""
    from PIL import Image

    folder = tmp_path / "other"
    if case == "no name in common":
        folder.mkdir()
        for k, path in enumerate(sorted(images.iterdir())):
            shutil.copyfile(path, folder / f"other_{k}.png")
    elif case == "same names, other pixels":
        folder.mkdir()
        for path in sorted(images.iterdir()):
            Image.open(path).transpose(Image.Transpose.FLIP_LEFT_RIGHT).save(folder / path.name)
    else:
        shutil.copytree(images, folder)
        first = sorted(folder.iterdir())[0]
        Image.open(first).rotate(5).save(first)
    before = snapshot(finished_run)
    result = run_cli("map", finished_run, "--images", folder, "-q")
    assert_error(result, 2, f"--images {folder}", "not hold the images", "image folder of the extraction")
    assert_kept(before, finished_run)


def test_map_with_a_copy_of_the_images(finished_run, images, tmp_path, run_cli):
    """A copy of the very images (other times, same bytes) is accepted."""
    folder = Path(shutil.copytree(images, tmp_path / "copy"))
    for path in folder.iterdir():
        os.utime(path, (1, 1))
    assert_ok(run_cli("map", finished_run, "--images", folder, "-q"))


@pytest.mark.parametrize("one_camera", [("--camera-mode", "single"), ("-s", "extract.camera_params=800,400,300,0")])
def test_one_camera_asked_for_images_of_two_sizes(one_camera, images, tmp_path, run_cli):
    """One camera for images of two sizes (`--camera-mode single`: COLMAP's extraction left the odd
    one out with a line in its own log only; `extract.camera_params`: it got intrinsics of another
    size, its principal point in a corner): the image of the rarer size is set aside with the reason,
    and the others are reconstructed."""
    from PIL import Image

    folder = tmp_path / "sizes"
    folder.mkdir()
    names = sorted(p.name for p in images.iterdir())
    for name in names:
        shutil.copyfile(images / name, folder / name)
    small = Image.open(images / names[0])
    small.resize((small.width // 2, small.height // 2)).save(folder / names[0])
    result = run_cli("run", folder, tmp_path / "out", "-q", *one_camera)
    assert_ok(result)
    skipped = json.loads((tmp_path / "out" / "run.json").read_text())["skipped_images"]
    assert set(skipped) == {names[0]} and "is not the one camera's" in skipped[names[0]]
    assert registered(tmp_path / "out") == names[1:]
