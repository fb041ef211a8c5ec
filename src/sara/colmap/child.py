"""sara's own child processes for COLMAP work (the SIFT extraction, the vocabulary-tree queries):
started as a plain `python -m MODULE JOB`, not a multiprocessing child (a user's script without a
`__main__` guard is not run again in it), stopped whole when the parent's side raises, and ending
by themselves when their parent is gone."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

#: seconds between two looks at the child's work (parent) and at the parent (child)
WATCH_S = 0.5


@contextlib.contextmanager
def child_process(module: str, job: dict[str, Any]) -> Iterator[subprocess.Popen]:
    """`python -m MODULE JOB` (the job as JSON), its stdout a text pipe for this side to read; the
    child is stopped when the block raises (Ctrl-C and sara's SIGTERM included), the pipe closed."""
    child = subprocess.Popen([sys.executable, "-m", module, json.dumps(job)], stdout=subprocess.PIPE,
                             stdin=subprocess.DEVNULL, text=True, encoding="utf-8")
    try:
        yield child
    except BaseException:
        child.terminate()
        child.wait()
        raise
    finally:
        if child.stdout:
            child.stdout.close()


def end_with_parent(parent: int) -> None:
    """End this process when its parent is gone (a SIGKILL gave it no chance to stop us): no orphan
    goes on writing into a database that the next run resumes."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(WATCH_S)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="sara-parent-watch").start()
