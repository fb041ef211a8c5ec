"""The SIFT extraction's single pass (issue 31): COLMAP's reader imports each image as it extracts
it, the features file and the focal check's pairs are made while COLMAP still extracts, and a run
cut short resumes with the images left."""

from __future__ import annotations

import shutil
import sqlite3
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from sara import colmap
from sara.execute import Beside
from sara.features.sift import hloc_descriptors
from sara.io.h5 import FeatureCache
from sara.scoring import focal


def _cameras(db: Path) -> list[int]:
    con = sqlite3.connect(db)
    try:
        return [row[0] for row in con.execute("SELECT DISTINCT camera_id FROM images")]
    finally:
        con.close()


def test_a_cut_extraction_resumes_with_the_images_left_in_the_same_camera(five_view_scene, tmp_path, run_cli,
                                                                         monkeypatch):
    images, _ = five_view_scene
    out, original, asked = tmp_path / "out", colmap.extract_sift, []

    def extract_three_then_stop(db_path, image_dir, names, **kwargs):
        original(db_path, image_dir, names[:3], **kwargs)
        raise KeyboardInterrupt  # as if Ctrl-C came after three images

    monkeypatch.setattr(colmap, "extract_sift", extract_three_then_stop)
    assert run_cli("extract", images, out, "-q").code == 130
    first = colmap.read_sift_rows(out / "database.db")
    assert len(first) == 3 and not (out / "features-sift.h5").exists()

    def extract_and_record(db_path, image_dir, names, **kwargs):
        asked.append(list(names))
        return original(db_path, image_dir, names, **kwargs)

    monkeypatch.setattr(colmap, "extract_sift", extract_and_record)
    assert run_cli("extract", images, out, "-q").code == 0
    names = sorted(p.name for p in images.iterdir())
    assert asked == [[n for n in names if n not in first]]  # only the images left are read again
    assert _cameras(out / "database.db") == [1]  # they joined the camera of the first three
    with h5py.File(out / "features-sift.h5", "r") as h5:
        assert sorted(h5) == names
        for name, (_, _, _, desc) in first.items():  # the first three's features were kept, not redone
            assert np.array_equal(h5[name]["descriptors"][()].T, hloc_descriptors(desc))


def test_the_features_file_holds_what_colmap_wrote(scene_features):
    with colmap.FeatureReader(scene_features / "database.db") as reader, \
            h5py.File(scene_features / "features-sift.h5", "r") as h5:
        ids = reader.image_ids()
        assert sorted(h5) == sorted(ids)
        for name, image_id in ids.items():
            kp, scale, desc = reader.read_sift(image_id)
            assert np.array_equal(h5[name]["keypoints"][()], colmap.colmap_to_hloc_keypoints(kp))
            assert np.array_equal(h5[name]["scores"][()], scale)
            assert np.array_equal(h5[name]["descriptors"][()].T, hloc_descriptors(desc))


def test_an_image_colmap_cannot_read_is_set_aside_after_its_one_pass(five_view_scene, tmp_path, run_cli):
    """A WebP under a .png name: Pillow's scan reads it, COLMAP's reader does not. It is found by
    the extraction's one pass (no decoding before it), kept out of the database, and set aside."""
    from PIL import Image

    images, _ = five_view_scene
    folder = tmp_path / "images"
    shutil.copytree(images, folder)
    Image.open(sorted(images.iterdir())[0]).save(folder / "zz-webp-inside.png", format="WEBP")
    result = run_cli("extract", folder, tmp_path / "out", "-q")
    assert result.code == 0, result.err
    assert "zz-webp-inside.png" not in colmap.database_images(tmp_path / "out" / "database.db")
    assert "skipping zz-webp-inside.png: COLMAP's image reader" in result.err
    with h5py.File(tmp_path / "out" / "features-sift.h5", "r") as h5:
        assert len(h5) == len(list(images.iterdir()))


