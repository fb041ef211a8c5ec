"""A model against the verified pairs between its views (`sara.colmap.consistency`), and the first
mapping done again under another seed when its model is contradicted (`sara.map_retries.agreeing`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from sara import colmap, map_retries, mapping
from sara.colmap.consistency import agreement
from sara.config import MapConfig
from sara.io import records


@pytest.fixture()
def scene(tmp_path: Path) -> tuple[pycolmap.Reconstruction, Path]:
    """pycolmap's synthetic scene of 6 views around one point cloud, its matches verified in a database."""
    pycolmap.set_random_seed(1)
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_cameras_per_rig, opts.num_frames_per_rig, opts.num_points3D = 1, 1, 6, 200
    db_path = tmp_path / "database.db"
    with pycolmap.Database.open(str(db_path)) as db:
        rec = pycolmap.synthesize_dataset(opts, db)
    return rec, db_path


def turned(rec: pycolmap.Reconstruction, image_id: int, degrees: float) -> pycolmap.Reconstruction:
    """A copy of `rec` with one view turned about its camera's y axis."""
    bent = pycolmap.Reconstruction(rec)
    frame = bent.frame(bent.image(image_id).frame_id)
    turn = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.0, np.sin(np.radians(degrees) / 2), 0.0,
                                                          np.cos(np.radians(degrees) / 2)])), np.zeros(3))
    frame.rig_from_world = turn * frame.rig_from_world
    return bent


def mapped_in_turn(monkeypatch, *models: pycolmap.Reconstruction) -> list[int]:
    """`mapping._incremental` replaced: its k-th call gives `models[k]` (the last one for every later
    call); returns the list the seeds of the calls go to."""
    seeds: list[int] = []

    def fake_incremental(conf, db, images, tmp, seed, progress, num_images, input_model, **kwargs):
        seeds.append(seed)
        return colmap.MappedModels({0: models[min(len(seeds), len(models)) - 1]})

    monkeypatch.setattr(mapping, "_incremental", fake_incremental)
    return seeds


def test_a_true_model_agrees_with_every_pair(scene):
    rec, db_path = scene
    check = agreement(rec, db_path)
    assert check.checked == 15 and check.contradicted == [] and check.share == 0.0


def test_a_model_folder_is_checked_as_written(scene, tmp_path):
    rec, db_path = scene
    turned(rec, 2, 3.0).write(str(tmp_path))
    assert len(colmap.model_agreement(tmp_path, db_path).contradicted) == 5


def test_a_view_turned_away_contradicts_exactly_its_pairs(scene):
    rec, db_path = scene
    name = rec.image(3).name
    check = agreement(turned(rec, 3, 3.0), db_path)
    assert check.checked == 15 and len(check.contradicted) == 5
    assert all(name in pair for pair in check.contradicted)
    assert check.most_contradicted_view() == name and agreement(rec, db_path).most_contradicted_view() is None
    # a turn far below the threshold (4 px at this focal length is about 0.2 degrees) is no contradiction
    assert agreement(turned(rec, 3, 0.01), db_path).contradicted == []


def test_a_contradicted_first_model_is_mapped_again_and_the_agreeing_one_kept(scene, tmp_path, monkeypatch, caplog):
    """The first mapping's model is contradicted by its pairs: the mapper runs again under the next
    seed, and the model every pair agrees with is kept, with the seed that built it."""
    rec, db_path = scene
    built = [turned(rec, 3, 3.0), rec]
    seeds = []

    starts = []

    def fake_incremental(conf, db, images, tmp, seed, progress, num_images, input_model, **kwargs):
        seeds.append(seed)
        starts.append((kwargs.get("first_image"), conf.num_threads))
        return colmap.MappedModels({0: built[len(seeds) - 1]})

    monkeypatch.setattr(mapping, "_incremental", fake_incremental)
    with caplog.at_level("WARNING", logger="sara.mapping"):
        recs, _, _ = mapping._map(MapConfig(), db_path, tmp_path, tmp_path, seed=7, progress=False)
    assert seeds == [7, 8] and recs.seed == 8 and recs.remaps == 1
    # the remap starts from the view the contradicting pairs share, on one thread
    assert starts == [(None, MapConfig().num_threads), (rec.image(3).name, map_retries.REMAP_THREADS)]
    assert recs.agreement_check.contradicted == [] and recs.reconstructions[0] is rec
    assert "5 of the 15 verified pairs between the views of the largest model contradict it" in caplog.text


