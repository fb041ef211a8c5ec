"""The `sara` command line. Only this module configures logging and prints."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from . import __version__

logger = logging.getLogger("sara")

EXIT_ERROR = 2
EXIT_INTERRUPTED = 130


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
    parser = argparse.ArgumentParser(
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
    p.add_argument("--num-images", type=int, default=24)
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
    p.add_argument("--no-plot", action="store_true", help="skip bench.png")
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
    metrics = evaluate(model, args.gt, args.json)
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
                             ablation=args.ablation, progress=not args.quiet, plot=not args.no_plot)
    print(bench.render_markdown(result.rows, bench.TABLE_COLUMNS, bench.TABLE_TITLE))
    if args.ablation:
        print(bench.render_markdown(result.ablation_rows, bench.ABLATION_COLUMNS, bench.ABLATION_TITLE,
                                    note=bench.ABLATION_NOTE, first="Variant"))
    print("results: " + ", ".join(str(p) for p in result.files))


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _setup_logging(args)
    from .extract import OutputMismatchError
    from .io import OutputLockedError

    commands = {
        "run": _cmd_run, "extract": lambda a: _cmd_run(a, "extract"), "pairs": lambda a: _cmd_run(a, "pairs"),
        "match": _cmd_match, "map": _cmd_map, "evaluate": _cmd_evaluate, "demo": _cmd_demo,
        "export": _cmd_export, "report": _cmd_report,
    }
    commands["bench"] = _cmd_bench
    from . import weights

    commands["weights"] = weights.cmd
    try:
        commands[args.command](args)
    except KeyboardInterrupt:
        print("sara: interrupted; run the same command again to resume where it stopped", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (FileNotFoundError, NotADirectoryError, ValueError, OutputLockedError, OutputMismatchError,
            weights.MissingExtraError) as exc:
        if args.verbose:
            logger.exception("failed")
        print(f"sara: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    return 0


if __name__ == "__main__":
    sys.exit(main())
