"""Class 4 of the fault suite: files that one decoder reads and another does not. COLMAP's reader
decides for SIFT (Pillow reads more formats than it does); a learned extractor skips a file that
vanished or cannot be decoded, naming why."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from harness import assert_ok, registered

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




def test_image_vanished_during_extraction_stays_set_aside(images, tmp_path, run_cli, monkeypatch):
    """An image deleted while COLMAP extracts is set aside; the same command again (the file still
    gone) is accepted, not refused as "other images", and reports it again (issue 30)."""
    import json
    import shutil

    from sara import colmap

    folder = tmp_path / "images"  # five of the scene's views: the first run extracts them all
    folder.mkdir()
    for path in sorted(images.iterdir())[:5]:
        shutil.copyfile(path, folder / path.name)
    gone = sorted(folder.iterdir())[3]
    original = colmap.extract_sift

    def delete_then_extract(db_path, image_dir, names, **kwargs):
        gone.unlink(missing_ok=True)  # the file vanishes after the checks, while COLMAP reads the images
        return original(db_path, image_dir, names, **kwargs)

    monkeypatch.setattr(colmap, "extract_sift", delete_then_extract)
    out = tmp_path / "out"
    first = run_cli("run", folder, out, "-q")
    assert_ok(first)
    monkeypatch.setattr(colmap, "extract_sift", original)
    reason = "the file disappeared during extraction"
    assert f"skipping {gone.name}: {reason}" in first.err
    for _ in range(2):  # the same command, twice: accepted each time, the image still set aside
        result = run_cli("run", folder, out, "-q")
        assert_ok(result)
        assert f"skipping {gone.name}: {reason}" in result.err
        assert json.loads((out / "run.json").read_text())["skipped_images"] == {gone.name: reason}
        assert gone.name not in registered(out) and len(registered(out)) == 4
    shutil.copyfile(sorted(images.iterdir())[3], gone)  # back again: it stays set aside, as documented
    result = run_cli("run", folder, out, "-q")
    assert_ok(result)
    assert json.loads((out / "run.json").read_text())["skipped_images"] == {gone.name: reason}
