"""sara's step-by-step incremental mapping (`sara.colmap.stepwise`): the models COLMAP's own loop
makes, with global adjustments allowed Ceres' direct sparse solver up to the size it is given."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from model_utils import synthetic_database
from sara.colmap import stepwise


@pytest.fixture(scope="module")
def database(tmp_path_factory) -> Path:
    """20 posed views of 400 points; their matches in `database.db`."""
    root = tmp_path_factory.mktemp("stepwise")
    synthetic_database(root / "database.db", 20, 400)
    (root / "images").mkdir()
    return root / "database.db"


def _options() -> pycolmap.IncrementalPipelineOptions:
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = 1
    opts.random_seed = opts.mapper.random_seed = opts.triangulation.random_seed = 0
    return opts


def _centres(rec: pycolmap.Reconstruction) -> dict[str, np.ndarray]:
    return {img.name: img.projection_center() for img in rec.images.values() if img.has_pose}


def _similarity_residual(a: np.ndarray, b: np.ndarray) -> float:
    """Largest distance between `b` and `a` mapped onto it by the best similarity, over b's spread."""
    ca, cb = a - a.mean(axis=0), b - b.mean(axis=0)
    u, sigma, vt = np.linalg.svd(cb.T @ ca)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ d @ vt
    scale = float(np.trace(np.diag(sigma) @ d) / (ca ** 2).sum())
    return float(np.linalg.norm(scale * ca @ rotation.T - cb, axis=1).max() / np.linalg.norm(cb, axis=1).max())


def test_the_stepwise_mapping_makes_the_models_colmaps_loop_makes(database: Path, tmp_path: Path):
    images = database.parent / "images"
    ours = stepwise.incremental_mapping(database, images, tmp_path / "ours", _options(), direct_up_to=5000)
    theirs = pycolmap.incremental_mapping(str(database), str(images), str(tmp_path / "theirs"), options=_options())
    assert len(ours) == len(theirs) == 1
    mine, colmaps = _centres(ours[0]), _centres(theirs[0])
    assert sorted(mine) == sorted(colmaps) and len(mine) == 20
    names = sorted(mine)
    residual = _similarity_residual(np.array([mine[n] for n in names]), np.array([colmaps[n] for n in names]))
    assert residual < 1e-6  # the same poses up to the gauge (scale, rotation, origin) each loop leaves
    assert ours[0].num_points3D() == theirs[0].num_points3D()
    assert (tmp_path / "ours" / "0" / "images.bin").exists()  # written as pycolmap writes its models


def test_the_global_adjustments_get_the_direct_solver_limit(database: Path):
    with pycolmap.Database.open(str(database)) as db:
        cache = pycolmap.DatabaseCache.create(db, pycolmap.DatabaseCacheOptions())
    run = stepwise._Run(_options(), cache, pycolmap.ReconstructionManager(), 5000, None)
    assert run.global_ba.ceres.max_num_images_direct_sparse_cpu_solver == 5000
    assert pycolmap.IncrementalPipelineOptions().get_global_bundle_adjustment() \
        .ceres.max_num_images_direct_sparse_cpu_solver == 1000  # COLMAP's own, which the loop replaces


def test_a_model_given_to_continue_from_is_continued(database: Path, tmp_path: Path):
    """sara's repair rounds continue a model: the views it lacks are registered into it."""
    images = database.parent / "images"
    full = stepwise.incremental_mapping(database, images, tmp_path / "full", _options(), direct_up_to=5000)[0]
    for image_id in sorted(full.reg_image_ids())[-5:]:
        full.deregister_frame(full.images[image_id].frame_id)
    start = tmp_path / "start"
    start.mkdir()
    full.write(str(start))
    continued = stepwise.incremental_mapping(database, images, tmp_path / "more", _options(), direct_up_to=5000,
                                             input_path=start)
    assert continued[0].num_reg_images() == 20


