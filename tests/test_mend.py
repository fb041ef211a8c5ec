"""A contradicted first model mended at its seam (`sara.colmap.mend`, `sara.map_retries.mended`): the
views around the contradicting pairs taken out, the rest continued by COLMAP's mapper."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from sara import colmap, mapping
from sara.colmap.consistency import agreement
from sara.config import MapConfig
from sara.io import records

NUM_VIEWS = 30
WINDOW = 2  # each view is matched with the views up to this many frames away, as along a sequence


@pytest.fixture()
def sequence(tmp_path: Path) -> tuple[pycolmap.Reconstruction, Path]:
    """pycolmap's synthetic scene of 30 views, its verified pairs only between views at most two
    apart in image id (a sequence's window: the views far from a seam share no pair with it)."""
    pycolmap.set_random_seed(0)
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_cameras_per_rig, opts.num_frames_per_rig, opts.num_points3D = 1, 1, NUM_VIEWS, 300
    db_path = tmp_path / "database.db"
    with pycolmap.Database.open(str(db_path)) as db:
        rec = pycolmap.synthesize_dataset(opts, db)
        for i in range(1, NUM_VIEWS + 1):
            for j in range(i + WINDOW + 1, NUM_VIEWS + 1):
                db.delete_two_view_geometry(i, j)
                db.delete_matches(i, j)
    return rec, db_path


def stretch_turned(rec: pycolmap.Reconstruction, image_ids: range, degrees: float) -> pycolmap.Reconstruction:
    """A copy of `rec` with the frames of `image_ids` turned together about the world's y axis: a
    stretch glued at the wrong place."""
    bent = pycolmap.Reconstruction(rec)
    half = np.radians(degrees) / 2
    turn = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.0, np.sin(half), 0.0, np.cos(half)])), np.zeros(3))
    for image_id in image_ids:
        frame = bent.frame(bent.image(image_id).frame_id)
        frame.rig_from_world = frame.rig_from_world * turn
    return bent


def first_mapping_gives(monkeypatch, model: pycolmap.Reconstruction) -> list[int]:
    """`mapping._incremental` from scratch gives `model` (every seed); continuing a model runs COLMAP's
    mapper for real. Returns the seeds of the mappings from scratch."""
    seeds: list[int] = []
    real = mapping._incremental

    def fake_incremental(conf, db, images, tmp, seed, progress, num_images, input_model, **kwargs):
        if input_model is not None:
            return real(conf, db, images, tmp, seed, progress, num_images, input_model, **kwargs)
        seeds.append(seed)
        return colmap.MappedModels({0: pycolmap.Reconstruction(model)})

    monkeypatch.setattr(mapping, "_incremental", fake_incremental)
    return seeds


def test_the_cut_takes_out_the_seam_and_the_views_two_pairs_from_it(sequence, tmp_path):
    rec, db_path = sequence
    bent = stretch_turned(rec, range(14, 17), 3.0)
    check = agreement(bent, db_path)
    seam = {view for pair in check.contradicted for view in pair}
    names = {img.image_id: img.name for img in rec.images.values()}
    assert seam == {names[i] for i in range(12, 19)}  # the stretch 14-16 and the two views each side of it
    cut = colmap.cut_at_seam(colmap.MappedModels({0: bent}), check, db_path, tmp_path / "cut", min_num_inliers=15)
    assert cut == colmap.Cut(taken_out=7 + 2 * 2 * WINDOW, dropped=0, kept=NUM_VIEWS - 15)
    kept = {img.name for img in pycolmap.Reconstruction(str(tmp_path / "cut")).images.values() if img.has_pose}
    assert kept == {names[i] for i in range(1, NUM_VIEWS + 1) if not 8 <= i <= 22}