def test_a_large_model_is_contradicted_by_a_count_of_pairs_its_share_would_hide():
    """A bend contradicts the pairs across its seam, however many pairs the rest of the model holds:
    20 contradicting pairs call for a remap at any size, fewer only above 0.5% of the pairs."""
    def check(contradicted: int, checked: int) -> colmap.Agreement:
        return colmap.Agreement(checked, [(f"a{i}", f"b{i}") for i in range(contradicted)])

    assert map_retries.CONTRADICTED_PAIRS == 20 and map_retries.CONTRADICTED_SHARE == 0.005
    assert map_retries.contradicted(check(76, 21_795))  # SARA's bent first model at 10,000 images (0.35%)
    assert map_retries.contradicted(check(45, 15_577))  # sequential + loop detection's at 3,000 (0.29%)
    assert map_retries.contradicted(check(20, 100_000)) and not map_retries.contradicted(check(19, 100_000))
    assert map_retries.contradicted(check(12, 683))  # a share above 0.5% (dtu-scan24, exhaustive)
    assert not map_retries.contradicted(check(2, 2_023)) and not map_retries.contradicted(check(0, 0))


def test_an_agreeing_first_model_is_not_mapped_again(scene, tmp_path, monkeypatch):
    rec, db_path = scene
    seeds = mapped_in_turn(monkeypatch, rec)
    recs, _, _ = mapping._map(MapConfig(), db_path, tmp_path, tmp_path, seed=0, progress=False)
    assert seeds == [0] and recs.remaps == 0 and recs.seed == 0


def test_remaps_can_be_turned_off(scene, tmp_path, monkeypatch):
    rec, db_path = scene
    seeds = mapped_in_turn(monkeypatch, turned(rec, 3, 3.0))
    recs, _, _ = mapping._map(MapConfig(contradicted_remaps=0), db_path, tmp_path, tmp_path, seed=0, progress=False)
    assert seeds == [0] and recs.remaps == 0 and len(recs.agreement_check.contradicted) == 5


def test_when_every_seed_is_contradicted_the_largest_model_is_kept(scene, tmp_path, monkeypatch):
    rec, db_path = scene
    small = pycolmap.Reconstruction(turned(rec, 3, 3.0))
    small.deregister_frame(small.image(6).frame_id)
    seeds = mapped_in_turn(monkeypatch, small, turned(rec, 2, 3.0), turned(rec, 4, 5.0))
    recs, _, _ = mapping._map(MapConfig(), db_path, tmp_path, tmp_path, seed=0, progress=False)
    assert seeds == [0, 1, 2] and recs.remaps == MapConfig().contradicted_remaps == 2
    assert recs.seed == 1 and recs.largest == 6  # the first of the two 6-view models, as contradicted as the other


def test_a_mapping_contradicted_by_the_same_pairs_again_ends_the_remaps(scene, tmp_path, monkeypatch, caplog):
    """The pairs that contradict the first model contradict the next seed's model too: they are wrong
    whatever the model, so no third mapping follows (dtu-scan24 under exhaustive matching: the same 12
    of 683 pairs under seeds 0 and 1)."""
    rec, db_path = scene
    seeds = mapped_in_turn(monkeypatch, turned(rec, 3, 3.0))
    with caplog.at_level("WARNING", logger="sara.mapping"):
        recs, _, _ = mapping._map(MapConfig(), db_path, tmp_path, tmp_path, seed=0, progress=False)
    assert MapConfig().contradicted_remaps == 2 and seeds == [0, 1] and recs.remaps == 1
    assert recs.seed == 0 and len(recs.agreement_check.contradicted) == 5  # the first of equals is kept
    assert "the same 5 pairs contradict the model under seed 1" in caplog.text


