"""`sara bench`: every pair source side by side on scenes with known poses.

    sara bench SCENE [SCENE ...] --out BENCH [--methods exhaustive,sequential,vocabtree,retrieval,sara]
               [--ablation] [-s key=value ...]

A scene folder holds `images/` and `gt/` (a COLMAP model with the true poses), and `masks/` where
its images have masks (`sara.masks`: every method extracts with them). Per scene:

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

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import extract, pipeline
from ..config import PipelineConfig, apply_overrides
from ..io import OutputLock, fingerprint, records, write_json_atomic, write_text_atomic
from .kinds import kind_summary, render_kinds
from .names import base_scene, renamed_scene
from .tables import (
    ABLATION_COLUMNS,
    ABLATION_NOTE,
    ABLATION_TITLE,
    AUC_THRESHOLDS,
    TABLE_COLUMNS,
    TABLE_TITLE,
    names_summary,
    plot_results,
    render_names,
    write_tables,
)

logger = logging.getLogger(__name__)

DEFAULT_METHODS = ("exhaustive", "sequential", "sequential-loop", "vocabtree", "retrieval", "sara")
#: bench methods that are a pair source with settings: name -> (pairs.method, overrides)
METHOD_SETTINGS: dict[str, tuple[str, dict[str, Any]]] = {
    "sequential-loop": ("sequential", {"sequential.loop_detection": True}),
}
#: methods that pair images by their name order: meaningless under random names (`--name-orders`)
ORDERED_METHODS = ("sequential", "sequential-loop")
BENCH_STAGE = "bench"
FEATURES_DIR = "features"
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
    from ..pairs import SOURCES

    names = [m.strip() for m in text.split(",")] if isinstance(text, str) else [m.strip() for m in text]
    names = list(dict.fromkeys(m for m in names if m))
    if not names:
        raise ValueError(f"no methods given; choose among {', '.join(SOURCES)}")
    known = [*SOURCES, *METHOD_SETTINGS]
    unknown = [m for m in names if m not in known]
    if unknown:
        raise ValueError(f"unknown method {unknown[0]!r} in --methods; choose among {', '.join(known)}")
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
        "repair_pairs": stages.get("rounds", {}).get("pairs_added", 0),
        # a vocabulary tree is normally built once and reused: its build time is reported apart
        "select_s": max(0.0, float(pairs.get("time_s", 0.0)) - tree_build_s),
        "tree_build_s": tree_build_s,
        "match_s": match.get("time_s"),
        "map_s": mapping.get("time_s"),
        **{f"auc@{t}": auc.get(t) for t in AUC_THRESHOLDS},
    }


def bench_key(conf: PipelineConfig, features_key: str, gt_dir: Path) -> str:
    """What a finished method row depends on: not where or how parallel the work ran (`execute.*`,
    which never changes results), so a bench resumed with other workers keeps its finished rows."""
    settings = {k: v for k, v in conf.to_dict().items() if k != "execute"}
    return fingerprint({"conf": settings, "features": features_key, "gt": str(Path(gt_dir).resolve())})


def run_method(conf: PipelineConfig, images: Path, gt_dir: Path, features_dir: Path, method_dir: Path, *,
               progress: bool = True) -> dict[str, Any]:
    """Run the pipeline for one configuration in `method_dir`; returns its bench row.

    Skipped (the stored row returned) when this folder already finished the same configuration on
    the same features and ground truth.
    """
    features_key = records.read_record(features_dir, extract.STAGE)["key"]
    key = bench_key(conf, features_key, gt_dir)
    if records.is_done(method_dir, BENCH_STAGE, key):
        logger.info("bench: %s already finished, skipping", method_dir)
        return dict(records.done_info(method_dir, BENCH_STAGE))
    if pipeline.share_features(features_dir, method_dir):
        logger.debug("bench: copied the shared features into %s", method_dir)
    report = pipeline.run(conf, images, method_dir, gt_dir=gt_dir, progress=progress)
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


def _end_to_end(row: dict[str, Any], extract_s: float) -> dict[str, Any]:
    """Seconds after extraction (selection, matching, mapping, the rounds included) and end to end
    (with the extraction every method shares, timed once)."""
    if row.get("error") or row.get("match_s") is None:
        return {}
    after = sum(float(row.get(k) or 0.0) for k in ("select_s", "tree_build_s", "match_s", "map_s"))
    return {"extract_s": extract_s, "after_extract_s": after, "end_to_end_s": extract_s + after}


def bench_scene(conf: PipelineConfig, scene: Path, out_dir: Path, methods: Sequence[str], *,
                ablation: bool = False, progress: bool = True) -> tuple[list[dict], list[dict]]:
    """All methods (and ablation variants) on one scene; returns (method rows, ablation rows)."""
    images, gt = scene_paths(scene)
    if (Path(scene) / "masks").is_dir():  # a scene's own masks, for every method (`sara.masks`)
        conf = apply_overrides(conf, {"extract.mask_path": str(Path(scene) / "masks")})
    scene_dir = Path(out_dir) / Path(scene).name
    features_dir = scene_dir / FEATURES_DIR
    logger.info("bench %s: extracting features once for all methods", scene.name)
    pipeline.run(conf, images, features_dir, progress=progress, stop_after="extract")
    extract_s = float((records.done_info(features_dir, extract.STAGE) or {}).get("time_s") or 0.0)
    rows = []
    for i, method in enumerate(methods, 1):
        if method in ORDERED_METHODS and base_scene(scene.name) != scene.name:
            logger.info("bench %s: %s skipped: it pairs by name order, which random names do not keep",
                        scene.name, method)
            continue
        logger.info("bench %s: method %s (%d/%d)", scene.name, method, i, len(methods))
        source, settings = METHOD_SETTINGS.get(method, (method, {}))
        method_conf = apply_overrides(conf, {"pairs.method": source, **settings})
        row = _run_guarded(method_conf, images, gt, features_dir, scene_dir / method, progress)
        rows.append({"scene": scene.name, "method": method, **row, **_end_to_end(row, extract_s)})
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
              plot: bool = True, name_orders: int = 0, kinds: dict[str, str] | None = None) -> BenchResult:
    """Benchmark `methods` on every scene into `out_dir`; writes and returns the results.

    With `name_orders` K > 0 each scene also runs under K random namings of its images
    (`names.renamed_scene`, kept in ``out_dir/renamed``), each a scene of its own, and
    ``out_dir/names.md`` sums each method up over the namings. ``out_dir/kinds.md`` sets SARA against
    each method per scene, the scenes grouped by `kinds` (scene folder name -> kind of capture)."""
    methods = parse_methods(list(methods))
    scenes = [Path(s) for s in scenes]
    if name_orders < 0:
        raise ValueError(f"name_orders must be >= 0, got {name_orders}")
    for scene in scenes:
        scene_paths(scene)  # fail before hours of work, not after
    names = [s.name for s in scenes]
    if len(set(names)) != len(names):
        raise ValueError(f"scene folder names must differ (they name the output folders): {names}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    result = BenchResult()
    meta = {"scenes": [str(s) for s in scenes], "methods": list(methods), "config": conf.to_dict(),
            "versions": pipeline.versions(), "name_orders": int(name_orders), "kinds": dict(kinds or {})}
    with OutputLock(out_dir):
        if name_orders:
            scenes = [s for scene in scenes for s in
                      [scene, *(renamed_scene(scene, out_dir / "renamed", k) for k in range(1, name_orders + 1))]]
        for i, scene in enumerate(scenes, 1):
            logger.info("bench: scene %s (%d/%d)", scene.name, i, len(scenes))
            rows, ablation_rows = bench_scene(conf, scene, out_dir, methods, ablation=ablation, progress=progress)
            result.rows += rows
            result.ablation_rows += ablation_rows
            add_exhaustive_ratios(result.rows)
            result.files = write_results(out_dir, result, meta, ablation=ablation, plot=plot,
                                         names=bool(name_orders))
    return result


def write_results(out_dir: Path, result: BenchResult, meta: dict[str, Any], *, ablation: bool,
                  plot: bool, names: bool = False) -> list[Path]:
    """Write the tables (and the plot) of the rows so far; returns the files written. `names`: also
    `names.json` and `names.md`, each method over the namings of its scenes (`--name-orders`)."""
    files = write_tables(out_dir / "results", result.rows, TABLE_COLUMNS, meta, title=TABLE_TITLE)
    if ablation:
        files += write_tables(out_dir / "ablation", result.ablation_rows, ABLATION_COLUMNS, meta,
                              title=ABLATION_TITLE, note=ABLATION_NOTE, first="Variant")
    if names:
        summary = names_summary(result.rows)
        write_json_atomic(out_dir / "names.json", {**meta, "summary": summary})
        write_text_atomic(out_dir / "names.md", render_names(summary))
        files += [out_dir / "names.json", out_dir / "names.md"]
    by_kind = kind_summary(result.rows, meta.get("kinds") or {})
    write_json_atomic(out_dir / "kinds.json", {**meta, "summary": by_kind})
    write_text_atomic(out_dir / "kinds.md", render_kinds(by_kind))
    files += [out_dir / "kinds.json", out_dir / "kinds.md"]
    png = plot_results(result.rows, out_dir / "bench.png") if plot else None
    return files + ([png] if png is not None else [])