def test_pairs_fitted_as_their_images_arrive_are_those_fitted_at_once(synthetic_scene, tmp_path):
    """On features of the synthetic scene's true observations (`write_superpoint_like`): SIFT at the
    test scenes' size finds too few matches between name-neighbours for the focal check."""
    from test_hloc import write_superpoint_like

    h5 = tmp_path / "features.h5"
    write_superpoint_like(synthetic_scene[1], h5)
    with h5py.File(h5, "r") as f:
        names = sorted(f)
    with FeatureCache(h5, top_k=focal.NUM_KEYPOINTS) as cache:
        at_once = focal.NearbyFundamentals(names).fundamentals(names, cache.get)[""]
        arriving = focal.NearbyFundamentals(names)
        for k in range(1, len(names), 3):  # a few images at each look, the last not yet come
            arriving.add(cache.get, set(names[:k]))
        assert len(arriving.found) < len(arriving.pairs)  # the last images had not come yet
        later = arriving.fundamentals(names, cache.get)[""]
    assert len(at_once) == len(later) >= focal.MIN_PAIRS
    assert all(np.array_equal(a, b) for a, b in zip(at_once, later))


def test_beside_runs_the_step_when_poked_and_raises_its_error_in_the_caller():
    ran = []
    with Beside(lambda: ran.append(threading.current_thread().name)) as beside:
        beside.poke()
        time.sleep(0.2)
    assert ran and ran[0] == "sara-beside"

    def fail() -> None:
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"), Beside(fail) as beside:
        beside.poke()
        time.sleep(0.2)
        beside.poke()


def test_the_copy_reads_the_database_a_few_images_at_a_time(scene_features, tmp_path, monkeypatch):
    from sara.features.sift import DatabaseToH5

    db = scene_features / "database.db"
    read, original = [], colmap.read_sift_rows

    def counting(*args, **kwargs):
        found = original(*args, **kwargs)
        read.append(len(found))
        return found

    monkeypatch.setattr(colmap, "read_sift_rows", counting)
    monkeypatch.setattr(DatabaseToH5, "BATCH", 3)
    with h5py.File(scene_features / "features-sift.h5", "r") as h5:
        sizes = {n: tuple(int(v) for v in h5[n]["image_size"][()]) for n in h5}
    with h5py.File(tmp_path / "copy.h5", "w") as h5:
        copy = DatabaseToH5(db, h5, sizes)
        assert sorted(copy.update()) == sorted(sizes)
        assert copy.update() == []  # nothing new since
    assert max(read) == 3 and sum(read) == len(sizes)


def test_images_are_numbered_in_name_order_with_their_features_and_frames(scene_features, tmp_path):
    """COLMAP's extraction numbers the images as its threads finish them; the stage numbers them in
    name order after, as an import in name order did (the mapper's ties follow the ids)."""
    import pycolmap

    db = tmp_path / "database.db"
    shutil.copyfile(scene_features / "database.db", db)
    ids = colmap.database_images(db)
    assert list(ids) == sorted(ids) and sorted(ids.values()) == list(ids.values())  # what the stage left

    def features_by_name() -> dict[str, np.ndarray]:
        return {name: row[3] for name, row in colmap.read_sift_rows(db).items()}

    names = sorted(ids)
    colmap.rename_images(db, {ids[n]: f"tmp-{n}" for n in names})  # the ids in reverse name order
    colmap.rename_images(db, {ids[n]: m for n, m in zip(names, reversed(names))})
    before = features_by_name()
    assert colmap.number_images_by_name(db) is True
    after = colmap.database_images(db)
    assert list(after) == names and [after[n] for n in names] == sorted(after.values())
    assert all(np.array_equal(before[n], f) for n, f in features_by_name().items())
    database = pycolmap.Database.open(str(db))
    try:
        frames = {f.frame_id: [d.id for d in f.data_ids] for f in database.read_all_frames()}
        assert all(frames[im.frame_id] == [im.image_id] for im in database.read_all_images())
    finally:
        database.close()
    assert colmap.number_images_by_name(db) is False  # in order now: nothing to do
