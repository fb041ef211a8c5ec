"""The incremental mapper's global bundle adjustments: COLMAP's schedule and refinement rounds below
`LARGE_SCENE_IMAGES` images, sparser and fewer from there, or the user's settings; and that they
reach pycolmap's options."""

from __future__ import annotations

from pathlib import Path

import pytest

from sara.config import ConfigError, make_config


@pytest.mark.parametrize("setting, num_images, expected", [
    (0.0, 119, None),     # the shared scenes: COLMAP's own schedule
    (0.0, 499, None),
    (0.0, 500, 1.4),
    (0.0, 10_000, 1.4),
    (1.2, 50, 1.2),       # the user's factor at any size
    (1.1, 3_000, 1.1),
])
def test_the_schedule_follows_the_size_unless_set(setting, num_images, expected):
    from sara import mapping

    conf = make_config("sift-offline", {"map.ba_global_growth": setting}).map
    assert mapping.ba_global_growth(conf, num_images) == expected


@pytest.mark.parametrize("bad", [1.0, 0.5, -1.0, float("nan")])
def test_a_growth_that_never_grows_is_refused(bad):
    with pytest.raises(ConfigError, match="ba_global_growth"):
        make_config("sift-offline", {"map.ba_global_growth": bad})


@pytest.mark.parametrize("setting, num_images, expected", [
    (0, 119, None),       # the shared scenes: COLMAP's 5
    (0, 499, None),
    (0, 500, 1),
    (3, 10_000, 3),       # the user's count at any size
    (5, 600, 5),
])
def test_the_refinement_rounds_follow_the_size_unless_set(setting, num_images, expected):
    from sara import mapping

    conf = make_config("sift-offline", {"map.ba_global_refinements": setting}).map
    assert mapping.ba_global_refinements(conf, num_images) == expected


def test_a_negative_refinement_count_is_refused():
    with pytest.raises(ConfigError, match="ba_global_refinements"):
        make_config("sift-offline", {"map.ba_global_refinements": -1})


@pytest.mark.parametrize("setting, num_images, expected", [
    (0, 999, None),       # COLMAP's own loop, whose solver is direct up to 1,000 images anyway
    (0, 1000, 20_000),    # sara's step-by-step loop, direct up to 20,000
    (0, 10_000, 20_000),
    (2000, 50, 2000),     # the user's limit at any size
])
def test_the_direct_solver_limit_follows_the_size_unless_set(setting, num_images, expected):
    from sara import mapping

    conf = make_config("sift-offline", {"map.ba_direct_max_images": setting}).map
    assert mapping.ba_direct_max_images(conf, num_images) == expected


def test_a_large_scene_is_mapped_step_by_step_with_the_direct_solver(monkeypatch, tmp_path: Path):
    """From 1,000 images the map stage hands the mapping to `colmap.stepwise` with its limit;
    below, to pycolmap's own loop (the test above)."""
    from sara import colmap, mapping
    from sara.colmap import stepwise

    seen: list = []

    def fake_stepwise(db, images, out, opts, *, direct_up_to, on_next_image, input_path, first_image_id=None,
                      checkpoint=None):
        seen.append((direct_up_to, opts.ba_global_max_refinements, opts.ba_global_frames_ratio))
        return {}

    monkeypatch.setattr(stepwise, "incremental_mapping", fake_stepwise)
    monkeypatch.setattr(colmap, "database_images", lambda db: dict.fromkeys(range(1200)))
    monkeypatch.setattr(colmap, "verified_graph", lambda db, min_inliers: (0, 0, [], 0))
    mapping._map(make_config("sift-offline", {}).map, tmp_path / "db", tmp_path, tmp_path, 0, False)
    assert seen
    assert all(limit == 20_000 and rounds == 1 and ratio == pytest.approx(1.4) for limit, rounds, ratio in seen)


