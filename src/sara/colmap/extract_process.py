"""COLMAP's SIFT extraction in a process of its own, watched from sara's.

The parent reads the progress from the database while COLMAP writes it. That must happen in
another process: Python's SQLite and pycolmap's, two libraries in one process, do not see each
other's locks on the same file, and a reader closing its connection tore the write-ahead log from
under COLMAP's writer (SIGBUS). The child is a plain `python -m` of this module, not a
multiprocessing child, so a user's script without a `__main__` guard is not run again in it.

Protocol: the job as JSON in argv; the child prints one JSON line, {"ok": true} or
{"error": "disk" | "colmap", "message": ...}, and ends with its parent.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .child import WATCH_S, child_process, end_with_parent


def run_watched(job: dict[str, Any], watch: Callable[[], None]) -> None:
    """Run the extraction `job` in a child process, calling `watch()` every `WATCH_S` seconds;
    when `watch` raises (Ctrl-C and sara's SIGTERM included), the child is stopped (the images it
    wrote stay: SQLite keeps the database whole) and the error is raised here."""
    from ..io import disk_full_error
    from .native import ColmapError

    with child_process(__name__, job) as child:
        while child.poll() is None:
            try:
                child.wait(WATCH_S)
            except subprocess.TimeoutExpired:
                watch()
        answer = child.stdout.read() if child.stdout else ""
    lines = answer.strip().splitlines()
    result = json.loads(lines[-1]) if lines and lines[-1].startswith("{") else None
    folder = Path(job["db_path"]).parent
    if result is None:
        raise ColmapError(f"COLMAP's SIFT extraction ended without a word (exit code {child.returncode}); "
                          f"its log is in {folder / 'logs'}")
    if result.get("error") == "disk":
        raise disk_full_error(folder)
    if "error" in result:
        raise ColmapError(result["message"])


def main(argv: list[str]) -> int:
    job = json.loads(argv[0])
    end_with_parent(job["parent"])
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the parent too: it decides
    from . import native, sift

    native.send_log_to(Path(job["log_dir"]) if job["log_dir"] else None, verbose=job["verbose"])
    try:
        with native.native_errors("extract SIFT features", Path(job["db_path"]).parent):
            sift.extract_now(**job["args"])
    except OSError as exc:
        print(json.dumps({"error": "disk", "message": str(exc)}), flush=True)
        return 1
    except Exception as exc:  # noqa: BLE001 - told to the parent, which raises it
        print(json.dumps({"error": "colmap", "message": str(exc)}), flush=True)
        return 1
    print(json.dumps({"ok": True}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
