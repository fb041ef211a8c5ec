"""How `camera_mode=auto` decides between one shared camera and one camera per image."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from sara.config import ExtractConfig
from sara.extract import resolve_camera_mode
from sara.io.images import exif_camera, scan_images


def _photo(path: Path, size=(64, 48), make: str | None = None, model: str | None = None,
           focal: float | None = None) -> None:
    image = Image.fromarray(np.random.default_rng(0).integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
    exif = Image.Exif()
    if make:
        exif[0x010F] = make
    if model:
        exif[0x0110] = model
    if focal:
        exif.get_ifd(0x8769)[0x920A] = focal
    image.save(path, exif=exif.tobytes())


def _mode(folder: Path) -> str:
    return resolve_camera_mode(scan_images(folder, progress=False), ExtractConfig())


def test_exif_camera_reads_make_model_and_focal(tmp_path: Path):
    _photo(tmp_path / "a.jpg", make="Apple", model="iPhone 13", focal=5.1)
    _photo(tmp_path / "b.jpg")
    assert exif_camera(tmp_path / "a.jpg") == ("Apple", "iPhone 13", 5.1)
    assert exif_camera(tmp_path / "b.jpg") == (None, None, None)
    assert exif_camera(tmp_path / "missing.jpg") == (None, None, None)


def test_same_size_photos_of_two_phones_get_a_camera_each(tmp_path: Path):
    for k in range(3):
        _photo(tmp_path / f"a{k}.jpg", make="Apple", model="iPhone 13", focal=5.1)
        _photo(tmp_path / f"b{k}.jpg", make="Google", model="Pixel 7", focal=5.1)
    assert _mode(tmp_path) == "per_image"


def test_one_camera_video_frames_and_different_sizes(tmp_path: Path):
    one, frames, sizes = tmp_path / "one", tmp_path / "frames", tmp_path / "sizes"
    for folder in (one, frames, sizes):
        folder.mkdir()
    for k in range(3):
        _photo(one / f"{k}.jpg", make="Apple", model="iPhone 13", focal=5.1)
        _photo(frames / f"{k}.jpg")  # no EXIF at all: frames of one video
        _photo(sizes / f"{k}.jpg", size=(64 + k, 48))
    assert _mode(one) == "single" and _mode(frames) == "single" and _mode(sizes) == "per_image"


def test_share_cameras_gives_a_group_one_camera_as_colmaps_single_mode_does(tmp_path: Path):
    """The frames of a video imported one camera each, then shared: the database holds what
    COLMAP's import of them under one camera holds (one camera, one rig, every frame in it)."""
    import sqlite3

    from sara import colmap

    folder = tmp_path / "frames"
    folder.mkdir()
    names = [f"clip_f{k}.jpg" for k in range(3)] + ["other_f0.jpg"]
    for name in names:
        _photo(folder / name)

    def layout(db: Path) -> list:
        """Cameras and rigs counted; the images that share a camera; each image's frame in its camera's rig."""
        with sqlite3.connect(db) as con:
            counts = [con.execute(f"SELECT count(*) FROM {t}").fetchone()[0] for t in ("cameras", "rigs")]
            cameras = dict(con.execute("SELECT name, camera_id FROM images"))
            in_rig = con.execute(
                "SELECT count(*) FROM images i JOIN frame_data d ON d.data_id = i.image_id AND d.sensor_id = "
                "i.camera_id JOIN frames f ON f.frame_id = d.frame_id JOIN rigs r ON r.rig_id = f.rig_id AND "
                "r.ref_sensor_id = i.camera_id").fetchone()[0]
        groups = sorted(sorted(n for n in cameras if cameras[n] == c) for c in set(cameras.values()))
        return [counts, groups, in_rig]

    shared, single = tmp_path / "shared.db", tmp_path / "single.db"
    for db, mode, batch in ((shared, "per_image", names), (single, "single", names[:3])):
        colmap.create_database(db)
        colmap.import_images(db, folder, batch, camera_mode=mode, camera_model="SIMPLE_RADIAL")
    colmap.import_images(single, folder, names[3:], camera_mode="single", camera_model="SIMPLE_RADIAL")
    assert layout(shared)[0] == [4, 4]
    assert colmap.share_cameras(shared, [names[:3], names[3:]]) == 2
    assert layout(shared) == layout(single)
    assert colmap.share_cameras(shared, [names[:3], names[3:]]) == 0  # done already: nothing changes


def test_frames_of_several_videos_get_a_camera_per_video(tmp_path: Path):
    for k in range(2):
        _photo(tmp_path / f"a_f{k}.jpg")
        _photo(tmp_path / f"b_f{k}.jpg")
    images = scan_images(tmp_path, progress=False)
    groups = {n: n.split("_")[0] + ".mp4" for n in images.names}
    assert resolve_camera_mode(images, ExtractConfig(), groups) == "per_video"
    assert resolve_camera_mode(images, ExtractConfig(), dict.fromkeys(images.names, "a.mp4")) == "single"
    assert resolve_camera_mode(images, ExtractConfig(camera_mode="single"), groups) == "single"  # as asked
