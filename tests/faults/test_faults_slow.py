"""The slow cases of the fault suite (issue 11): signals during extraction and to whole process
groups, kills while matching beside the previous matches, a database lost after extraction.
Run with `python -m pytest -m slow tests/faults/test_faults_slow.py`."""

from __future__ import annotations

import shutil
import signal
from pathlib import Path

import pytest

from harness import (
    SPACED_NAMES,
    aliased_in,
    assert_error,
    assert_kept,
    assert_ok,
    present_for,
    registered,
    sara_process,
    signal_when,
    snapshot,
)

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("signum,code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)], ids=["SIGTERM", "SIGINT"])
def test_signal_during_extraction_then_resume(signum, code, images, finished_run_template, tmp_path):
    fresh = tmp_path / "fresh"
    result = signal_when(["run", images, fresh, "-q"], fresh / "database.db", signum)
    assert_error(result, code, f"interrupted by {signal.Signals(signum).name}", "run the same command again")
    assert not list(fresh.glob(".*.tmp"))
    assert_ok(sara_process("run", images, fresh, "-q"))
    assert registered(fresh) == registered(finished_run_template)


def _children(pid: int) -> list[int]:
    """The process ids of `pid`'s children (Linux /proc); empty when they cannot be read."""
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except (OSError, ValueError):
        return []


def test_sigterm_to_the_process_group_with_workers(finished_run, images):
    """`timeout` and schedulers signal every process of the group: the workers end silently (no
    native stack dump from pycolmap's handler), the driver prints its one line."""
    (finished_run / "pairs.txt").unlink()
    cmd = ["run", images, finished_run, "-q", "--workers", "2", "--executor", "processes",
           "-s", "execute.shard_size=4"]

    def scoring_in_workers(pid: int) -> bool:  # the view store is written and the workers are up
        return any((finished_run / ".sara").rglob("score-views-*")) and bool(_children(pid))

    result = signal_when(cmd, scoring_in_workers, signal.SIGTERM, new_session=True)
    if result.code == 0:
        pytest.skip("the run finished before the signal")
    assert_error(result, 143, "interrupted by SIGTERM")


def test_sigterm_while_matching_beside_then_resume(finished_run, images):
    """Exhaustive pairs with other matching settings, one pair per chunk, into
    `.sara/database.next.db`: SIGTERM keeps the previous matches and model; the same command then
    finishes."""
    before = snapshot(finished_run)
    cmd = ["run", images, finished_run, "-q", "--pairs", "exhaustive", "-s", "match.chunk_size=1",
           "-s", "match.max_ratio=0.75"]
    result = signal_when(cmd, finished_run / ".sara" / "match_chunk.txt", signal.SIGTERM)
    if result.code == 0:
        pytest.skip("the run finished before the signal")
    assert_error(result, 143, "interrupted by SIGTERM")
    assert_kept(before, finished_run, ("database.db", "sparse", "run.json", "report.md"))
    assert_ok(sara_process(*cmd))
    assert len(registered(finished_run)) == 10


def test_kill_while_matching_beside_resumes_the_copy(finished_run, images, tmp_path):
    """SIGKILL (nothing can be cleaned) while matching into the copy: the next run continues in the
    copy and ends with the same pairs and model as a run that was never stopped."""
    options = ["--pairs", "exhaustive", "-s", "match.chunk_size=2", "-s", "match.max_ratio=0.75"]
    cmd = ["run", images, finished_run, "-q", *options]
    reference = Path(shutil.copytree(finished_run, tmp_path / "reference"))
    assert_ok(sara_process("run", images, reference, "-q", *options))
    result = signal_when(cmd, finished_run / ".sara" / "match_chunk.txt", signal.SIGKILL)
    if result.code == 0:
        pytest.skip("the run finished before the kill")
    assert (finished_run / ".sara" / "database.next.db").exists()
    assert_ok(sara_process(*cmd))
    assert (finished_run / "pairs.txt").read_text() == (reference / "pairs.txt").read_text()
    assert registered(finished_run) == registered(reference)


def test_lost_database_is_extracted_again(finished_run, images, finished_run_template):
    """The database went missing after extraction: extraction and matching are redone (exit 0)."""
    (finished_run / "database.db").unlink()
    assert_ok(sara_process("run", images, finished_run, "-q"))
    assert registered(finished_run) == registered(finished_run_template)


def test_killed_rematch_with_other_settings_never_mixes_matches(finished_run, images, finished_run_template):
    """Killed while matching with other settings (in the copy), then run with the original settings:
    the database keeps exactly the original matches, and the model is the original one."""
    from sara.match import matches_digest

    cmd = ["run", images, finished_run, "-q", "-s", "match.max_ratio=0.7", "-s", "match.chunk_size=1"]
    result = signal_when(cmd, finished_run / ".sara" / "match_chunk.txt", signal.SIGKILL)
    if result.code == 0:
        pytest.skip("the run finished before the kill")
    assert_ok(sara_process("run", images, finished_run, "-q"))
    assert matches_digest(finished_run / "database.db") == matches_digest(finished_run_template / "database.db")
    assert registered(finished_run) == registered(finished_run_template)


def test_overwrite_mends_a_damaged_database(finished_run, images, finished_run_template):
    """The fix the message names (`--overwrite`) works: extraction and matching are redone."""
    data = (finished_run / "database.db").read_bytes()
    (finished_run / "database.db").write_bytes(data[: len(data) // 2])
    result = sara_process("run", images, finished_run, "-q")
    assert_error(result, 3, "database.db is damaged", "--overwrite")
    assert_ok(sara_process("run", images, finished_run, "-q", "--overwrite"))
    assert registered(finished_run) == registered(finished_run_template)


def test_kill_while_names_are_aliased_resumes(spaced_folder, tmp_path, run_cli):
    """SIGKILL while names with spaces are aliased in the database for COLMAP (issue 30: every
    retry then exited 3, "no longer holds the keypoints"): the next run gives the names back and
    finishes, every image registered under its own name."""
    out = tmp_path / "out"
    assert_ok(run_cli("pairs", spaced_folder, out, "-q"))  # extraction and pairs done: the run goes on to match
    cmd = ["run", spaced_folder, out, "-q", "-s", "match.chunk_size=1"]
    # the aliases are saved just before the names change, and kept until matching ends
    result = signal_when(cmd, present_for(out / ".sara" / "name_aliases.json", 0.3), signal.SIGKILL)
    assert result.code == -signal.SIGKILL, result.err
    if not aliased_in(out / "database.db"):
        pytest.skip("the kill came before or after the names were aliased")
    assert_ok(sara_process(*cmd))
    assert set(SPACED_NAMES) <= set(registered(out))
    assert not (out / ".sara" / "name_aliases.json").exists()
