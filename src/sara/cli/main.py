"""`sara COMMAND ...`: parse, set up logging, run the command's handler, and turn what it raises
into one `sara: error:` line and a documented exit code (see `errors.py`)."""

from __future__ import annotations

import logging
import signal
import sys

from tqdm import tqdm

from .errors import RECEIVED_SIGNALS, catch_termination, describe_error, exit_now, interrupt_behind, interrupted_line
from .parser import build_parser

logger = logging.getLogger("sara")


def setup_logging(verbose: bool, quiet: bool) -> None:
    """sara's log on stderr: INFO, DEBUG with -v, warnings only with -q (only the CLI does this)."""
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    handler = _BesideProgressBars(sys.stderr)
    handler.setFormatter(logging.Formatter("[%(name)s] %(levelname)s: %(message)s"))
    root = logging.getLogger("sara")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False


class _BesideProgressBars(logging.StreamHandler):
    """Log lines on their own lines while a progress bar runs (the matching's estimate comes
    mid-bar): tqdm clears the bar, writes the line, and draws the bar again."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            tqdm.write(self.format(record), file=self.stream)
        except Exception:  # logging's contract: a failing handler reports, never raises
            self.handleError(record)


def main(argv: list[str] | None = None) -> int:
    """Run `sara ARGV` (default: the process's arguments); returns the exit code.

    Called in-process (argv given) the caller's signal handlers are put back afterwards; as the
    `sara` command, an interruption ends the process at once with its code (`errors.exit_now`).
    """
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser(argv).parse_args(argv)
    setup_logging(args.verbose, args.quiet)
    RECEIVED_SIGNALS.clear()
    previous = catch_termination() if getattr(args, "catch_signals", True) else {}
    try:
        try:
            args.handler(args)
        except Exception as exc:
            interrupt = interrupt_behind(exc)
            if interrupt is None:
                raise
            raise interrupt from exc
    except KeyboardInterrupt as exc:
        code, message = interrupted_line(exc)
        for other in (signal.SIGINT, *previous):  # a second signal while exiting changes nothing
            signal.signal(other, signal.SIG_IGN)
        previous = {}
        print(f"sara: error: {message}", file=sys.stderr)
        if argv is None:
            exit_now(code)
        return code
    except Exception as exc:  # noqa: BLE001 - every failure ends in one line and a documented code
        code, message = describe_error(exc, args)
        if args.verbose:
            logger.exception("failed")
        print(f"sara: error: {message}", file=sys.stderr)
        return code
    finally:
        for signum, handler in previous.items():
            # called in-process (argv given): put the caller's handlers back; as the `sara` command,
            # a signal while the interpreter exits after the work is done changes nothing
            signal.signal(signum, handler if argv is not None else signal.SIG_IGN)
    return 0
