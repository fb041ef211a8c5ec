"""Class 4 of the fault suite: files that one decoder reads and another does not. COLMAP's reader
decides for SIFT (Pillow reads more formats than it does); a learned extractor skips a file that
vanished or cannot be decoded, naming why."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

FORMATS = {  # format written under an image extension -> COLMAP's reader decodes it
    ("png", "PNG"): True, ("jpg", "JPEG"): True, ("bmp", "BMP"): True, ("tif", "TIFF"): True,
    ("ppm", "PPM"): True, ("png", "WEBP"): False, ("jpg", "GIF"): False,
}


@pytest.mark.parametrize("ext,fmt", list(FORMATS), ids=lambda v: str(v))
def test_colmap_reader_decides_for_sift(ext, fmt, synthetic_scene, tmp_path):
    from sara.colmap import image_read_problem
    from sara.io.images import check_image

    path = tmp_path / f"image.{ext}"
    Image.open(sorted(synthetic_scene[0].iterdir())[0]).convert("RGB").save(path, format=fmt)
    assert check_image(path)[1] is None  # Pillow reads them all
    assert (image_read_problem(path) is None) == FORMATS[(ext, fmt)]


def test_learned_extraction_skips_a_vanished_file(tmp_path):
    from sara import extract
    from sara.config import ExtractConfig
    from sara.features import Keypoints

    class Dummy:
        name = "dummy"

        def extract(self, image):
            return Keypoints(np.zeros((1, 2), np.float32), np.ones(1, np.float32), np.ones((1, 4), np.float32))

    conf = ExtractConfig(backend="dummy-test")
    Image.new("RGB", (64, 64), (10, 20, 30)).save(tmp_path / "here.png")
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    extract._BACKENDS[extract._backend_key(conf)] = Dummy()
    try:
        job = extract._ExtractJob(conf, str(tmp_path), ["here.png", "gone.png", "broken.png"])
        found = extract._extract_images(job)
    finally:
        extract._BACKENDS.clear()
    assert isinstance(found[0], Keypoints)
    assert found[1] == "the file disappeared during extraction"
    assert "could not be decoded" in found[2]