@pytest.mark.parametrize("num_images, expected, refinements", [(40, 1.1, 5), (600, 1.4, 1)])
def test_the_map_stage_hands_the_schedule_to_pycolmap(monkeypatch, tmp_path: Path, num_images, expected,
                                                      refinements):
    """Through the map stage and sara's call of pycolmap, down to the options pycolmap receives."""
    import pycolmap

    from sara import colmap, mapping

    seen: list = []

    def fake_pycolmap_mapping(db, images, out, *, options, input_path, next_image_callback):
        seen.append((options.ba_global_frames_ratio, options.ba_global_points_ratio,
                     options.ba_global_max_refinements))
        return {}

    monkeypatch.setattr(pycolmap, "incremental_mapping", fake_pycolmap_mapping)
    monkeypatch.setattr(colmap, "database_images", lambda db: dict.fromkeys(range(num_images)))
    monkeypatch.setattr(colmap, "verified_graph", lambda db, min_inliers: (0, 0, [], 0))
    mapping._map(make_config("sift-offline", {}).map, tmp_path / "db", tmp_path, tmp_path, 0, False)
    assert seen and all(frames == pytest.approx(expected) and points == pytest.approx(expected)
                        and rounds == refinements for frames, points, rounds in seen)


def test_a_model_mapped_before_the_setting_existed_is_not_mapped_again():
    """The default leaves the map stage's key as it was; a factor set by hand changes it."""
    import dataclasses

    from sara import mapping
    from sara.io import fingerprint

    conf = make_config("sift-offline", {}).map
    added = ("ba_global_growth", "ba_global_refinements", "ba_direct_max_images", "contradicted_remaps",
             "checkpoint_minutes", "refine_distortion", "mend_seam", "two_view_points")
    before = {k: v for k, v in conf.__dict__.items() if k not in added}
    assert mapping.state_key(conf, 0, "up") == fingerprint({"conf": before, "seed": 0, "upstream": "up"})
    # how often a long mapping keeps its models changes no model: never in the key
    assert mapping.state_key(dataclasses.replace(conf, checkpoint_minutes=0.0), 0, "up") == \
        mapping.state_key(conf, 0, "up")
    for setting in ({"ba_global_growth": 1.4}, {"ba_global_refinements": 1}, {"ba_direct_max_images": 3000},
                    {"contradicted_remaps": 0}, {"mend_seam": False}, {"two_view_points": True}):
        by_hand = dataclasses.replace(conf, **setting)
        assert mapping.state_key(by_hand, 0, "up") != mapping.state_key(conf, 0, "up")


@pytest.mark.parametrize("setting, refined", [({}, True), ({"map.refine_distortion": "false"}, False)])
def test_the_map_stage_hands_whether_distortion_is_refined_to_pycolmap(monkeypatch, tmp_path: Path, setting,
                                                                       refined):
    import pycolmap

    from sara import colmap, mapping

    seen: list = []

    def fake_pycolmap_mapping(db, images, out, *, options, input_path, next_image_callback):
        seen.append(options.ba_refine_extra_params)
        return {}

    monkeypatch.setattr(pycolmap, "incremental_mapping", fake_pycolmap_mapping)
    monkeypatch.setattr(colmap, "database_images", lambda db: dict.fromkeys(range(40)))
    monkeypatch.setattr(colmap, "verified_graph", lambda db, min_inliers: (0, 0, [], 0))
    mapping._map(make_config("sift-offline", setting).map, tmp_path / "db", tmp_path, tmp_path, 0, False)
    assert seen and all(value is refined for value in seen)


class _Rec:
    """A stand-in for a pycolmap model: only its size."""

    def __init__(self, n: int):
        self.n = n

    def num_reg_images(self) -> int:
        return self.n


