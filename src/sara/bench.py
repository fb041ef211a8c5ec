"""`sara bench`: every pair source side by side on scenes with known poses.

    sara bench SCENE [SCENE ...] --out BENCH [--methods exhaustive,sequential,vocabtree,retrieval,sara]
               [--ablation] [-s key=value ...]

A scene folder holds `images/` and `gt/` (a COLMAP model with the true poses). Per scene:

    BENCH/<scene>/features/      SIFT extracted once (`sara extract`), shared by every method
    BENCH/<scene>/<method>/      a `sara run` with pairs.method=<method>, started from a copy of the
                                 features database (no matches) and its extract record
    BENCH/<scene>/sara-<variant>/  with --ablation: SARA with parts of its graph stage switched off
                                 (the full variant is BENCH/<scene>/sara)

Every method runs the very same matching, mapping and evaluation code, so the comparison measures
pair selection alone. Results go to BENCH/results.{json,csv,md} (and ablation.{json,csv,md}), with
a plot BENCH/bench.png when matplotlib is installed. Ratios against exhaustive are measured in the
same run on the same machine. A re-run skips every method already finished.
"""

from __future__ import annotations

import argparse
import csv
import io
import logging
import math
import os
import shutil
import sqlite3
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from . import extract
from .io import records
from .config import PipelineConfig, apply_overrides, make_config, parse_override_args
from .io import OutputLock, atomic_path, fingerprint, write_json_atomic, write_text_atomic

logger = logging.getLogger(__name__)

DEFAULT_METHODS = ("exhaustive", "sequential", "vocabtree", "retrieval", "sara")
BENCH_STAGE = "bench"
FEATURES_DIR = "features"
AUC_THRESHOLDS = ("1", "3", "5", "10")
TABLE_TITLE = "Pair sources side by side"
ABLATION_TITLE = "SARA ablation (graph stages)"

# SARA's graph stage with parts switched off (GraphConfig.use_*); "full" is the plain `sara` method.
ABLATION_VARIANTS: dict[str, dict[str, bool]] = {
    "full": {},
    "no_loops": {"graph.use_loops": False},
    "no_anchors": {"graph.use_anchors": False},
    "no_weak": {"graph.use_weak": False},
    "only_loops": {"graph.use_anchors": False, "graph.use_weak": False},
    "only_anchors": {"graph.use_loops": False, "graph.use_weak": False},
    "only_weak": {"graph.use_loops": False, "graph.use_anchors": False},
    "tree_only": {"graph.use_loops": False, "graph.use_anchors": False, "graph.use_weak": False},
}

# (row key, column title, number format) of the main table: the paper's Table 1, then ours.
TABLE_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("registered_pct", "Reg. %", ".1f"),
    ("rot_error_deg", "Rot. err (deg)", ".3f"),
    ("trans_error_deg", "Trans. err (deg)", ".3f"),
    ("matches_per_pair", "Matches/pair", ".0f"),
    ("reproj_mean_px", "Reproj. mean (px)", ".3f"),
    ("reproj_median_px", "Reproj. median (px)", ".3f"),
    ("points3d", "3D points", "d"),
    ("track_length", "Track len.", ".2f"),
    ("pairs", "Pairs", "d"),
    ("match_s", "Match (s)", ".1f"),
    ("auc@1", "AUC@1", ".3f"),
    ("auc@3", "AUC@3", ".3f"),
    ("auc@5", "AUC@5", ".3f"),
    ("auc@10", "AUC@10", ".3f"),
    ("select_s", "Select (s)", ".2f"),
    ("map_s", "Map (s)", ".1f"),
    ("pairs_vs_exhaustive", "Pairs / exh.", ".3f"),
    ("match_time_vs_exhaustive", "Match time / exh.", ".3f"),
    ("select_time_vs_exhaustive_match", "Select time / exh. match", ".3f"),
)
ABLATION_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("num_registered", "Registered", "d"),
    ("points3d", "3D points", "d"),
    ("track_length", "Track len.", ".2f"),
    ("pairs", "Pairs", "d"),
    ("auc@5", "AUC@5", ".3f"),
    ("match_s", "Match (s)", ".1f"),
)
# Every field of a row, in the order of the CSV files.
ROW_FIELDS = (
    "scene", "method", "num_images", "num_registered", "registered_pct", "num_components", "rot_error_deg",
    "trans_error_deg", "matches_per_pair", "verified_pairs", "reproj_mean_px", "reproj_median_px", "points3d",
    "track_length", "pairs", "repair_pairs", "select_s", "tree_build_s", "match_s", "map_s",
    "auc@1", "auc@3", "auc@5", "auc@10", "pairs_vs_exhaustive", "match_time_vs_exhaustive",
    "select_time_vs_exhaustive_match", "error",
)