def test_the_stage_record_keeps_the_first_models_check_through_a_continuation(scene, tmp_path, monkeypatch):
    """`run.json` says which seed built the first model and how many pairs contradicted it; a model
    continued from it by a later round keeps that in its record."""
    rec, db_path = scene
    built = [turned(rec, 3, 3.0), rec]

    def fake_incremental(conf, db, images, tmp, seed, progress, num_images, input_model, **kwargs):
        return colmap.MappedModels({0: built.pop(0)})

    monkeypatch.setattr(mapping, "_incremental", fake_incremental)
    mapping.run(MapConfig(), db_path, tmp_path, tmp_path / "out", seed=0, progress=False)
    first = records.done_info(tmp_path / "out", "map")
    assert {k: first[k] for k in mapping.FIRST_MODEL_KEYS} == {
        "seed": 1, "remaps": 1, "mended": False, "first_model_pairs_checked": 15, "first_model_pairs_contradicted": 0}
    continued = mapping._first_model_check(colmap.MappedModels({0: rec}), records.read_record(tmp_path / "out", "map"))
    assert continued == {k: first[k] for k in mapping.FIRST_MODEL_KEYS}
    assert mapping._first_model_check(colmap.MappedModels({0: rec}), None) == {}


def test_a_contradicted_global_model_is_mapped_again_by_the_incremental_mapper(scene, tmp_path, monkeypatch, caplog):
    """The global mapper glues stretches of a sparse graph at wrong rotations: when the model's own
    pairs contradict it, the incremental mapper maps the scene too, and the model they agree with is
    kept and recorded as the incremental mapper's; a global model they agree with is kept alone."""
    rec, db_path = scene
    seeds = mapped_in_turn(monkeypatch, rec)
    globals_built = [turned(rec, 3, 3.0), rec]
    monkeypatch.setattr(colmap, "global_mapping", lambda *a, **k: colmap.MappedModels({0: globals_built.pop(0)}))
    with caplog.at_level("WARNING", logger="sara.mapping"):
        mapping.run(MapConfig(mapper="global"), db_path, tmp_path, tmp_path / "out", seed=3, progress=False)
    info = records.done_info(tmp_path / "out", "map")
    assert seeds == [3] and info["mapper"] == "incremental" and info["first_model_pairs_contradicted"] == 0
    assert "5 of the 15 verified pairs between the views of the global mapper's largest model contradict it" \
        in caplog.text
    recs, _, _ = mapping._map(MapConfig(mapper="global"), db_path, tmp_path, tmp_path / "again", seed=3,
                              progress=False)
    assert seeds == [3] and recs.mapper is None and recs.agreement_check.contradicted == []


def test_a_contradicted_global_model_is_kept_when_remaps_are_off(scene, tmp_path, monkeypatch):
    rec, db_path = scene
    seeds = mapped_in_turn(monkeypatch, rec)
    monkeypatch.setattr(colmap, "global_mapping", lambda *a, **k: colmap.MappedModels({0: turned(rec, 3, 3.0)}))
    mapping.run(MapConfig(mapper="global", contradicted_remaps=0), db_path, tmp_path, tmp_path / "out", seed=0,
                progress=False)
    info = records.done_info(tmp_path / "out", "map")
    assert seeds == [] and info["mapper"] == "global" and info["first_model_pairs_contradicted"] == 5