@pytest.mark.parametrize("setting, refined, held, expected_calls, kept", [
    # (forward start, distortion refined) of each mapping
    ({}, 14, 47, [(False, True), (False, False)], 47),  # could not grow; held holds all: kept, no forward retry
    ({}, 14, 10, [(False, True), (False, False), (True, True)], 14),  # held holds fewer: the first kept
    ({}, 30, 47, [(False, True)], 30),                  # over half the joined views: no retry
    ({"map.refine_distortion": "false"}, 47, 14, [(False, False), (True, False)], 14),  # held already
])
def test_a_first_model_that_could_not_grow_is_mapped_again_with_the_distortion_held(
        monkeypatch, tmp_path: Path, setting, refined, held, expected_calls, kept):
    """The low-texture stand-in: the refined radial term ran away and the first models held 7-16 of
    47 views; with it held, 47. The retry runs where the forward retry does (under half the joined
    views), before it, and its model replaces the first only when it holds more views."""
    from sara import colmap, mapping
    from sara.colmap.sfm import MappedModels

    calls: list[tuple[bool, bool]] = []

    def fake_mapping(*args, refine_extra_params=True, forward_start=False, **kwargs):
        calls.append((forward_start, refine_extra_params))
        return MappedModels({0: _Rec(refined if refine_extra_params else held)})

    monkeypatch.setattr(colmap, "incremental_mapping", fake_mapping)
    monkeypatch.setattr(colmap, "database_images", lambda db: dict.fromkeys(range(47)))
    monkeypatch.setattr(MappedModels, "agreement", lambda self, db, n: colmap.Agreement(0))
    monkeypatch.setattr(colmap, "verified_graph", lambda db, min_inliers: (200, 47, [47], 100))
    recs, _, _ = mapping._map(make_config("sift-offline", setting).map, tmp_path / "db", tmp_path, tmp_path, 0, False)
    assert calls == expected_calls
    assert recs.largest == kept
    assert recs.distortion_held == (kept == held != refined and not setting)


def test_the_rounds_continue_a_model_mapped_with_the_distortion_held_with_it_held(monkeypatch, tmp_path: Path):
    """The map stage records that its model was mapped with the distortion held; a continuation of
    that model (the rounds' mappings) holds it too, and the record keeps saying so."""
    from sara import colmap, mapping
    from sara.colmap.sfm import MappedModels
    from sara.io import records

    conf = make_config("sift-offline", {}).map
    seen: list[bool] = []

    def fake_extend(conf, db_path, images_root, tmp, seed, progress, input_model, min_num_inliers):
        seen.append(conf.refine_distortion)
        return MappedModels({0: _Rec(5)}), 5, 0.1

    monkeypatch.setattr(mapping, "_extend", fake_extend)
    monkeypatch.setattr(MappedModels, "write_by_size", lambda self, folder: [5])
    monkeypatch.setattr(MappedModels, "agreement", lambda self, db, n: colmap.Agreement(10))
    for held in (True, False):
        out = tmp_path / str(held)
        records.mark_done(out, mapping.STAGE, "before", {"mapper": "incremental", "distortion_held": held})
        mapping.run(conf, tmp_path / "db", tmp_path, out, input_model=tmp_path / "model", progress=False)
        assert seen[-1] is not held
        assert records.done_info(out, mapping.STAGE)["distortion_held"] is held


@pytest.mark.parametrize("fisheye, setting, held", [
    (True, {}, True),     # a fisheye model: held from the first mapping on
    (False, {}, False),   # the default camera: refined, as COLMAP does
    (True, {"map.refine_distortion": "false"}, True),  # held anyway
])
def test_a_fisheye_camera_is_mapped_with_its_distortion_held(monkeypatch, tmp_path: Path, fisheye, setting, held):
    """fountain-P11 through a fisheye lens, OPENCV_FISHEYE: the four distortion terms fitted to the
    first model of SARA's few pairs left 7 of 11 views registered (0.28 / 0.36); held, 11 (0.69 /
    0.94, exhaustive matching's). A first mapping of fisheye cameras holds them; the record says so."""
    from sara import colmap, mapping
    from sara.colmap.sfm import MappedModels
    from sara.io import records

    seen: list[bool] = []

    def fake_map(conf, *args, **kwargs):
        seen.append(conf.refine_distortion)
        return MappedModels({0: _Rec(11)}), 11, 0.1

    monkeypatch.setattr(mapping, "_map", fake_map)
    monkeypatch.setattr(colmap, "fisheye_cameras", lambda db: [1] if fisheye else [])
    monkeypatch.setattr(MappedModels, "write_by_size", lambda self, folder: [11])
    monkeypatch.setattr(mapping, "_first_model_check", lambda recs, previous: {})
    mapping.run(make_config("sift-offline", setting).map, tmp_path / "db", tmp_path, tmp_path / "out", progress=False)
    assert seen == [not held]
    assert records.done_info(tmp_path / "out", mapping.STAGE)["distortion_held"] is (held and not setting)
