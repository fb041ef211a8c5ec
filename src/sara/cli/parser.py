"""The argument parser: one function per command, each attaching its handler with
`set_defaults(handler=...)`. The names of backends, presets, pair sources and export formats come
from their registries, so a new one appears here without an edit."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import NoReturn

from .. import __version__
from . import commands
from .errors import EXIT_USAGE


class ArgumentParser(argparse.ArgumentParser):
    """argparse, with usage errors as one `sara: error:` line and exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"sara: error: {message} (see `{self.prog} --help`)\n")


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The `sara` parser; every command carries its handler (checked here: none can be missing).

    Given the arguments to parse, only their command's parser is built when they name one: each
    command's choices (presets, pair sources, export formats, bench methods) import their modules,
    a tenth of a second or more that `sara extract` would otherwise pay for `sara bench`'s sake."""
    parser = ArgumentParser(prog="sara", description="Scene-aware pair selection for Structure-from-Motion, "
                                                     "and the COLMAP pipeline around it.")
    parser.add_argument("--version", action="version", version=f"sara {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    named = _command_named(argv)
    for name, add in _COMMANDS.items():
        if named in (None, name):
            add(sub)
    missing = commands_without_handler(parser)
    if missing:
        raise RuntimeError(f"commands without a handler: {', '.join(missing)}")
    return parser


def _command_named(argv: list[str] | None) -> str | None:
    """The command `argv` names, or None (no arguments, an option first, an unknown word)."""
    if not argv or argv[0] not in _COMMANDS:
        return None
    return argv[0]


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """Command name -> its parser."""
    actions = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return {name: p for action in actions for name, p in action.choices.items()}


def commands_without_handler(parser: argparse.ArgumentParser) -> list[str]:
    """The commands whose parser has no callable `handler` default (an empty list when all are wired)."""
    return [name for name, p in subcommands(parser).items() if not callable(p.get_default("handler"))]


# ---------------------------------------------------------------------------------------------
# Options several commands share
# ---------------------------------------------------------------------------------------------


def _add_config_options(p: argparse.ArgumentParser) -> None:
    from ..config import PRESETS
    from ..execute import EXECUTORS

    _add_preset_and_overrides(p, PRESETS)
    p.add_argument("--recursive", action="store_true", help="also use images in sub-folders")
    p.add_argument("--camera-mode", choices=["auto", "single", "per_image", "per_folder"],
                   help="how images share cameras (default auto: one camera when all images have the same size and "
                   "EXIF camera, else one per video or per phone by EXIF where images share one)")
    p.add_argument("--masks", metavar="DIR", help="a folder of masks: keypoints on their black pixels are left out "
                   "(DIR/<image name>.png, or the name without its extension, as COLMAP and nerfstudio name them); "
                   "one mask image: the same mask for every image")
    p.add_argument("--seed", type=int, help="random seed (default 0): the same inputs give the same pairs")
    p.add_argument("--overwrite", action="store_true", help="redo every stage instead of resuming")
    p.add_argument("--workers", type=int, help="parallel workers (default 0: one per CPU core); results do not change")
    p.add_argument("--executor", choices=EXECUTORS.names(),
                   help="where parallel work runs (default auto: processes, or serial with --workers 1)")
    p.add_argument("--ray-address", help="with --executor ray: a cluster address, or auto for a running one")


def _add_preset_and_overrides(p: argparse.ArgumentParser, presets: dict, *, every_method: bool = False) -> None:
    p.add_argument("--preset", default="sift-offline", choices=list(presets),
                   help="configuration preset (default: sift-offline)")
    target = " for every method" if every_method else ", e.g. -s retrieval.num_neighbors=20"
    p.add_argument("-s", "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help=f"override a configuration value{target} (repeatable)")


def _add_output_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars, warnings only")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging and COLMAP's log on the console")


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


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a number above 0, got {text}")
    return value


def _pair_source_names() -> str:
    from ..pairs import SOURCES

    return ", ".join(SOURCES)


def _export_format_names() -> list[str]:
    from ..export import FORMATS

    return FORMATS.names()


class _ExportHelpFormatter(argparse.HelpFormatter):
    """Describes each export format by the first line of its writer's docstring, loaded only when
    the help is shown (a format's module is imported when it is used, not to build the parser)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.dest != "format":
            return super()._get_help_string(action)
        from ..export import FORMATS

        lines = [(FORMATS.get(name).__doc__ or "").strip().splitlines() or [name] for name in FORMATS]
        described = [f"{name}: {line[0][:1].lower()}{line[0][1:].rstrip('.')}" for name, line in zip(FORMATS, lines)]
        return "; ".join(described).replace("%", "%%")


# ---------------------------------------------------------------------------------------------
# The commands
# ---------------------------------------------------------------------------------------------


def _add_sequence(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sequence", choices=["auto", "yes", "no"], default=None,
                   help="the images are frames in capture order, numbered by their names (video, drive): yes, "
                        "auto (the default: when their looks agree with the names' order, from "
                        "sequence.auto_min_frames frames) or no")


def _add_run(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="images -> pairs -> matches -> COLMAP model (sparse/0) in one go")
    p.add_argument("images", type=Path, help="folder of images, a video, or a folder of videos")
    p.add_argument("out", type=Path, help="output folder (created; re-running resumes)")
    p.add_argument("--pairs", default=None,
                   help=f"pair source: one of {_pair_source_names()} (default sara), or a pairs file")
    frames = p.add_mutually_exclusive_group()
    frames.add_argument("--frames", type=_int_at_least(2),
                        help="video input: frames to pick per video, a sharp one of each even window (default 150, "
                             "at most every frame), written to OUT/images")
    frames.add_argument("--fps", type=_positive_float, help="video input: frames to pick per second of video, "
                                                            "instead of --frames")
    p.add_argument("--mapper", choices=["incremental", "global"], help="COLMAP mapper (default incremental)")
    _add_sequence(p)
    p.add_argument("--gt", type=Path, help="known poses, a COLMAP model folder or a transforms.json (nerfstudio, "
                                           "instant-ngp, NeRF synthetic): evaluate the result against them")
    p.add_argument("--export", choices=_export_format_names(),
                   help="also export the model into OUT/<format> (see `sara export`)")
    _add_config_options(p)
    _add_output_options(p)
    p.set_defaults(handler=commands.cmd_run)


def _add_extract(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("extract", help="local features into OUT/features-<backend>.h5 and OUT/database.db")
    p.add_argument("images", type=Path)
    p.add_argument("out", type=Path)
    _add_config_options(p)
    _add_output_options(p)
    p.set_defaults(handler=commands.cmd_extract)


def _add_pairs(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("pairs", help="select the pairs to match (SARA by default) into OUT/pairs.txt")
    p.add_argument("images", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--pairs", "--method", dest="method", default=None,
                   help=f"pair source: one of {_pair_source_names()} (default sara), or a pairs file; as "
                        "`sara run --pairs` (--method: its older name)")
    _add_sequence(p)
    _add_config_options(p)
    _add_output_options(p)
    p.set_defaults(handler=commands.cmd_pairs)


def _add_match(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("match", help="match the pairs of a pairs file into OUT/database.db (after extract)")
    p.add_argument("out", type=Path, help="an output folder of `sara extract`")
    p.add_argument("--pairs", type=Path, help="pairs file (default OUT/pairs.txt)")
    _add_config_options(p)
    _add_output_options(p)
    p.set_defaults(handler=commands.cmd_match)


def _add_map(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("map", help="COLMAP mapping of OUT/database.db into OUT/sparse/N")
    p.add_argument("out", type=Path, help="an output folder of `sara match`")
    p.add_argument("--images", type=Path, help="image folder (default: the one recorded in OUT/run.json)")
    p.add_argument("--mapper", choices=["incremental", "global"])
    _add_config_options(p)
    _add_output_options(p)
    p.set_defaults(handler=commands.cmd_map)


def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="compare a model with a ground-truth model")
    p.add_argument("model", type=Path, help="a model folder, a sparse/ folder, or a sara output folder")
    p.add_argument("gt", type=Path, help="known poses: a COLMAP model folder (text or binary), or a transforms.json "
                                         "(nerfstudio, instant-ngp, NeRF synthetic; the file or its folder)")
    p.add_argument("--json", type=Path, help="also write the metrics to this JSON file")
    _add_output_options(p)
    p.set_defaults(handler=commands.cmd_evaluate)


def _add_export(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write a run's model for 3DGS, nerfstudio or COLMAP's GUI",
                       formatter_class=_ExportHelpFormatter)
    p.add_argument("out", type=Path, help="an output folder of `sara run`")
    p.add_argument("dest", type=Path, help="folder to write the export into (created)")
    p.add_argument("--format", required=True, choices=_export_format_names(),
                   help="the layout to write (each format's own line is shown here)")
    p.add_argument("--model", type=int, default=0, help="which model of OUT/sparse (default 0, the largest)")
    p.add_argument("--images", type=Path, help="image folder (default: the one recorded in OUT/run.json)")
    p.add_argument("--undistort", action="store_true", help="nerfstudio: undistorted images (3dgs always)")
    p.add_argument("--max-image-size", type=int, default=-1,
                   help="with undistortion: longer image side at most this many pixels")
    _add_output_options(p)
    p.set_defaults(handler=commands.cmd_export)


def _add_report(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="(re)write OUT/report.html")
    p.add_argument("out", type=Path, help="an output folder of `sara run`")
    _add_output_options(p)
    p.set_defaults(handler=commands.cmd_report)


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="offline self-test: synthesise a scene, reconstruct it, evaluate")
    p.add_argument("out", type=Path, nargs="?", default=Path("sara-demo"), help="output folder (default ./sara-demo)")
    p.add_argument("--num-images", type=_int_at_least(2), default=24)
    _add_output_options(p)
    p.set_defaults(handler=commands.cmd_demo)


def _add_weights(sub: argparse._SubParsersAction) -> None:
    from .. import weights

    # listing files needs no signal handling (and no COLMAP import, which installing it implies)
    weights.add_parser(sub).set_defaults(handler=weights.cmd, catch_signals=False)


def _add_bench(sub: argparse._SubParsersAction) -> None:
    from ..bench import DEFAULT_METHODS
    from ..config import PRESETS

    p = sub.add_parser("bench", help="compare pair sources on scenes with ground truth")
    p.add_argument("scenes", nargs="+", type=Path, help="scene folders holding images/ and gt/")
    p.add_argument("--out", type=Path, required=True, help="benchmark folder (created; re-running resumes)")
    p.add_argument("--methods", default=",".join(DEFAULT_METHODS),
                   help=f"comma-separated pair sources (default {','.join(DEFAULT_METHODS)})")
    p.add_argument("--ablation", action="store_true",
                   help="also run SARA with loops / anchors / weak-view reinforcement switched off and on")
    _add_preset_and_overrides(p, PRESETS, every_method=True)
    p.add_argument("--workers", type=int, help="parallel workers (default 0: one per CPU core); results do not change")
    p.add_argument("--no-plot", action="store_true", help="skip bench.png")
    p.add_argument("--kind", action="append", default=[], metavar="SCENE=KIND",
                   help="the kind of capture of a scene (driving, object, facade, ...): kinds.md groups the "
                        "scenes by it (repeatable)")
    p.add_argument("--name-orders", type=int, default=0, metavar="K",
                   help="also run each scene under K random namings of its images (names.md: the spread "
                        "that file names alone cause)")
    _add_output_options(p)
    p.set_defaults(handler=commands.cmd_bench)


#: every command, in the order `sara --help` lists them, with the function that adds its parser
_COMMANDS = {"run": _add_run, "extract": _add_extract, "pairs": _add_pairs, "match": _add_match, "map": _add_map,
             "evaluate": _add_evaluate, "export": _add_export, "report": _add_report, "demo": _add_demo,
             "weights": _add_weights, "bench": _add_bench}
