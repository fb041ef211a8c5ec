"""pycolmap's native side: its errors, its signal handlers, its log, its random seed and version.

COLMAP reports failures as RuntimeError with a terse message and writes its log through glog;
this module turns the first into errors a user can act on and routes the second to a file.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import pycolmap

from ..io import LOW_SPACE_BYTES, disk_full_error, free_bytes


def _sigterm_without_stack_dump() -> None:
    """pycolmap installs glog's failure handler, which prints a native stack dump on SIGTERM (a
    request to stop, not a crash: schedulers, `timeout` and `docker stop` send it, often to every
    process of the group). Give SIGTERM its default action back, unless Python code set a handler;
    crashes (SIGSEGV, SIGABRT) keep their dump. The `sara` command then installs its own handler."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGTERM) in (
            signal.SIG_DFL, None):
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


_sigterm_without_stack_dump()


class ColmapError(RuntimeError):
    """COLMAP failed for a reason that is not a full disk or a damaged database (see its log)."""


@contextlib.contextmanager
def native_errors(what: str, folder: Path) -> Iterator[None]:
    """Turn pycolmap's RuntimeError into an error that says what happened: OSError(ENOSPC) when the
    disk of `folder` is (nearly) full, else ColmapError naming `what` and COLMAP's log."""
    try:
        yield
    except RuntimeError as exc:
        if isinstance(exc, ColmapError):
            raise
        if free_bytes(folder) < LOW_SPACE_BYTES:
            raise disk_full_error(folder) from None
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ColmapError(f"COLMAP could not {what} ({detail}); its log is in {Path(folder) / 'logs'}") from None


def quiet_signals_in_worker() -> None:
    """In a worker process of ours: SIGTERM ends it silently (instead of the stack dump of
    pycolmap's native handler) and SIGINT is left to the driver, which stops the pool."""
    import multiprocessing
    import signal

    if multiprocessing.parent_process() is None:
        return
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


#: the arguments of the last `send_log_to` in this process, for a process it starts to log alike
log_settings: dict = {"log_dir": None, "verbose": False}


def send_log_to(log_dir: Path | None, *, verbose: bool = False) -> None:
    """Route COLMAP's own log into `log_dir/colmap-<time>.<pid>` (or to the console when verbose).

    Without a folder and not verbose, only COLMAP's errors reach the console; with a folder, none
    (sara reports a failure in one line that names the log).
    """
    log_settings.update(log_dir=log_dir, verbose=verbose)
    logging_ = pycolmap.logging
    if verbose:
        logging_.minloglevel = 0
        logging_.alsologtostderr = True
        return
    logging_.alsologtostderr = False
    logging_.stderrthreshold = 2  # without a log file, errors still reach the console
    if log_dir is None:
        logging_.minloglevel = 2
        return
    logging_.stderrthreshold = 3  # with one, sara's own one-line error says what failed and names the log
    Path(log_dir).mkdir(parents=True, exist_ok=True)
    logging_.minloglevel = 0
    logging_.set_log_destination(logging_.INFO, str(Path(log_dir) / "colmap-"))
    for level in (logging_.WARNING, logging_.ERROR):
        logging_.set_log_destination(level, "")


def set_seed(seed: int) -> None:
    """Seed pycolmap's global random generator (RANSAC, clustering, synthetic scenes)."""
    pycolmap.set_random_seed(seed)


def version() -> str:
    """The version of the installed pycolmap."""
    return pycolmap.__version__
