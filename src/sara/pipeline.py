"""`sara run`: images -> features -> pairs -> matches -> sparse model (-> evaluation), resumable.

Files are the contract between stages; each stage reads what the one before wrote:

    features-<backend>.h5, database.db   extract (the database: images, cameras, keypoints)
    pairs.txt (+ scores.csv,             pairs (SARA also writes its scores and global descriptors)
      global-<descriptor>.h5)
    database.db                          match (matches and verified two-view geometries)
    sparse/0, sparse/1, ...              map (0 is the largest model)
    metrics.json                         with a ground truth
    run.json, report.md                  configuration, versions, per-stage times and counts
    logs/                                COLMAP's own log

After mapping, a pair source may ask for more pairs (SARA's repair of views left out of the
main model); they are matched and the model mapped again, and `pairs.txt` and the records then
say what was really matched.
"""

from __future__ import annotations

import logging
import os
import platform
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from . import __version__, colmap, extract, mapping, match
from .config import PipelineConfig
from .execute import Executor, make_executor
from .features import features_file_name
from .io import (
    OutputLock,
    atomic_path,
    fingerprint,
    read_json,
    records,
    write_json_atomic,
    write_text_atomic,
)
from .io.images import ImageSet, scan_images, upright_copy
from .io.pairs import read_pairs, write_pairs
from .pairs import SOURCES, PairContext, get_after_mapping, get_source
from .tables import markdown_table

logger = logging.getLogger(__name__)

PAIRS_STAGE = "pairs"
PAIRS_NAME = "pairs.txt"
AFTER_MAPPING_STAGE = "repair"


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


# ---------------------------------------------------------------------------------------------
# Stage `pairs`
# ---------------------------------------------------------------------------------------------


def pairs_key(conf: PipelineConfig, extract_key: str, source_file: Path | None) -> str:
    data: dict[str, Any] = {"extract": extract_key, "pairs": conf.pairs.__dict__, "seed": conf.seed}
    if conf.pairs.method == "sara" or conf.pairs.sequential_loop_detection or conf.pairs.method == "retrieval":
        data.update(retrieval=conf.retrieval.__dict__, score=conf.score.__dict__, graph=conf.graph.__dict__)
    if source_file is not None:
        data["file"] = source_file.read_text(encoding="utf-8", errors="replace")
    return fingerprint(data)


def pair_source_file(method: str) -> Path | None:
    """None for a named pair source; the path for a pairs file (FileNotFoundError when neither)."""
    if method in SOURCES:
        return None
    path = Path(method)
    if not path.is_file():
        raise FileNotFoundError(f"--pairs {method}: not a pair source ({', '.join(SOURCES)}) and no such pairs file")
    return path


def pair_context(conf: PipelineConfig, images: ImageSet, features_path: Path, out_dir: Path, *,
                 executor: Executor | None = None, progress: bool = True) -> PairContext:
    return PairContext(names=images.names, images_root=images.root, features_path=features_path,
                       db_path=out_dir / extract.DB_NAME, out_dir=out_dir, conf=conf, progress=progress,
                       executor=executor)