@dataclass
class BenchResult:
    rows: list[dict[str, Any]] = field(default_factory=list)  # one per (scene, method)
    ablation_rows: list[dict[str, Any]] = field(default_factory=list)  # one per (scene, variant)
    files: list[Path] = field(default_factory=list)


# ---------------------------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------------------------


def parse_methods(text: str | Sequence[str]) -> list[str]:
    """'exhaustive,sara' -> ['exhaustive', 'sara'] (order kept, duplicates dropped); unknown names are errors."""
    from .pairs import SOURCES

    names = [m.strip() for m in text.split(",")] if isinstance(text, str) else [m.strip() for m in text]
    names = list(dict.fromkeys(m for m in names if m))
    if not names:
        raise ValueError(f"no methods given; choose among {', '.join(SOURCES)}")
    unknown = [m for m in names if m not in SOURCES]
    if unknown:
        raise ValueError(f"unknown method {unknown[0]!r} in --methods; choose among {', '.join(SOURCES)}")
    return names


def scene_paths(scene: Path) -> tuple[Path, Path]:
    """(images folder, gt folder) of a benchmark scene; FileNotFoundError when one is missing."""
    scene = Path(scene)
    images, gt = scene / "images", scene / "gt"
    for folder, what in ((images, "images/ (the photographs)"), (gt, "gt/ (a COLMAP model of the true poses)")):
        if not folder.is_dir():
            raise FileNotFoundError(f"scene {scene} has no {what}: a bench scene holds images/ and gt/")
    return images, gt


# ---------------------------------------------------------------------------------------------
# Shared features: extract once, copy per method
# ---------------------------------------------------------------------------------------------


def copy_sqlite(src: Path, dst: Path) -> None:
    """Copy a SQLite database consistently (its WAL included) through SQLite's backup API."""
    with atomic_path(dst) as tmp:
        source = sqlite3.connect(f"file:{src}?mode=ro", uri=True)
        target = sqlite3.connect(tmp)
        try:
            source.backup(target)
        finally:
            target.close()
            source.close()


