"""Running `sara` as the tests need it, and checking what it says and what it leaves behind.

Commands run in this process through `sara.cli.main` (the `run_cli` fixture of conftest.py), which
is fast and shows the real exit codes and messages. A subprocess (`sara_process`, `signal_when`) is
used only where a real signal or a real kill of the process is the point of the test.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import pytest

from sara.cli import main

#: what a crash below Python prints; never allowed on stderr
NATIVE_NOISE = ("Traceback", "*** Aborted", "stack trace", "SIGSEGV", "SIGABRT", "terminate called")

#: the shared scenes with known poses (`../shared/data` beside the project, or $SARA_DATA)
DATA_ROOT = Path(os.environ.get("SARA_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def scene_dir(name: str) -> Path:
    """A shared scene's folder; the test is skipped, with the reason, where it is absent."""
    path = DATA_ROOT / name
    if not (path / "images").is_dir():
        pytest.skip(f"real scene {name} not available at {path} (set SARA_DATA to its parent folder)")
    return path


class CliResult(NamedTuple):
    """Exit code and output of one `sara` command."""

    code: int
    out: str
    err: str

    @property
    def error_lines(self) -> list[str]:
        """The `sara: error:` lines of stderr (a user error gives exactly one)."""
        return [line for line in self.err.splitlines() if line.startswith("sara: error:")]


def _call_main(args: tuple) -> int:
    try:
        return main([str(a) for a in args])
    except SystemExit as exc:  # argparse: --help and usage errors
        return exc.code if isinstance(exc.code, int) else 1


def run_in_process(capture, *args) -> CliResult:
    """`sara ARGS` through `sara.cli.main`; `capture` is pytest's capfd (or capsys), emptied first."""
    capture.readouterr()
    code = _call_main(args)
    captured = capture.readouterr()
    return CliResult(code, captured.out, captured.err)


def run_redirected(*args) -> CliResult:
    """`sara ARGS` in this process with Python's streams redirected: for module- and session-scoped
    fixtures, which cannot use capfd."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        code = _call_main(args)
    return CliResult(code, out.getvalue(), err.getvalue())


def sara_process(*args, env=None, timeout: float = 300) -> CliResult:
    """`python -m sara ARGS` in a new process, waited for."""
    proc = subprocess.run([sys.executable, "-m", "sara", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=env)
    return CliResult(proc.returncode, proc.stdout, proc.stderr)


def wait_for(condition: Callable[[], bool], *, timeout: float, poll_s: float = 0.02) -> bool:
    """Poll `condition` until it holds or `timeout` seconds pass; returns whether it held."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(poll_s)
    return condition()


def _default_sigint() -> None:
    """In the child: SIGINT as a foreground program gets it. A shell starts background jobs (e.g.
    `.ci/run &`) with SIGINT ignored, Python keeps that, and the run would never see the signal."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def ignores(pid: int, signum: int) -> bool:
    """Whether process `pid` now ignores `signum` (Linux /proc): sara's handler ignores a second
    termination signal once it has taken the first."""
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("SigIgn:"):
                    return bool(int(line.split()[1], 16) >> (signum - 1) & 1)
    except OSError:
        return True  # the process is gone: nothing to wait for
    return False


def signal_when(cmd: list, marker: Path | Callable[[int], bool], signum: int, *, times: int = 1,
                timeout: float = 240, new_session: bool = False) -> CliResult:
    """Start `sara CMD`, send `signum` once `marker` exists (a path, or a condition on the process
    id that holds), `times` times (each after the run took the one before); returns the finished
    process's result. With `new_session`, the signal goes to the whole process group, workers too."""
    proc = subprocess.Popen([sys.executable, "-m", "sara", *map(str, cmd)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint,
                            start_new_session=new_session)
    reached = (lambda: marker(proc.pid)) if callable(marker) else Path(marker).exists
    wait_for(lambda: reached() or proc.poll() is not None, timeout=timeout)
    for k in range(times):
        if proc.poll() is not None:
            break
        if k:  # the next signal only once the run has taken the one before (and now ignores it)
            wait_for(lambda: ignores(proc.pid, signum) or proc.poll() is not None, timeout=30)
        if new_session:
            os.killpg(proc.pid, signum)
        else:
            proc.send_signal(signum)
    _, err = proc.communicate(timeout=timeout)
    return CliResult(proc.returncode, "", err)


def assert_error(result: CliResult, code: int, *fragments: str) -> str:
    """Exit `code`, exactly one `sara: error:` line holding every fragment, no traceback; returns the line."""
    assert result.code == code, f"exit {result.code}, expected {code}:\n{result.err}"
    for noise in NATIVE_NOISE:
        assert noise not in result.err, result.err
    lines = result.error_lines
    assert len(lines) == 1, result.err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


def assert_ok(result: CliResult) -> None:
    assert result.code == 0, result.err
    assert "sara: error:" not in result.err and "Traceback" not in result.err, result.err


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
    """The image names in an output folder's model sparse/0."""
    from sara.colmap import registered_images

    return sorted(registered_images(Path(out) / "sparse" / "0"))


def truncate(path: Path, keep: float) -> None:
    """Cut a file to the share `keep` of its bytes, as a full disk or a kill leaves it."""
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


#: names that COLMAP's pair importer would misread: aliased in the database while matching
SPACED_NAMES = ["view one.png", "#view two.png", " view three.png", "view four .png"]


def aliased_in(db_path: Path) -> bool:
    """Whether the database holds a name aliased for COLMAP's pair importer (read it only once
    sara has stopped: a reader beside COLMAP can make its writes fail as "database is locked")."""
    import sqlite3

    con = sqlite3.connect(f"file:{db_path}?mode=ro", uri=True)
    try:
        return con.execute("SELECT COUNT(*) FROM images WHERE name LIKE 'sara-alias-%'").fetchone()[0] > 0
    finally:
        con.close()


def present_for(path: Path, seconds: float) -> Callable[[int], bool]:
    """A condition for `signal_when`: `path` has existed for `seconds` (seen by polling)."""
    first_seen: list[float] = []

    def check(pid: int) -> bool:
        if not Path(path).exists():
            return False
        first_seen[:] = first_seen or [time.monotonic()]
        return time.monotonic() - first_seen[0] >= seconds
    return check


def best_matched_pair(out: Path) -> tuple[str, str, int]:
    """(name0, name1, inlier matches) of the verified pair with the most inlier matches in a run's
    database: two views close enough that COLMAP's mapper has the matches to start from them."""
    from sara import colmap

    names = {image_id: name for name, image_id in colmap.image_ids(out / "database.db").items()}
    i, j, inliers = max(colmap.verified_image_pairs(out / "database.db"), key=lambda p: p[2])
    return names[i], names[j], inliers