def test_a_round_continues_the_incremental_model_that_replaced_a_global_one(scene, tmp_path, monkeypatch):
    """Once the incremental mapper's model replaced a contradicted global one, a round that maps again
    continues that model with the incremental mapper, as when it was asked for."""
    rec, db_path = scene
    calls = []

    def fake_incremental(conf, db, images, tmp, seed, progress, num_images, input_model, **kwargs):
        calls.append(("incremental", input_model is not None))
        return colmap.MappedModels({0: rec})

    def fake_global(*args, **kwargs):
        calls.append(("global", False))
        return colmap.MappedModels({0: turned(rec, 3, 3.0)})

    monkeypatch.setattr(mapping, "_incremental", fake_incremental)
    monkeypatch.setattr(colmap, "global_mapping", fake_global)
    out = tmp_path / "out"
    mapping.run(MapConfig(mapper="global"), db_path, tmp_path, out, seed=0, progress=False)
    assert calls == [("global", False), ("incremental", False)]
    mapping.run(MapConfig(mapper="global"), db_path, tmp_path, out, seed=0, progress=False, upstream_key="round 1",
                input_model=out / "sparse" / "0")
    info = records.done_info(out, "map")
    assert calls[2:] == [("incremental", True)] and info["continued"] and info["mapper"] == "incremental"


def test_a_mapping_that_built_nothing_never_replaces_a_contradicted_model(scene, tmp_path, monkeypatch):
    """No model has no pair to contradict it, yet it is no better than a contradicted one: neither a
    remap nor the incremental mapper behind a global one that built nothing replaces the model."""
    rec, db_path = scene
    seeds = []

    def fake_incremental(conf, db, images, tmp, seed, progress, num_images, input_model, **kwargs):
        seeds.append(seed)
        return colmap.MappedModels({0: turned(rec, 3, 3.0)} if len(seeds) == 1 else {})

    monkeypatch.setattr(mapping, "_incremental", fake_incremental)
    recs, _, _ = mapping._map(MapConfig(contradicted_remaps=1), db_path, tmp_path, tmp_path, seed=0, progress=False)
    assert seeds == [0, 1] and recs.seed == 0 and recs.largest == 6
    monkeypatch.setattr(mapping, "_incremental", lambda *a, **k: colmap.MappedModels({}))
    monkeypatch.setattr(colmap, "global_mapping", lambda *a, **k: colmap.MappedModels({0: turned(rec, 3, 3.0)}))
    (tmp_path / "g").mkdir()
    recs, _, _ = mapping._map(MapConfig(mapper="global"), db_path, tmp_path, tmp_path / "g", seed=0, progress=False)
    assert recs.mapper is None and recs.largest == 6


def test_an_agreeing_remap_that_lost_more_views_than_the_seam_holds_does_not_replace_the_bent_model():
    """The 10,000-image world: a bent first model of 9,350 views, 81 pairs contradicting it, and a remap
    that broke the street into pieces, the largest of 3,167 views that none of its 7,352 pairs
    contradicts. Pieces are not a mended bend: the bent model stays. A remap that holds every view but
    the seam's replaces it."""
    from types import SimpleNamespace

    def views(n: int) -> SimpleNamespace:
        return SimpleNamespace(largest=n)

    seam = colmap.Agreement(21_808, [(f"a{i}", f"b{i}") for i in range(81)])  # 162 views
    clean = colmap.Agreement(4_000, [])
    assert not map_retries.better(views(3_167), clean, views(9_350), seam)
    assert map_retries.better(views(9_350), seam, views(3_167), clean)
    assert map_retries.better(views(9_350 - 162), clean, views(9_350), seam)  # mended, the seam's views left out
    assert not map_retries.better(views(9_350 - 163), clean, views(9_350), seam)
    assert map_retries.better(views(1), clean, views(0), clean)  # any model beats none


def test_the_views_that_verified_pairs_join_are_read_once_per_mapping(monkeypatch, tmp_path):
    """The retries ask for them twice (the distortion's and the forward start's), through copies of
    their `Attempts`: the database is read once."""
    from dataclasses import replace

    reads = []
    monkeypatch.setattr(colmap, "verified_graph", lambda db, n: reads.append(db) or (3, 4, [4, 2], 100))
    tries = map_retries.Attempts(MapConfig(), tmp_path / "database.db", tmp_path, 0, 15, None,
                                 lambda *a, **k: None, lambda *a: None)
    assert tries.reachable() == 4
    assert replace(tries, conf=replace(tries.conf, refine_distortion=False)).reachable() == 4
    assert len(reads) == 1
