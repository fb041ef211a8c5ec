"""How `camera_mode=auto` shares cameras: one for all images, one per video or numbered sequence of
frames, one per phone (EXIF) or one per image."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from sara.cameras import ExifCamera, camera_sharing, exif_camera
from sara.config import ExtractConfig
from sara.io.images import scan_images


def _photo(path: Path, size=(64, 48), make: str | None = None, model: str | None = None,
           focal: float | None = None, focal_35mm: int | None = None) -> None:
    image = Image.fromarray(np.random.default_rng(0).integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
    exif = Image.Exif()
    if make:
        exif[0x010F] = make
    if model:
        exif[0x0110] = model
    if focal:
        exif.get_ifd(0x8769)[0x920A] = focal
    if focal_35mm:
        exif.get_ifd(0x8769)[0xA405] = focal_35mm
    image.save(path, exif=exif.tobytes())


def _mode(folder: Path) -> str:
    return camera_sharing(scan_images(folder, progress=False), ExtractConfig())[0]


def test_exif_camera_reads_make_model_and_focal(tmp_path: Path):
    _photo(tmp_path / "a.jpg", make="Apple", model="iPhone 13", focal=5.1)
    _photo(tmp_path / "b.jpg")
    assert exif_camera(tmp_path / "a.jpg") == ExifCamera("Apple", "iPhone 13", 5.1, None)
    nothing = ExifCamera(None, None, None, None)
    assert exif_camera(tmp_path / "b.jpg") == exif_camera(tmp_path / "missing.jpg") == nothing


def test_photos_of_a_few_phones_get_a_camera_per_phone_held_each_way(tmp_path: Path):
    """Two phones of one resolution must not share intrinsics, but the photos of one phone do; held
    upright its photos have another size (a camera of their own), zoomed another field of view."""
    for k in range(3):
        _photo(tmp_path / f"a{k}.jpg", make="Apple", model="iPhone 13", focal=5.1)
        _photo(tmp_path / f"b{k}.jpg", make="Google", model="Pixel 7", focal=5.1)
    _photo(tmp_path / "a_upright.jpg", size=(48, 64), make="Apple", model="iPhone 13", focal=5.1)
    _photo(tmp_path / "a_zoomed.jpg", make="Apple", model="iPhone 13", focal=5.1, focal_35mm=52)
    _photo(tmp_path / "no_exif.jpg")
    mode, groups = camera_sharing(scan_images(tmp_path, progress=False), ExtractConfig())
    assert mode == "per_exif"
    together = sorted(sorted(n for n in groups if groups[n] == g) for g in set(groups.values()))
    assert together == [["a0.jpg", "a1.jpg", "a2.jpg"], ["a_upright.jpg"], ["a_zoomed.jpg"],
                        ["b0.jpg", "b1.jpg", "b2.jpg"]]  # and no_exif.jpg a camera of its own
    assert camera_sharing(scan_images(tmp_path, progress=False), ExtractConfig(camera_mode="per_image")) \
        == ("per_image", None)


def test_photos_that_share_no_phone_get_a_camera_each(tmp_path: Path):
    _photo(tmp_path / "a.jpg", make="Apple", model="iPhone 13", focal=5.1)
    _photo(tmp_path / "b.jpg", make="Google", model="Pixel 7", focal=5.1)
    _photo(tmp_path / "c.jpg", size=(64, 64))
    _photo(tmp_path / "d.jpg", size=(64, 64))  # no EXIF: nothing says these two are one camera
    assert _mode(tmp_path) == "per_image"


def test_a_photo_added_later_joins_its_phones_camera(five_view_scene, tmp_path: Path, run_cli):
    """The photos of two phones, extracted with a camera per phone; one more photo of the first
    phone added to the folder: the update gives it that phone's camera."""
    import sqlite3

    images, _ = five_view_scene
    folder = tmp_path / "photos"
    folder.mkdir()
    paths = sorted(images.iterdir())
    phone = {p.stem + ".jpg": ("Apple", "iPhone 13") if k % 2 == 0 else ("Google", "Pixel 7")
             for k, p in enumerate(paths)}

    def copy(path: Path) -> None:
        make, model = phone[path.stem + ".jpg"]
        with Image.open(path) as im:
            exif = Image.Exif()
            exif[0x010F], exif[0x0110] = make, model
            exif.get_ifd(0x8769)[0x920A] = 5.1
            im.convert("RGB").save(folder / (path.stem + ".jpg"), quality=95, exif=exif.tobytes())

    for path in paths[1:]:
        copy(path)
    out = tmp_path / "out"
    assert run_cli("extract", folder, out, "-q").code == 0
    copy(paths[0])
    result = run_cli("extract", folder, out, "-q")
    assert result.code == 0, result.err
    with sqlite3.connect(out / "database.db") as con:
        cameras = dict(con.execute("SELECT name, camera_id FROM images"))
    assert len(cameras) == len(paths) and len(set(cameras.values())) == 2
    assert all((cameras[a] == cameras[b]) == (phone[a] == phone[b]) for a in cameras for b in cameras)
    record = json.loads((out / "run.json").read_text())
    assert record["stages"]["extract"]["camera_mode"] == "per_exif"


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
    assert camera_sharing(images, ExtractConfig(), groups) == ("per_video", groups)
    assert camera_sharing(images, ExtractConfig(), dict.fromkeys(images.names, "a.mp4"))[0] == "single"
    assert camera_sharing(images, ExtractConfig(camera_mode="single"), groups)[0] == "single"  # as asked


