"""Class 3b of the fault suite: what else is in the image folder (issue 30). sara's own output
folder inside the image folder is never read as input; every file that is not used is said so
(one warning line counting them by reason, each in run.json's `skipped_images`); HEIC photos are
read where pillow-heif is installed, and otherwise named with the extra to install; WebP photos are
read through Pillow and exported under names COLMAP can write."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import pytest
from PIL import Image

from harness import assert_ok, registered


def _rotated_folder(images: Path, folder: Path) -> Path:
    """The scene as JPEGs, every third stored sideways with an EXIF tag that turns it upright."""
    folder.mkdir()
    for k, path in enumerate(sorted(images.iterdir())):
        pixels, exif = Image.open(path).convert("RGB"), Image.Exif()
        if k % 3 == 0:
            exif[0x0112] = 6
            pixels = pixels.rotate(90, expand=True)
        pixels.save(folder / f"{path.stem}.jpg", exif=exif, quality=95)
    return folder


def _used(result) -> int:
    line = next(line for line in result.out.splitlines() if line.startswith("Images:"))
    return int(line.split()[1])


# the export case takes 9 s: slow, for the default suite's 5 minutes (run with -m slow)
@pytest.mark.parametrize("case", ["EXIF applied", pytest.param("3dgs export", marks=pytest.mark.slow)])
def test_output_folder_inside_the_image_folder(case, images, tmp_path, run_cli):
    """OUT inside IMAGES with --recursive: sara's upright copies (or the export's images) under OUT
    are never taken for input. Issue 30: the second run refused ("other images"), and with
    --overwrite used 64 images out of 16, one level deeper each run."""
    views = tmp_path / "views"  # five of the scene's views: each of the three runs extracts them all
    views.mkdir()
    for path in sorted(images.iterdir())[:5]:
        shutil.copyfile(path, views / path.name)
    if case == "EXIF applied":
        folder = _rotated_folder(views, tmp_path / "images")
        options = ["-s", "images.exif_orientation=apply"]
    else:
        folder = Path(shutil.copytree(views, tmp_path / "images"))
        options = ["--export", "3dgs"]
    out = folder / "out"
    num_images = len(list(views.iterdir()))
    for extra in ([], [], ["--overwrite"]):
        result = run_cli("run", folder, out, "-q", "--recursive", *options, *extra)
        assert_ok(result)
        assert _used(result) == num_images
        assert not json.loads((out / "run.json").read_text())["skipped_images"]
        assert len(registered(out)) == num_images and not any(n.startswith("out/") for n in registered(out))
    assert result.err.count("not looking for images in") == 1 and str(out) in result.err


def test_other_sara_output_folders_are_not_scanned(images, tmp_path, monkeypatch):
    """A folder with sara's marker (an output folder of another run) is left out too."""
    import logging

    from sara.io.images import scan_images

    said: list[str] = []

    class Keep(logging.Handler):  # its own handler: the CLI's in-process runs leave the "sara" logger's
        def emit(self, record: logging.LogRecord) -> None:  # handlers and propagation as they set them
            said.append(record.getMessage())

    scan_logger = logging.getLogger("sara.io.images")
    monkeypatch.setattr(scan_logger, "disabled", False)
    monkeypatch.setattr(scan_logger, "handlers", [Keep()])
    folder = Path(shutil.copytree(images, tmp_path / "images"))
    for marker in ("run-a/.sara", "run-b/.sara.lock"):
        shutil.copytree(images, folder / Path(marker).parent / "images_upright")
        (folder / marker).mkdir() if marker.endswith(".sara") else (folder / marker).write_text("")
    found = scan_images(folder, recursive=True, progress=False)
    assert found.names == sorted(p.name for p in images.iterdir()) and not found.skipped
    said = [m for m in said if "not looking for images in" in m]
    assert len(said) == 2 and "run-a" in said[0] and "run-b" in said[1]


NOT_USED = {  # file name -> what the run record says about it
    "broken-link.png": "broken symbolic link",
    "anim.gif": "a .gif file, a format sara does not read",
    "photo.heic": "pip install 'sara[heic]'",
    "PHOTO2.HEIC": "pip install 'sara[heic]'",
    "x.png ": "blank characters after its extension",
    "notes.txt": "not an image file",
    "IMG_0001.MOV": "a video among images: sara uses the images; `sara run` on the video",  # a Live Photo's clip
}


@pytest.fixture
def cluttered(images, tmp_path) -> Path:
    """The scene with a file of each kind sara does not use."""
    folder = tmp_path / "images"
    folder.mkdir()
    for path in sorted(images.iterdir())[:3]:  # few images: extraction stays quick
        shutil.copyfile(path, folder / path.name)
    first = sorted(images.iterdir())[0]
    (folder / "broken-link.png").symlink_to(tmp_path / "gone.png")
    Image.open(first).save(folder / "anim.gif")
    (folder / "photo.heic").write_bytes(b"\0\0\0\x18ftypheic" + b"\0" * 64)  # not decoded without pillow-heif
    (folder / "PHOTO2.HEIC").write_bytes(b"\0\0\0\x18ftypheic" + b"\0" * 64)
    shutil.copyfile(first, folder / "x.png ")
    (folder / "notes.txt").write_text("shot on a tripod")
    (folder / "IMG_0001.MOV").write_bytes(b"\0\0\0\x14ftypqt  " + b"\0" * 64)
    return folder