def test_saras_own_adjustments_get_the_direct_solver_limit(monkeypatch):
    """The track extension and the pose-guided refinement adjust whole models too."""
    from sara.colmap import sfm

    seen = []
    monkeypatch.setattr(pycolmap, "bundle_adjustment",
                        lambda rec, options: seen.append(options.ceres.max_num_images_direct_sparse_cpu_solver))
    monkeypatch.setattr(pycolmap.logging, "logtostderr", True)  # the plain call, no console juggling
    sfm.bundle_adjust(pycolmap.Reconstruction())
    assert seen == [stepwise.DIRECT_SOLVER_MAX_IMAGES]


def test_a_continued_model_is_grown_on_the_lighter_schedule(database: Path, tmp_path: Path, monkeypatch):
    """Continuing, each new view gets one round of local adjustment and the whole model is adjusted
    by growth only, not every `ba_global_frames_freq` views as when mapping from a first pair."""
    images = database.parent / "images"
    opts = _options()
    opts.ba_global_frames_freq = 1  # COLMAP's schedule: the whole model after every view
    opts.ba_global_frames_ratio = opts.ba_global_points_ratio = 100.0
    full = stepwise.incremental_mapping(database, images, tmp_path / "full", opts, direct_up_to=5000)[0]
    for image_id in sorted(full.reg_image_ids())[-8:]:
        full.deregister_frame(full.images[image_id].frame_id)
    for point_id in sorted(full.point3D_ids())[::2]:  # the views added back triangulate points anew
        full.delete_point3D(point_id)
    start = tmp_path / "start"
    start.mkdir()
    full.write(str(start))

    local_rounds: list[int] = []
    refines: list[int] = []

    class Counting(pycolmap.IncrementalMapper):
        def iterative_local_refinement(self, max_refinements, *args):
            local_rounds.append(max_refinements)
            return super().iterative_local_refinement(max_refinements, *args)

    monkeypatch.setattr(pycolmap, "IncrementalMapper", Counting)
    refine = stepwise._Run.refine

    def counted_refine(self, mapper, options):
        refines.append(1)
        refine(self, mapper, options)

    monkeypatch.setattr(stepwise._Run, "refine", counted_refine)
    continued = stepwise.incremental_mapping(database, images, tmp_path / "more", opts, direct_up_to=5000,
                                             input_path=start)
    assert continued[0].num_reg_images() == 20
    assert local_rounds == [stepwise.CONTINUED_LOCAL_REFINEMENTS] * 8
    assert len(refines) == 1  # when the registrations end, not again on the same views

    local_rounds.clear()
    refines.clear()
    stepwise.incremental_mapping(database, images, tmp_path / "again", opts, direct_up_to=5000)
    assert set(local_rounds) == {opts.ba_local_max_refinements} and len(refines) >= 15  # from a first pair


def test_each_model_logs_its_time_by_step(database: Path, tmp_path: Path, caplog):
    """Where a large mapping's time goes is in the log: one line per model with each step's seconds."""
    with caplog.at_level("INFO", logger="sara.colmap.stepwise"):
        stepwise.incremental_mapping(database, database.parent / "images", tmp_path / "m", _options(),
                                     direct_up_to=5000)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("map: model of")]
    assert len(lines) == 1 and lines[0].startswith("map: model of 20 views (new): ")
    for step in ("registration", "triangulation", "local adjustment", "global adjustment"):
        assert f"{step} " in lines[0]


def test_the_first_model_starts_from_the_given_image_and_the_others_still_start(tmp_path: Path):
    """Two groups of ten views with no match between them: the mapper's own first pair lies in the
    second group; given an image of the first, the first model is that group's and the second group
    still gets its model (COLMAP's `init_image_id1` would hold every model to the given image)."""
    db_path = tmp_path / "database.db"
    synthetic_database(db_path, 20, 400)
    (tmp_path / "images").mkdir()
    with pycolmap.Database.open(str(db_path)) as db:
        for a in range(1, 11):
            for b in range(11, 21):
                db.delete_two_view_geometry(a, b)
                db.delete_matches(a, b)

    def groups(first_image_id):
        models = stepwise.incremental_mapping(db_path, tmp_path / "images", tmp_path / f"from-{first_image_id}",
                                              _options(), direct_up_to=0, first_image_id=first_image_id)
        return [sorted(rec.reg_image_ids()) for rec in models.values()]

    second, first = list(range(11, 21)), list(range(1, 11))
    assert groups(None) == [second, first]
    assert groups(3) == [first, second]


