"""The `sara` command line. Only this module configures logging and prints.

Every expected failure ends in exactly one line on stderr, `sara: error: <what happened and what
to do>`, and one of these exit codes (README, "Bad input"):

    0    success
    1    internal error (a bug; `-v` shows the traceback)
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

import argparse
import errno
import logging
import signal
import sys
from pathlib import Path
from typing import Any, NoReturn

from . import __version__

logger = logging.getLogger("sara")

EXIT_INTERNAL = 1
EXIT_ERROR = EXIT_USAGE = 2
EXIT_STATE = 3
EXIT_FILESYSTEM = 4
EXIT_NO_RESULT = 5
EXIT_INTERRUPTED = 130  # 128 + SIGINT
EXIT_TERMINATED = 143  # 128 + SIGTERM

#: the flag that sets each option, to name it in an error about its value
FLAGS = {"seed": "--seed", "execute.workers": "--workers", "execute.executor": "--executor",
         "execute.ray_address": "--ray-address", "map.mapper": "--mapper", "extract.camera_mode": "--camera-mode",
         "images.recursive": "--recursive", "pairs.method": "--pairs"}


#: termination signals received by this command (the error that follows one is reported as it)
_RECEIVED: list[int] = []


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, handled like Ctrl-C (clean-up runs, one line, exit 128 + signal)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


class ArgumentParser(argparse.ArgumentParser):
    """argparse, with usage errors as one `sara: error:` line and exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"sara: error: {message} (see `{self.prog} --help`)\n")


def _int_at_least(low: int):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be an integer >= {low}, got {value}")
        return value

    return parse


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", default="sift-offline", help="configuration preset (default: sift-offline)")
    p.add_argument("-s", "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a configuration value, e.g. -s retrieval.num_neighbors=20 (repeatable)")
    p.add_argument("--recursive", action="store_true", help="also use images in sub-folders")
    p.add_argument("--camera-mode", choices=["auto", "single", "per_image", "per_folder"],
                   help="how images share cameras (default auto: one camera when all images have the same size)")
    p.add_argument("--seed", type=int, help="random seed (default 0): the same inputs give the same pairs")
    p.add_argument("--overwrite", action="store_true", help="redo every stage instead of resuming")
    p.add_argument("--workers", type=int, help="parallel workers (default 0: one per CPU core); results do not change")
    p.add_argument("--executor", choices=["auto", "serial", "processes", "ray"],
                   help="where parallel work runs (default auto: processes, or serial with --workers 1)")
    p.add_argument("--ray-address", help="with --executor ray: a cluster address, or auto for a running one")