def test_a_cut_that_would_keep_under_half_the_model_is_not_made(sequence, tmp_path):
    """A seam whose neighbourhood is most of the model: no local mend (the remaps are for that)."""
    rec, db_path = sequence
    bent = stretch_turned(stretch_turned(rec, range(5, 6), 3.0), range(25, 26), 3.0)
    check = agreement(bent, db_path)
    models = colmap.MappedModels({0: bent})
    assert colmap.cut_at_seam(models, check, db_path, tmp_path / "cut", min_num_inliers=15) is None
    assert not (tmp_path / "cut").exists()
    # the seams alone are small: it is the views within two pairs of them that make most of the model
    assert colmap.cut_at_seam(models, check, db_path, tmp_path / "cut", min_num_inliers=15, hops=0).kept > NUM_VIEWS / 2
    assert colmap.cut_at_seam(colmap.MappedModels({0: rec}), agreement(rec, db_path), db_path, tmp_path / "cut",
                              min_num_inliers=15) is None  # nothing contradicts it: nothing to cut


def test_a_first_model_wrong_in_one_stretch_is_mended_without_mapping_again(sequence, tmp_path, monkeypatch, caplog):
    """The stretch goes out with its surroundings, the mapper registers it again from both sides: every
    view back in one model that no pair contradicts, and no remap from scratch."""
    rec, db_path = sequence
    seeds = first_mapping_gives(monkeypatch, stretch_turned(rec, range(14, 17), 3.0))
    with caplog.at_level("WARNING", logger="sara.mapping"):
        mapping.run(MapConfig(num_threads=1), db_path, tmp_path, tmp_path / "out", seed=0, progress=False)
    assert seeds == [0]
    info = records.done_info(tmp_path / "out", "map")
    assert info["mended"] and info["remaps"] == 0 and info["num_registered"] == NUM_VIEWS
    assert info["first_model_pairs_contradicted"] == 0
    assert "taking out the 15 views up to 2 pairs from them" in caplog.text
    mended = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
    assert agreement(mended, db_path).contradicted == []
    # the stretch is back where the truth has it, relative to the views that were not touched
    by_name = {img.name: img for img in mended.images.values()}

    def relative(model_image, other_image) -> pycolmap.Rigid3d:
        return model_image.cam_from_world() * other_image.cam_from_world().inverse()

    for i in (15, 22):
        truth = relative(rec.image(i), rec.image(1))
        found = relative(by_name[rec.image(i).name], by_name[rec.image(1).name])
        assert np.degrees((truth.rotation * found.rotation.inverse()).angle()) < 0.1


def test_the_mend_can_be_turned_off(sequence, tmp_path, monkeypatch):
    rec, db_path = sequence
    seeds = first_mapping_gives(monkeypatch, stretch_turned(rec, range(14, 17), 3.0))
    recs, _, _ = mapping._map(MapConfig(mend_seam=False), db_path, tmp_path, tmp_path, seed=0, progress=False)
    assert not recs.mended and recs.remaps == 1 and seeds == [0, 1]  # the same pairs again: one remap only


def test_a_mend_contradicted_by_other_pairs_is_followed_by_the_remaps(sequence, tmp_path, monkeypatch):
    """The continued model is bent elsewhere: the remaps run as without the mend, from the first
    model's seam."""
    rec, db_path = sequence
    seeds = first_mapping_gives(monkeypatch, stretch_turned(rec, range(14, 17), 3.0))
    elsewhere = stretch_turned(rec, range(4, 7), 3.0)
    monkeypatch.setattr(mapping, "_extend", lambda *args: (colmap.MappedModels({0: elsewhere}), NUM_VIEWS, 0.0))
    recs, _, _ = mapping._map(MapConfig(), db_path, tmp_path, tmp_path, seed=0, progress=False)
    assert seeds == [0, 1] and recs.remaps == 1  # (the less contradicted of the three is kept)


def test_a_mend_contradicted_by_the_same_pairs_ends_it_without_a_remap(sequence, tmp_path, monkeypatch, caplog):
    """The same pairs contradict the model with the seam's views registered again: the pairs are wrong,
    not the model, and a remap from scratch (hours at 10,000 images) would not help."""
    rec, db_path = sequence
    bent = stretch_turned(rec, range(14, 17), 3.0)
    seeds = first_mapping_gives(monkeypatch, bent)
    monkeypatch.setattr(mapping, "_extend", lambda *args: (colmap.MappedModels({0: pycolmap.Reconstruction(bent)}),
                                                           NUM_VIEWS, 0.0))
    with caplog.at_level("WARNING", logger="sara.mapping"):
        recs, _, _ = mapping._map(MapConfig(), db_path, tmp_path, tmp_path, seed=0, progress=False)
    wrong = len(agreement(bent, db_path).contradicted)
    assert seeds == [0] and recs.remaps == 0 and len(recs.agreement_check.contradicted) == wrong > 0
    assert f"the same {wrong} pairs contradict the mended model" in caplog.text


