"""Bad input and faults, by class (issue 11): nothing lost, nothing silently wrong.

Every case runs a `sara` command (in this process through `sara.cli.main`, or as a subprocess
where a signal or a native crash is involved) on a copy of one finished run, then checks the exit
code, that stderr holds exactly one `sara: error:` line (naming the problem and the fix) and no
traceback or native stack dump, and that the previous outputs are byte-identical where they should
be. Classes: 1 resume trusts state, 2 a failed run destroys a good one, 3 names, 4 decoders,
5 the file system, 6 signals, 7 options and commands. Slow cases are in test_faults_slow.py.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from sara import config as sara_config
from sara.cli import main

# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------


def sara(capfd, *args) -> tuple[int, str]:
    """Run `sara ARGS` in this process; returns (exit code, stderr)."""
    rc, _, err = sara_output(capfd, *args)
    return rc, err


def sara_output(capfd, *args) -> tuple[int, str, str]:
    """Run `sara ARGS` in this process; returns (exit code, stdout, stderr)."""
    try:
        rc = main([str(a) for a in args])
    except SystemExit as exc:  # argparse
        rc = exc.code if isinstance(exc.code, int) else 1
    captured = capfd.readouterr()
    return rc, captured.out, captured.err


def sara_process(*args, env=None, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sara", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=env)


NATIVE_NOISE = ("Traceback", "*** Aborted", "stack trace", "SIGSEGV", "SIGABRT", "terminate called")


def assert_error(rc: int, err: str, code: int, *fragments: str) -> str:
    """Exit code `code`, exactly one `sara: error:` line holding every fragment, no traceback."""
    assert rc == code, f"exit {rc}, expected {code}:\n{err}"
    for noise in NATIVE_NOISE:
        assert noise not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("sara: error:")]
    assert len(lines) == 1, err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


def assert_ok(rc: int, err: str) -> None:
    assert rc == 0, err
    assert "sara: error:" not in err and "Traceback" not in err, err


def snapshot(out: Path) -> dict[str, str]:
    """sha256 of every file of an output folder (COLMAP's logs and the lock file aside).

    For an SQLite database, its file change counter (header bytes 24-27 and 92-95) is left out:
    pycolmap bumps it whenever it opens the file, even only to read; every other byte counts.
    """
    out = Path(out)
    digests = {}
    for path in sorted(out.rglob("*")):
        rel = path.relative_to(out).as_posix()
        if path.is_file() and not rel.startswith("logs/") and rel != ".sara.lock":
            data = bytearray(path.read_bytes())
            if data.startswith(b"SQLite format 3\x00") and len(data) >= 100:
                data[24:28] = data[92:96] = b"\0\0\0\0"
            digests[rel] = hashlib.sha256(data).hexdigest()
    return digests


def assert_kept(before: dict[str, str], out: Path, names: tuple[str, ...] | None = None) -> None:
    """The files of `before` (or those among `names`, and everything under them) are unchanged."""
    now = snapshot(out)
    if names is None:
        assert now == before
        return
    keep = {k: v for k, v in before.items() if any(k == n or k.startswith(n + "/") for n in names)}
    assert keep, names
    assert {k: now.get(k) for k in keep} == keep


#: what a run that produced nothing must leave as it was
PREVIOUS_OUTPUTS = ("database.db", "sparse", "run.json", "report.md", "metrics.json")


def registered(out: Path) -> list[str]:
    from sara.colmap import registered_images

    return sorted(registered_images(Path(out) / "sparse" / "0"))


def write_record(out: Path, stage: str, **changes) -> None:
    path = Path(out) / ".sara" / f"{stage}.json"
    record = json.loads(path.read_text())
    record.update(changes)
    path.write_text(json.dumps(record))


# ---------------------------------------------------------------------------------------------
# One finished run, copied for every case
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def finished(tmp_path_factory, synthetic_scene) -> Path:
    """A finished `sara run` (with evaluation) of the synthetic scene; never modified."""
    images, gt = synthetic_scene
    out = tmp_path_factory.mktemp("finished") / "out"
    assert main(["run", str(images), str(out), "-q", "--gt", str(gt)]) == 0
    return out


@pytest.fixture
def out(finished, tmp_path) -> Path:
    """A copy of the finished run."""
    return Path(shutil.copytree(finished, tmp_path / "out", symlinks=True))


@pytest.fixture
def images(synthetic_scene) -> Path:
    return synthetic_scene[0]


# ---------------------------------------------------------------------------------------------
# Class 1: resume trusts state it should not
# ---------------------------------------------------------------------------------------------


def _truncate(path: Path, keep: float) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def _drop_one_geometry(out: Path) -> None:
    con = sqlite3.connect(out / "database.db")
    con.execute("DELETE FROM two_view_geometries WHERE pair_id = (SELECT MIN(pair_id) FROM two_view_geometries)")
    con.commit()
    con.close()


DAMAGE = {
    "killed match, then map": (lambda o: write_record(o, "match", done=False), ["map"], 3, "match stage", "did not finish"),
    "match never ran, then map": (lambda o: (o / ".sara" / "match.json").unlink(), ["map"], 3, "never ran"),
    "matches changed, then map": (_drop_one_geometry, ["map"], 3, "no longer holds the matches", "sara match"),
    "pairs.txt shortened": (lambda o: _truncate(o / "pairs.txt", 0.5), ["run"], 3, "pairs.txt was changed", "delete it"),
    "pairs.txt emptied": (lambda o: (o / "pairs.txt").write_text(""), ["run"], 3, "pairs.txt was changed"),
    "pairs.txt line added": (lambda o: (o / "pairs.txt").open("a").write("x.png y.png\n"), ["run"], 3, "was changed"),
    "pairs.txt edited, then match": (lambda o: _truncate(o / "pairs.txt", 0.3), ["match"], 3, "pairs.txt was changed"),
    "database truncated": (lambda o: _truncate(o / "database.db", 0.4), ["run"], 3, "database.db is damaged",
                           "--overwrite"),
    "database emptied": (lambda o: (o / "database.db").write_bytes(b""), ["run"], 3, "database.db is damaged"),
    "database overwritten": (lambda o: (o / "database.db").write_bytes(b"not a database" * 100), ["run"], 3,
                             "database.db is damaged"),
    "database truncated, then map": (lambda o: _truncate(o / "database.db", 0.6), ["map"], 3, "is damaged"),
    "database truncated, then match": (lambda o: _truncate(o / "database.db", 0.6), ["match"], 3, "is damaged"),
    "model file truncated": (lambda o: _truncate(o / "sparse" / "0" / "images.bin", 0.5), ["run"], 3,
                             "sparse was changed", "move it away"),
    "model file deleted": (lambda o: (o / "sparse" / "0" / "points3D.bin").unlink(), ["run"], 3, "sparse was changed"),
    "killed extraction, then match": (lambda o: write_record(o, "extract", done=False), ["match"], 3,
                                      "extract stage", "did not finish"),
}


@pytest.mark.parametrize("case", list(DAMAGE))
def test_damaged_state_is_refused(case, out, images, capfd):
    """A record is never taken as proof: damaged or unfinished state stops with one line (exit 3)
    and nothing is written."""
    damage, command, code, *fragments = DAMAGE[case]
    damage(out)
    before = snapshot(out)
    args = {"run": ["run", images, out], "map": ["map", out], "match": ["match", out]}[command[0]]
    rc, err = sara(capfd, *args, "-q")
    assert_error(rc, err, code, *fragments)
    assert_kept(before, out)


def test_other_extraction_settings_refused(out, images, capfd):
    before = snapshot(out)
    rc, err = sara(capfd, "run", images, out, "-q", "-s", "extract.max_num_features=1000")
    assert_error(rc, err, 3, "other images or other extraction settings", "--overwrite")
    assert_kept(before, out)


def test_other_image_folder_refused(out, images, tmp_path, capfd):
    other = tmp_path / "more_images"
    shutil.copytree(images, other)
    shutil.copyfile(other / sorted(os.listdir(other))[0], other / "extra.png")
    before = snapshot(out)
    rc, err = sara(capfd, "run", other, out, "-q")
    assert_error(rc, err, 3, "other images")
    assert_kept(before, out)


@pytest.mark.parametrize("damage", ["truncated", "overwritten"])
def test_damaged_features_are_made_again(damage, out, images, finished, capfd):
    """The features file is derived from the database: a damaged one is written again, the same."""
    from sara.io.h5 import features_digest

    h5 = out / "features-sift.h5"
    if damage == "truncated":
        _truncate(h5, 0.3)
    else:
        h5.write_bytes(b"\0" * 4096)
    before = snapshot(out)
    rc, err = sara(capfd, "run", images, out, "-q")
    assert_ok(rc, err)
    assert "extracting the features again" in err
    assert features_digest(h5) == features_digest(finished / "features-sift.h5")
    assert_kept(before, out, ("pairs.txt", "scores.csv", "sparse"))


def test_damaged_scores_are_made_again(out, images, finished, capfd):
    _truncate(out / "scores.csv", 0.5)
    rc, err = sara(capfd, "run", images, out, "-q")
    assert_ok(rc, err)
    assert "scores.csv differs from what the pairs stage wrote" in err
    assert (out / "scores.csv").read_bytes() == (finished / "scores.csv").read_bytes()
    assert registered(out) == registered(finished)


@pytest.mark.parametrize("loss", ["sparse deleted", "map record cut short"])
def test_lost_model_is_mapped_again(loss, out, images, finished, capfd):
    if loss == "sparse deleted":
        shutil.rmtree(out / "sparse")
    else:
        _truncate(out / ".sara" / "map.json", 0.5)
    before = snapshot(out)
    rc, err = sara(capfd, "run", images, out, "-q")
    assert_ok(rc, err)
    assert registered(out) == registered(finished)
    assert_kept(before, out, ("pairs.txt", "scores.csv", "features-sift.h5"))


# ---------------------------------------------------------------------------------------------
# Class 2: a failed or degenerate run never destroys a good one
# ---------------------------------------------------------------------------------------------


def _pairs_file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "my_pairs.txt"
    path.write_text(text)
    return path


NO_RESULT = {
    "empty pairs file": (lambda t, n: ["--pairs", _pairs_file(t, "")], "lists no pairs"),
    "pairs file of comments": (lambda t, n: ["--pairs", _pairs_file(t, "# nothing\n\n#  a b\n")], "lists no pairs"),
    "scores reject every pair": (lambda t, n: ["-s", "score.min_overlap=1"], "selected no pairs",
                                 "relax the score.* thresholds"),
    "verification rejects every pair": (lambda t, n: ["-s", "match.min_num_inliers=100000"], "none of the",
                                        "match.min_num_inliers"),
    "only two close views matched": (lambda t, n: ["--pairs", _pairs_file(t, f"{n[0]} {n[1]}\n")],
                                     "no model could be built", "degrees of triangulation angle"),
}


@pytest.mark.parametrize("case", list(NO_RESULT))
def test_run_without_result_keeps_previous_outputs(case, out, images, tmp_path, capfd):
    """Exit 5, one line saying why, and the previous matches, model, run.json and report.md kept."""
    make_args, *fragments = NO_RESULT[case]
    names = sorted(os.listdir(images))
    before = snapshot(out)
    rc, err = sara(capfd, "run", images, out, "-q", *make_args(tmp_path, names))
    assert_error(rc, err, 5, *fragments)
    assert_kept(before, out, PREVIOUS_OUTPUTS)
    assert not (out / ".sara" / "database.next.db").exists() and not (out / ".sara" / "pairs.next").exists()


@pytest.mark.parametrize("case", ["empty pairs file", "no verified pair"])
def test_match_without_result_keeps_previous_matches(case, out, tmp_path, capfd):
    args = ["--pairs", _pairs_file(tmp_path, "")] if case == "empty pairs file" else \
        ["-s", "match.min_num_inliers=100000"]
    before = snapshot(out)
    rc, err = sara(capfd, "match", out, "-q", *args)
    assert_error(rc, err, 5)
    assert_kept(before, out)


BAD_OPTIONS_OF_A_RUN = {
    "seed": (["--seed", "-1"], "--seed", "seed must be an integer from 0 to"),
    "extract backend": (["-s", "extract.backend=nope"], "extract.backend must be one of"),
    "matcher": (["-s", "match.backend=nope"], "match.backend must be auto or one of"),
    "descriptor": (["-s", "retrieval.descriptor=nope"], "retrieval.descriptor must be one of"),
    "pair source": (["--pairs", "nope"], "not a pair source"),
    "unknown option": (["-s", "retrieval.k=3"], "unknown option 'retrieval.k'"),
}


@pytest.mark.parametrize("case", list(BAD_OPTIONS_OF_A_RUN))
def test_bad_option_leaves_run_json(case, out, images, capfd):
    """A run stopped by a bad option writes nothing: run.json still describes sparse/0 and report.md."""
    args, *fragments = BAD_OPTIONS_OF_A_RUN[case]
    before = snapshot(out)
    rc, err = sara(capfd, "run", images, out, "-q", *args)
    assert_error(rc, err, 2, *fragments)
    assert_kept(before, out)


# ---------------------------------------------------------------------------------------------
# Class 3: names
# ---------------------------------------------------------------------------------------------

#: name -> works end to end (True) or is skipped with a warning naming it (False)
NAMES = {
    "#hash.png": True,
    "# hash space.png": True,
    " leading.png": True,
    "trailing .png": True,
    "two  spaces.png": True,
    "ü ñ é.png": True,
    "\u3000ideographic space.png": True,
    "quote'\"q.png": True,
    "comma,semi;.png": True,
    "-dash.png": True,
    "new\nline.png": False,
    "tab\t.png": False,
    "carriage\r.png": False,
    "line\u2028separator.png": False,
    os.fsdecode(b"latin1-\xe9.png"): False,
    ".hidden.png": False,
}


@pytest.fixture(scope="module")
def small_png(tmp_path_factory, synthetic_scene) -> bytes:
    first = sorted(synthetic_scene[0].iterdir())[0]
    path = tmp_path_factory.mktemp("png") / "small.png"
    Image.open(first).convert("L").resize((96, 72)).save(path)
    return path.read_bytes()


@pytest.mark.parametrize("name", list(NAMES), ids=lambda n: ascii(n))
def test_each_name_is_decided_once_at_scan(name, small_png, tmp_path, caplog, monkeypatch):
    import logging

    from sara.io.images import display_name, scan_images

    monkeypatch.setattr(logging.getLogger("sara"), "propagate", True)  # the CLI's own tests turn it off

    folder = tmp_path / "imgs"
    folder.mkdir()
    (folder / "plain.png").write_bytes(small_png)
    with open(os.fsencode(folder) + b"/" + os.fsencode(name), "wb") as f:
        f.write(small_png)
    images = scan_images(folder, progress=False)
    if NAMES[name]:
        assert name in images.names and not images.skipped
    else:
        assert name not in images.names and list(images.skipped) == [display_name(name)]
        assert any(display_name(name) in r.getMessage() for r in caplog.records)
        json.dumps(images.skipped, ensure_ascii=False).encode("utf-8")  # run.json can hold it


PAIR_FILES = {
    "hash names are pairs, not comments": (["#a.png", "b.png"], "#a.png b.png\n", [("#a.png", "b.png")]),
    "a comment stays a comment": (["a.png", "b.png"], "# a.png b.png\na.png b.png\n", [("a.png", "b.png")]),
    "leading space": ([" a.png", "a.png", "b.png"], " a.png b.png\n", [(" a.png", "b.png")]),
    "trailing space": (["a .png", "b.png"], "a .png b.png\n", [("a .png", "b.png")]),
    "inner spaces": (["x y.png", "z.png"], "x y.png z.png\n", [("x y.png", "z.png")]),
    "score column": (["x y.png", "z.png"], "x y.png z.png 0.5\n", [("x y.png", "z.png")]),
    "windows line ends": (["a.png", "b.png"], "a.png b.png\r\n", [("a.png", "b.png")]),
}


@pytest.mark.parametrize("case", list(PAIR_FILES))
def test_pairs_file_never_misreads_a_name(case, tmp_path):
    from sara.io.pairs import read_pairs, write_pairs

    names, text, expected = PAIR_FILES[case]
    path = tmp_path / "pairs.txt"
    path.write_text(text, newline="")
    assert read_pairs(path, known_names=names) == expected
    write_pairs(path, expected)  # and what sara writes reads back the same
    assert read_pairs(path, known_names=names) == expected


def test_ambiguous_pair_line_is_an_error(tmp_path):
    from sara.io.pairs import read_pairs

    path = tmp_path / "pairs.txt"
    path.write_text("a b c\n")
    with pytest.raises(ValueError, match="more than one pair"):
        read_pairs(path, known_names=["a", "b c", "a b", "c"])


def test_names_sara_cannot_carry_are_refused_by_the_writer(tmp_path):
    from sara.io.pairs import write_pairs

    with pytest.raises(ValueError, match="control character"):
        write_pairs(tmp_path / "p.txt", [("a\nb.png", "c.png")])


# An end-to-end run on odd names, a file COLMAP cannot read and an image that COLMAP's extraction
# skips (as when it vanishes or changes during extraction): one run, checked per name.

ODD_NAMES = ["#hash.png", " leading.png", "trailing .png", "two  spaces.png", "ü ñ.png"]
ODD_SKIPPED = {"new\nline.png": "control character", os.fsdecode(b"bad-\xff.png"): "not valid UTF-8",
               ".hidden.png": "hidden file", "webp-inside.png": "COLMAP's image reader cannot decode it",
               "vanishes.png": "COLMAP's extraction skipped it"}


@pytest.fixture(scope="module")
def odd_run(tmp_path_factory, synthetic_scene):
    """(output folder, stderr of the run, stderr of a second run) on 5 views with odd names."""
    from sara import colmap

    src = sorted(synthetic_scene[0].iterdir())
    folder = tmp_path_factory.mktemp("odd") / "images"
    folder.mkdir()
    for path, name in zip(src[:5], ODD_NAMES):
        shutil.copyfile(path, folder / name)
    for path, name in zip(src[5:], [n for n in ODD_SKIPPED if n not in ("webp-inside.png",)]):
        with open(os.fsencode(folder) + b"/" + os.fsencode(name), "wb") as f:
            f.write(path.read_bytes())
    Image.open(src[0]).save(folder / "webp-inside.png", format="WEBP")
    out = folder.parent / "out"
    original = colmap.extract_sift

    def extract_but_one(db_path, image_dir, names, **kwargs):  # as if the file changed under COLMAP
        return original(db_path, image_dir, [n for n in names if n != "vanishes.png"], **kwargs)

    mp = pytest.MonkeyPatch()
    mp.setattr(colmap, "extract_sift", extract_but_one)
    try:
        first = subprocess_free_run(["run", folder, out, "-q"])
    finally:
        mp.undo()
    second = subprocess_free_run(["run", folder, out, "-q"])
    return out, first, second


def subprocess_free_run(args) -> tuple[int, str]:
    """`sara ARGS` in this process with stderr captured (for module fixtures, where capfd is not)."""
    import contextlib
    import io

    buffer = io.StringIO()
    with contextlib.redirect_stderr(buffer), contextlib.redirect_stdout(io.StringIO()):
        rc = main([str(a) for a in args])
    return rc, buffer.getvalue()


@pytest.mark.parametrize("name", ODD_NAMES, ids=ascii)
def test_odd_name_works_end_to_end(name, odd_run):
    out, (rc, err), (rc2, err2) = odd_run
    assert_ok(rc, err)
    assert_ok(rc2, err2)
    assert name in registered(out)
    from sara.io.pairs import read_pairs

    names = [n for n in ODD_NAMES]
    assert any(name in pair for pair in read_pairs(out / "pairs.txt", known_names=names))


@pytest.mark.parametrize("name", list(ODD_SKIPPED), ids=ascii)
def test_odd_file_is_skipped_with_a_warning(name, odd_run):
    """Skipped once, before extraction (or when COLMAP skips it), named in a warning and in run.json;
    the next run (all stages done) neither fails nor forgets it."""
    from sara.io.images import display_name

    out, (rc, err), (rc2, err2) = odd_run
    assert_ok(rc, err)
    assert_ok(rc2, err2)
    shown = display_name(name)
    skipped = json.loads((out / "run.json").read_text())["skipped_images"]
    assert ODD_SKIPPED[name] in skipped[shown]
    assert f"skipping {shown}:" in err and f"skipping {shown}:" in err2
    assert err.count(f"skipping {shown}:") == 1


# ---------------------------------------------------------------------------------------------
# Class 4: files that one decoder reads and another does not
# ---------------------------------------------------------------------------------------------

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
        found = extract._extract_images(extract._ExtractJob(conf, str(tmp_path), ["here.png", "gone.png", "broken.png"]))
    finally:
        extract._BACKENDS.clear()
    assert isinstance(found[0], Keypoints)
    assert found[1] == "the file disappeared during extraction"
    assert "could not be decoded" in found[2]


# ---------------------------------------------------------------------------------------------
# Class 5: the file system
# ---------------------------------------------------------------------------------------------


def test_output_path_is_a_file(images, tmp_path, capfd):
    target = tmp_path / "out.txt"
    target.write_text("keep me")
    rc, err = sara(capfd, "run", images, target, "-q")
    assert_error(rc, err, 2, "is a file")
    assert target.read_text() == "keep me"


def test_output_parent_is_a_file(images, tmp_path, capfd):
    (tmp_path / "file").write_text("keep me")
    rc, err = sara(capfd, "run", images, tmp_path / "file" / "out", "-q")
    assert_error(rc, err, 2, "is a file")


@pytest.mark.parametrize("command", ["run", "match"])
def test_pairs_option_names_a_folder(command, out, images, tmp_path, capfd):
    before = snapshot(out)
    args = ["run", images, out] if command == "run" else ["match", out]
    rc, err = sara(capfd, *args, "--pairs", tmp_path, "-q")
    assert_error(rc, err, 2, "a folder, not a pairs file")
    assert_kept(before, out)


@pytest.mark.parametrize("what", ["image folder is a file", "image folder missing"])
def test_bad_image_folder(what, tmp_path, capfd):
    path = tmp_path / "imgs"
    if what == "image folder is a file":
        path.write_text("x")
    rc, err = sara(capfd, "run", path, tmp_path / "out", "-q")
    assert_error(rc, err, 2, str(path))
    assert not (tmp_path / "out").exists()


FS_ERRORS = {
    "disk full": (errno.ENOSPC, "No space left on device", "free some space"),
    "read-only": (errno.EROFS, "Read-only file system", "choose an output folder you can write to"),
    "permission denied": (errno.EACCES, "Permission denied", "choose an output folder you can write to"),
    "input/output error": (errno.EIO, "Input/output error"),
    "quota": (errno.EDQUOT, "Disk quota exceeded", "free some space"),
}


@pytest.mark.parametrize("case", list(FS_ERRORS))
def test_file_system_errors_while_writing_run_json(case, out, images, monkeypatch, capfd):
    """Any OSError family at the very end (run.json) is one line, exit 4, and run.json is intact."""
    from sara import pipeline

    code, text, *fragments = FS_ERRORS[case]

    def fail(path, data):
        raise OSError(code, os.strerror(code), str(path))

    monkeypatch.setattr(pipeline, "write_json_atomic", fail)
    before = snapshot(out)
    rc, err = sara(capfd, "run", images, out, "-q")
    assert_error(rc, err, 4, text, *fragments)
    assert_kept(before, out, ("run.json", "report.md", "sparse", "database.db"))


def test_disk_nearly_full_before_writing(out, images, monkeypatch, capfd):
    """Native writers (HDF5, SQLite in COLMAP) crash on a full disk: sara checks first."""
    from sara import io as sara_io

    monkeypatch.setattr(sara_io, "free_bytes", lambda path: 1000)
    before = snapshot(out)
    rc, err = sara(capfd, "run", images, out, "-q", "--pairs", "exhaustive")  # new pairs: matching must write
    assert_error(rc, err, 4, "no space left", "MB free", "run the same command again")
    assert_kept(before, out, PREVIOUS_OUTPUTS)
    assert not (out / ".sara" / "pairs.next").exists() and not (out / ".sara" / "database.next.db").exists()


@pytest.fixture
def small_disk(tmp_path):
    """A 64 MB tmpfs (skipped where mounting is not permitted); unmounted afterwards."""
    mount = tmp_path / "disk"
    mount.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64m", "tmpfs", str(mount)], capture_output=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.decode().strip()}")
    yield mount
    subprocess.run(["umount", "-l", str(mount)], check=False)


def _fill(disk: Path, leave_bytes: int) -> Path:
    filler = disk / "filler"
    free = shutil.disk_usage(disk).free
    with open(filler, "wb") as f:
        f.truncate(0)
        remaining = max(0, free - leave_bytes)
        block = b"\0" * 2**20
        while remaining > 0:
            n = min(remaining, len(block))
            f.write(block[:n])
            remaining -= n
    return filler


def test_real_full_disk_during_extraction(small_disk, images):
    _fill(small_disk, 4 * 2**20)
    proc = sara_process("run", images, small_disk / "out", "-q")
    assert_error(proc.returncode, proc.stderr, 4, "no space left", "free some space")


@pytest.mark.slow  # depends on free-space margins of a real tmpfs; failed once after the issue 13 defaults changed
def test_real_full_disk_during_matching_then_resume(small_disk, finished, images):
    """Exhaustive pairs on a disk with 10 MB free: matching stops before COLMAP writes (exit 4);
    with space again the same command finishes."""
    out = small_disk / "out"
    shutil.copytree(finished, out)
    filler = _fill(small_disk, 10 * 2**20)
    before = snapshot(out)
    proc = sara_process("run", images, out, "-q", "--pairs", "exhaustive")
    assert_error(proc.returncode, proc.stderr, 4, "no space left", "run the same command again")
    assert_kept(before, out, ("sparse", "run.json", "report.md", "features-sift.h5"))
    filler.unlink()
    proc = sara_process("run", images, out, "-q", "--pairs", "exhaustive")
    assert_ok(proc.returncode, proc.stderr)
    assert len(registered(out)) == len(registered(finished))


@pytest.fixture
def read_only(finished, tmp_path):
    """A copy of the finished run seen through a read-only bind mount."""
    src, view = tmp_path / "src", tmp_path / "ro"
    shutil.copytree(finished, src)
    view.mkdir()
    steps = [["mount", "--bind", str(src), str(view)], ["mount", "-o", "remount,ro,bind", str(view)]]
    for step in steps:
        proc = subprocess.run(step, capture_output=True)
        if proc.returncode != 0:
            subprocess.run(["umount", "-l", str(view)], check=False, capture_output=True)
            pytest.skip(f"cannot make a read-only mount here: {proc.stderr.decode().strip()}")
    yield view
    subprocess.run(["umount", "-l", str(view)], check=False)


@pytest.mark.parametrize("command", ["run", "map"])
def test_read_only_output_folder(command, read_only, images, capfd):
    before = snapshot(read_only)
    args = ["run", images, read_only] if command == "run" else ["map", read_only]
    rc, err = sara(capfd, *args, "-q")
    assert_error(rc, err, 4, "Read-only file system", "choose an output folder you can write to")
    assert_kept(before, read_only)


def test_temporaries_of_killed_runs_are_cleaned(out, images, finished, capfd):
    sara_dir = out / ".sara"
    left = [out / ".run.json.k3j2l1x0.tmp", out / ".pairs.txt.abcd1234.tmp", sara_dir / ".map.json.zz9y8x7w.tmp",
            sara_dir / "match_chunk.txt", out / "sparse" / "0" / ".images.bin.q1w2e3r4.tmp"]
    for path in left:
        path.write_text("left by a killed run")
    for folder in ("score-views-abc123", "sparse.partial/0", "pairs.next"):
        (sara_dir / folder).mkdir(parents=True)
        (sara_dir / folder / "x.bin").write_bytes(b"x")
    before = snapshot(finished)
    rc, err = sara(capfd, "run", images, out, "-q")
    assert_ok(rc, err)
    leftovers = [p for p in out.rglob("*") if ".tmp" in p.name or "partial" in p.name or "score-views" in p.name
                 or "chunk" in p.name or p.name == "pairs.next"]
    assert leftovers == []
    assert_kept(before, out, ("pairs.txt", "scores.csv", "database.db", "sparse"))


@pytest.mark.parametrize("umask,mode", [(0o022, 0o644), (0o027, 0o640), (0o002, 0o664)])
def test_outputs_follow_the_umask(umask, mode, tmp_path):
    from sara.io import write_json_atomic
    from sara.io.h5 import write_global

    old = os.umask(umask)
    try:
        write_json_atomic(tmp_path / "a.json", {"x": 1})
        write_global(tmp_path / "g.h5", ["a"], np.ones((1, 4)), {"k": "v"})
    finally:
        os.umask(old)
    for name in ("a.json", "g.h5"):
        assert (tmp_path / name).stat().st_mode & 0o777 == mode


def test_finished_run_files_follow_the_umask(finished):
    umask = os.umask(0o022)
    os.umask(umask)
    modes = {p.name: p.stat().st_mode & 0o777 for p in finished.iterdir() if p.is_file() and p.name != ".sara.lock"}
    assert modes and all(m == 0o666 & ~umask for m in modes.values()), modes  # not mkstemp's 0600


def test_atomic_write_leaves_nothing_when_it_fails(tmp_path):
    from sara.io import atomic_path

    with pytest.raises(OSError), atomic_path(tmp_path / "x.txt") as tmp:
        tmp.write_text("half")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------------------
# Class 6: signals (subprocesses; the slow ones, during extraction, are in test_faults_slow.py)
# ---------------------------------------------------------------------------------------------


def _default_sigint() -> None:
    """In the child: SIGINT as a foreground program gets it. A shell starts background jobs (e.g.
    `.ci/run &`) with SIGINT ignored, Python keeps that, and the run would never see the signal."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def interrupt_when(cmd: list, marker: Path, signum: int, *, times: int = 1, timeout: float = 240):
    """Start `sara CMD`, send `signum` once `marker` exists; returns the finished process."""
    proc = subprocess.Popen([sys.executable, "-m", "sara", *map(str, cmd)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint)
    deadline = time.monotonic() + timeout
    while not marker.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    for _ in range(times):
        if proc.poll() is None:
            proc.send_signal(signum)
            time.sleep(0.05)
    _, err = proc.communicate(timeout=timeout)
    return proc.returncode, err


SIGNALS = {
    "SIGTERM during pair selection": (signal.SIGTERM, 143, "pairs"),
    "SIGINT during pair selection": (signal.SIGINT, 130, "pairs"),
    "SIGTERM twice during pair selection": (signal.SIGTERM, 143, "pairs"),
    "SIGHUP during mapping": (signal.SIGHUP, 129, "map"),
    "SIGTERM during mapping": (signal.SIGTERM, 143, "map"),
}


@pytest.mark.parametrize("case", list(SIGNALS))
def test_signal_is_one_clean_line_and_resumes(case, out, images, finished):
    signum, code, stage = SIGNALS[case]
    if stage == "pairs":
        (out / "pairs.txt").unlink()
        marker = out / ".sara" / "pairs.next"
    else:
        shutil.rmtree(out / "sparse")
        marker = out / ".sara" / "sparse.partial"
    before = snapshot(out)
    rc, err = interrupt_when(["run", images, out, "-q"], marker, signum, times=2 if "twice" in case else 1)
    if rc == 0:
        pytest.skip("the run finished before the signal arrived (machine too fast for this case)")
    assert_error(rc, err, code, f"interrupted by {signal.Signals(signum).name}", "run the same command again")
    assert not marker.exists()  # its half-built output is removed
    assert_kept(before, out, ("database.db", "features-sift.h5", "run.json", "report.md"))
    proc = sara_process("run", images, out, "-q")
    assert_ok(proc.returncode, proc.stderr)
    assert registered(out) == registered(finished)


# ---------------------------------------------------------------------------------------------
# Class 7: options and commands
# ---------------------------------------------------------------------------------------------

BAD_VALUES = {
    "--seed -1": (["--seed", "-1"], "--seed", "from 0 to 2147483647"),
    "--seed 2**31": (["--seed", str(2**31)], "seed must be"),
    "--workers -1": (["--workers", "-1"], "--workers", "execute.workers must be an integer >= 0"),
    "zero features": (["-s", "extract.max_num_features=0"], "extract.max_num_features", ">= 1"),
    "negative image size": (["-s", "extract.max_image_size=-5"], "extract.max_image_size", ">= 32"),
    "NaN weight exponent": (["-s", "score.alpha=nan"], "score.alpha", "finite"),
    "infinite weight exponent": (["-s", "score.beta=inf"], "score.beta", "finite"),
    "zero chunk size": (["-s", "match.chunk_size=0"], "match.chunk_size", ">= 1"),
    "zero shard size": (["-s", "execute.shard_size=0"], "execute.shard_size", ">= 1"),
    "zero neighbours": (["-s", "retrieval.num_neighbors=0"], "retrieval.num_neighbors", ">= 1"),
    "ratio above 1": (["-s", "match.max_ratio=1.5"], "match.max_ratio", "(0, 1]"),
    "model of one image": (["-s", "map.min_model_size=1"], "map.min_model_size", ">= 2"),
    "inliers above matches": (["-s", "score.min_inliers=100"], "score.min_inliers", "score.num_matches"),
    "unknown camera model": (["-s", "extract.camera_model=FOO"], "extract.camera_model", "PINHOLE"),
    "camera params not numbers": (["-s", "extract.camera_params=a,b"], "extract.camera_params", "comma-separated"),
    "unknown orientation mode": (["-s", "images.exif_orientation=rotate"], "images.exif_orientation", "ignore, apply"),
    "NaN budget": (["-s", "graph.loop_budget_ratio=nan"], "graph.loop_budget_ratio", "finite"),
    "negative rounds": (["-s", "pairs.repair_rounds=-1"], "pairs.repair_rounds", ">= 0"),
    "unknown device": (["-s", "extract.device=gpu"], "extract.device", "cuda"),
    "zero focal factor": (["-s", "extract.default_focal_length_factor=0"], "default_focal_length_factor", "(0, 100]"),
    "zero inlier ratio": (["-s", "map.abs_pose_min_inlier_ratio=0"], "map.abs_pose_min_inlier_ratio", "(0, 1]"),
    "not a number": (["-s", "score.alpha=abc"], "score.alpha", "not a float"),
    "unknown mapper flag": (["--mapper", "foo"], "--mapper", "invalid choice"),
    "unknown camera mode flag": (["--camera-mode", "x"], "--camera-mode", "invalid choice"),
}


@pytest.mark.parametrize("case", list(BAD_VALUES))
def test_out_of_range_option_fails_at_parse_time(case, finished, images, capfd):
    """The message names the option and its valid range; nothing is read or written."""
    args, *fragments = BAD_VALUES[case]
    before = snapshot(finished)
    rc, err = sara(capfd, "run", images, finished, "-q", *args)
    assert_error(rc, err, 2, *fragments)
    assert_kept(before, finished)


def test_every_option_has_a_valid_range():
    from sara.config import RULES, PipelineConfig

    def options(conf, prefix=""):
        for f in dataclasses.fields(conf):
            value = getattr(conf, f.name)
            if dataclasses.is_dataclass(value):
                yield from options(value, f"{prefix}{f.name}.")
            else:
                yield prefix + f.name

    missing = [o for o in options(PipelineConfig()) if o not in sara_config.RULES and o != "graph.loop_scale_fractions"]
    assert missing == [], f"options without a valid range in sara.config.RULES: {missing}"
    assert RULES


@pytest.mark.parametrize("argv,fragment", [
    (["demo", "--num-images", "1"], "--num-images"),
    (["nope"], "invalid choice"),
    (["run"], "required"),
], ids=["demo of one image", "unknown command", "missing arguments"])
def test_usage_errors_are_one_line(argv, fragment, capfd):
    rc, err = sara(capfd, *argv)
    assert_error(rc, err, 2, fragment)


@pytest.fixture
def other_scene_gt(synthetic_scene, tmp_path) -> Path:
    """The ground truth with every image renamed: the truth of another scene."""
    gt = Path(shutil.copytree(synthetic_scene[1], tmp_path / "other_gt"))
    text = (gt / "images.txt").read_text()
    for name in sorted(os.listdir(synthetic_scene[0])):
        text = text.replace(name, "other_" + name)
    (gt / "images.txt").write_text(text)
    return gt


EVALUATE = {
    "folder without a model": (lambda t, o, g: (t, g), 2, "holds no COLMAP model"),
    "missing model folder": (lambda t, o, g: (t / "nope", g), 2, "does not exist"),
    "ground truth of another scene": (lambda t, o, g: (o, "OTHER"), 2, "share no image name", "another scene"),
    "missing ground truth": (lambda t, o, g: (o, t / "nope"), 2, "ground-truth model folder not found"),
    "damaged model": (lambda t, o, g: (_damaged_model(o), g), 2, "no readable COLMAP model"),
}


def _damaged_model(out: Path) -> Path:
    _truncate(out / "sparse" / "0" / "images.bin", 0.5)
    return out


@pytest.mark.parametrize("case", list(EVALUATE))
def test_evaluate_refuses_what_it_cannot_score(case, out, synthetic_scene, other_scene_gt, tmp_path, capfd):
    make, code, *fragments = EVALUATE[case]
    model, gt = make(tmp_path / "empty", out, synthetic_scene[1])
    (tmp_path / "empty").mkdir()
    gt = other_scene_gt if gt == "OTHER" else gt
    rc, err = sara(capfd, "evaluate", model, gt)
    assert_error(rc, err, code, *fragments)


def test_evaluate_scores_a_model(out, synthetic_scene, capfd):
    rc, stdout, err = sara_output(capfd, "evaluate", out, synthetic_scene[1])
    assert_ok(rc, err)
    assert "num_registered" in stdout


def test_run_against_another_scenes_truth_fails_before_any_work(out, images, other_scene_gt, capfd):
    before = snapshot(out)
    rc, err = sara(capfd, "run", images, out, "-q", "--gt", other_scene_gt)
    assert_error(rc, err, 2, "shares no image name", "another scene")
    assert_kept(before, out)


def test_one_image_is_refused(images, tmp_path, capfd):
    folder = tmp_path / "one"
    folder.mkdir()
    shutil.copyfile(sorted(images.iterdir())[0], folder / "only.png")
    rc, err = sara(capfd, "run", folder, tmp_path / "out", "-q")
    assert_error(rc, err, 2, "only one usable image", "at least 2")
    assert not (tmp_path / "out").exists()


def test_two_close_views_say_why_no_model(images, tmp_path, capfd):
    """Two views with well over 100 inlier matches: the message says what COLMAP's mapper lacks
    (triangulation angle), not "too few verified matches"."""
    folder = tmp_path / "two"
    folder.mkdir()
    for path in sorted(images.iterdir())[:2]:
        shutil.copyfile(path, folder / path.name)
    rc, err = sara(capfd, "run", folder, tmp_path / "out", "-q")
    line = assert_error(rc, err, 5, "no model could be built", "inlier matches", "16 degrees")
    assert "too few verified matches" not in line
    assert not (tmp_path / "out" / "sparse").exists() and not (tmp_path / "out" / "report.md").exists()


def test_map_with_a_missing_image_folder(out, tmp_path, capfd):
    before = snapshot(out)
    rc, err = sara(capfd, "map", out, "--images", tmp_path / "gone", "-q")
    assert_error(rc, err, 2, "not found", "--images")
    assert_kept(before, out)


def test_match_on_a_folder_that_is_not_a_run(tmp_path, capfd):
    rc, err = sara(capfd, "match", tmp_path, "-q")
    assert_error(rc, err, 2, "run `sara extract")