def _add_output(p: argparse.ArgumentParser) -> None:
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars, warnings only")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging and COLMAP's log on the console")


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(
        prog="sara", description="Scene-aware pair selection for Structure-from-Motion, and the COLMAP pipeline around it.")
    parser.add_argument("--version", action="version", version=f"sara {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("run", help="images -> pairs -> matches -> COLMAP model (sparse/0) in one go")
    p.add_argument("images", type=Path, help="folder of images")
    p.add_argument("out", type=Path, help="output folder (created; re-running resumes)")
    p.add_argument("--pairs", default=None,
                   help="pair source: sara (default), exhaustive, sequential, vocab_tree, retrieval, or a pairs file")
    p.add_argument("--mapper", choices=["incremental", "global"], help="COLMAP mapper (default incremental)")
    p.add_argument("--gt", type=Path, help="ground-truth model folder: evaluate the result against it")
    p.add_argument("--export", choices=["3dgs", "nerfstudio", "colmap"],
                   help="also export the model into OUT/<format> (see `sara export`)")
    _add_common(p)
    _add_output(p)

    p = sub.add_parser("extract", help="local features into OUT/features-<backend>.h5 and OUT/database.db")
    p.add_argument("images", type=Path)
    p.add_argument("out", type=Path)
    _add_common(p)
    _add_output(p)

    p = sub.add_parser("pairs", help="select the pairs to match (SARA by default) into OUT/pairs.txt")
    p.add_argument("images", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--method", default=None, help="sara (default), exhaustive, sequential, vocab_tree, retrieval")
    _add_common(p)
    _add_output(p)

    p = sub.add_parser("match", help="match the pairs of a pairs file into OUT/database.db (after extract)")
    p.add_argument("out", type=Path, help="an output folder of `sara extract`")
    p.add_argument("--pairs", type=Path, help="pairs file (default OUT/pairs.txt)")
    _add_common(p)
    _add_output(p)

    p = sub.add_parser("map", help="COLMAP mapping of OUT/database.db into OUT/sparse/N")
    p.add_argument("out", type=Path, help="an output folder of `sara match`")
    p.add_argument("--images", type=Path, help="image folder (default: the one recorded in OUT/run.json)")
    p.add_argument("--mapper", choices=["incremental", "global"])
    _add_common(p)
    _add_output(p)

    p = sub.add_parser("evaluate", help="compare a model with a ground-truth model")
    p.add_argument("model", type=Path, help="a model folder, a sparse/ folder, or a sara output folder")
    p.add_argument("gt", type=Path, help="ground-truth model folder (COLMAP text or binary)")
    p.add_argument("--json", type=Path, help="also write the metrics to this JSON file")
    _add_output(p)

    p = sub.add_parser("export", help="write a run's model for 3DGS, nerfstudio or COLMAP's GUI")
    p.add_argument("out", type=Path, help="an output folder of `sara run`")
    p.add_argument("dest", type=Path, help="folder to write the export into (created)")
    p.add_argument("--format", required=True, choices=["3dgs", "nerfstudio", "colmap"],
                   help="3dgs: undistorted images + PINHOLE sparse/0; nerfstudio: transforms.json + images; "
                        "colmap: database, models and project.ini")
    p.add_argument("--model", type=int, default=0, help="which model of OUT/sparse (default 0, the largest)")
    p.add_argument("--images", type=Path, help="image folder (default: the one recorded in OUT/run.json)")
    p.add_argument("--undistort", action="store_true", help="nerfstudio: undistorted images (3dgs always)")
    p.add_argument("--max-image-size", type=int, default=-1,
                   help="with undistortion: longer image side at most this many pixels")
    _add_output(p)

    p = sub.add_parser("report", help="(re)write OUT/report.html")
    p.add_argument("out", type=Path, help="an output folder of `sara run`")
    _add_output(p)

    p = sub.add_parser("demo", help="offline self-test: synthesise a scene, reconstruct it, evaluate")
    p.add_argument("out", type=Path, nargs="?", default=Path("sara-demo"), help="output folder (default ./sara-demo)")
    p.add_argument("--num-images", type=_int_at_least(2), default=24)
    _add_output(p)

    from . import weights
    from .bench import DEFAULT_METHODS

    weights.add_parser(sub)

    p = sub.add_parser("bench", help="compare pair sources on scenes with ground truth")
    p.add_argument("scenes", nargs="+", type=Path, help="scene folders holding images/ and gt/")
    p.add_argument("--out", type=Path, required=True, help="benchmark folder (created; re-running resumes)")
    p.add_argument("--methods", default=",".join(DEFAULT_METHODS),
                   help=f"comma-separated pair sources (default {','.join(DEFAULT_METHODS)})")
    p.add_argument("--ablation", action="store_true",
                   help="also run SARA with loops / anchors / weak-view reinforcement switched off and on")
    p.add_argument("--preset", default="sift-offline", help="configuration preset (default: sift-offline)")
    p.add_argument("-s", "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a configuration value for every method (repeatable)")
    p.add_argument("--workers", type=int, help="parallel workers (default 0: one per CPU core); results do not change")
    p.add_argument("--no-plot", action="store_true", help="skip bench.png")
    p.add_argument("--name-orders", type=int, default=0, metavar="K",
                   help="also run each scene under K random namings of its images (names.md: the spread "
                        "that file names alone cause)")
    _add_output(p)
    return parser


def _config(args: argparse.Namespace):
    from .config import make_config, parse_override_args

    overrides = parse_override_args(args.overrides)
    for flag, key in (("recursive", "images.recursive"), ("camera_mode", "extract.camera_mode"),
                      ("seed", "seed"), ("mapper", "map.mapper"), ("workers", "execute.workers"),
                      ("executor", "execute.executor"), ("ray_address", "execute.ray_address")):
        value = getattr(args, flag, None)
        if value not in (None, False):
            overrides[key] = value
    pairs = getattr(args, "pairs", None) if args.command == "run" else getattr(args, "method", None)
    if pairs is not None:
        overrides["pairs.method"] = str(pairs)
    return make_config(args.preset, overrides)


def _setup_logging(args: argparse.Namespace) -> None:
    level = logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("[%(name)s] %(levelname)s: %(message)s"))
    root = logging.getLogger("sara")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False


def _cmd_run(args: argparse.Namespace, stop_after: str | None = None) -> None:
    from .pipeline import run

    report = run(_config(args), args.images, args.out, gt_dir=getattr(args, "gt", None), overwrite=args.overwrite,
                 progress=not args.quiet, verbose_colmap=args.verbose, stop_after=stop_after)
    if stop_after is None:
        from .report.html import write_report

        print((args.out / "report.md").read_text(encoding="utf-8"))
        print(f"report: {write_report(args.out)}")
        if getattr(args, "export", None):
            from .export import export

            dest = export(args.out, args.out / args.export, args.export, progress=not args.quiet,
                          verbose_colmap=args.verbose)
            print(f"{args.export} export -> {dest}")
    elif stop_after == "pairs":
        info = report.stages["pairs"]
        print(f"{info['num_pairs']} pairs ({100 * info['fraction_of_exhaustive']:.1f}% of exhaustive) "
              f"-> {args.out / 'pairs.txt'}")
    else:
        info = report.stages["extract"]
        print(f"features of {report.stages['images']['num_images']} images -> {args.out / info['features']}")


def _cmd_match(args: argparse.Namespace) -> None:
    from .pipeline import match_only

    info = match_only(_config(args), args.out, args.pairs, progress=not args.quiet, verbose_colmap=args.verbose)
    print(f"matched {info['num_pairs']} pairs in {info['time_s']:.1f} s: {info['num_verified_pairs']} verified")


def _cmd_map(args: argparse.Namespace) -> None:
    from .pipeline import map_only

    info = map_only(_config(args), args.out, args.images, progress=not args.quiet, verbose_colmap=args.verbose)
    print(f"{info['num_components']} model(s) with {info['component_sizes']} images -> {args.out / 'sparse'}")


def _cmd_evaluate(args: argparse.Namespace) -> None:
    from .evaluation import evaluate, format_table

    if not args.gt.exists():
        raise FileNotFoundError(f"ground-truth model folder not found: {args.gt}")
    model = args.model
    if (model / "sparse").is_dir():
        model = model / "sparse"
    metrics = evaluate(model, args.gt, args.json, require_model=True)
    print(format_table(metrics))


def _cmd_export(args: argparse.Namespace) -> None:
    from .export import export

    dest = export(args.out, args.dest, args.format, model_index=args.model, images=args.images,
                  undistort=args.undistort, max_image_size=args.max_image_size, progress=not args.quiet,
                  verbose_colmap=args.verbose)
    print(f"{args.format} export of {args.out / 'sparse' / str(args.model)} -> {dest}")


def _cmd_report(args: argparse.Namespace) -> None:
    from .report.html import write_report

    print(f"report: {write_report(args.out)}")


def _cmd_demo(args: argparse.Namespace) -> None:
    from .demo import run_demo

    print(run_demo(args.out, num_images=args.num_images, progress=not args.quiet))


def _cmd_bench(args: argparse.Namespace) -> None:
    from . import bench
    from .config import make_config, parse_override_args

    overrides = parse_override_args(args.overrides)
    if "pairs.method" in overrides:
        raise ValueError("choose the pair sources with --methods, not -s pairs.method")
    conf = make_config(args.preset, overrides)
    result = bench.run_bench(args.scenes, args.out, conf, methods=bench.parse_methods(args.methods),
                             ablation=args.ablation, progress=not args.quiet, plot=not args.no_plot,
                             name_orders=args.name_orders)
    print(bench.render_markdown(result.rows, bench.TABLE_COLUMNS, bench.TABLE_TITLE))
    if args.ablation:
        print(bench.render_markdown(result.ablation_rows, bench.ABLATION_COLUMNS, bench.ABLATION_TITLE,
                                    note=bench.ABLATION_NOTE, first="Variant"))
    if args.name_orders:
        print(bench.render_names(bench.names_summary(result.rows)))
    print("results: " + ", ".join(str(p) for p in result.files))


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _setup_logging(args)
    from . import weights

    commands = {
        "run": _cmd_run, "extract": lambda a: _cmd_run(a, "extract"), "pairs": lambda a: _cmd_run(a, "pairs"),
        "match": _cmd_match, "map": _cmd_map, "evaluate": _cmd_evaluate, "demo": _cmd_demo,
        "bench": _cmd_bench, "weights": weights.cmd,
    }
    _RECEIVED.clear()
    previous = _handle_termination() if args.command != "weights" else {}
    try:
        try:
            commands[args.command](args)
        except Exception as exc:
            interrupt = _interrupt_behind(exc)
            if interrupt is None:
                raise
            raise interrupt from exc
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Terminated) else signal.SIGINT
        for other in (signal.SIGINT, *previous):  # a second signal while exiting changes nothing
            signal.signal(other, signal.SIG_IGN)
        previous = {}
        name = signal.Signals(signum).name
        print(f"sara: error: interrupted by {name}; run the same command again to resume where it stopped",
              file=sys.stderr)
        if argv is None:
            _exit_now(128 + signum)
        return 128 + signum
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