def test_a_continuation_that_fails_leaves_the_first_model_to_the_remaps(sequence, tmp_path, monkeypatch, caplog):
    """COLMAP failing inside the mend loses nothing: the first model stays and the remaps run (a stage
    that failed there would fail again on every resume, from the same checkpoint)."""
    rec, db_path = sequence
    seeds = first_mapping_gives(monkeypatch, stretch_turned(rec, range(14, 17), 3.0))

    def failing(*args):
        raise colmap.ColmapError("mapper: out of memory")

    monkeypatch.setattr(mapping, "_extend", failing)
    with caplog.at_level("WARNING", logger="sara.mapping"):
        recs, _, _ = mapping._map(MapConfig(), db_path, tmp_path, tmp_path, seed=0, progress=False)
    assert "continuing the cut model failed (mapper: out of memory): keeping the first model" in caplog.text
    assert seeds == [0, 1] and recs.remaps == 1 and not recs.mended and recs.largest == NUM_VIEWS


@pytest.mark.parametrize("mend_seam", [True, False])
def test_a_rounds_continuation_bent_in_one_stretch_is_mended_too(sequence, tmp_path, monkeypatch, caplog, mend_seam):
    """A round continues the model (`input_model`); where the continued model is bent in a stretch, its
    pairs contradict it and it is mended as a first model is: every view back, no pair contradicting,
    and the record says so. With the mend off it is kept as it is, the contradicting pairs counted."""
    rec, db_path = sequence
    start = tmp_path / "start"
    start.mkdir()
    rec.write(str(start))
    real, calls = mapping._extend, []

    def bent_then_real(conf, db, images, tmp, seed, progress, input_model, min_num_inliers):
        calls.append(input_model)
        if len(calls) == 1:  # the round's continuation
            return colmap.MappedModels({0: stretch_turned(rec, range(14, 17), 3.0)}), NUM_VIEWS, 0.0
        return real(conf, db, images, tmp, seed, progress, input_model, min_num_inliers)  # the mend's

    monkeypatch.setattr(mapping, "_extend", bent_then_real)
    with caplog.at_level("WARNING", logger="sara.map_retries"):
        mapping.run(MapConfig(num_threads=1, mend_seam=mend_seam), db_path, tmp_path, tmp_path / "out", seed=0,
                    progress=False, input_model=start)
    info = records.done_info(tmp_path / "out", "map")
    model = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
    assert info["continued"] and info["num_registered"] == NUM_VIEWS and info["continued_pairs_checked"] > 0
    if mend_seam:
        assert len(calls) == 2 and info["continued_mended"] and info["continued_pairs_contradicted"] == 0
        assert agreement(model, db_path).contradicted == []
    else:
        assert len(calls) == 1 and "continued_mended" not in info
        assert info["continued_pairs_contradicted"] == len(agreement(model, db_path).contradicted) > 0
        assert "map.mend_seam is off" in caplog.text


def test_a_rounds_continuation_its_pairs_agree_with_is_kept_as_it_is(sequence, tmp_path):
    rec, db_path = sequence
    start = tmp_path / "start"
    start.mkdir()
    rec.write(str(start))
    mapping.run(MapConfig(num_threads=1), db_path, tmp_path, tmp_path / "out", seed=0, progress=False,
                input_model=start)
    info = records.done_info(tmp_path / "out", "map")
    assert info["continued"] and info["num_registered"] == NUM_VIEWS and "continued_mended" not in info
    assert info["continued_pairs_contradicted"] == 0 and info["continued_pairs_checked"] == NUM_VIEWS * 2 - 3