class Killed(Exception):
    """Stands for the signal that stops a run."""


def _killed_after(n: int):
    """An `on_next_image` that stops the mapping at its `n`-th registered view; counts them all."""
    seen = []

    def on_next_image():
        seen.append(1)
        if len(seen) == n:
            raise Killed
    return on_next_image, seen


def test_a_killed_mapping_resumes_from_its_checkpoint(database: Path, tmp_path: Path, caplog):
    """Stopped at its 12th view, the mapping has kept the model as of its last global adjustment;
    run again, it registers only the views that model lacks and ends as the uninterrupted one."""
    images = database.parent / "images"
    checkpoint = stepwise.Checkpoint(tmp_path / "ckpt", "key-1", every_s=0.0)
    stop, _ = _killed_after(12)
    with pytest.raises(Killed):
        stepwise.incremental_mapping(database, images, tmp_path / "a", _options(), direct_up_to=5000,
                                     on_next_image=stop, checkpoint=checkpoint)
    record = json.loads((tmp_path / "ckpt" / "checkpoint.json").read_text())
    assert record["current"] == 0 and 2 < record["views"][0] < 14  # the first pair's two, then 12
    count, seen = _killed_after(0)
    with caplog.at_level("WARNING", logger="sara.colmap.stepwise"):
        resumed = stepwise.incremental_mapping(database, images, tmp_path / "b", _options(), direct_up_to=5000,
                                               on_next_image=count, checkpoint=checkpoint)
    assert any("resuming the mapping from its checkpoint" in r.getMessage() for r in caplog.records)
    assert len(seen) == 20 - record["views"][0]  # the kept views were not registered again
    assert json.loads((tmp_path / "ckpt" / "checkpoint.json").read_text())["current"] is None  # ended
    whole = stepwise.incremental_mapping(database, images, tmp_path / "c", _options(), direct_up_to=5000)
    mine, theirs = _centres(resumed[0]), _centres(whole[0])
    assert sorted(mine) == sorted(theirs) and len(mine) == 20
    names = sorted(mine)
    assert _similarity_residual(np.array([mine[n] for n in names]), np.array([theirs[n] for n in names])) < 1e-4


def test_an_ended_checkpoint_gives_its_models_and_another_key_is_ignored(database: Path, tmp_path: Path):
    images = database.parent / "images"
    checkpoint = stepwise.Checkpoint(tmp_path / "ckpt", "key-1", every_s=1e9)  # written once, at the end
    first = stepwise.incremental_mapping(database, images, tmp_path / "a", _options(), direct_up_to=5000,
                                         checkpoint=checkpoint)
    count, seen = _killed_after(0)
    again = stepwise.incremental_mapping(database, images, tmp_path / "b", _options(), direct_up_to=5000,
                                         on_next_image=count, checkpoint=checkpoint)
    assert not seen and _centres(again[0]).keys() == _centres(first[0]).keys()  # nothing mapped again
    assert (tmp_path / "b" / "0" / "images.bin").exists()
    other = stepwise.Checkpoint(tmp_path / "ckpt", "key-2", every_s=1e9)  # other matches: from the start
    stepwise.incremental_mapping(database, images, tmp_path / "c", _options(), direct_up_to=5000,
                                 on_next_image=count, checkpoint=other)
    assert len(seen) == 18  # every view but the first pair's


