"""Ordered captures: frame orders from names, the descriptors' agreement, the window candidates,
and the mapper's start from views that moved forward."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sara.config import SequenceConfig, make_config
from sara.pairs.sara import sequence


def _names(n: int, pattern: str = "frame_{:06d}.png") -> list[str]:
    return [pattern.format(i) for i in range(n)]


def test_numbered_names_give_one_order_by_number_not_by_text():
    names = ["f10.png", "f9.png", "f100.png", "f8.png"]
    assert sequence.frame_orders(names) == [[3, 1, 0, 2]]


def test_two_videos_are_two_sequences_and_other_names_no_order():
    names = _names(4, "a_{:03d}.jpg") + _names(5, "b/{:04d}.JPG")
    orders = sequence.frame_orders(names)
    assert sorted(map(len, orders)) == [4, 5]
    assert sequence.frame_orders(["castle.png", "tower.png", "gate.png", "frame_1.png"]) == []


def test_a_few_unnumbered_names_among_many_frames_keep_the_order():
    names = _names(30) + ["cover.png"]
    assert len(sequence.frame_orders(names)) == 1
    assert sequence.frame_orders(_names(5) + ["a.png", "b.png"]) == []  # 5/7 < MIN_COVERED


def _walk_descriptors(n: int, seed: int = 0) -> np.ndarray:
    """Descriptors of a camera walking on: each frame close to its neighbours."""
    rng = np.random.default_rng(seed)
    return np.cumsum(rng.normal(size=(n, 64)), axis=0)


def test_auto_uses_the_order_only_when_the_looks_agree():
    names, desc = _names(40), _walk_descriptors(40)
    conf = SequenceConfig(mode="auto", auto_min_frames=40)
    found = sequence.detect(names, desc, conf)
    assert found.used and found.agreement > 0.9
    shuffled = np.random.default_rng(1).permutation(40)
    unrelated = sequence.detect(names, desc[shuffled], conf)  # numbered like a phone, shot anywhere
    assert not unrelated.used and not unrelated.too_short and unrelated.agreement < conf.min_agreement
    assert sequence.detect(names, desc[shuffled], SequenceConfig(mode="yes")).used
    assert not sequence.detect(names, desc, SequenceConfig(mode="no")).used


def test_a_long_walk_over_the_same_streets_counts_at_ten_times_chance():
    """Three passes over one path: most nearest neighbours lie on the other passes, so the agreement is
    below min_agreement, yet far above what a shuffled order gives; for 40 frames the bar stays 0.5."""
    rng = np.random.default_rng(0)
    path = np.cumsum(rng.normal(size=(300, 64)), axis=0)
    desc = np.concatenate([path + rng.normal(scale=0.3, size=path.shape) for _ in range(3)])
    names, conf = _names(900), SequenceConfig(mode="auto")
    found = sequence.detect(names, desc, conf)
    chance = sequence.chance_agreement(found.orders, len(names), conf.window)
    assert chance == pytest.approx(2 * conf.window / 899, rel=0.01)
    assert found.used and found.agreement < conf.min_agreement and found.needed == pytest.approx(10 * chance)
    assert found.summary("auto", 0)["agreement_needed"] == round(found.needed, 4)  # what run.json records
    shuffled = sequence.detect(names, desc[rng.permutation(900)], conf)
    assert not shuffled.used and shuffled.agreement < 2 * chance
    assert sequence.detect(_names(40), _walk_descriptors(40), conf).needed == conf.min_agreement


def test_auto_leaves_a_short_sequence_to_the_retrieval_neighbours():
    """Under auto_min_frames frames (the default 500) auto records the order and its agreement but does
    not use it; yes does."""
    names, desc = _names(40), _walk_descriptors(40)
    found = sequence.detect(names, desc, SequenceConfig())
    assert SequenceConfig().mode == "auto" and len(found.orders) == 1 and found.agreement > 0.9
    assert not found.used and found.too_short
    assert sequence.detect(names, desc, SequenceConfig(mode="yes")).used


def test_yes_without_numbered_names_is_a_clear_error():
    with pytest.raises(ValueError, match="do not number frames"):
        sequence.detect(["a.png", "b.png", "c.png"], None, SequenceConfig(mode="yes"))


def test_window_pairs_follow_each_sequence_not_across():
    orders = [[0, 1, 2, 3], [4, 5, 6]]
    pairs = sequence.window_pairs(orders, 2).tolist()
    assert pairs == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3], [4, 5], [4, 6], [5, 6]]


def test_sequence_mode_is_a_config_key_and_a_flag():
    assert make_config("sift-offline", {"sequence.mode": "no"}).sequence.mode == "no"
    from sara.cli.parser import build_parser

    args = build_parser().parse_args(["run", "IMAGES", "OUT", "--sequence", "yes"])
    from sara.cli.commands import config_from_args

    assert config_from_args(args).sequence.mode == "yes"


def test_the_mapper_starts_from_forward_motion_when_nothing_else_starts(monkeypatch, tmp_path: Path):
    """COLMAP refuses to start from views that moved along the optical axis; a forward drive has
    no other pair, so the map stage asks again with that refusal lifted, and says so."""
    from sara import colmap, mapping
    from sara.colmap.sfm import MappedModels

    calls: list[bool] = []

    class Rec:
        def num_reg_images(self) -> int:
            return 7

    def fake_mapping(*args, forward_start=False, **kwargs):
        calls.append(forward_start)
        return MappedModels({0: Rec()} if forward_start else {})

    monkeypatch.setattr(colmap, "incremental_mapping", fake_mapping)
    monkeypatch.setattr(colmap, "database_images", lambda db: {})
    # the check itself: test_consistency.py
    monkeypatch.setattr(MappedModels, "agreement", lambda self, db, n: colmap.Agreement(0))
    monkeypatch.setattr(colmap, "verified_graph", lambda db, min_inliers: (10, 7, [7], 200))
    recs, _, _ = mapping._map(make_config("sift-offline", {}).map, tmp_path / "db", tmp_path, tmp_path, 0, False)
    assert calls == [False, True] and recs.forward_start and recs.largest == 7


@pytest.mark.parametrize("first, joined, forward, expected", [
    (2, 51, 51, [False, False, True, 51]),  # a start that could not grow (kitti-seq1, seed 0): the distortion
                                            # held first (no more views), then a forward pair: kept
    (5, 51, 3, [False, False, True, 5]),  # the retry holds fewer views: the first kept (before it,
                                          # the distortion held: test_map_schedule.py)
    (30, 51, 51, [False, 30]),        # more than half the joined views: no retry
])
def test_a_first_model_far_smaller_than_the_joined_views_is_mapped_again_from_a_forward_pair(
        monkeypatch, tmp_path: Path, first, joined, forward, expected):
    from sara import colmap, mapping
    from sara.colmap.sfm import MappedModels

    calls: list = []

    class Rec:
        def __init__(self, n: int):
            self.n = n

        def num_reg_images(self) -> int:
            return self.n

    def fake_mapping(*args, forward_start=False, **kwargs):
        calls.append(forward_start)
        return MappedModels({0: Rec(forward if forward_start else first)})

    monkeypatch.setattr(colmap, "incremental_mapping", fake_mapping)
    monkeypatch.setattr(colmap, "database_images", lambda db: {})
    # the check itself: test_consistency.py
    monkeypatch.setattr(MappedModels, "agreement", lambda self, db, n: colmap.Agreement(0))
    monkeypatch.setattr(colmap, "verified_graph", lambda db, min_inliers: (100, joined, [joined], 200))
    recs, _, _ = mapping._map(make_config("sift-offline", {}).map, tmp_path / "db", tmp_path, tmp_path, 0, False)
    assert calls + [recs.largest] == expected
    assert recs.forward_start == (recs.largest > first)


def test_low_texture_is_said_before_matching_with_the_backend_to_try():
    from sara.pipeline import advice

    text = advice.low_texture({"num_images": 48, "keypoints_mean": 251.0}, "sift")
    assert "251 keypoints per image" in text and "--preset aliked-lightglue" in text
    assert advice.low_texture({"num_images": 48, "keypoints_mean": 4000.0}, "sift") == ""
    assert advice.low_texture({"num_images": 48, "keypoints_mean": 251.0}, "aliked") == ""
    assert "camera is a guess" not in text  # EXIF gave it (no focal check in the record)
    guessed = {"prior_px": 384.0, "estimated_px": 80.0, "applied": False, "sound": False}
    text = advice.low_texture({"num_images": 47, "keypoints_mean": 211.0, "focal": guessed}, "sift")
    assert "camera is a guess (focal length 384 px" in text and "extract.camera_params" in text
    assert "map.hold_distortion_starved" in text and "-s map.refine_distortion=false" in text
    applied = {**guessed, "estimated_px": 1500.0, "applied": True}
    assert "a guess" not in advice.low_texture({"num_images": 47, "keypoints_mean": 211.0, "focal": applied}, "sift")


def test_starved_means_few_sift_keypoints_and_a_camera_guessed():
    from sara.pipeline import advice

    few, many = {"num_images": 47, "keypoints_mean": 211.0}, {"num_images": 47, "keypoints_mean": 4000.0}
    assert advice.starved({**few, "cameras_guessed": [1, 1]}, "sift")
    assert advice.starved({**few, "cameras_guessed": [1, 2]}, "sift")
    assert not advice.starved({**few, "cameras_guessed": [0, 2]}, "sift")  # EXIF or camera_params gave them
    assert not advice.starved(few, "sift")  # a record made before sara counted them: not known
    assert not advice.starved({**many, "cameras_guessed": [1, 1]}, "sift")
    assert not advice.starved({**few, "cameras_guessed": [1, 1]}, "aliked")


def test_a_starved_capture_is_mapped_with_the_distortion_held_from_the_start(synthetic_scene, scene_features,
                                                                            tmp_path: Path, monkeypatch):
    """A capture without EXIF whose SIFT keypoints count as starved (the bar raised above the
    synthetic scene's count: its rendered points give no matches at a few hundred keypoints): the
    first mapping holds the lens distortion and says so; with the option off it is refined."""
    import json

    from harness import run_redirected
    from sara import mapping
    from sara.pipeline import advice, share_features

    monkeypatch.setattr(advice, "LOW_TEXTURE_KEYPOINTS", 100_000)
    refined, real_map = [], mapping._map
    monkeypatch.setattr(mapping, "_map", lambda conf, *a, **k: refined.append(conf.refine_distortion) or real_map(
        conf, *a, **k))
    images, _ = synthetic_scene
    for setting, held in (("true", True), ("false", False)):
        out = tmp_path / setting
        share_features(scene_features, out)  # the scene's features, made once for the session
        result = run_redirected("run", images, out, "-q", "-s", f"map.hold_distortion_starved={setting}")
        assert result.code == 0, result.err
        assert refined[0] is not held  # the first mapping; the rounds' continue as it did
        assert ("the lens distortion is held while mapping" in result.err) is held
        assert json.loads((out / "run.json").read_text())["stages"]["map"]["distortion_held"] is held
        refined.clear()


def test_a_run_with_starved_sift_records_and_prints_the_advice(synthetic_scene, tmp_path: Path):
    """A real run, cut to 200 SIFT features per image: the warning reaches the console and run.json."""
    import json
    import shutil

    from harness import run_redirected

    images = tmp_path / "images"  # three of the scene's views: the advice reads the mean, not the count
    images.mkdir()
    for path in sorted(synthetic_scene[0].iterdir())[:3]:
        shutil.copyfile(path, images / path.name)
    out = tmp_path / "out"
    result = run_redirected("pairs", images, out, "-s", "extract.max_num_features=200", "-q", "--method", "exhaustive")
    assert result.code == 0, result.err
    assert "keypoints per image on average" in result.err
    assert json.loads((out / "run.json").read_text())["stages"]["extract"]["low_texture"] is True


def test_images_shaped_as_360_degree_panoramas_get_the_advice(synthetic_scene, tmp_path: Path):
    """2:1 images, as a 360-degree camera writes them: the run says before matching that COLMAP's
    cameras cannot describe them; 16:9 frames, and a few 2:1 images among others, are silent."""
    from PIL import Image

    from harness import run_redirected
    from sara.pipeline import advice

    assert advice.count_panoramas({"a": (5760, 2880), "b": (3841, 1920), "c": (3840, 2160), "d": (400, 200)}) == 2
    assert advice.panoramas({"panoramas": 3, "num_images": 4}) and not advice.panoramas({"panoramas": 1,
                                                                                         "num_images": 4})
    images = tmp_path / "images"
    images.mkdir()
    for path in sorted(synthetic_scene[0].iterdir())[:4]:
        Image.open(path).resize((1200, 600)).save(images / path.name)
    result = run_redirected("pairs", images, tmp_path / "out", "-q", "--method", "exhaustive")
    assert result.code == 0, result.err
    assert "4 of the 4 images are twice as wide as high" in result.err and "360-degree camera" in result.err


def test_images_of_their_own_guessed_cameras_get_the_advice(synthetic_scene, tmp_path: Path):
    """Photos of different sizes without EXIF: a camera each, each from a guessed focal length; the
    run says so before matching. One camera (same size) or cameras with EXIF focal lengths: silent."""
    import json

    from PIL import Image

    from harness import run_redirected
    from sara.pipeline import advice

    assert advice.guessed_cameras({"cameras_guessed": [30, 30]})
    assert not advice.guessed_cameras({"cameras_guessed": [1, 30]})  # most focal lengths from EXIF
    for mode in ("per_video", "per_sequence"):  # two clips: each camera's guess refined from all its frames
        assert not advice.guessed_cameras({"cameras_guessed": [2, 2], "camera_mode": mode})
    assert not advice.guessed_cameras({"camera_mode": "single"})
    images = tmp_path / "images"
    images.mkdir()
    for k, path in enumerate(sorted(synthetic_scene[0].iterdir())[:4]):
        im = Image.open(path)
        im.resize((im.width - 8 * k, im.height - 6 * k)).save(images / path.name)  # each its own size
    out = tmp_path / "out"
    result = run_redirected("pairs", images, out, "-q", "--method", "exhaustive")
    assert result.code == 0, result.err
    assert "4 of the 4 cameras" in result.err and "no EXIF focal length" in result.err
    assert json.loads((out / ".sara" / "extract.json").read_text())["info"]["cameras_guessed"] == [4, 4]
    same = tmp_path / "same"
    same.mkdir()
    for path in sorted(synthetic_scene[0].iterdir())[:4]:
        Image.open(path).save(same / path.name)
    result = run_redirected("pairs", same, tmp_path / "out_same", "-q", "--method", "exhaustive")
    assert result.code == 0 and "no EXIF focal length" not in result.err


@pytest.mark.parametrize("per_frame, expected", [
    (1, {(0, 2), (2, 4), (4, 5)}),
    (2, {(0, 2), (0, 1), (2, 4), (3, 2), (4, 5)}),
    (0, set()),
])
def test_the_chain_takes_each_frames_best_left_out_candidate_among_the_next_frames(per_frame, expected):
    """Frames 0-5 in one sequence, view 6 in none, window 2: each frame's best unselected accepted
    candidate among the two frames after it becomes "chain"; selected, rejected, too distant and
    unordered candidates are left as they were."""
    from types import SimpleNamespace

    from sara.pairs.sara.source import chain_through_time, is_selected

    candidates = {(0, 1): ("unselected", 0.2), (0, 2): ("unselected", 0.5), (0, 3): ("unselected", 0.9),
                  (1, 2): ("tree", 0.3), (1, 3): ("rejected", 0.9), (3, 2): ("unselected", 0.3),
                  (2, 4): ("unselected", 0.4), (4, 5): ("unselected", 0.1), (5, 6): ("unselected", 1.0),
                  (0, 5): ("unselected", 0.8)}
    edges = np.array(list(candidates), dtype=np.int64)
    roles = [role for role, _ in candidates.values()]
    scores = SimpleNamespace(weight=np.array([w for _, w in candidates.values()]))
    conf = make_config("sift-offline", {"sequence.window": 2, "sequence.chain": per_frame}).sequence
    added = chain_through_time(edges, roles, scores, [[0, 1, 2, 3, 4, 5]], conf)
    chained = {pair for pair, role in zip(candidates, roles) if role == "chain"}
    assert added == len(expected) and chained == expected
    assert all(is_selected(role) for role in roles if role == "chain") and roles[3] == "tree" and roles[4] == "rejected"
    # a chain never joins two sequences
    roles = [role for role, _ in candidates.values()]
    chain_through_time(edges, roles, scores, [[0, 1, 2], [3, 4, 5]], conf)
    assert roles[5] == "unselected"  # (3, 2): frames of two sequences


def test_sara_pairs_on_a_sequence_selects_each_frames_chain_pair(synthetic_scene, scene_features, tmp_path: Path):
    """`sara pairs --sequence yes` on the numbered synthetic frames: each frame whose candidates among
    the window's next frames were left out by the selection gets its best one (role chain in
    scores.csv, in pairs.txt, counted in run.json)."""
    import csv
    import json

    from harness import run_redirected
    from sara.io.pairs import read_pairs
    from sara.pipeline import share_features

    images, _ = synthetic_scene
    out = tmp_path / "out"
    share_features(scene_features, out)
    result = run_redirected("pairs", images, out, "--sequence", "yes", "-q")
    assert result.code == 0, result.err
    rows = list(csv.DictReader(open(out / "scores.csv")))
    window = SequenceConfig().window
    frame = {name: int(name.rsplit("frame", 1)[1].split(".")[0]) for r in rows for name in (r["name0"], r["name1"])}
    left_out: dict[str, list[tuple[float, int, tuple[str, str]]]] = {}
    for k, r in enumerate(rows):  # the best weight; on a tie the candidate listed first
        a, b = sorted((r["name0"], r["name1"]), key=frame.get)
        if r["role"] in ("unselected", "chain") and 0 < frame[b] - frame[a] <= window:
            left_out.setdefault(a, []).append((float(r["weight"]), -k, (r["name0"], r["name1"])))
    expected = {max(options)[2] for options in left_out.values()}
    chained = {(r["name0"], r["name1"]) for r in rows if r["role"] == "chain"}
    assert chained and chained == expected
    assert chained <= {tuple(p) for p in read_pairs(out / "pairs.txt")}
    record = json.loads((out / "run.json").read_text())
    assert record["stages"]["pairs"]["num_chain"] == len(chained)


def test_views_moving_straight_ahead_without_the_intrinsics_get_the_advice_to_give_them():
    """After a mapping that could start only from a pair moving along the optical axis, the run says
    that the principal point is not found from such views (kitti-seq1: AUC@1 0.03
    with the guess, 0.68 with its calibration), unless the intrinsics were given."""
    from sara.pipeline import advice

    guessed = {"settings": {"camera_params": ""}, "cameras_guessed": [1, 1]}
    text = advice.forward_guess(guessed, {"forward_start": True})
    assert "principal point" in text and "-s extract.camera_params=fx,fy,cx,cy" in text
    assert advice.forward_guess(guessed, {"forward_start": False}) == ""
    assert advice.forward_guess(guessed, {}) == ""  # no model, or a record from before
    given = {"settings": {"camera_params": "707,707,602,183"}, "cameras_guessed": [0, 1]}
    assert advice.forward_guess(given, {"forward_start": True}) == ""
    exif = {"settings": {"camera_params": ""}, "cameras_guessed": [0, 1]}  # EXIF's focal length, the centre a guess
    assert advice.forward_guess(exif, {"forward_start": True}) == text


def test_a_calibrated_drive_keeps_the_papers_weight_in_its_spanning_tree(tmp_path: Path, run_cli):
    """kitti-seq1's first 8 frames with their calibration (an 82-degree field of view, which alone
    would rank the tree by overlap): the scorer's poses show the views moving along their axes, so
    the tree keeps the paper's weight, and the record says why."""
    import shutil

    from harness import scene_dir
    from sara.io import read_json

    scene = scene_dir("kitti-seq1")
    images = tmp_path / "images"
    images.mkdir()
    for path in sorted((scene / "images").iterdir())[:8]:
        shutil.copy(path, images / path.name)
    calibration = ("-s", "extract.camera_model=PINHOLE", "-s",
                   "extract.camera_params=707.0912,707.0912,601.8873,183.1104")
    result = run_cli("pairs", images, tmp_path / "out", "-q", *calibration)
    assert result.code == 0, result.err
    pairs = read_json(tmp_path / "out" / "run.json")["stages"]["pairs"]
    assert pairs["field_of_view_deg"] == pytest.approx(81.8, abs=0.1) and pairs["axial_motion"] > 0.99
    assert pairs["moving_ahead"] and pairs["tree_overlap"] == "best"
