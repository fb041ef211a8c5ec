"""Single stages on an existing output folder (`sara match OUT`, `sara map OUT`), and giving an
output folder the features of another (bench methods and the demo share one extraction)."""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
from pathlib import Path
from typing import Any

from .. import colmap, extract, incremental, mapping, match
from ..config import PipelineConfig
from ..features import features_file_name
from ..io import (
    DamagedOutputError,
    IncompleteStageError,
    OutputLock,
    link_or_copy,
    read_json,
    records,
    write_text_atomic,
)
from ..io.images import folder_mismatch
from . import pairs_stage
from .record import RunReport, render_report
from .run import finish_update, map_model, match_pairs, preflight, recover

logger = logging.getLogger(__name__)

PAIRS_NAME = pairs_stage.PAIRS_NAME
PAIRS_STAGE = pairs_stage.STAGE


def load_run(out_dir: Path) -> dict[str, Any]:
    path = Path(out_dir) / "run.json"
    if not path.exists():
        raise FileNotFoundError(f"{out_dir} holds no sara run (no run.json); run `sara run` or `sara extract` first")
    return read_json(path)


def _require_database(out_dir: Path, hint: str) -> Path:
    """OUT's database; a missing OUT is bad usage (exit 2), an OUT where the extract stage never
    made one is an earlier stage unfinished (exit 3, as `sara map` after an unfinished match)."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise FileNotFoundError(f"output folder not found: {out_dir} ({hint})")
    db = out_dir / extract.DB_NAME
    if not db.exists():
        raise IncompleteStageError(f"the extract stage in {out_dir} never ran (no {db.name}): {hint}")
    return db


def _require_finished(out_dir: Path, stage: str, command: str) -> dict[str, Any]:
    record = records.read_record(out_dir, stage)
    if record is None or record.get("done") is not True:
        state = "never ran" if record is None else "did not finish (stopped or killed)"
        raise IncompleteStageError(f"the {stage} stage in {out_dir} {state}: run `{command}` first")
    return record


def match_only(conf: PipelineConfig, out_dir: Path, pairs_path: Path | None = None, *, progress: bool = True,
               verbose_colmap: bool = False, overwrite: bool = False) -> dict[str, Any]:
    """`sara match OUT`: match a pairs file (default OUT/pairs.txt) into OUT's database (with
    `overwrite`, every pair matched again)."""
    out_dir = Path(out_dir)
    db = _require_database(out_dir, f"run `sara extract IMAGES {out_dir}` first")
    pairs_path = Path(pairs_path or out_dir / PAIRS_NAME)
    if pairs_path.is_dir():
        raise IsADirectoryError(f"--pairs {pairs_path}: a folder, not a pairs file ('name0 name1' per line)")
    preflight(dataclasses.replace(conf, pairs=dataclasses.replace(conf.pairs, method="exhaustive")))
    with OutputLock(out_dir, clean=True):
        recover(out_dir)
        record = _require_finished(out_dir, extract.STAGE, f"sara extract IMAGES {out_dir}")
        backend = record.get("info", {}).get("backend", conf.extract.backend)
        if backend != conf.extract.backend:
            raise ValueError(f"{out_dir} holds {backend} features, not {conf.extract.backend}: give the options of "
                             "the extraction (--preset, -s extract.backend=...)")
        selected = records.read_record(out_dir, PAIRS_STAGE)
        if pairs_path == out_dir / PAIRS_NAME and selected is not None:
            # a changed pairs.txt of the pairs stage is not matched silently
            pairs_stage.pairs_intact(out_dir, selected.get("key", ""))
        colmap.send_log_to(out_dir / "logs", verbose=verbose_colmap)
        features = out_dir / features_file_name(conf.extract)
        # a pending update (`sara extract` on a changed folder): pairs matched before are copied
        reserve = None if overwrite else incremental.earlier_matches(out_dir, record.get("key", ""))
        before = records.read_record(out_dir, match.STAGE)
        work = match_pairs(conf, pairs_path, features, out_dir, progress=progress, beside=True, overwrite=overwrite,
                           reserve=reserve)
        match.commit(work, db, out_dir)
        if records.read_record(out_dir, match.STAGE) != before:  # matched now, not found up to date
            _record_in_run(out_dir, conf, match.STAGE)
    return records.done_info(out_dir, match.STAGE)


def map_only(conf: PipelineConfig, out_dir: Path, images_root: Path | None = None, *, progress: bool = True,
             verbose_colmap: bool = False, overwrite: bool = False) -> dict[str, Any]:
    """`sara map OUT`: map OUT's database into OUT/sparse (images: the folder recorded in run.json;
    with `overwrite`, mapped again even when the model is up to date).

    Refuses when the match stage did not finish, or when the database no longer holds the matches
    it recorded: an unfinished match is never mapped as if it were complete.
    """
    out_dir = Path(out_dir)
    db = _require_database(out_dir, "run `sara extract` and `sara match` first")
    given = images_root is not None
    images_root = Path(images_root or load_run(out_dir)["images_root"])
    if not images_root.is_dir():
        raise FileNotFoundError(f"image folder {images_root} not found: give it with --images")
    _check_image_folder(out_dir, images_root, f"--images {images_root}" if given else f"the image folder {images_root}")
    preflight(dataclasses.replace(conf, pairs=dataclasses.replace(conf.pairs, method="exhaustive")))
    with OutputLock(out_dir, clean=True):
        recover(out_dir)
        record = _require_finished(out_dir, match.STAGE, f"sara match {out_dir}")
        try:
            now = match.matches_digest(db)
        except DamagedOutputError as exc:
            raise DamagedOutputError(f"{exc}; run `sara run` again with --overwrite to redo it") from None
        recorded = record.get("outputs", {}).get(match.DB_NAME)
        if recorded is not None and recorded != now:
            raise IncompleteStageError(f"{db} no longer holds the matches of the last match stage (changed, or a "
                                       f"run stopped before it finished): run `sara match {out_dir}` first")
        colmap.send_log_to(out_dir / "logs", verbose=verbose_colmap)
        # a pending update continues the earlier model, as `sara run` does, and is closed
        extract_key = (records.read_record(out_dir, extract.STAGE) or {}).get("key", "")
        start = incremental.start_model(out_dir, extract_key) if conf.rounds.extend_model and not overwrite else None
        before = records.read_record(out_dir, mapping.STAGE)
        map_model(conf, images_root, out_dir, progress=progress, overwrite=overwrite, input_model=start)
        finish_update(out_dir, extract_key)
        after = records.read_record(out_dir, mapping.STAGE)
        if after != before:  # mapped now, not found up to date
            changed = (after or {}).get("outputs") != (before or {}).get("outputs")
            _record_in_run(out_dir, conf, mapping.STAGE, model_changed=changed)
    return records.done_info(out_dir, mapping.STAGE)


#: where `sara map` moves the accuracy of the model it replaced
EARLIER_METRICS = "metrics.earlier.json"


def _record_in_run(out_dir: Path, conf: PipelineConfig, stage: str, *, model_changed: bool = False) -> None:
    """After `sara match` or `sara map`: run.json and report.md describe the stage as it ran now (its
    record, and the settings it ran with in place of the run's), so that the report of the folder is
    the report of what it holds. A new model makes the accuracy measured on the one before it stale:
    metrics.json is moved to EARLIER_METRICS and run.json's metrics are dropped."""
    path = out_dir / "run.json"
    if not path.exists():
        return
    run = read_json(path)
    report = RunReport(out_dir, Path(run["images_root"]), {**run.get("config", {}), stage: conf.to_dict()[stage]},
                       stages={**run.get("stages", {}), stage: records.done_info(out_dir, stage)},
                       skipped_images=run.get("skipped_images", {}), metrics=run.get("metrics"))
    if model_changed and (report.metrics or (out_dir / "metrics.json").exists()):
        report.metrics = None
        if (out_dir / "metrics.json").exists():
            os.replace(out_dir / "metrics.json", out_dir / EARLIER_METRICS)
        logger.warning("map: a new model: the accuracy measured on the one before it is in %s; measure this one "
                       "with `sara evaluate %s GT --json %s`", EARLIER_METRICS, out_dir, out_dir / "metrics.json")
    report.save()
    if "images" in report.stages:  # written by every run that got past extraction
        write_text_atomic(out_dir / "report.md", render_report(report))


def _check_image_folder(out_dir: Path, images_root: Path, what: str) -> None:
    """The images mapping reads (for the colours of the points) must be those the features were
    made from: another scene's folder, or one whose images share their names only, is refused."""
    upright = out_dir / "images_upright"  # EXIF-rotated images re-encoded upright by sara
    rotated = frozenset(p.relative_to(upright).as_posix() for p in upright.rglob("*")
                        if p.is_file() and not p.is_symlink()) if upright.is_dir() else frozenset()
    problem = folder_mismatch(images_root, out_dir / ".sara" / extract.DIGESTS_NAME, rotated=rotated)
    if problem is not None:
        raise ValueError(f"{what} does not hold the images {out_dir} was made from: {problem}; "
                         "give the image folder of the extraction with --images")


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
    colmap.remove_database(out_dir / extract.DB_NAME)
    colmap.copy_database(features_dir / extract.DB_NAME, out_dir / extract.DB_NAME)
    link_or_copy(features_dir / features_name, out_dir / features_name)
    records.mark_done(out_dir, extract.STAGE, source["key"], source.get("info", {}), outputs=source.get("outputs"))
    return True

