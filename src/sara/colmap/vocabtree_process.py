"""COLMAP's vocabulary-tree queries in a process of its own, their answers read line by line.

COLMAP's `VocabTreePairGenerator` queries ahead in a thread pool that reads its visual index and the
database; freeing it before every query is answered (a Ctrl-C between two of them) frees the index
under those threads and crashes the process. In a child, a stop ends the child whole, and the
answers received so far are the caller's to keep.

Protocol: the job as JSON in argv; the child prints one JSON line per query, [query, [retrieved,
...]], then {"ok": true} or {"error": "colmap" | "tree", "message": ...} ("tree": the tree file itself
does not read), and ends with its parent.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any


class UnreadableTreeError(ValueError):
    """The tree file given is no visual index COLMAP reads (a bad input, not a failure of COLMAP)."""


def run_queries(job: dict[str, Any], queries: Sequence[str] | None,
                answer: Callable[[str, list[str]], None]) -> None:
    """Run the queries of `job` in a child, calling `answer(query, retrieved)` for each as it comes;
    when anything raises here (Ctrl-C and sara's SIGTERM included) the child is stopped and the
    error raised. `queries`: the images that query (None: every image of the database)."""
    from .child import child_process
    from .native import ColmapError, log_settings

    with tempfile.TemporaryDirectory(prefix="sara-queries-") as folder:
        job = {**job, "parent": os.getpid(), "verbose": log_settings["verbose"],
               "log_dir": str(log_settings["log_dir"]) if log_settings["log_dir"] else None}
        if queries is not None:
            match_list = Path(folder) / "queries.txt"
            match_list.write_text("".join(f"{name}\n" for name in queries), encoding="utf-8")
            job["match_list_path"] = str(match_list)
        end: dict[str, Any] | None = None
        with child_process(__name__, job) as child:
            for line in child.stdout or ():
                message = json.loads(line)
                if isinstance(message, dict):
                    end = message
                    break
                answer(message[0], message[1])
            child.wait()
    if end is not None and end.get("error") == "tree":
        raise UnreadableTreeError(f"not a vocabulary tree COLMAP can read: {job['tree_path']} ({end['message']})")
    if end is None or "error" in end:
        why = end["message"] if end else f"it ended without a word (exit code {child.returncode})"
        raise ColmapError(f"COLMAP's vocabulary-tree retrieval failed: {why}")


def main(argv: list[str]) -> int:
    from .child import end_with_parent

    job = json.loads(argv[0])
    end_with_parent(job["parent"])
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the parent too: it decides
    from . import native
    from .vocabtree import query_all

    native.send_log_to(Path(job["log_dir"]) if job["log_dir"] else None, verbose=job["verbose"])
    channel = os.fdopen(os.dup(1), "w", encoding="utf-8")  # the answers' own: a native library's
    os.dup2(2, 1)  # print to stdout goes to stderr and cannot cut into an answer

    def answer(query: str, retrieved: list[str]) -> None:
        print(json.dumps([query, retrieved]), file=channel, flush=True)

    try:
        with native.native_errors("retrieve images with the vocabulary tree", Path(job["db_path"]).parent):
            query_all(job, answer)
    except Exception as exc:  # noqa: BLE001 - told to the parent, which raises it
        kind = "colmap" if _tree_reads(job["tree_path"]) else "tree"
        print(json.dumps({"error": kind, "message": str(exc)}), file=channel, flush=True)
        return 1
    print(json.dumps({"ok": True}), file=channel, flush=True)
    return 0


def _tree_reads(path: str) -> bool:
    """Whether COLMAP reads the tree file on its own: asked only once the queries failed."""
    import pycolmap

    try:
        pycolmap.VisualIndex.read(path)
    except Exception:  # noqa: BLE001 - any failure to read it says the file is the cause
        return False
    return True


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