def test_the_map_stage_keeps_the_checkpoint_of_a_killed_run_and_removes_it_when_done(database: Path,
                                                                                       tmp_path: Path, monkeypatch):
    """... and the stage that resumes it records the time mapped before the kill with its own (the
    checkpoint keeps it: else a mapping of hours killed near its end would say it took minutes)."""
    import time

    from sara import mapping
    from sara.config import make_config
    from sara.io import records

    out = tmp_path / "out"
    out.mkdir()
    conf = make_config("sift-offline", {"map.ba_direct_max_images": 5000, "map.checkpoint_minutes": 1e-9,
                                        "map.num_threads": 1, "map.contradicted_remaps": 0}).map
    register = stepwise._Run.register_next
    calls = []

    def slow_then_stopped(self, *args):
        calls.append(1)
        if len(calls) == 10:
            raise KeyboardInterrupt
        time.sleep(0.2)
        return register(self, *args)

    monkeypatch.setattr(stepwise._Run, "register_next", slow_then_stopped)
    with pytest.raises(KeyboardInterrupt):
        mapping.run(conf, database, database.parent / "images", out, progress=False)
    kept = out / ".sara" / mapping.CHECKPOINT
    record = json.loads((kept / "checkpoint.json").read_text())
    assert record["current"] == 0 and record["elapsed_s"] >= 1.0  # most of the nine slow registrations
    assert not (out / "sparse").exists()
    monkeypatch.setattr(stepwise._Run, "register_next", register)
    tic = time.perf_counter()
    mapping.run(conf, database, database.parent / "images", out, progress=False)
    resumed_s = time.perf_counter() - tic
    assert len(pycolmap.Reconstruction(str(out / "sparse" / "0")).reg_image_ids()) == 20
    assert not kept.exists()
    assert record["elapsed_s"] <= records.done_info(out, "map")["time_s"] <= record["elapsed_s"] + resumed_s


def test_a_damaged_checkpoint_is_mapped_from_the_start(database: Path, tmp_path: Path):
    images = database.parent / "images"
    checkpoint = stepwise.Checkpoint(tmp_path / "ckpt", "key-1", every_s=1e9)
    stepwise.incremental_mapping(database, images, tmp_path / "a", _options(), direct_up_to=5000, checkpoint=checkpoint)
    (tmp_path / "ckpt" / "0" / "images.bin").write_bytes(b"\0" * 10)
    count, seen = _killed_after(0)
    again = stepwise.incremental_mapping(database, images, tmp_path / "b", _options(), direct_up_to=5000,
                                         on_next_image=count, checkpoint=checkpoint)
    assert len(seen) == 18 and len(again) == 1 and again[0].num_reg_images() == 20


