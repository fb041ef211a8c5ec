"""`sara run`: images -> features -> pairs -> matches -> sparse model (-> evaluation), resumable.

Output folder:
    features.h5, database.db     stage extract
    pairs.txt (+ scores.csv,     stage pairs (SARA also writes its scores and global descriptors)
      global.h5)
    sparse/0, sparse/1, ...      stage map (0 is the largest model)
    metrics.json                 with --gt
    run.json, report.md          configuration, versions, per-stage times and counts
    logs/                        COLMAP's own log
"""

from __future__ import annotations

import logging
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from . import __version__, colmap, extract, mapping, match
from .io import records
from .config import PipelineConfig
from .io.images import ImageSet, scan_images, upright_copy
from .io import OutputLock, fingerprint, read_json, write_json_atomic, write_text_atomic
from .pairs import PairContext, get_source
from .io.pairs import read_pairs, write_pairs

logger = logging.getLogger(__name__)

PAIRS_STAGE = "pairs"


@dataclass
class RunReport:
    """Everything `run.json` records about a run."""

    out_dir: Path
    images_root: Path
    config: dict[str, Any]
    stages: dict[str, dict[str, Any]] = field(default_factory=dict)
    skipped_images: dict[str, str] = field(default_factory=dict)
    metrics: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "sara_version": __version__,
            "versions": versions(),
            "images_root": str(self.images_root.resolve()),
            "config": self.config,
            "skipped_images": self.skipped_images,
            "stages": self.stages,
            "metrics": self.metrics,
        }

    def save(self) -> None:
        write_json_atomic(self.out_dir / "run.json", self.to_dict())


def versions() -> dict[str, str]:
    import numpy

    return {"python": platform.python_version(), "pycolmap": colmap.version(), "numpy": numpy.__version__}


def pairs_key(conf: PipelineConfig, extract_key: str, source_file: Path | None) -> str:
    data: dict[str, Any] = {"extract": extract_key, "pairs": conf.pairs.__dict__, "seed": conf.seed}
    if conf.pairs.method == "sara" or conf.pairs.sequential_loop_detection or conf.pairs.method == "retrieval":
        data.update(retrieval=conf.retrieval.__dict__, score=conf.score.__dict__, graph=conf.graph.__dict__)
    if source_file is not None:
        data["file"] = source_file.read_text(encoding="utf-8", errors="replace")
    return fingerprint(data)


