"""The slow cases of the fault suite (issue 11): signals during extraction and to whole process
groups, kills while matching beside the previous matches, a database lost after extraction.
Run with `python -m pytest -m slow tests/test_faults_slow.py`; the helpers are test_faults.py's."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_faults import (  # noqa: F401 - fixtures too
    assert_error,
    assert_kept,
    assert_ok,
    finished,
    interrupt_when,
    out,
    registered,
    sara_process,
    snapshot,
)

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("signum,code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)], ids=["SIGTERM", "SIGINT"])
def test_signal_during_extraction_then_resume(signum, code, synthetic_scene, finished, tmp_path):
    images = synthetic_scene[0]
    fresh = tmp_path / "fresh"
    rc, err = interrupt_when(["run", images, fresh, "-q"], fresh / "database.db", signum)
    assert_error(rc, err, code, f"interrupted by {signal.Signals(signum).name}", "run the same command again")
    assert not list(fresh.glob(".*.tmp"))
    proc = sara_process("run", images, fresh, "-q")
    assert_ok(proc.returncode, proc.stderr)
    assert registered(fresh) == registered(finished)


def test_sigterm_to_the_process_group_with_workers(out, synthetic_scene):
    """`timeout` and schedulers signal every process of the group: the workers end silently (no
    native stack dump from pycolmap's handler), the driver prints its one line."""
    images = synthetic_scene[0]
    (out / "pairs.txt").unlink()
    marker = out / ".sara" / "pairs.next"
    proc = subprocess.Popen([sys.executable, "-m", "sara", "run", str(images), str(out), "-q", "--workers", "2",
                             "--executor", "processes", "-s", "execute.shard_size=4"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    while not marker.exists() and proc.poll() is None:
        time.sleep(0.05)
    time.sleep(3.0)  # the workers are scoring
    if proc.poll() is not None:
        pytest.skip("the run finished before the signal")
    os.killpg(proc.pid, signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert_error(proc.returncode, err, 143, "interrupted by SIGTERM")


def test_sigterm_while_matching_beside_then_resume(out, synthetic_scene):
    """Exhaustive pairs with other matching settings, one pair per chunk, into
    `.sara/database.next.db`: SIGTERM keeps the previous matches and model; the same command then
    finishes."""
    images = synthetic_scene[0]
    before = snapshot(out)
    cmd = ["run", images, out, "-q", "--pairs", "exhaustive", "-s", "match.chunk_size=1", "-s", "match.max_ratio=0.75"]
    rc, err = interrupt_when(cmd, out / ".sara" / "match_chunk.txt", signal.SIGTERM)
    if rc == 0:
        pytest.skip("the run finished before the signal")
    assert_error(rc, err, 143, "interrupted by SIGTERM")
    assert_kept(before, out, ("database.db", "sparse", "run.json", "report.md"))
    proc = sara_process(*cmd)
    assert_ok(proc.returncode, proc.stderr)
    assert len(registered(out)) == 10


def test_kill_while_matching_beside_resumes_the_copy(out, synthetic_scene, tmp_path):
    """SIGKILL (nothing can be cleaned) while matching into the copy: the next run continues in the
    copy and ends with the same pairs and model as a run that was never stopped."""
    images = synthetic_scene[0]
    options = ["--pairs", "exhaustive", "-s", "match.chunk_size=2", "-s", "match.max_ratio=0.75"]
    cmd = ["run", images, out, "-q", *options]
    reference = Path(shutil.copytree(out, tmp_path / "reference"))
    proc = sara_process("run", images, reference, "-q", *options)
    assert_ok(proc.returncode, proc.stderr)
    rc, _ = interrupt_when(cmd, out / ".sara" / "match_chunk.txt", signal.SIGKILL)
    if rc == 0:
        pytest.skip("the run finished before the kill")
    assert (out / ".sara" / "database.next.db").exists()
    proc = sara_process(*cmd)
    assert_ok(proc.returncode, proc.stderr)
    assert (out / "pairs.txt").read_text() == (reference / "pairs.txt").read_text()
    assert registered(out) == registered(reference)


def test_lost_database_is_extracted_again(out, synthetic_scene, finished):
    """The database went missing after extraction: extraction and matching are redone (exit 0)."""
    images = synthetic_scene[0]
    (out / "database.db").unlink()
    proc = sara_process("run", images, out, "-q")
    assert_ok(proc.returncode, proc.stderr)
    assert registered(out) == registered(finished)


def test_killed_rematch_with_other_settings_never_mixes_matches(out, synthetic_scene, finished):
    """Killed while matching with other settings (in the copy), then run with the original settings:
    the database keeps exactly the original matches, and the model is the original one."""
    from sara.match import matches_digest

    images = synthetic_scene[0]
    cmd = ["run", images, out, "-q", "-s", "match.max_ratio=0.7", "-s", "match.chunk_size=1"]
    rc, _ = interrupt_when(cmd, out / ".sara" / "match_chunk.txt", signal.SIGKILL)
    if rc == 0:
        pytest.skip("the run finished before the kill")
    proc = sara_process("run", images, out, "-q")
    assert_ok(proc.returncode, proc.stderr)
    assert matches_digest(out / "database.db") == matches_digest(finished / "database.db")
    assert registered(out) == registered(finished)


def test_overwrite_mends_a_damaged_database(out, synthetic_scene, finished):
    """The fix the message names (`--overwrite`) works: extraction and matching are redone."""
    images = synthetic_scene[0]
    data = (out / "database.db").read_bytes()
    (out / "database.db").write_bytes(data[: len(data) // 2])
    proc = sara_process("run", images, out, "-q")
    assert_error(proc.returncode, proc.stderr, 3, "database.db is damaged", "--overwrite")
    proc = sara_process("run", images, out, "-q", "--overwrite")
    assert_ok(proc.returncode, proc.stderr)
    assert registered(out) == registered(finished)