def _link_or_copy(src: Path, dst: Path) -> None:
    """Hard-link a read-only input (features.h5) into a method folder; copy across file systems."""
    dst.unlink(missing_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        with atomic_path(dst) as tmp:
            shutil.copyfile(src, tmp)


def prepare_method_dir(features_dir: Path, method_dir: Path) -> bool:
    """Give `method_dir` the shared features: database.db (features only), features.h5, extract record.

    Kept as it is when it already holds these very features (a re-run resumes); otherwise its stage
    records are cleared so that no stage is skipped on matches of other features. Returns True when
    the features were (re)copied.
    """
    features_dir, method_dir = Path(features_dir), Path(method_dir)
    source = records.read_record(features_dir, extract.STAGE)
    if source is None or source.get("done") is not True:
        raise FileNotFoundError(f"no finished feature extraction in {features_dir}")
    current = records.read_record(method_dir, extract.STAGE)
    if (current is not None and current.get("key") == source["key"] and current.get("done") is True
            and (method_dir / extract.DB_NAME).exists() and (method_dir / extract.FEATURES_NAME).exists()):
        return False
    shutil.rmtree(method_dir / ".sara", ignore_errors=True)
    method_dir.mkdir(parents=True, exist_ok=True)
    copy_sqlite(features_dir / extract.DB_NAME, method_dir / extract.DB_NAME)
    _link_or_copy(features_dir / extract.FEATURES_NAME, method_dir / extract.FEATURES_NAME)
    records.mark_done(method_dir, extract.STAGE, source["key"], source.get("info", {}))
    return True


# ---------------------------------------------------------------------------------------------
# One method on one scene
# ---------------------------------------------------------------------------------------------


def row_from_report(stages: dict[str, Any], metrics: dict[str, Any] | None) -> dict[str, Any]:
    """The bench row (every field of ROW_FIELDS but scene, method and the ratios) of one run."""
    pairs, match, mapping = stages.get("pairs", {}), stages.get("match", {}), stages.get("map", {})
    m = metrics or {}
    auc = m.get("auc") or {}
    tree_build_s = float((pairs.get("timings_s") or {}).get("build_tree", 0.0))
    return {
        "num_images": stages.get("images", {}).get("num_images"),
        "num_registered": m.get("num_registered"),
        "registered_pct": m.get("registered_pct"),
        "num_components": m.get("num_components"),
        "rot_error_deg": m.get("rel_rotation_error_median_deg"),
        "trans_error_deg": m.get("rel_translation_error_median_deg"),
        "matches_per_pair": match.get("inlier_matches_per_pair_mean"),
        "verified_pairs": match.get("num_verified_pairs"),
        "reproj_mean_px": m.get("reproj_error_mean_px"),
        "reproj_median_px": m.get("reproj_error_median_px"),
        "points3d": m.get("num_points3d"),
        "track_length": m.get("mean_track_length"),
        # pairs actually matched: SARA's selection plus any pairs its repair step added
        "pairs": match.get("num_pairs", pairs.get("num_pairs")),
        "repair_pairs": stages.get("repair", {}).get("pairs_added", 0),
        # a vocabulary tree is normally built once and reused: its build time is reported apart
        "select_s": max(0.0, float(pairs.get("time_s", 0.0)) - tree_build_s),
        "tree_build_s": tree_build_s,
        "match_s": match.get("time_s"),
        "map_s": mapping.get("time_s"),
        **{f"auc@{t}": auc.get(t) for t in AUC_THRESHOLDS},
    }


def bench_key(conf: PipelineConfig, features_key: str, gt_dir: Path) -> str:
    return fingerprint({"conf": conf.to_dict(), "features": features_key, "gt": str(Path(gt_dir).resolve())})


def run_method(conf: PipelineConfig, images: Path, gt_dir: Path, features_dir: Path, method_dir: Path, *,
               progress: bool = True) -> dict[str, Any]:
    """Run the pipeline for one configuration in `method_dir`; returns its bench row.

    Skipped (the stored row returned) when this folder already finished the same configuration on
    the same features and ground truth.
    """
    from .pipeline import run

    features_key = records.read_record(features_dir, extract.STAGE)["key"]
    key = bench_key(conf, features_key, gt_dir)
    if records.is_done(method_dir, BENCH_STAGE, key):
        logger.info("bench: %s already finished, skipping", method_dir)
        return dict(records.done_info(method_dir, BENCH_STAGE))
    if prepare_method_dir(features_dir, method_dir):
        logger.debug("bench: copied the shared features into %s", method_dir)
    report = run(conf, images, method_dir, gt_dir=gt_dir, progress=progress)
    row = row_from_report(report.stages, report.metrics)
    records.mark_done(method_dir, BENCH_STAGE, key, row)
    return row


def _run_guarded(conf: PipelineConfig, images: Path, gt: Path, features_dir: Path, method_dir: Path,
                 progress: bool) -> dict[str, Any]:
    """`run_method`, with a failure recorded in the row (and retried by the next run) instead of raised."""
    try:
        return {**run_method(conf, images, gt, features_dir, method_dir, progress=progress), "error": None}
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as exc:  # noqa: BLE001 - one failing method must not stop a long benchmark
        logger.exception("bench: %s failed", method_dir)
        return {"error": f"{type(exc).__name__}: {exc}"}


# ---------------------------------------------------------------------------------------------
# The benchmark
# ---------------------------------------------------------------------------------------------


def add_exhaustive_ratios(rows: list[dict[str, Any]]) -> None:
    """Per scene: pairs and matching time as fractions of exhaustive's, when exhaustive ran."""
    reference = {r["scene"]: r for r in rows if r["method"] == "exhaustive" and not r.get("error")}
    for row in rows:
        ref = reference.get(row["scene"])
        row["pairs_vs_exhaustive"] = _ratio(row.get("pairs"), ref and ref.get("pairs"))
        row["match_time_vs_exhaustive"] = _ratio(row.get("match_s"), ref and ref.get("match_s"))
        row["select_time_vs_exhaustive_match"] = _ratio(row.get("select_s"), ref and ref.get("match_s"))


def _ratio(value: Any, reference: Any) -> float | None:
    if value is None or not reference:
        return None
    return float(value) / float(reference)


def bench_scene(conf: PipelineConfig, scene: Path, out_dir: Path, methods: Sequence[str], *,
                ablation: bool = False, progress: bool = True) -> tuple[list[dict], list[dict]]:
    """All methods (and ablation variants) on one scene; returns (method rows, ablation rows)."""
    from .pipeline import run

    images, gt = scene_paths(scene)
    scene_dir = Path(out_dir) / Path(scene).name
    features_dir = scene_dir / FEATURES_DIR
    logger.info("bench %s: extracting features once for all methods", scene.name)
    run(conf, images, features_dir, progress=progress, stop_after="extract")
    rows = []
    for i, method in enumerate(methods, 1):
        logger.info("bench %s: method %s (%d/%d)", scene.name, method, i, len(methods))
        method_conf = apply_overrides(conf, {"pairs.method": method})
        row = _run_guarded(method_conf, images, gt, features_dir, scene_dir / method, progress)
        rows.append({"scene": scene.name, "method": method, **row})
    ablation_rows = []
    if ablation:
        for i, (variant, overrides) in enumerate(ABLATION_VARIANTS.items(), 1):
            logger.info("bench %s: SARA ablation %s (%d/%d)", scene.name, variant, i, len(ABLATION_VARIANTS))
            variant_conf = apply_overrides(conf, {"pairs.method": "sara", **overrides})
            variant_dir = scene_dir / ("sara" if variant == "full" else f"sara-{variant}")
            row = _run_guarded(variant_conf, images, gt, features_dir, variant_dir, progress)
            ablation_rows.append({"scene": scene.name, "method": variant, **row})
    return rows, ablation_rows


def run_bench(scenes: Sequence[Path], out_dir: Path, conf: PipelineConfig, *,
              methods: Sequence[str] = DEFAULT_METHODS, ablation: bool = False, progress: bool = True,
              plot: bool = True) -> BenchResult:
    """Benchmark `methods` on every scene into `out_dir`; writes and returns the results."""
    methods = parse_methods(list(methods))
    scenes = [Path(s) for s in scenes]
    for scene in scenes:
        scene_paths(scene)  # fail before hours of work, not after
    names = [s.name for s in scenes]
    if len(set(names)) != len(names):
        raise ValueError(f"scene folder names must differ (they name the output folders): {names}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    result = BenchResult()
    meta = {"scenes": [str(s) for s in scenes], "methods": list(methods), "config": conf.to_dict()}
    with OutputLock(out_dir):
        for i, scene in enumerate(scenes, 1):
            logger.info("bench: scene %s (%d/%d)", scene.name, i, len(scenes))
            rows, ablation_rows = bench_scene(conf, scene, out_dir, methods, ablation=ablation, progress=progress)
            result.rows += rows
            result.ablation_rows += ablation_rows
            add_exhaustive_ratios(result.rows)
            result.files = write_results(out_dir, result, meta, ablation=ablation, plot=plot)
    return result


def write_results(out_dir: Path, result: BenchResult, meta: dict[str, Any], *, ablation: bool,
                  plot: bool) -> list[Path]:
    """Write the tables (and the plot) of the rows so far; returns the files written."""
    files = write_tables(out_dir / "results", result.rows, TABLE_COLUMNS, meta, title=TABLE_TITLE)
    if ablation:
        files += write_tables(out_dir / "ablation", result.ablation_rows, ABLATION_COLUMNS, meta,
                              title=ABLATION_TITLE, note=ABLATION_NOTE, first="Variant")
    png = plot_results(result.rows, out_dir / "bench.png") if plot else None
    return files + ([png] if png is not None else [])


# ---------------------------------------------------------------------------------------------
# Output: JSON, CSV, Markdown and a plot
# ---------------------------------------------------------------------------------------------


def _format(value: Any, spec: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if spec == "d":
        return str(int(value))
    return format(float(value), spec)


def markdown_table(rows: Sequence[dict[str, Any]], columns: Sequence[tuple[str, str, str]], *,
                   first: str = "Method") -> str:
    """A Markdown table, one row per method, one column per `columns` entry; failures say so."""
    lines = [f"| {first} | " + " | ".join(title for _, title, _ in columns) + " |",
             "|---|" + "---:|" * len(columns)]
    for row in rows:
        if row.get("error"):
            cells = [f"failed: {row['error']}"] + [""] * (len(columns) - 1)
        else:
            cells = [_format(row.get(key), spec) for key, _, spec in columns]
        lines.append(f"| {row['method']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


TABLE_NOTE = ("Errors are medians over co-registered pairs (relative poses, degrees); matches/pair are inlier "
              "matches per verified pair; AUC of max(rotation, translation) error over all gt pairs. Select (s) "
              "leaves out the one-off build of a vocabulary tree (tree_build_s in the CSV). Times are seconds "
              "on this machine in this run; ratios are against exhaustive on the same scene.")
ABLATION_NOTE = ("SARA with parts of its graph stage switched off (graph.use_loops / use_anchors / use_weak); "
                 "registered images of the largest model; AUC@5 over all gt pairs.")


def render_markdown(rows: Sequence[dict[str, Any]], columns: Sequence[tuple[str, str, str]], title: str, *,
                    note: str = TABLE_NOTE, first: str = "Method") -> str:
    lines = [f"# {title}", ""]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        scene_rows = [r for r in rows if r["scene"] == scene]
        num_images = next((r.get("num_images") for r in scene_rows if r.get("num_images")), None)
        lines += [f"## {scene}" + (f" ({num_images} images)" if num_images else ""), "",
                  markdown_table(scene_rows, columns, first=first), ""]
    return "\n".join(lines + [note, ""])


def rows_to_csv(rows: Sequence[dict[str, Any]]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(ROW_FIELDS), extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if row.get(k) is None else row.get(k) for k in ROW_FIELDS})
    return buffer.getvalue()


def write_tables(stem: Path, rows: Sequence[dict[str, Any]], columns: Sequence[tuple[str, str, str]],
                 meta: dict[str, Any], *, title: str, note: str = TABLE_NOTE, first: str = "Method") -> list[Path]:
    """`<stem>.json`, `<stem>.csv` and `<stem>.md`; returns their paths."""
    from .pipeline import versions

    paths = [stem.with_suffix(".json"), stem.with_suffix(".csv"), stem.with_suffix(".md")]
    write_json_atomic(paths[0], {**meta, "versions": versions(), "rows": list(rows)})
    write_text_atomic(paths[1], rows_to_csv(rows))
    write_text_atomic(paths[2], render_markdown(rows, columns, title, note=note, first=first))
    return paths


def plot_results(rows: Sequence[dict[str, Any]], path: Path) -> Path | None:
    """Pairs vs AUC@5 and matching time vs pairs, every method on every scene; None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.ticker import LogFormatter
    except ImportError:
        logger.warning("matplotlib is not installed: no plot (pip install 'sara[plot]')")
        return None
    done = [r for r in rows if not r.get("error") and r.get("pairs")]
    methods = list(dict.fromkeys(r["method"] for r in done))
    scenes = list(dict.fromkeys(r["scene"] for r in done))
    markers = "osD^vP*Xh<>"
    fig, (ax_auc, ax_time) = plt.subplots(1, 2, figsize=(12, 5))
    for s, scene in enumerate(scenes):
        for m, method in enumerate(methods):
            for r in (r for r in done if r["scene"] == scene and r["method"] == method):
                style = {"marker": markers[m % len(markers)], "color": f"C{s % 10}", "linestyle": "none"}
                ax_auc.plot(r["pairs"], r.get("auc@5") or 0.0, **style)
                if r.get("match_s") is not None:
                    ax_time.plot(r["pairs"], r["match_s"], **style)
    handles = [plt.Line2D([], [], marker=markers[m % len(markers)], color="gray", linestyle="none", label=method)
               for m, method in enumerate(methods)]
    handles += [plt.Line2D([], [], color=f"C{s % 10}", linewidth=5, label=scene) for s, scene in enumerate(scenes)]
    ax_auc.set(xscale="log", ylim=(0.0, 1.02), xlabel="pairs matched", ylabel="AUC@5",
               title="Accuracy vs pairs matched")
    ax_time.set(xscale="log", yscale="log", xlabel="pairs matched", ylabel="matching time (s)",
                title="Matching time vs pairs matched")
    for ax in (ax_auc, ax_time):
        ax.grid(True, which="both", alpha=0.3)
        for axis in (ax.xaxis, ax.yaxis):  # 30, 100, 300 rather than 3x10^1
            if axis.get_scale() == "log":
                axis.set_major_formatter(LogFormatter(labelOnlyBase=False, minor_thresholds=(2, 0.5)))
                axis.set_minor_formatter(LogFormatter(labelOnlyBase=False, minor_thresholds=(2, 0.5)))
    ax_time.legend(handles=handles, fontsize="small", loc="best")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------------


def add_bench_parser(sub: argparse._SubParsersAction, add_output: Callable[[argparse.ArgumentParser], None]) -> None:
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
    add_output(p)


def cmd_bench(args: argparse.Namespace) -> None:
    overrides = parse_override_args(args.overrides)
    if "pairs.method" in overrides:
        raise ValueError("choose the pair sources with --methods, not -s pairs.method")
    conf = make_config(args.preset, overrides)
    result = run_bench(args.scenes, args.out, conf, methods=parse_methods(args.methods), ablation=args.ablation,
                       progress=not args.quiet, plot=not args.no_plot)
    print(render_markdown(result.rows, TABLE_COLUMNS, TABLE_TITLE))
    if args.ablation:
        print(render_markdown(result.ablation_rows, ABLATION_COLUMNS, ABLATION_TITLE, note=ABLATION_NOTE,
                              first="Variant"))
    print("results: " + ", ".join(str(p) for p in result.files))
