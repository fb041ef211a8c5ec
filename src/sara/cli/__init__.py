"""The `sara` command line. Only this package configures logging and prints.

`parser.py` builds one parser per command, each carrying its handler (`commands.py`); `main.py`
dispatches to it; `errors.py` maps what it raises to one line and an exit code.

Every expected failure ends in exactly one line on stderr, `sara: error: <what happened and what
to do>`, and one of these exit codes (README, "Bad input"):

    0    success
    1    internal error: a bug (any exception that is not one of the errors below); the line names
         the exception and asks for a report, `-v` shows the traceback
    2    bad usage or input: an option out of range, a missing or unusable image folder, pairs
         file or ground truth, an output path that is a file
    3    the output folder cannot be used as it is: made from other images or settings, damaged
         files, an earlier stage unfinished, in use by another sara process
    4    the file system: disk full, read-only, permission denied, input/output error
    5    no result: the run produced no pairs, no verified pair or no model; the previous outputs
         are kept
    130  interrupted by SIGINT (Ctrl-C); 143 by SIGTERM; 129 by SIGHUP: run the same command
         again to resume
"""

from __future__ import annotations

from .errors import (
    EXIT_ERROR,
    EXIT_FILESYSTEM,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_NO_RESULT,
    EXIT_OK,
    EXIT_STATE,
    EXIT_TERMINATED,
    EXIT_USAGE,
    describe_error,
)
from .main import main
from .parser import build_parser

__all__ = ["EXIT_ERROR", "EXIT_FILESYSTEM", "EXIT_INTERNAL", "EXIT_INTERRUPTED", "EXIT_NO_RESULT", "EXIT_OK",
           "EXIT_STATE", "EXIT_TERMINATED", "EXIT_USAGE", "build_parser", "describe_error", "main"]
