"""One handler per command: `cmd_<name>(args)` does the work and prints the result (only the CLI
prints). The parser attaches each handler to its command (`parser.py`)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

#: command-line flags that set a configuration key (applied over the preset and the -s overrides)
FLAG_OVERRIDES = (("recursive", "images.recursive"), ("camera_mode", "extract.camera_mode"), ("seed", "seed"),
                  ("mapper", "map.mapper"), ("workers", "execute.workers"), ("executor", "execute.executor"),
                  ("ray_address", "execute.ray_address"), ("sequence", "sequence.mode"), ("masks", "extract.mask_path"))


def config_from_args(args: argparse.Namespace, pair_source: Any = None) -> Any:
    """The PipelineConfig of a command: its preset, then `-s KEY=VALUE`, then its flags."""
    from ..config import make_config, parse_override_args

    overrides = parse_override_args(args.overrides)
    for flag, key in FLAG_OVERRIDES:
        value = getattr(args, flag, None)
        if value not in (None, False):
            overrides[key] = value
    if pair_source is not None:
        overrides["pairs.method"] = str(pair_source)
    return make_config(args.preset, overrides)


def cmd_run(args: argparse.Namespace) -> None:
    """`sara run`: every stage, then report.md on stdout, report.html and the export if asked."""
    from ..pipeline import run
    from ..report.html import write_report

    conf = config_from_args(args, args.pairs)
    images, gt = _video_frames(args, conf)
    run(conf, images, args.out, gt_dir=gt, overwrite=args.overwrite, progress=not args.quiet,
        verbose_colmap=args.verbose)
    print((args.out / "report.md").read_text(encoding="utf-8"))
    print(f"report: {write_report(args.out)}")
    if args.export:
        from ..export import export

        dest = export(args.out, args.out / args.export, args.export, progress=not args.quiet,
                      verbose_colmap=args.verbose)
        print(f"{args.export} export -> {dest}")


def _video_frames(args: argparse.Namespace, conf: Any) -> tuple[Path, Path | None]:
    """(images, ground truth) of `sara run`: for a video or a folder of videos, the frames picked into
    OUT/images and the ground truth of those frames (`sara.video`); else the arguments as given."""
    from ..video import FrameSettings, find_videos, frames_for_run

    videos = find_videos(args.images, recursive=conf.images.recursive)
    if not videos:
        if args.frames is not None or args.fps is not None:
            raise ValueError(f"--{'frames' if args.fps is None else 'fps'} applies to a video or a folder of "
                             f"videos; {args.images} is a folder of images")
        return args.images, args.gt
    from ..pipeline import preflight

    preflight(conf)  # a bad option or --pairs fails before the video is decoded
    return frames_for_run(videos, args.out, FrameSettings(frames=args.frames, fps=args.fps), gt_dir=args.gt,
                          overwrite=args.overwrite, progress=not args.quiet)


def cmd_extract(args: argparse.Namespace) -> None:
    """`sara extract`: the pipeline up to the features."""
    from ..pipeline import run

    report = run(config_from_args(args), args.images, args.out, overwrite=args.overwrite, progress=not args.quiet,
                 verbose_colmap=args.verbose, stop_after="extract")
    info = report.stages["extract"]
    print(f"features of {report.stages['images']['num_images']} images -> {args.out / info['features']}")


def cmd_pairs(args: argparse.Namespace) -> None:
    """`sara pairs`: the pipeline up to the selected pairs."""
    from ..pipeline import run

    report = run(config_from_args(args, args.method), args.images, args.out, overwrite=args.overwrite,
                 progress=not args.quiet, verbose_colmap=args.verbose, stop_after="pairs")
    info = report.stages["pairs"]
    print(f"{info['num_pairs']} pairs ({100 * info['fraction_of_exhaustive']:.1f}% of exhaustive) "
          f"-> {args.out / 'pairs.txt'}")


def cmd_match(args: argparse.Namespace) -> None:
    from ..pipeline import match_only

    info = match_only(config_from_args(args), args.out, args.pairs, progress=not args.quiet,
                      verbose_colmap=args.verbose, overwrite=args.overwrite)
    print(f"matched {info['num_pairs']} pairs in {info['time_s']:.1f} s: {info['num_verified_pairs']} verified")


def cmd_map(args: argparse.Namespace) -> None:
    from ..pipeline import map_only

    info = map_only(config_from_args(args), args.out, args.images, progress=not args.quiet,
                    verbose_colmap=args.verbose, overwrite=args.overwrite)
    print(f"{info['num_components']} model(s) with {info['component_sizes']} images -> {args.out / 'sparse'}")


def cmd_evaluate(args: argparse.Namespace) -> None:
    from ..evaluation import evaluate, format_table

    if not args.gt.exists():
        raise FileNotFoundError(f"ground truth not found: {args.gt} (a COLMAP model folder or a transforms.json)")
    model = args.model
    if (model / "sparse").is_dir():
        model = model / "sparse"
    metrics = evaluate(model, args.gt, args.json, require_model=True)
    print(format_table(metrics))


def cmd_export(args: argparse.Namespace) -> None:
    from ..export import export

    dest = export(args.out, args.dest, args.format, model_index=args.model, images=args.images,
                  undistort=args.undistort, max_image_size=args.max_image_size, progress=not args.quiet,
                  verbose_colmap=args.verbose)
    print(f"{args.format} export of {args.out / 'sparse' / str(args.model)} -> {dest}")


def cmd_report(args: argparse.Namespace) -> None:
    from ..report.html import write_report

    print(f"report: {write_report(args.out)}")


def cmd_demo(args: argparse.Namespace) -> None:
    from ..demo import run_demo

    print(run_demo(args.out, num_images=args.num_images, progress=not args.quiet))


def cmd_bench(args: argparse.Namespace) -> None:
    from .. import bench
    from ..config import make_config, parse_override_args

    overrides = parse_override_args(args.overrides)
    if "pairs.method" in overrides:
        raise ValueError("choose the pair sources with --methods, not -s pairs.method")
    if args.workers is not None:
        overrides["execute.workers"] = args.workers
    conf = make_config(args.preset, overrides)
    result = bench.run_bench(args.scenes, args.out, conf, methods=bench.parse_methods(args.methods),
                             ablation=args.ablation, progress=not args.quiet, plot=not args.no_plot,
                             name_orders=args.name_orders, kinds=bench.parse_kinds(args.kind))
    print(bench.render_markdown(result.rows, bench.TABLE_COLUMNS, bench.TABLE_TITLE))
    if args.ablation:
        print(bench.render_markdown(result.ablation_rows, bench.ABLATION_COLUMNS, bench.ABLATION_TITLE,
                                    note=bench.ABLATION_NOTE, first="Variant"))
    if args.name_orders:
        print(bench.render_names(bench.names_summary(result.rows)))
    print("results: " + ", ".join(str(p) for p in result.files))
