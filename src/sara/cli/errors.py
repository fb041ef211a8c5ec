"""Exit codes, termination signals and the one line each failure ends in.

`describe_error` is the one place that maps an exception to an exit code and a message. Only the
error families that mean "the user can fix this" get codes 2-5; any other exception (KeyError,
IndexError, TypeError, AttributeError, ZeroDivisionError, ...) is a bug in sara: exit 1, and the
line says so, with the exception's type, so that the report names it.
"""

from __future__ import annotations

import argparse
import errno
import os
import signal
import sys
from typing import Any, NoReturn

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_ERROR = EXIT_USAGE = 2
EXIT_STATE = 3
EXIT_FILESYSTEM = 4
EXIT_NO_RESULT = 5
EXIT_INTERRUPTED = 128 + signal.SIGINT  # 130
EXIT_TERMINATED = 128 + signal.SIGTERM  # 143

#: the flag that sets each option, to name it in an error about its value
FLAGS = {"seed": "--seed", "execute.workers": "--workers", "execute.executor": "--executor",
         "execute.ray_address": "--ray-address", "map.mapper": "--mapper", "extract.camera_mode": "--camera-mode",
         "images.recursive": "--recursive", "pairs.method": "--pairs",
         "sequence.mode": "--sequence", "extract.mask_path": "--masks"}

#: termination signals received by this command (the error that follows one is reported as it)
RECEIVED_SIGNALS: list[int] = []


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, handled like Ctrl-C (clean-up runs, one line, exit 128 + signal)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def catch_termination() -> dict[int, Any]:
    """SIGTERM and SIGHUP raise Terminated, like SIGINT raises KeyboardInterrupt: clean-up code
    runs and the user gets one line. pycolmap installs a native handler that prints a stack dump on
    SIGTERM; it is imported first so that ours replaces it. Returns the handlers to put back."""
    from .. import colmap  # noqa: F401 - pycolmap's native signal handlers, replaced below

    def terminate(signum: int, frame: object) -> None:
        signal.signal(signum, signal.SIG_IGN)  # a second signal does not break the clean-up
        RECEIVED_SIGNALS.append(signum)
        raise Terminated(signum)

    previous = {}
    for signum in (signal.SIGTERM, signal.SIGHUP):
        previous[signum] = signal.signal(signum, terminate)
    return previous