def test_numbered_sequences_of_one_size_get_a_camera_each(tmp_path: Path):
    """Frames a user extracted from two clips (`clip0_0001.png`, ...; no EXIF): a camera per
    sequence, each of one size; the rule holds within a sequence what `single` asks of a folder.
    Frames of clips of one size get a camera per clip too, as the frames of videos do."""
    clips, collection, short = tmp_path / "clips", tmp_path / "collection", tmp_path / "short"
    for folder in (clips, collection, short):
        folder.mkdir()
    for k in range(3):
        _photo(clips / f"clip0_{k:04d}.png", size=(64, 48))
        _photo(clips / f"clip1_{k:04d}.png", size=(48, 64))  # the phone held upright
        _photo(collection / f"{k:05d}.jpg", size=(64 + k % 2, 48))  # numbered, but of two sizes: no clip
        _photo(collection / f"{k + 3:05d}.jpg", size=(64 + k % 2, 48))
        _photo(short / f"{k}_x.png", size=(64 + k, 48))
    _photo(clips / "still.jpg", size=(50, 40))  # not in a sequence: its own camera
    images = scan_images(clips, progress=False)
    mode, groups = camera_sharing(images, ExtractConfig())
    assert mode == "per_sequence"
    assert groups == {n: f"frames clip{n[4]}_#.png" for n in images.names if n.startswith("clip")}
    assert _mode(collection) == "per_image" and _mode(short) == "per_image"
    same, one = tmp_path / "same", tmp_path / "one"  # clips of one size: a zoom or another lens may differ
    for folder in (same, one):
        folder.mkdir()
    for k in range(3):
        _photo(same / f"wide_{k:04d}.png")
        _photo(same / f"main_{k:04d}.png")
        _photo(one / f"frame_{k:05d}.png")
    assert _mode(same) == "per_sequence" and _mode(one) == "single"
    on = tmp_path / "numbered_on"  # two clips' frames numbered on from one to the other
    on.mkdir()
    for k in range(7):
        _photo(on / f"frame_{k:05d}.png", size=(64, 48) if k < 4 else (48, 64))
    images = scan_images(on, progress=False)
    mode, groups = camera_sharing(images, ExtractConfig())
    assert mode == "per_sequence" and len(set(groups.values())) == 2
    assert len({groups[f"frame_{k:05d}.png"] for k in range(4)}) == 1
    frames_of_one_video = scan_images(same, progress=False)
    assert camera_sharing(frames_of_one_video, ExtractConfig(), dict.fromkeys(frames_of_one_video.names, "v.mp4")) \
        == ("single", None)  # sara's own frames of one video: the video says
    for k in range(2):  # two frames of one more clip: too few to tell a clip
        _photo(short / f"c_{k}.png", size=(32, 32))
    assert _mode(short) == "per_image"
    assert camera_sharing(images, ExtractConfig(camera_mode="per_image"))[0] == "per_image"  # as asked