def test_a_remap_of_a_killed_run_resumes_from_its_own_checkpoint(database: Path, tmp_path: Path, monkeypatch):
    """A first model found contradicted is mapped again under the next seed; a run killed during that
    remap goes on from the remap's checkpoint, the first mapping's (ended) restored as it was."""
    from sara import map_retries, mapping
    from sara.config import make_config
    from sara.io import records

    out = tmp_path / "out"
    out.mkdir()
    conf = make_config("sift-offline", {"map.ba_direct_max_images": 5000, "map.checkpoint_minutes": 1e-9,
                                        "map.num_threads": 1, "map.contradicted_remaps": 1}).map
    monkeypatch.setattr(map_retries, "contradicted", lambda check: True)  # every model found bent: one remap
    register, incremental = stepwise._Run.register_next, mapping._incremental
    registered, remapping = [], []

    def counting(self, *args):
        image_id, ok = register(self, *args)
        registered.append(ok)
        if remapping and remapping[-1] == "stop" and sum(registered) == 8:
            raise KeyboardInterrupt
        return image_id, ok

    def marking(*args, checkpoint=None, **kwargs):
        registered.clear()
        remapping.append("stop" if checkpoint is not None and checkpoint.folder.name.endswith("-seed-1") else "go")
        return incremental(*args, checkpoint=checkpoint, **kwargs)

    monkeypatch.setattr(stepwise._Run, "register_next", counting)
    monkeypatch.setattr(mapping, "_incremental", marking)
    with pytest.raises(KeyboardInterrupt):
        mapping.run(conf, database, database.parent / "images", out, progress=False)
    first, remap = out / ".sara" / mapping.CHECKPOINT, out / ".sara" / f"{mapping.CHECKPOINT}-seed-1"
    assert remapping == ["go", "stop"]
    ended = json.loads((first / "checkpoint.json").read_text())
    assert ended["current"] is None  # the first mapping ended
    kept = json.loads((remap / "checkpoint.json").read_text())
    assert kept["current"] == 0 and 2 < kept["views"][0] < 20

    remapping.clear()  # no more stops
    per_mapping = []

    def tracing(*args, **kwargs):
        registered.clear()
        models = incremental(*args, **kwargs)
        per_mapping.append(sum(registered))
        return models

    monkeypatch.setattr(mapping, "_incremental", tracing)
    mapping.run(conf, database, database.parent / "images", out, progress=False)
    # the first mapping registered nothing again, the remap only the views its checkpoint lacked
    assert per_mapping == [0, 20 - kept["views"][0]]
    # the stage's time holds both mappings' time before the kill, read from their checkpoints
    assert records.done_info(out, "map")["time_s"] >= ended["elapsed_s"] + kept["elapsed_s"] > 0
    assert len(pycolmap.Reconstruction(str(out / "sparse" / "0")).reg_image_ids()) == 20
    assert not list((out / ".sara").glob(mapping.CHECKPOINT + "*"))  # every checkpoint removed once done


def test_removing_a_checkpoint_removes_those_derived_from_it_and_nothing_else(tmp_path: Path):
    base = stepwise.Checkpoint(tmp_path / "ckpt", "key-1", every_s=1.0)
    derived = base.derived("seed-1", "view.jpg")
    assert derived.folder == tmp_path / "ckpt-seed-1" and derived.key != base.key
    assert derived.key != base.derived("seed-1", "other.jpg").key  # another start: another mapping
    for name in ("ckpt", "ckpt.old", "ckpt-seed-1", "ckpt-seed-1.next", "ckpt2", "other"):
        (tmp_path / name).mkdir()
    base.remove()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt2", "other"]


@pytest.mark.parametrize("direct_up_to", [None, 5000])  # COLMAP's own loop, and sara's step-by-step one
def test_a_view_left_without_verified_pairs_is_taken_out_of_the_model_continued(database, tmp_path, caplog,
                                                                                 direct_up_to):
    """An update took away the images a view was matched with: COLMAP loads no view without verified
    pairs, and continuing a model that still holds one failed (IndexError: unordered_map::at)."""
    import shutil
    import sqlite3

    from sara.colmap import sfm

    images = database.parent / "images"
    full = stepwise.incremental_mapping(database, images, tmp_path / "full", _options(), direct_up_to=5000)[0]
    alone = sorted(full.reg_image_ids())[7]
    shutil.copy(database, tmp_path / "database.db")
    with sqlite3.connect(tmp_path / "database.db") as con:
        for table in ("matches", "two_view_geometries"):
            con.execute(f"DELETE FROM {table} WHERE pair_id / 2147483647 = ? OR pair_id % 2147483647 = ?",
                        (alone, alone))
    with caplog.at_level("WARNING", logger="sara.colmap.sfm"):
        continued = sfm.incremental_mapping(tmp_path / "database.db", images, tmp_path / "more", seed=0,
                                            min_model_size=3, abs_pose_min_num_inliers=30,
                                            abs_pose_min_inlier_ratio=0.25, num_threads=1,
                                            input_path=tmp_path / "full" / "0", direct_solver_up_to=direct_up_to)
    rec = continued.reconstructions[0]
    assert rec.num_reg_images() == 19 and alone not in rec.reg_image_ids()
    assert "1 of the 20 views of the model continued have no verified pair left" in caplog.text
    assert not list((tmp_path / "more").glob(".start-*"))  # the trimmed copy is gone