def _exit_now(code: int) -> NoReturn:
    """End the `sara` command with `code` once an interruption has been handled.

    About one Ctrl-C in twenty during pair selection, the interpreter ended the process by SIGINT
    (exit -2) after the message was printed and 130 returned. The likely cause: CPython 3.11 sets
    its "unhandled KeyboardInterrupt" flag when the exception passes through code that a C
    extension runs with `PyRun_String`, even if ours catches it later, and then exits by SIGINT.
    The work's own clean-up has run by now (the exception went through it), so the interpreter's
    exit handlers are skipped and the code is the one documented.
    """
    import os

    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed or broken pipe: nothing more can be said there
            pass
    os._exit(code)


def _interrupt_behind(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C or termination that a library turned into another error, if any: a signal that
    arrives while a module is imported can come back as that module's own error (poselib raises
    RuntimeError when the import of its extension is interrupted, without the chain)."""
    if _RECEIVED:
        return Terminated(_RECEIVED[-1])
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return cause
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return None


def _handle_termination() -> dict[int, Any]:
    """SIGTERM and SIGHUP raise Terminated, like SIGINT raises KeyboardInterrupt: clean-up code
    runs and the user gets one line. pycolmap installs a native handler that prints a stack dump on
    SIGTERM; it is imported first so that ours replaces it. Returns the handlers to put back."""
    from . import colmap  # noqa: F401 - pycolmap's native signal handlers, replaced below

    def terminate(signum: int, frame: object) -> None:
        signal.signal(signum, signal.SIG_IGN)  # a second signal does not break the clean-up
        _RECEIVED.append(signum)
        raise Terminated(signum)

    previous = {}
    for signum in (signal.SIGTERM, signal.SIGHUP):
        previous[signum] = signal.signal(signum, terminate)
    return previous


def describe_error(exc: BaseException, args: argparse.Namespace | None = None) -> tuple[int, str]:
    """The exit code and the one-line message of an error (the one place that maps them)."""
    import sqlite3

    from .config import ConfigError
    from .io import NoResultError, OutputStateError
    from .weights import MissingExtraError

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
    if isinstance(exc, (ValueError, MissingExtraError, LookupError)):
        return EXIT_USAGE, text
    if isinstance(exc, MemoryError):
        return EXIT_FILESYSTEM, "out of memory; use fewer workers (--workers) or smaller images (-s extract.max_image_size=...)"
    from .colmap import ColmapError

    if isinstance(exc, ColmapError):
        return EXIT_INTERNAL, text
    return EXIT_INTERNAL, (f"internal error ({type(exc).__name__}: {text}); please report it with the command "
                           "that caused it (-v shows the traceback)")


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
        hint = "" if "run the same command again" in detail else "; free some space and run the same command again to resume"
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


if __name__ == "__main__":
    sys.exit(main())