def test_every_file_not_used_is_reported(cluttered, tmp_path, run_cli, monkeypatch):
    """Issue 30: broken links, GIFs, HEIC photos, `x.png ` were left out without a word; a video
    among the photos (an iPhone's Live Photo clip) is named as one."""
    monkeypatch.setitem(sys.modules, "pillow_heif", None)  # as where it is not installed
    result = run_cli("extract", cluttered, tmp_path / "out", "-q")
    assert_ok(result)
    summary = [line for line in result.err.splitlines() if "not used:" in line]
    assert len(summary) == 1, result.err
    for fragment in ("7 file(s)", "2 HEIC photo (pip install 'sara[heic]')", "1 broken link", "1 not an image",
                     "1 unsupported image format", "1 blank after the extension", "1 video (`sara run VIDEO` for its "
                     "frames)", "skipped_images"):
        assert fragment in summary[0]
    skipped = json.loads((tmp_path / "out" / "run.json").read_text())["skipped_images"]
    assert set(skipped) == set(NOT_USED)
    for name, fragment in NOT_USED.items():
        assert fragment in skipped[name]
    assert "install pillow-heif (pip install 'sara[heic]')" in skipped["photo.heic"]


def test_a_folder_of_heic_photos_without_pillow_heif(images, tmp_path, run_cli, monkeypatch):
    monkeypatch.setitem(sys.modules, "pillow_heif", None)
    folder = tmp_path / "phone"
    folder.mkdir()
    for k in range(3):
        (folder / f"IMG_{k}.HEIC").write_bytes(b"\0\0\0\x18ftypheic" + b"\0" * 64)
    result = run_cli("run", folder, tmp_path / "out", "-q")
    assert result.code == 2, result.err
    assert "no images found" in result.err and "3 HEIC photo (pip install 'sara[heic]')" in result.err


def test_heic_photos_are_used_with_pillow_heif(images, tmp_path, run_cli):
    """With pillow-heif installed, HEIC photos are decoded, reconstructed from JPEG copies (COLMAP
    cannot read HEIC) and registered under their own names."""
    pillow_heif = pytest.importorskip("pillow_heif", reason="pillow-heif is not installed (pip install 'sara[heic]')")
    pillow_heif.register_heif_opener()
    folder = tmp_path / "phone"
    folder.mkdir()
    names = []
    for k, path in enumerate(sorted(images.iterdir())):
        name = f"IMG_{k:02d}.HEIC" if k % 2 == 0 else path.name
        Image.open(path).convert("RGB").save(folder / name, format="HEIF", quality=95) if k % 2 == 0 \
            else shutil.copyfile(path, folder / name)
        names.append(name)
    result = run_cli("run", folder, tmp_path / "out", "-q")
    assert_ok(result)
    assert registered(tmp_path / "out") == sorted(names)
    assert not json.loads((tmp_path / "out" / "run.json").read_text())["skipped_images"]


def test_webp_photos_are_used_and_exported(images, tmp_path, run_cli):
    """A photo collection downloaded from the web holds WebP files, which COLMAP cannot read: sara
    decodes them with Pillow, reconstructs from JPEG copies, and the 3DGS export (COLMAP's
    undistorter cannot write WebP) names those images `<name>.jpg`."""
    from PIL import features

    if not features.check("webp"):
        pytest.skip("this Pillow was built without WebP")
    folder = tmp_path / "downloads"
    folder.mkdir()
    names = []
    for k, path in enumerate(sorted(images.iterdir())):
        name = f"{path.stem}.webp" if k % 2 == 0 else path.name
        Image.open(path).convert("RGB").save(folder / name, quality=95) if k % 2 == 0 \
            else shutil.copyfile(path, folder / name)
        names.append(name)
    out = tmp_path / "out"
    assert_ok(run_cli("run", folder, out, "-q"))
    assert registered(out) == sorted(names)
    assert not json.loads((out / "run.json").read_text())["skipped_images"]
    assert_ok(run_cli("export", out, tmp_path / "splat", "--format", "3dgs", "-q"))
    exported = sorted(p.name for p in (tmp_path / "splat" / "images").iterdir())
    assert exported == sorted(f"{n}.jpg" if n.endswith(".webp") else n for n in names)
    from sara.colmap.model import read_model

    assert sorted(read_model(tmp_path / "splat" / "sparse" / "0").names) == exported
    assert_ok(run_cli("export", out, tmp_path / "ns", "--format", "nerfstudio", "-q"))  # not undistorted: copies
    frames = json.loads((tmp_path / "ns" / "transforms.json").read_text())["frames"]
    assert sorted(Path(f["file_path"]).name for f in frames) == exported
    assert sorted(p.name for p in (tmp_path / "ns" / "images").iterdir()) == exported
    with Image.open(tmp_path / "splat" / "images" / f"{names[0]}.jpg") as im:
        assert im.format == "JPEG"