def interrupt_behind(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C or termination that a library turned into another error, if any: a signal that
    arrives while a module is imported can come back as that module's own error (poselib raises
    RuntimeError when the import of its extension is interrupted, without the chain)."""
    if RECEIVED_SIGNALS:
        return Terminated(RECEIVED_SIGNALS[-1])
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return cause
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return None


def interrupted_line(exc: KeyboardInterrupt) -> tuple[int, str]:
    """The exit code (128 + signal) and the message of an interruption."""
    signum = exc.signum if isinstance(exc, Terminated) else signal.SIGINT
    name = signal.Signals(signum).name
    return 128 + signum, f"interrupted by {name}; run the same command again to resume where it stopped"


def exit_now(code: int) -> NoReturn:
    """End the `sara` command with `code` once an interruption has been handled.

    About one Ctrl-C in twenty during pair selection, the interpreter ended the process by SIGINT
    (exit -2) after the message was printed and 130 returned. The likely cause: CPython 3.11 sets
    its "unhandled KeyboardInterrupt" flag when the exception passes through code that a C
    extension runs with `PyRun_String`, even if ours catches it later, and then exits by SIGINT.
    The work's own clean-up has run by now (the exception went through it), so the interpreter's
    exit handlers are skipped and the code is the one documented.
    """
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed or broken pipe: nothing more can be said there
            pass
    os._exit(code)


def describe_error(exc: BaseException, args: argparse.Namespace | None = None) -> tuple[int, str]:
    """The exit code and the one-line message of an error (the one place that maps them).

    ConfigError, ValueError, MissingExtraError -> 2; OutputStateError -> 3; the file system -> 4
    (or 2 for a missing path, 3 for an unreadable file); NoResultError -> 5; ColmapError -> 1 with
    its own message; anything else -> 1, "internal error" (a bug).
    """
    import sqlite3

    from ..config import ConfigError
    from ..io import NoResultError, OutputStateError
    from ..weights import MissingExtraError

    text = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, ConfigError):
        flag = FLAGS.get(exc.option)
        given = getattr(args, _flag_dest(flag), None) if (args is not None and flag) else None
        return EXIT_USAGE, (f"{flag}: {text}" if given not in (None, False) else text)
    if isinstance(exc, NoResultError):
        return EXIT_NO_RESULT, text
    if isinstance(exc, OutputStateError):
        return EXIT_STATE, text
    if isinstance(exc, sqlite3.DatabaseError):
        if "full" in text:
            return EXIT_FILESYSTEM, f"disk full while writing the database ({text}); free some space and run again"
        return EXIT_STATE, f"the database is damaged ({text}); run again with --overwrite to redo it"
    if isinstance(exc, OSError):
        return _describe_os_error(exc, text)
    if isinstance(exc, (ValueError, MissingExtraError)):
        return EXIT_USAGE, text
    if isinstance(exc, MemoryError):
        return EXIT_FILESYSTEM, ("out of memory; use fewer workers (--workers) or smaller images "
                                 "(-s extract.max_image_size=...)")
    from concurrent.futures.process import BrokenProcessPool

    if isinstance(exc, BrokenProcessPool):
        return _worker_died(args)
    from ..colmap import ColmapError

    if isinstance(exc, ColmapError):
        return EXIT_INTERNAL, text
    return EXIT_INTERNAL, internal_error_line(exc)


def _worker_died(args: argparse.Namespace | None) -> tuple[int, str]:
    """A worker process ended by a signal (a native abort, the kernel's out-of-memory killer):
    a full disk of the output folder is said as such (COLMAP aborts when it cannot write)."""
    from ..io import LOW_SPACE_BYTES, free_bytes

    out = getattr(args, "out", None)
    if out is not None and free_bytes(out) < LOW_SPACE_BYTES:
        return EXIT_FILESYSTEM, (f"no space left on the device of {out} ({free_bytes(out) / 1e6:.1f} MB free): a "
                                 "worker process ended when it could not write; free some space and run the same "
                                 "command again to resume")
    return EXIT_INTERNAL, ("a worker process ended abruptly (killed, out of memory, or a crash in a native "
                           "library); run the same command again to resume, with fewer workers (--workers) if "
                           "memory is short")


def internal_error_line(exc: BaseException) -> str:
    """The message of an exception no user can fix: it names the type and asks for a report."""
    text = " ".join(str(exc).split())
    what = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    return (f"internal error: {what} (a bug: please report it with the command that caused it; "
            "-v shows the traceback)")


def _flag_dest(flag: str) -> str:
    return flag.lstrip("-").replace("-", "_") if flag != "--pairs" else "pairs"


_FS_ERRNOS = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
              errno.EROFS: "read-only file system", errno.EACCES: "permission denied",
              errno.EPERM: "operation not permitted", errno.EIO: "input/output error",
              errno.EMFILE: "too many open files", errno.ENFILE: "too many open files in the system",
              errno.EFBIG: "file too large", errno.ENAMETOOLONG: "file name too long"}


def _describe_os_error(exc: OSError, text: str) -> tuple[int, str]:
    where = f": {exc.filename}" if exc.filename and str(exc.filename) not in (exc.strerror or "") else ""
    detail = " ".join(str(exc.strerror).split()) if exc.strerror else text
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        hint = ("" if "run the same command again" in detail
                else "; free some space and run the same command again to resume")
        return EXIT_FILESYSTEM, f"{detail}{where}{hint}"
    if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        return EXIT_FILESYSTEM, f"{detail}{where}: cannot write there; choose an output folder you can write to"
    if exc.errno in _FS_ERRNOS:
        return EXIT_FILESYSTEM, f"{detail}{where}"
    if isinstance(exc, (FileNotFoundError, NotADirectoryError, IsADirectoryError, FileExistsError)):
        return EXIT_USAGE, f"{detail}{where}"
    if exc.errno is None:  # HDF5 reports a damaged file this way
        return EXIT_STATE, f"a file could not be read ({text}); run again with --overwrite to redo it"
    return EXIT_FILESYSTEM, f"{detail}{where}"