def select_pairs(conf: PipelineConfig, images: ImageSet, out_dir: Path, *, progress: bool = True) -> dict:
    """Stage `pairs`: write `pairs.txt` from the configured source; returns its info and times."""
    method = conf.pairs.method
    source_file = Path(method) if method not in _source_names() else None
    if source_file is not None and not source_file.exists():
        raise FileNotFoundError(f"--pairs {method}: not a pair source ({', '.join(_source_names())}) "
                                "and no such pairs file")
    key = pairs_key(conf, (records.read_record(out_dir, extract.STAGE) or {}).get("key", ""), source_file)
    pairs_path = out_dir / "pairs.txt"
    if records.is_done(out_dir, PAIRS_STAGE, key) and pairs_path.exists():
        logger.info("pairs: %s up to date, skipping", pairs_path)
        return records.done_info(out_dir, PAIRS_STAGE)
    records.mark_started(out_dir, PAIRS_STAGE, key)
    tic = time.perf_counter()
    if source_file is not None:
        pairs = read_pairs(source_file, known_names=images.names)
        info: dict[str, Any] = {"source": str(source_file)}
    else:
        ctx = PairContext(names=images.names, images_root=images.root, features_path=out_dir / extract.FEATURES_NAME,
                          db_path=out_dir / extract.DB_NAME, out_dir=out_dir, conf=conf, progress=progress)
        result = get_source(method)(ctx)
        pairs, info = result.pairs, {**result.info, "timings_s": result.timings_s}
    write_pairs(pairs_path, pairs)
    info.update(method=method, num_pairs=len(pairs), time_s=time.perf_counter() - tic)
    n = len(images.names)
    info["fraction_of_exhaustive"] = len(pairs) / max(1, n * (n - 1) // 2)
    records.mark_done(out_dir, PAIRS_STAGE, key, info)
    return info


def _source_names() -> list[str]:
    from .pairs import SOURCES

    return list(SOURCES)


def run(conf: PipelineConfig, images_root: Path, out_dir: Path, *, gt_dir: Path | None = None,
        overwrite: bool = False, progress: bool = True, verbose_colmap: bool = False,
        stop_after: str | None = None) -> RunReport:
    """The whole pipeline; every stage skips work already done, so a re-run resumes.

    stop_after: "extract" or "pairs" to run only the stages up to that one.
    """
    if stop_after not in (None, "extract", "pairs"):
        raise ValueError(f"stop_after must be extract or pairs, not {stop_after!r}")
    out_dir = Path(out_dir)
    images_root = Path(images_root)
    if gt_dir is not None and not Path(gt_dir).exists():
        raise FileNotFoundError(f"ground-truth folder not found: {gt_dir}")
    images = scan_images(images_root, recursive=conf.images.recursive, progress=progress)
    out_dir.mkdir(parents=True, exist_ok=True)
    with OutputLock(out_dir):
        images = _handle_orientation(conf.images.exif_orientation, images, out_dir, progress)
        colmap.send_log_to(out_dir / "logs", verbose=verbose_colmap)
        colmap.set_seed(conf.seed)
        report = RunReport(out_dir, images_root, conf.to_dict(), skipped_images=images.skipped)
        report.stages["images"] = {"num_images": len(images.names), "num_skipped": len(images.skipped)}
        tic = time.perf_counter()
        extract.run(conf.extract, images, out_dir, overwrite=overwrite, progress=progress)
        report.stages["extract"] = {**records.done_info(out_dir, extract.STAGE), "time_s": time.perf_counter() - tic}
        report.save()
        if stop_after == "extract":
            return report
        report.stages["pairs"] = select_pairs(conf, images, out_dir, progress=progress)
        report.save()
        if stop_after == "pairs":
            return report
        report.stages["match"] = match.run(conf.match, out_dir / "pairs.txt", out_dir / extract.DB_NAME, out_dir,
                                           progress=progress)
        report.save()
        report.stages["map"] = _map(conf, images, out_dir, progress)
        if conf.pairs.method == "sara" and conf.pairs.repair_rounds > 0:
            _repair(conf, images, out_dir, report, progress)
        if gt_dir is not None:
            from .evaluate import run as evaluate_run

            report.metrics = evaluate_run(out_dir / "sparse", Path(gt_dir), out_dir / "metrics.json")
        report.save()
        write_text_atomic(out_dir / "report.md", render_report(report))
    return report


def _map(conf: PipelineConfig, images: ImageSet, out_dir: Path, progress: bool) -> dict:
    upstream = (records.read_record(out_dir, match.STAGE) or {}).get("key", "")
    return mapping.run(conf.map, out_dir / extract.DB_NAME, images.root, out_dir, seed=conf.seed,
                       upstream_key=upstream, progress=progress)


def _repair(conf: PipelineConfig, images: ImageSet, out_dir: Path, report: RunReport, progress: bool) -> None:
    """Re-link views that the mapper left out of the main model (see `repair.py`)."""
    from . import repair

    pairs_path = out_dir / "pairs.txt"
    info: dict[str, Any] = {"rounds": 0, "pairs_added": 0, "time_s": 0.0}
    for _ in range(conf.pairs.repair_rounds):
        pairs = read_pairs(pairs_path, known_names=images.names)
        main = repair.model_images(out_dir / "sparse" / "0")
        left_out = repair.left_out_views(images.names, pairs, main)
        if not left_out:
            break
        extra = repair.repair_pairs(out_dir / "scores.csv", pairs, main, left_out, conf.pairs.repair_pairs_per_view)
        if not extra:
            break
        logger.warning("%d views were left out of the main model: matching %d more pairs and mapping again",
                       len(left_out), len(extra))
        tic = time.perf_counter()
        write_pairs(pairs_path, pairs + extra)
        spent = {stage: report.stages[stage].get("time_s", 0.0) for stage in ("match", "map")}
        report.stages["match"] = match.run(conf.match, pairs_path, out_dir / extract.DB_NAME, out_dir,
                                           progress=progress)
        report.stages["map"] = _map(conf, images, out_dir, progress)
        for stage, seconds in spent.items():  # the repair's cost is part of the run's cost
            report.stages[stage] = {**report.stages[stage], "time_s": report.stages[stage]["time_s"] + seconds}
        info["rounds"] += 1
        info["pairs_added"] += len(extra)
        info["time_s"] += time.perf_counter() - tic
        info.setdefault("left_out", []).append(len(left_out))
    if info["rounds"]:
        records.mark_done(out_dir, "repair", "", info)
    if records.read_record(out_dir, "repair"):
        report.stages["repair"] = records.done_info(out_dir, "repair")


def _handle_orientation(mode: str, images: ImageSet, out_dir: Path, progress: bool) -> ImageSet:
    if mode not in ("ignore", "apply"):
        raise ValueError(f"images.exif_orientation must be ignore or apply, not {mode!r}")
    if not images.orientation:
        return images
    if mode == "apply":
        logger.warning("%d images carry an EXIF rotation: reconstructing from upright copies in %s",
                       len(images.orientation), out_dir / "images_upright")
        return upright_copy(images, out_dir / "images_upright", progress=progress)
    logger.warning("%d images carry an EXIF rotation (e.g. %s); like COLMAP, sara uses the stored pixels. "
                   "Use -s images.exif_orientation=apply for upright copies", len(images.orientation),
                   next(iter(images.orientation)))
    return images


def render_report(report: RunReport) -> str:
    """A short human-readable summary of a run (Markdown)."""
    s = report.stages
    lines = [f"# sara run: {report.out_dir.name}", "",
             f"Images: {s['images']['num_images']} used, {s['images']['num_skipped']} skipped "
             f"(from `{report.images_root}`)", ""]
    lines += ["| stage | time (s) | result |", "|---|---:|---|"]
    ex, pr, ma, mp = s.get("extract", {}), s.get("pairs", {}), s.get("match", {}), s.get("map", {})
    lines.append(f"| extract | {ex.get('time_s', 0):.1f} | {ex.get('keypoints_mean', 0):.0f} keypoints per image |")
    lines.append(f"| pairs ({pr.get('method')}) | {pr.get('time_s', 0):.1f} | {pr.get('num_pairs', 0)} pairs "
                 f"({100 * pr.get('fraction_of_exhaustive', 0):.1f}% of exhaustive) |")
    lines.append(f"| match | {ma.get('time_s', 0):.1f} | {ma.get('num_verified_pairs', 0)} verified pairs, "
                 f"{ma.get('inlier_matches_per_pair_mean', 0):.0f} inlier matches per pair |")
    lines.append(f"| map | {mp.get('time_s', 0):.1f} | {mp.get('num_components', 0)} model(s): "
                 f"{mp.get('component_sizes', [])} images registered |")
    if report.skipped_images:
        lines += ["", "Skipped images:", ""] + [f"- `{n}`: {r}" for n, r in report.skipped_images.items()]
    if report.metrics:
        from .evaluate import format_table

        lines += ["", "## Accuracy against ground truth", "", "```", format_table(report.metrics), "```"]
    return "\n".join(lines) + "\n"


def load_run(out_dir: Path) -> dict[str, Any]:
    path = Path(out_dir) / "run.json"
    if not path.exists():
        raise FileNotFoundError(f"{out_dir} holds no sara run (no run.json); run `sara run` or `sara extract` first")
    return read_json(path)
