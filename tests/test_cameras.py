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
