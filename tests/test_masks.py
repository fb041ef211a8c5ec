"""Masks (`--masks DIR`): keypoints on a mask's black pixels are left out of the features file and
the database before any pair is scored or matched; bad masks are one line before any work."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sqlite3
from pathlib import Path

import h5py
import numpy as np
import pytest
from PIL import Image

from harness import assert_error, assert_ok, registered, run_redirected

FIRST = 6  # images of the first run in the update test


def _write_masks(images: Path, folder: Path, names: list[str]) -> dict[str, float]:
    """Masks whose left part is black, named the COLMAP way and the nerfstudio way in turn, every
    third at half the image's scale; returns name -> the first pixel column kept."""
    folder.mkdir(parents=True, exist_ok=True)
    kept_from = {}
    for k, name in enumerate(names):
        w, h = Image.open(images / name).size
        scale = 2 if k % 3 == 2 else 1
        mask = np.full((h // scale, w // scale), 255, np.uint8)
        cut = (w // scale) * (k % 4 + 1) // 6
        mask[:, :cut] = 0
        target = folder / (f"{name}.png" if k % 2 else f"{Path(name).stem}.png")
        Image.fromarray(mask).save(target)
        kept_from[name] = cut * scale
    return kept_from


def _db_keypoints(db: Path) -> dict[str, np.ndarray]:
    with contextlib.closing(sqlite3.connect(db)) as con:
        rows = con.execute("SELECT name, rows, cols, data FROM images JOIN keypoints USING (image_id)").fetchall()
    return {name: np.frombuffer(data, np.float32).reshape(n, c) for name, n, c, data in rows}


def _check_features(out: Path, kept_from: dict[str, float]) -> None:
    """No keypoint left of its mask's cut, in the features file (hloc's pixels, the first centred at
    0) nor in the database (COLMAP's, at 0.5), and the two hold the same keypoints."""
    db = _db_keypoints(out / "database.db")
    with h5py.File(out / "features-sift.h5", "r") as h5:
        for name, cut in kept_from.items():
            xy = h5[name]["keypoints"][()]
            assert len(xy) > 20 and xy[:, 0].min() >= cut - 0.5, (name, cut, xy[:, 0].min())
            np.testing.assert_allclose(db[name][:, :2] - 0.5, xy, atol=1e-3)


def test_keypoints_on_black_pixels_are_left_out(synthetic_scene, tmp_path, run_cli):
    images, _ = synthetic_scene
    names = sorted(os.listdir(images))
    kept_from = _write_masks(images, tmp_path / "masks", names[:-1])  # the last image has no mask
    out = tmp_path / "out"
    result = run_cli("extract", images, out, "-q", "--masks", tmp_path / "masks")
    assert_ok(result)
    assert f"1 of {len(names)} images have no mask" in result.err
    _check_features(out, kept_from)
    counts = {name: len(xy) for name, xy in _db_keypoints(out / "database.db").items()}
    with h5py.File(out / "features-sift.h5", "r") as h5:
        assert all(counts[n] == len(h5[n]["keypoints"]) for n in names)
    info = json.loads((out / ".sara" / "extract.json").read_text())["info"]["masked_keypoints"]
    assert info["num_images"] == len(names) - 1 and info["num_keypoints"] > 100
    assert info["images_without_mask"] == [names[-1]]
    # the same command again: up to date, nothing taken out twice; a mask changed: other features
    assert_ok(run_cli("extract", images, out, "-q", "--masks", tmp_path / "masks"))
    assert {name: len(xy) for name, xy in _db_keypoints(out / "database.db").items()} == counts
    Image.new("L", Image.open(tmp_path / "masks" / f"{Path(names[0]).stem}.png").size, 255).save(
        tmp_path / "masks" / f"{Path(names[0]).stem}.png")
    assert_error(run_cli("extract", images, out, "-q", "--masks", tmp_path / "masks"), 3, "other extraction settings")


@pytest.mark.parametrize("case, message", [
    ("no folder", "mask folder not found"),
    ("no mask fits", "no mask in"),
    ("another shape", "a mask has its image's shape"),
    ("not an image", "does not read as an image"),
])
def test_a_bad_mask_is_one_line_before_any_work(case, message, synthetic_scene, tmp_path, run_cli):
    images, _ = synthetic_scene
    name = sorted(os.listdir(images))[0]
    masks = tmp_path / "masks"
    if case != "no folder":
        masks.mkdir()
    if case == "no mask fits":
        Image.new("L", (8, 8), 255).save(masks / "other.png")
    if case == "another shape":
        w, h = Image.open(images / name).size
        Image.new("L", (w, w), 255).save(masks / f"{name}.png")
    if case == "not an image":
        (masks / f"{name}.png").write_text("not a picture")
    result = run_cli("run", images, tmp_path / "out", "-q", "--masks", masks)
    line = assert_error(result, 2, message)
    assert str(masks) in line or case in ("another shape", "not an image")
    assert not (tmp_path / "out" / "database.db").exists()  # before any work


def test_images_added_to_a_masked_run_are_masked_too(synthetic_scene, tmp_path):
    source, _ = synthetic_scene
    names = sorted(os.listdir(source))
    images = tmp_path / "images"
    images.mkdir()
    for name in names[:FIRST]:
        shutil.copyfile(source / name, images / name)
    kept_from = _write_masks(source, tmp_path / "masks", names)
    out = tmp_path / "out"
    assert_ok(run_redirected("run", images, out, "-q", "--masks", tmp_path / "masks"))
    for name in names[FIRST:]:
        shutil.copyfile(source / name, images / name)
    assert_ok(run_redirected("run", images, out, "-q", "--masks", tmp_path / "masks"))
    assert json.loads((out / "run.json").read_text())["stages"]["update"]["num_added"] == len(names) - FIRST
    _check_features(out, kept_from)
    assert len(registered(out)) >= len(names) - 1
    assert "per image on the masks' black pixels left out" in (out / "report.md").read_text()
    # the nerfstudio export carries them: each frame's mask_path, at its image's size, black where it was
    assert_ok(run_redirected("export", out, tmp_path / "ns", "--format", "nerfstudio", "-q"))
    frames = json.loads((tmp_path / "ns" / "transforms.json").read_text())["frames"]
    assert len(frames) == len(registered(out)) and all(f["mask_path"].startswith("masks/") for f in frames)
    for frame in frames:
        name = Path(frame["file_path"]).name
        mask = np.asarray(Image.open(tmp_path / "ns" / frame["mask_path"]))
        assert mask.shape[::-1] == Image.open(images / name).size
        assert not mask[:, : kept_from[name] - 1].any() and mask[:, kept_from[name] + 1:].all()
    result = run_redirected("export", out, tmp_path / "ns2", "--format", "nerfstudio", "--undistort", "-q")
    assert_ok(result)
    assert "masks are not exported beside undistorted images" in result.err
    assert not (tmp_path / "ns2" / "masks").exists()


def test_a_bench_scene_with_masks_uses_them_under_every_naming(five_view_scene, tmp_path):
    """A scene's masks/ go to every method's extraction, and to its renamed copies under the new names."""
    from sara import bench
    from sara.config import make_config

    images, gt = five_view_scene
    scene = tmp_path / "masked"
    shutil.copytree(images, scene / "images")
    shutil.copytree(gt, scene / "gt")
    names = sorted(os.listdir(images))
    _write_masks(images, scene / "masks", names)
    result = bench.run_bench([scene], tmp_path / "bench", make_config(), methods=["exhaustive"], progress=False,
                             plot=False, name_orders=1)
    assert [r["scene"] for r in result.rows] == ["masked", "masked~names1"] and all(r["auc@5"] for r in result.rows)
    for folder in ("masked", "masked~names1"):
        record = json.loads((tmp_path / "bench" / folder / "features" / ".sara" / "extract.json").read_text())
        assert record["info"]["masked_keypoints"]["num_images"] == len(names)
    renamed = tmp_path / "bench" / "renamed" / "masked~names1"
    mapping = json.loads((renamed / "names.json").read_text())
    assert sorted(p.name for p in (renamed / "masks").iterdir()) == sorted(f"{new}.png" for new in mapping.values())


def test_candidates_matching_at_the_same_pixels_point_to_masks(caplog):
    """Most candidates without parallax (something that moves with the camera, or a camera that stood
    still) give one warning naming --masks; a scene's few such pairs, or pairs not triangulated, none."""
    from sara.io.scores import PairScores
    from sara.pairs.sara.source import _warn_if_still

    def scores(parallax):
        n = len(parallax)
        return PairScores(name0=[f"a{k}" for k in range(n)], name1=[f"b{k}" for k in range(n)],
                          num_matches=np.full(n, 50), num_inliers=np.full(n, 40), overlap=np.full(n, 0.1),
                          parallax_deg=np.array(parallax, float), weight=np.zeros(n), accepted=np.zeros(n, bool),
                          reason=["low_parallax"] * n)

    _warn_if_still(scores([0.0] * 18 + [3.0] * 2))
    assert "18 of 20 candidate pairs match at the same pixels" in caplog.text and "--masks" in caplog.text
    caplog.clear()
    _warn_if_still(scores([0.0] * 3 + [3.0] * 17))
    _warn_if_still(scores([float("nan")] * 20))
    assert "same pixels" not in caplog.text


def test_a_run_without_masks_says_nothing_of_them(finished_run_template):
    assert "masks" not in (finished_run_template / "report.md").read_text()
    assert "masked_keypoints" not in json.loads((finished_run_template / "run.json").read_text())["stages"]["extract"]


def test_masks_of_photos_turned_by_their_exif_orientation(synthetic_scene, tmp_path, run_cli):
    """With images.exif_orientation=apply a photo is read upright, and so is its mask: one of the
    upright shape is used; one of the stored shape is one line before any work."""
    source, _ = synthetic_scene
    images = tmp_path / "images"
    images.mkdir()
    for name in sorted(os.listdir(source))[:4]:
        stored = Image.open(source / name).convert("RGB").transpose(Image.Transpose.ROTATE_90)
        exif = Image.Exif()
        exif[0x0112] = 6  # shown turned a quarter clockwise: upright again
        stored.save(images / f"{Path(name).stem}.jpg", exif=exif, quality=95)
    names = sorted(os.listdir(images))
    w, h = Image.open(images / names[0]).size  # stored: portrait
    masks = tmp_path / "masks"
    masks.mkdir()
    for name in names:
        upright = np.full((w, h), 255, np.uint8)  # (rows, cols) of the upright landscape image
        upright[:, : h // 2] = 0
        Image.fromarray(upright).save(masks / f"{name}.png")
    turned = ["-s", "images.exif_orientation=apply", "--masks", masks]
    assert_ok(run_cli("extract", images, tmp_path / "out", "-q", *turned))
    with h5py.File(tmp_path / "out" / "features-sift.h5", "r") as h5:
        assert all(h5[n]["keypoints"][()][:, 0].min() >= h // 2 - 0.5 for n in names)
    for name in names:
        Image.new("L", (w, h), 255).save(masks / f"{name}.png")
    assert_error(run_cli("extract", images, tmp_path / "out2", "-q", *turned), 2, "a mask has its image's shape")
    assert not (tmp_path / "out2" / "database.db").exists()


def test_one_mask_image_masks_every_image(synthetic_scene, tmp_path, run_cli):
    """`--masks FILE`: the same mask for every image (a car's bonnet, a mount), at half the scale."""
    images, _ = synthetic_scene
    names = sorted(os.listdir(images))
    w, h = Image.open(images / names[0]).size
    mask = np.full((h // 2, w // 2), 255, np.uint8)
    mask[h // 4:, :] = 0  # the lower half
    Image.fromarray(mask).save(tmp_path / "bonnet.png")
    assert_ok(run_cli("extract", images, tmp_path / "out", "-q", "--masks", tmp_path / "bonnet.png"))
    with h5py.File(tmp_path / "out" / "features-sift.h5", "r") as h5:
        assert all(h5[n]["keypoints"][()][:, 1].max() < h // 2 - 0.5 for n in names)
    info = json.loads((tmp_path / "out" / ".sara" / "extract.json").read_text())["info"]["masked_keypoints"]
    assert info["num_images"] == len(names) and info["num_images_without_mask"] == 0


def test_masks_given_by_a_relative_path_are_recorded_whole(synthetic_scene, tmp_path, run_cli, monkeypatch):
    """`--masks masks` from the images' parent: run.json records the whole path, so that an export
    made from another folder still finds them."""
    images, _ = synthetic_scene
    names = sorted(os.listdir(images))
    _write_masks(images, tmp_path / "masks", names)
    monkeypatch.chdir(tmp_path)
    assert_ok(run_cli("run", images, tmp_path / "out", "-q", "--masks", "masks"))
    recorded = json.loads((tmp_path / "out" / "run.json").read_text())["config"]["extract"]["mask_path"]
    assert recorded == str(tmp_path / "masks")
    monkeypatch.chdir(images)
    assert_ok(run_cli("export", tmp_path / "out", tmp_path / "ns", "--format", "nerfstudio", "-q"))
    assert all("mask_path" in f for f in json.loads((tmp_path / "ns" / "transforms.json").read_text())["frames"])