def select_pairs(conf: PipelineConfig, images: ImageSet, features_path: Path, out_dir: Path, *,
                 executor: Executor | None = None, overwrite: bool = False, progress: bool = True) -> Path:
    """Stage `pairs`: write `pairs.txt` from the configured source; returns its path."""
    method = conf.pairs.method
    source_file = pair_source_file(method)
    key = pairs_key(conf, (records.read_record(out_dir, extract.STAGE) or {}).get("key", ""), source_file)
    pairs_path = out_dir / PAIRS_NAME
    if not overwrite and records.is_done(out_dir, PAIRS_STAGE, key) and pairs_path.exists():
        logger.info("pairs: %s up to date, skipping", pairs_path)
        return pairs_path
    records.mark_started(out_dir, PAIRS_STAGE, key)
    records.clear(out_dir, AFTER_MAPPING_STAGE)
    tic = time.perf_counter()
    if source_file is not None:
        pairs = read_pairs(source_file, known_names=images.names)
        info: dict[str, Any] = {"source": str(source_file)}
    else:
        ctx = pair_context(conf, images, features_path, out_dir, executor=executor, progress=progress)
        result = get_source(method)(ctx)
        pairs, info = result.pairs, {**result.info, "timings_s": result.timings_s}
    write_pairs(pairs_path, pairs)
    n = len(images.names)
    info.update(method=method, num_pairs=len(pairs), num_selected=len(pairs), time_s=time.perf_counter() - tic,
                fraction_of_exhaustive=len(pairs) / max(1, n * (n - 1) // 2))
    records.mark_done(out_dir, PAIRS_STAGE, key, info)
    return pairs_path


# ---------------------------------------------------------------------------------------------
# Matching and mapping, and the rounds after mapping
# ---------------------------------------------------------------------------------------------


def match_pairs(conf: PipelineConfig, pairs_path: Path, features_path: Path, out_dir: Path, *,
                executor: Executor | None = None, progress: bool = True) -> Path:
    """Stage `match` with this run's matcher; returns the database."""
    return match.run(conf.match, pairs_path, out_dir / extract.DB_NAME, out_dir, features_path=features_path,
                     features_backend=conf.extract.backend, executor=executor, progress=progress)


def map_model(conf: PipelineConfig, images_root: Path, out_dir: Path, *, progress: bool = True) -> Path:
    """Stage `map` on the matches now in the database; returns `sparse/`."""
    upstream = (records.read_record(out_dir, match.STAGE) or {}).get("key", "")
    return mapping.run(conf.map, out_dir / extract.DB_NAME, images_root, out_dir, seed=conf.seed,
                       upstream_key=upstream, progress=progress)


def after_mapping_rounds(conf: PipelineConfig, images: ImageSet, features_path: Path, out_dir: Path, *,
                         executor: Executor | None = None, progress: bool = True) -> dict[str, Any] | None:
    """Let the pair source look at the model and ask for more pairs; match them and map again.

    Up to `pairs.repair_rounds` rounds. `pairs.txt` then lists every pair matched, and the pairs
    record says how many were added. Returns the round record's info (None when no round ran).
    """
    step = get_after_mapping(conf.pairs.method)
    if step is None or conf.pairs.repair_rounds <= 0:
        return None
    pairs_path = out_dir / PAIRS_NAME
    ctx = pair_context(conf, images, features_path, out_dir, executor=executor, progress=progress)
    info = records.done_info(out_dir, AFTER_MAPPING_STAGE) or {
        "rounds": 0, "pairs_added": 0, "time_s": 0.0,  # time of the extra rounds
        # match and map time of the whole run: the first round, then each extra one added
        "match_time_s": records.done_info(out_dir, match.STAGE).get("time_s", 0.0),
        "map_time_s": records.done_info(out_dir, mapping.STAGE).get("time_s", 0.0)}
    while info["rounds"] < conf.pairs.repair_rounds:
        pairs = read_pairs(pairs_path, known_names=images.names)
        extra = step(ctx, pairs, out_dir / "sparse" / "0")
        if not extra:
            break
        tic = time.perf_counter()
        write_pairs(pairs_path, pairs + extra)
        _add_to_pairs_record(out_dir, len(extra))
        match_pairs(conf, pairs_path, features_path, out_dir, executor=ctx.executor, progress=progress)
        map_model(conf, images.root, out_dir, progress=progress)
        info["rounds"] += 1
        info["pairs_added"] += len(extra)
        info["time_s"] += time.perf_counter() - tic
        info["match_time_s"] += records.done_info(out_dir, match.STAGE).get("time_s", 0.0)
        info["map_time_s"] += records.done_info(out_dir, mapping.STAGE).get("time_s", 0.0)
        records.mark_done(out_dir, AFTER_MAPPING_STAGE, "", info)
    return info if info["rounds"] else None


def _add_to_pairs_record(out_dir: Path, num_added: int) -> None:
    record = records.read_record(out_dir, PAIRS_STAGE) or {}
    info = record.get("info", {})
    info["num_added_after_mapping"] = info.get("num_added_after_mapping", 0) + num_added
    info["num_pairs"] = info.get("num_selected", info.get("num_pairs", 0)) + info["num_added_after_mapping"]
    records.mark_done(out_dir, PAIRS_STAGE, record.get("key", ""), info)


# ---------------------------------------------------------------------------------------------
# The whole pipeline
# ---------------------------------------------------------------------------------------------


def run(conf: PipelineConfig, images_root: Path, out_dir: Path, *, gt_dir: Path | None = None,
        overwrite: bool = False, progress: bool = True, verbose_colmap: bool = False,
        stop_after: str | None = None) -> RunReport:
    """The whole pipeline; every stage skips work already done, so a re-run resumes.

    stop_after: "extract" or "pairs" to run only the stages up to that one.
    """
    if stop_after not in (None, "extract", "pairs"):
        raise ValueError(f"stop_after must be extract or pairs, not {stop_after!r}")
    out_dir, images_root = Path(out_dir), Path(images_root)
    if gt_dir is not None and not Path(gt_dir).exists():
        raise FileNotFoundError(f"ground-truth folder not found: {gt_dir}")
    pair_source_file(conf.pairs.method)  # a bad --pairs fails before any work
    images = scan_images(images_root, recursive=conf.images.recursive, progress=progress)
    out_dir.mkdir(parents=True, exist_ok=True)
    executor = make_executor(conf.execute.executor, conf.execute.workers, conf.execute.ray_address)
    try:
        with OutputLock(out_dir):
            return _run_stages(conf, images, images_root, out_dir, executor, gt_dir=gt_dir, overwrite=overwrite,
                               progress=progress, verbose_colmap=verbose_colmap, stop_after=stop_after)
    finally:
        executor.close()


def _run_stages(conf: PipelineConfig, images: ImageSet, images_root: Path, out_dir: Path, executor: Executor, *,
                gt_dir: Path | None, overwrite: bool, progress: bool, verbose_colmap: bool,
                stop_after: str | None) -> RunReport:
    images = _handle_orientation(conf.images.exif_orientation, images, out_dir, progress)
    colmap.send_log_to(out_dir / "logs", verbose=verbose_colmap)
    colmap.set_seed(conf.seed)
    report = RunReport(out_dir, images_root, conf.to_dict(), skipped_images=images.skipped)
    report.stages["images"] = {"num_images": len(images.names), "num_skipped": len(images.skipped)}
    tic = time.perf_counter()
    features = extract.run(conf.extract, images, out_dir, executor=executor, overwrite=overwrite, progress=progress)
    report.stages["extract"] = {**records.done_info(out_dir, extract.STAGE), "time_s": time.perf_counter() - tic}
    report.save()
    if stop_after == "extract":
        return report
    pairs_path = select_pairs(conf, images, features, out_dir, executor=executor, progress=progress)
    report.stages["pairs"] = records.done_info(out_dir, PAIRS_STAGE)
    report.save()
    if stop_after == "pairs":
        return report
    match_pairs(conf, pairs_path, features, out_dir, executor=executor, progress=progress)
    report.stages["match"] = records.done_info(out_dir, match.STAGE)
    report.save()
    map_model(conf, images.root, out_dir, progress=progress)
    report.stages["map"] = records.done_info(out_dir, mapping.STAGE)
    _collect_after_mapping(report, after_mapping_rounds(conf, images, features, out_dir, executor=executor,
                                                        progress=progress))
    if gt_dir is not None:
        from .evaluation import evaluate

        report.metrics = evaluate(out_dir / "sparse", Path(gt_dir), out_dir / "metrics.json")
    report.save()
    write_text_atomic(out_dir / "report.md", render_report(report))
    return report


def _collect_after_mapping(report: RunReport, info: dict[str, Any] | None) -> None:
    """The records after every round; stage times then count every round."""
    out_dir = report.out_dir
    info = info or records.done_info(out_dir, AFTER_MAPPING_STAGE) or None
    report.stages["pairs"] = records.done_info(out_dir, PAIRS_STAGE)
    report.stages["match"] = records.done_info(out_dir, match.STAGE)
    report.stages["map"] = records.done_info(out_dir, mapping.STAGE)
    if info and info.get("rounds"):
        report.stages["repair"] = info
        report.stages["match"]["time_s"] = info["match_time_s"]
        report.stages["map"]["time_s"] = info["map_time_s"]


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


# ---------------------------------------------------------------------------------------------
# Single stages on an existing output folder (`sara match OUT`, `sara map OUT`)
# ---------------------------------------------------------------------------------------------


def load_run(out_dir: Path) -> dict[str, Any]:
    path = Path(out_dir) / "run.json"
    if not path.exists():
        raise FileNotFoundError(f"{out_dir} holds no sara run (no run.json); run `sara run` or `sara extract` first")
    return read_json(path)


def _require_database(out_dir: Path, hint: str) -> Path:
    db = Path(out_dir) / extract.DB_NAME
    if not db.exists():
        raise FileNotFoundError(f"{db} not found: {hint}")
    return db


def match_only(conf: PipelineConfig, out_dir: Path, pairs_path: Path | None = None, *, progress: bool = True,
               verbose_colmap: bool = False) -> dict[str, Any]:
    """`sara match OUT`: match a pairs file (default OUT/pairs.txt) into OUT's database."""
    out_dir = Path(out_dir)
    _require_database(out_dir, f"run `sara extract IMAGES {out_dir}` first")
    features = out_dir / features_file_name(conf.extract)
    with OutputLock(out_dir):
        colmap.send_log_to(out_dir / "logs", verbose=verbose_colmap)
        match_pairs(conf, Path(pairs_path or out_dir / PAIRS_NAME), features, out_dir, progress=progress)
    return records.done_info(out_dir, match.STAGE)


def map_only(conf: PipelineConfig, out_dir: Path, images_root: Path | None = None, *, progress: bool = True,
             verbose_colmap: bool = False) -> dict[str, Any]:
    """`sara map OUT`: map OUT's database into OUT/sparse (images: the folder recorded in run.json)."""
    out_dir = Path(out_dir)
    _require_database(out_dir, "run `sara extract` and `sara match` first")
    images_root = Path(images_root or load_run(out_dir)["images_root"])
    with OutputLock(out_dir):
        colmap.send_log_to(out_dir / "logs", verbose=verbose_colmap)
        map_model(conf, images_root, out_dir, progress=progress)
    return records.done_info(out_dir, mapping.STAGE)


def share_features(features_dir: Path, out_dir: Path) -> bool:
    """Give `out_dir` the features of another output folder: the database (features only), the
    features file (hard-linked) and the extract record, so that several runs (bench methods, the
    demo) share one extraction.

    Kept as it is when it already holds these very features (a re-run resumes); otherwise its stage
    records are cleared so that no stage is skipped on matches of other features. Returns True when
    the features were (re)copied.
    """
    features_dir, out_dir = Path(features_dir), Path(out_dir)
    source = records.read_record(features_dir, extract.STAGE)
    if source is None or source.get("done") is not True:
        raise FileNotFoundError(f"no finished feature extraction in {features_dir}")
    features_name = source.get("info", {}).get("features", "features-sift.h5")
    current = records.read_record(out_dir, extract.STAGE)
    if (current is not None and current.get("key") == source["key"] and current.get("done") is True
            and (out_dir / extract.DB_NAME).exists() and (out_dir / features_name).exists()):
        return False
    shutil.rmtree(out_dir / ".sara", ignore_errors=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    colmap.copy_database(features_dir / extract.DB_NAME, out_dir / extract.DB_NAME)
    _link_or_copy(features_dir / features_name, out_dir / features_name)
    records.mark_done(out_dir, extract.STAGE, source["key"], source.get("info", {}))
    return True


def _link_or_copy(src: Path, dst: Path) -> None:
    """Hard-link a read-only input into another folder; copy across file systems."""
    dst.unlink(missing_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        with atomic_path(dst) as tmp:
            shutil.copyfile(src, tmp)


# ---------------------------------------------------------------------------------------------
# report.md
# ---------------------------------------------------------------------------------------------


def render_report(report: RunReport) -> str:
    """A short human-readable summary of a run (Markdown)."""
    s = report.stages
    ex, pr, ma, mp = s.get("extract", {}), s.get("pairs", {}), s.get("match", {}), s.get("map", {})
    added = pr.get("num_added_after_mapping", 0)
    rows = [
        [f"extract ({ex.get('backend', 'sift')})", f"{ex.get('time_s', 0):.1f}",
         f"{ex.get('keypoints_mean', 0):.0f} keypoints per image"],
        [f"pairs ({pr.get('method')})", f"{pr.get('time_s', 0):.1f}",
         f"{pr.get('num_pairs', 0)} pairs ({100 * pr.get('fraction_of_exhaustive', 0):.1f}% of exhaustive)"
         + (f", {added} of them added after mapping" if added else "")],
        [f"match ({ma.get('matcher', '')})", f"{ma.get('time_s', 0):.1f}",
         f"{ma.get('num_verified_pairs', 0)} verified pairs, "
         f"{ma.get('inlier_matches_per_pair_mean', 0):.0f} inlier matches per pair"],
        ["map", f"{mp.get('time_s', 0):.1f}",
         f"{mp.get('num_components', 0)} model(s): {mp.get('component_sizes', [])} images registered"],
    ]
    lines = [f"# sara run: {report.out_dir.name}", "",
             f"Images: {s['images']['num_images']} used, {s['images']['num_skipped']} skipped "
             f"(from `{report.images_root}`)", "", markdown_table(["stage", "time (s)", "result"], rows)]
    if report.skipped_images:
        lines += ["", "Skipped images:", ""] + [f"- `{n}`: {r}" for n, r in report.skipped_images.items()]
    if report.metrics:
        from .evaluation import format_table

        lines += ["", "## Accuracy against ground truth", "", "```", format_table(report.metrics), "```"]
    return "\n".join(lines) + "\n"
