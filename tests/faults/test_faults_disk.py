"""Class 5 of the fault suite: the file system. Output paths that are files, write errors of every
OSError family (exit 4, nothing lost), a disk nearly full (checked before native writers crash), a
real full tmpfs, a read-only mount, temporaries of killed runs cleaned, and the umask followed."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from harness import PREVIOUS_OUTPUTS, assert_error, assert_kept, assert_ok, registered, sara_process, snapshot


def test_output_path_is_a_file(images, tmp_path, run_cli):
    target = tmp_path / "out.txt"
    target.write_text("keep me")
    result = run_cli("run", images, target, "-q")
    assert_error(result, 2, "is a file")
    assert target.read_text() == "keep me"


def test_output_parent_is_a_file(images, tmp_path, run_cli):
    (tmp_path / "file").write_text("keep me")
    result = run_cli("run", images, tmp_path / "file" / "out", "-q")
    assert_error(result, 2, "is a file")


@pytest.mark.parametrize("command", ["run", "match"])
def test_pairs_option_names_a_folder(command, finished_run, images, tmp_path, run_cli):
    before = snapshot(finished_run)
    args = ["run", images, finished_run] if command == "run" else ["match", finished_run]
    result = run_cli(*args, "--pairs", tmp_path, "-q")
    assert_error(result, 2, "a folder, not a pairs file")
    assert_kept(before, finished_run)


@pytest.mark.parametrize("what", ["image folder is a file", "image folder missing"])
def test_bad_image_folder(what, tmp_path, run_cli):
    path = tmp_path / "imgs"
    if what == "image folder is a file":
        path.write_text("x")
    result = run_cli("run", path, tmp_path / "out", "-q")
    assert_error(result, 2, str(path))
    assert not (tmp_path / "out").exists()


FS_ERRORS = {
    "disk full": (errno.ENOSPC, "No space left on device", "free some space"),
    "read-only": (errno.EROFS, "Read-only file system", "choose an output folder you can write to"),
    "permission denied": (errno.EACCES, "Permission denied", "choose an output folder you can write to"),
    "input/output error": (errno.EIO, "Input/output error"),
    "quota": (errno.EDQUOT, "Disk quota exceeded", "free some space"),
}


@pytest.mark.parametrize("case", list(FS_ERRORS))
def test_file_system_errors_while_writing_run_json(case, finished_run, images, monkeypatch, run_cli):
    """Any OSError family at the very end (run.json) is one line, exit 4, and run.json is intact."""
    from sara.pipeline import record  # where run.json is written

    code, text, *fragments = FS_ERRORS[case]

    def fail(path, data):
        raise OSError(code, os.strerror(code), str(path))

    monkeypatch.setattr(record, "write_json_atomic", fail)
    before = snapshot(finished_run)
    result = run_cli("run", images, finished_run, "-q")
    assert_error(result, 4, text, *fragments)
    assert_kept(before, finished_run, ("run.json", "report.md", "sparse", "database.db"))


def test_disk_nearly_full_before_writing(finished_run, images, monkeypatch, run_cli):
    """Native writers (HDF5, SQLite in COLMAP) crash on a full disk: sara checks first."""
    from sara import io as sara_io

    monkeypatch.setattr(sara_io, "free_bytes", lambda path: 1000)
    before = snapshot(finished_run)
    result = run_cli("run", images, finished_run, "-q", "--pairs", "exhaustive")  # new pairs: matching writes
    assert_error(result, 4, "no space left", "MB free", "run the same command again")
    assert_kept(before, finished_run, PREVIOUS_OUTPUTS)
    assert not (finished_run / ".sara" / "pairs.next").exists()
    assert not (finished_run / ".sara" / "database.next.db").exists()


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
    result = sara_process("run", images, small_disk / "out", "-q")
    assert_error(result, 4, "no space left", "free some space")


@pytest.mark.slow  # depends on free-space margins of a real tmpfs; failed once after the issue 13 defaults changed
def test_real_full_disk_during_matching_then_resume(small_disk, finished_run_template, images):
    """Exhaustive pairs on a disk with 10 MB free: matching stops before COLMAP writes (exit 4);
    with space again the same command finishes."""
    out = small_disk / "out"
    shutil.copytree(finished_run_template, out)
    filler = _fill(small_disk, 10 * 2**20)
    before = snapshot(out)
    result = sara_process("run", images, out, "-q", "--pairs", "exhaustive")
    assert_error(result, 4, "no space left", "run the same command again")
    assert_kept(before, out, ("sparse", "run.json", "report.md", "features-sift.h5"))
    filler.unlink()
    result = sara_process("run", images, out, "-q", "--pairs", "exhaustive")
    assert_ok(result)
    assert len(registered(out)) == len(registered(finished_run_template))


@pytest.fixture
def read_only(finished_run_template, tmp_path):
    """A copy of the finished run seen through a read-only bind mount."""
    src, view = tmp_path / "src", tmp_path / "ro"
    shutil.copytree(finished_run_template, src)
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
def test_read_only_output_folder(command, read_only, images, run_cli):
    before = snapshot(read_only)
    args = ["run", images, read_only] if command == "run" else ["map", read_only]
    result = run_cli(*args, "-q")
    assert_error(result, 4, "Read-only file system", "choose an output folder you can write to")
    assert_kept(before, read_only)


def test_temporaries_of_killed_runs_are_cleaned(finished_run, images, finished_run_template, run_cli):
    sara_dir = finished_run / ".sara"
    left = [finished_run / ".run.json.k3j2l1x0.tmp", finished_run / ".pairs.txt.abcd1234.tmp",
            sara_dir / ".map.json.zz9y8x7w.tmp", sara_dir / "match_chunk.txt",
            finished_run / "sparse" / "0" / ".images.bin.q1w2e3r4.tmp"]
    for path in left:
        path.write_text("left by a killed run")
    for folder in ("score-views-abc123", "sparse.partial/0", "pairs.next"):
        (sara_dir / folder).mkdir(parents=True)
        (sara_dir / folder / "x.bin").write_bytes(b"x")
    before = snapshot(finished_run_template)
    result = run_cli("run", images, finished_run, "-q")
    assert_ok(result)
    leftovers = [p for p in finished_run.rglob("*") if ".tmp" in p.name or "partial" in p.name
                 or "score-views" in p.name or "chunk" in p.name or p.name == "pairs.next"]
    assert leftovers == []
    assert_kept(before, finished_run, ("pairs.txt", "scores.csv", "database.db", "sparse"))


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


def test_finished_run_files_follow_the_umask(finished_run_template):
    umask = os.umask(0o022)
    os.umask(umask)
    modes = {p.name: p.stat().st_mode & 0o777 for p in finished_run_template.iterdir()
             if p.is_file() and p.name != ".sara.lock"}
    assert modes and all(m == 0o666 & ~umask for m in modes.values()), modes  # not mkstemp's 0600


def test_atomic_write_leaves_nothing_when_it_fails(tmp_path):
    from sara.io import atomic_path

    with pytest.raises(OSError), atomic_path(tmp_path / "x.txt") as tmp:
        tmp.write_text("half")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert list(tmp_path.iterdir()) == []




@pytest.mark.parametrize("command", ["match", "map", "run"])
def test_full_disk_is_not_taken_for_a_damaged_database(command, small_disk, finished_run_template, images):
    """No byte free: SQLite cannot open the database for writing ("disk I/O error"). Issue 30: that
    was exit 3, "database.db is damaged ... --overwrite" (advice that would throw the run away)."""
    out = small_disk / "out"
    shutil.copytree(finished_run_template, out)
    _fill(small_disk, 0)
    before = snapshot(out)
    args = {"match": ["match", out, "--pairs", out / "pairs.txt"], "map": ["map", out],
            "run": ["run", images, out, "--pairs", "exhaustive"]}[command]
    result = sara_process(*args, "-q")
    line = assert_error(result, 4, "no space left", "free some space")
    assert "damaged" not in line and "--overwrite" not in line
    assert_kept(before, out, ("database.db", "sparse", "run.json", "features-sift.h5"))


def test_matching_checks_room_for_every_pair_first(finished_run, images, monkeypatch, run_cli):
    """COLMAP aborts the process when the database cannot grow: the check before matching counts
    every pair of the stage (and the copy of the database), not only the first chunk's. Issue 30:
    a disk with room for one chunk let the stage start."""
    from sara import colmap
    from sara import io as sara_io
    from sara.match import BYTES_PER_PAIR

    calls = []
    monkeypatch.setattr(colmap, "match_pairs", lambda *a, **k: calls.append(a))
    room_for_one_chunk = sara_io.LOW_SPACE_BYTES + 2 * BYTES_PER_PAIR  # 45 pairs need far more
    monkeypatch.setattr(sara_io, "free_bytes", lambda path: room_for_one_chunk)
    before = snapshot(finished_run)
    result = run_cli("run", images, finished_run, "-q", "--pairs", "exhaustive", "-s", "match.chunk_size=1")
    assert_error(result, 4, "no space left", "MB are needed", "run the same command again")
    assert calls == []  # COLMAP never started
    assert_kept(before, finished_run, PREVIOUS_OUTPUTS)


@pytest.mark.slow  # 8 s; the room checks before writing and before matching stay in the default suite
def test_disk_filling_during_extraction(images, tmp_path, monkeypatch, run_cli):
    """Another program fills the disk while COLMAP extracts: the extraction is stopped before the
    database cannot grow (COLMAP would abort the process with a stack dump); one line, exit 4; the
    same command then resumes."""
    from sara import colmap
    from sara import io as sara_io
    from sara.colmap import extract_process

    original, free, watched = colmap.extract_sift, [10**12], []

    def fill_then_extract(*args, watch, **kwargs):
        def watch_and_record(done):
            watched.append(done)
            free[0] = 2 * 2**20  # filled by someone else while COLMAP extracts
            watch(done)
        original(*args, watch=watch_and_record, **kwargs)

    monkeypatch.setattr(extract_process, "WATCH_S", 0.01)  # the watcher looks before COLMAP is through
    monkeypatch.setattr(colmap, "extract_sift", fill_then_extract)
    monkeypatch.setattr(sara_io, "free_bytes", lambda path: free[0])
    out = tmp_path / "out"
    result = run_cli("run", images, out, "-q")
    assert_error(result, 4, "no space left", "2.1 MB free", "run the same command again")
    assert len(watched) == 1  # stopped at the first look that saw the disk full
    monkeypatch.undo()
    assert_ok(run_cli("run", images, out, "-q"))
    assert len(registered(out)) == len(list(images.iterdir()))


def test_worker_that_died_on_a_full_disk_is_one_line(tmp_path, monkeypatch):
    """A worker process that COLMAP aborted (it cannot write) breaks the pool: said as a full disk
    where the output folder's disk is full, else as a worker that ended (never a bare traceback)."""
    import argparse
    from concurrent.futures.process import BrokenProcessPool

    from sara import io as sara_io
    from sara.cli.errors import describe_error

    args = argparse.Namespace(out=tmp_path)
    monkeypatch.setattr(sara_io, "free_bytes", lambda path: 1000)
    code, line = describe_error(BrokenProcessPool("A child process terminated abruptly"), args)
    assert code == 4 and "no space left" in line and "run the same command again" in line
    monkeypatch.setattr(sara_io, "free_bytes", lambda path: 10**12)
    code, line = describe_error(BrokenProcessPool("A child process terminated abruptly"), args)
    assert code == 1 and "worker process ended abruptly" in line and "internal error" not in line