def test_an_update_of_one_camera_works_the_cameras_out_again_only_for_another_clip_size_or_phone(tmp_path: Path):
    from sara.cameras import may_leave_single

    for k in range(4):
        _photo(tmp_path / f"a_{k:04d}.png")
    _photo(tmp_path / "b_0000.png")
    images = scan_images(tmp_path, progress=False)
    assert not may_leave_single(images, ["a_0003.png"])  # one more frame of the clip: no EXIF read
    assert may_leave_single(images, ["b_0000.png"])  # another clip
    _photo(tmp_path / "a_0004.png", size=(48, 64))
    assert may_leave_single(scan_images(tmp_path, progress=False), ["a_0004.png"])  # another size
    phones = tmp_path / "phones"
    phones.mkdir()
    for k in range(3):
        _photo(phones / f"IMG_{k:04d}.JPG", make="Apple", model="iPhone 13", focal=5.1)
    _photo(phones / "IMG_0100.JPG", make="Google", model="Pixel 7", focal=6.8)
    _photo(phones / "IMG_0101.JPG", make="Apple", model="iPhone 13", focal=5.1)
    images = scan_images(phones, progress=False)
    assert may_leave_single(images, ["IMG_0100.JPG"])  # another phone, its photos of the same size
    assert not may_leave_single(images, ["IMG_0101.JPG"])


@pytest.mark.parametrize("name, orientation, rotate", [("IMG_0001.HEIC", 1, False), ("IMG_0002.jpg", 6, True)])
def test_copies_keep_the_exif_camera(tmp_path: Path, name, orientation, rotate):
    """Photos COLMAP cannot read (an iPhone's HEIC) and photos turned upright are read from copies:
    the copies keep the EXIF camera, so COLMAP's focal prior and the camera per phone still hold."""
    from sara import colmap
    from sara.io.images import upright_copy

    if name.endswith(".HEIC"):
        pytest.importorskip("pillow_heif", reason="pillow-heif is not installed (pip install 'sara[heic]')") \
            .register_heif_opener()
    folder = tmp_path / "photos"
    folder.mkdir()
    exif = Image.Exif()
    exif[0x010F], exif[0x0110], exif[0x0112] = "Apple", "iPhone 13", orientation
    exif.get_ifd(0x8769)[0x920A], exif.get_ifd(0x8769)[0xA405] = 5.1, 26
    pixels = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(folder / name, format="HEIF" if rotate is False else "JPEG", exif=exif.tobytes())
    images = scan_images(folder, progress=False)
    copies = upright_copy(images, tmp_path / "copies", rotate=rotate, progress=False)
    assert exif_camera(copies.root / name) == ExifCamera("Apple", "iPhone 13", 5.1, 26)
    with Image.open(copies.root / name) as im:
        assert im.size == ((48, 64) if rotate else (64, 48)) and im.getexif().get(0x0112, 1) == 1
    colmap.create_database(tmp_path / "database.db")
    colmap.import_images(tmp_path / "database.db", copies.root, [name], camera_mode="per_image",
                         camera_model="SIMPLE_RADIAL")
    assert list(colmap.camera_priors(tmp_path / "database.db").values()) == [True]  # EXIF gave the focal length
