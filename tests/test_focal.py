"""The shared focal length estimated from the images (`sara.scoring.focal`) and its use in extract."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from conftest import scene_dir

from sara.scoring import focal


def _fundamentals(f: float, width: int, height: int, num: int, seed: int = 0) -> list[np.ndarray]:
    """F = K^-T [t]x R K^-1 of random, general relative poses (optical axes not meeting)."""
    rng = np.random.default_rng(seed)
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    K_inv = np.linalg.inv(K)
    out = []
    for _ in range(num):
        axis = rng.normal(size=3)
        angle = np.radians(rng.uniform(3, 15))
        k = axis / np.linalg.norm(axis)
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        R = np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx
        t = rng.normal(size=3)
        tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
        out.append(K_inv.T @ tx @ R @ K_inv)
    return out


def test_estimate_finds_a_long_focal_length_three_times_the_prior():
    width, height = 640, 480
    prior = 1.2 * width
    found = focal.estimate(_fundamentals(3 * prior, width, height, 20), width, height, prior)
    assert found is not None and found.num_pairs == 20
    assert abs(np.log(found.focal_px / (3 * prior))) < np.log(1.07)  # one grid step
    assert found.cost < found.cost_at_prior / 20


def test_estimate_needs_enough_pairs():
    assert focal.estimate(_fundamentals(800, 640, 480, focal.MIN_PAIRS - 1), 640, 480, 768) is None


def test_nearby_pairs_are_neighbours_in_name_order_spread_over_the_collection():
    names = [f"{k:03d}.jpg" for k in range(100)]
    pairs = focal.nearby_pairs(names)
    assert len(pairs) == focal.MAX_PAIRS and len(set(pairs)) == len(pairs)
    assert all(names.index(b) - names.index(a) in (1, 2) for a, b in pairs)
    assert pairs[0][0] == names[0] and names[-1] in pairs[-1]
    assert focal.nearby_pairs(names[:4]) == [("000.jpg", "001.jpg"), ("001.jpg", "002.jpg"), ("002.jpg", "003.jpg"),
                                             ("000.jpg", "002.jpg"), ("001.jpg", "003.jpg")]


def test_a_long_lens_crop_of_a_real_scene_gets_a_longer_focal_length(tmp_path: Path):
    """Centre crops (a quarter of each side) of Herz-Jesus-P25: a 16-degree field of view where
    COLMAP's prior assumes 45; the true focal length is 3x the prior."""
    from sara import extract
    from sara.colmap import shared_camera
    from sara.config import ExtractConfig
    from sara.io import records
    from sara.io.images import scan_images

    scene = scene_dir("strecha-Herz-Jesus-P25")
    images = tmp_path / "images"
    images.mkdir()
    for path in sorted((scene / "images").iterdir()):
        with Image.open(path) as im:
            w, h = im.size
            im.crop((3 * w // 8, 3 * h // 8, 5 * w // 8, 5 * h // 8)).save(images / path.name)
    prior = 1.2 * (w // 4)
    out = tmp_path / "out"
    conf = ExtractConfig(num_threads=2)
    extract.run(conf, scan_images(images, progress=False), out, progress=False)
    found = records.done_info(out, extract.STAGE)["focal"]
    assert found["applied"] and focal.LONGER_THAN_PRIOR * prior <= found["estimated_px"] < 4.5 * prior
    assert shared_camera(out / extract.DB_NAME).mean_focal_length() == found["estimated_px"]
    # switched off: the prior stays
    off = tmp_path / "off"
    extract.run(ExtractConfig(num_threads=2, estimate_focal=False), scan_images(images, progress=False), off,
                progress=False)
    assert "focal" not in records.done_info(off, extract.STAGE)
    assert abs(shared_camera(off / extract.DB_NAME).mean_focal_length() - prior) < 1.0


def test_the_new_setting_keeps_earlier_extractions_valid(tmp_path: Path):
    """Features extracted before `estimate_focal` existed keep their key at its default."""
    from sara import extract
    from sara.config import ExtractConfig
    from sara.extract import _key
    from sara.io import fingerprint, records
    from sara.io.images import scan_images

    for k in range(2):
        Image.fromarray(np.random.default_rng(k).integers(0, 255, (48, 64, 3), dtype=np.uint8)).save(tmp_path / f"{k}.png")
    images = scan_images(tmp_path, progress=False)
    out = tmp_path / "out"
    before = {k: v for k, v in ExtractConfig().__dict__.items() if k != "estimate_focal"}
    old_key = fingerprint({"images": images.fingerprint_data(), "conf": before})  # as sara keyed it then
    records.mark_done(out, extract.STAGE, old_key)
    assert _key(images, ExtractConfig(), out, progress=False)[0] == old_key
    assert _key(images, ExtractConfig(estimate_focal=False), out, progress=False)[0] != old_key
