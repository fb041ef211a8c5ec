"""`sara run`: images -> features -> pairs -> matches -> (rounds) -> sparse model -> evaluation.

`run` checks every option and name before any work, then `_run_stages` runs the stages in order;
each skips work already done, so a re-run resumes.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from .. import colmap, extract, incremental, mapping, masks, match, video, weights
from ..config import PipelineConfig, apply_overrides
from ..execute import Executor, make_executor
from ..features import BACKENDS as FEATURE_BACKENDS
from ..io import NoResultError, OutputLock, fingerprint, prepare_output_dir, records, write_text_atomic
from ..io.images import ImageSet, scan_images, upright_copy
from ..io.pairs import read_pairs
from ..matchers import BACKENDS as MATCHER_BACKENDS
from ..matchers import resolve_name
from ..pairs import get_source
from ..retrieval import DESCRIPTORS
from . import advice, pairs_stage, rounds
from .record import RunReport, collect_stages, render_report

logger = logging.getLogger(__name__)


def run(conf: PipelineConfig, images_root: Path, out_dir: Path, *, gt_dir: Path | None = None,
        overwrite: bool = False, progress: bool = True, verbose_colmap: bool = False,
        stop_after: str | None = None) -> RunReport:
    """The whole pipeline; every stage skips work already done, so a re-run resumes.

    stop_after: "extract" or "pairs" to run only the stages up to that one.
    """
    if stop_after not in (None, "extract", "pairs"):
        raise ValueError(f"stop_after must be extract or pairs, not {stop_after!r}")
    out_dir, images_root = Path(out_dir), Path(images_root)
    if conf.extract.mask_path:  # recorded whole in run.json: an export from another folder finds the masks
        conf = apply_overrides(conf, {"extract.mask_path": str(Path(conf.extract.mask_path).expanduser().resolve())})
    preflight(conf, extract_only=stop_after == "extract")  # a bad option or --pairs fails before any work
    if gt_dir is not None:
        _check_ground_truth(Path(gt_dir), images_root)
    images = scan_images(images_root, recursive=conf.images.recursive, progress=progress, out_dir=out_dir)
    if stop_after != "extract" and len(images.names) < 2:
        raise ValueError(f"only one usable image in {images_root} ({images.names[0]}): a reconstruction needs "
                         "at least 2")
    if gt_dir is not None:
        _check_ground_truth(Path(gt_dir), images_root, images.names)
    masks.check(conf.extract.mask_path, images, upright=conf.images.exif_orientation == "apply")  # before any work
    pairs_file = pairs_stage.pair_source_file(conf.pairs.method)
    if pairs_file is not None and stop_after != "extract":
        read_pairs(pairs_file, known_names=images.names)  # unreadable, or naming other images: before any work
    prepare_output_dir(out_dir)
    executor = make_executor(conf.execute.executor, conf.execute.workers, conf.execute.ray_address)
    try:
        with OutputLock(out_dir, clean=True):
            recover(out_dir)
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
    first_run = not (out_dir / "run.json").exists()
    groups = video.camera_groups(out_dir, images_root)  # frame -> its video, for a run on videos
    if overwrite:
        incremental.discard(out_dir)
    else:  # images added, removed or changed since the last run: only they are extracted
        incremental.update_features(conf.extract, images, out_dir, executor=executor, progress=progress,
                                    camera_groups=groups)
    features = extract.run(conf.extract, images, out_dir, executor=executor, overwrite=overwrite, progress=progress,
                           camera_groups=groups)
    images = extract.usable(images, out_dir)
    report = RunReport(out_dir, images_root, conf.to_dict(), skipped_images=images.skipped)
    report.stages["images"] = {"num_images": len(images.names), "num_skipped": len(images.skipped)}
    if groups:  # the frames of a video run: where they came from
        report.stages["video"] = video.summary(out_dir)
    report.stages["extract"] = records.done_info(out_dir, extract.STAGE)  # its time_s: when it really ran
    if stop_after != "extract" and advice.warn_low_texture(report.stages["extract"], conf.extract.backend):
        report.stages["extract"] = {**report.stages["extract"], "low_texture": True}
    if stop_after != "extract" and (guessed := advice.guessed_cameras(report.stages["extract"])):
        logger.warning(guessed)
    report.stages["extract"] = {**report.stages["extract"], "panoramas": advice.count_panoramas(images.sizes)}
    if stop_after != "extract" and (wide := advice.panoramas(report.stages["extract"])):
        logger.warning(wide)
    if first_run or stop_after == "extract":
        report.save()  # `sara map OUT` finds the images through run.json
    if stop_after == "extract":
        return report
    pairs_path = pairs_stage.run(conf, images, features, out_dir, executor=executor, overwrite=overwrite,
                                 progress=progress)
    report.stages["pairs"] = records.done_info(out_dir, pairs_stage.STAGE)
    if stop_after == "pairs":
        report.save()
        return report
    extract_key = (records.read_record(out_dir, extract.STAGE) or {}).get("key", "")
    reserve = incremental.earlier_matches(out_dir, extract_key)
    source_rounds = _rounds_run(conf, images, features, out_dir, executor, progress, extract_key, reserve)
    work = match_pairs(conf, pairs_path, features, out_dir, executor=executor, progress=progress, beside=True,
                       overwrite=overwrite, reserve=reserve)
    staged = None
    if source_rounds is not None:
        work, staged = rounds.before_mapping(source_rounds, work)
    start = incremental.start_model(out_dir, extract_key) if conf.rounds.extend_model else None
    map_model(conf, images.root, out_dir, db_path=work, progress=progress, overwrite=overwrite,
              commit_round=(lambda: rounds.commit_staged(source_rounds, staged)) if staged else None,
              input_model=start)
    if source_rounds is not None:
        rounds.after_mapping(source_rounds)
    collect_stages(report, pairs_stage.current_key(conf, out_dir))
    if ahead := advice.forward_guess(report.stages.get("extract", {}), report.stages.get("map", {})):
        logger.warning(ahead)
    update = finish_update(out_dir, extract_key)
    if update is not None:
        report.stages["update"] = update
    if gt_dir is not None:
        from ..evaluation import evaluate

        report.metrics = evaluate(out_dir / "sparse", Path(gt_dir), out_dir / "metrics.json")
    report.save()
    write_text_atomic(out_dir / "report.md", render_report(report))
    return report


def _rounds_run(conf: PipelineConfig, images: ImageSet, features: Path, out_dir: Path, executor: Executor,
                progress: bool, extract_key: str, reserve: Path | None = None) -> rounds.RoundsRun | None:
    """The pair source's rounds around mapping, ready to run (None when it has none, or when an update
    only renamed images: the earlier rounds' pairs stand, and the model they made is continued)."""
    source = get_source(conf.pairs.method) if pairs_stage.pair_source_file(conf.pairs.method) is None else None
    if source is None or source.rounds is None or incremental.renamed_only(incremental.pending(out_dir, extract_key)):
        return None
    ctx = pairs_stage.pair_context(conf, images, features, out_dir, executor=executor, progress=progress)
    return rounds.RoundsRun(source.rounds, ctx, conf, out_dir, pairs_stage.current_key(conf, out_dir), progress,
                            reserve)


def finish_update(out_dir: Path, extract_key: str) -> dict[str, Any] | None:
    """Close a pending incremental update once its model is in place; its counts (None: no update)."""
    return incremental.finish(out_dir, extract_key, _update_counts(out_dir, extract_key))


def _update_counts(out_dir: Path, extract_key: str) -> dict[str, int]:
    """What a pending incremental update redid after extraction: pairs scored and matched."""
    update = incremental.pending(out_dir, extract_key)
    if update is None:
        return {}
    kept, _, _ = incremental.kept_pairs(out_dir, update)
    selected = records.done_info(out_dir, pairs_stage.STAGE)
    scored = selected.get("num_candidates_scored", selected.get("num_candidates", 0))
    final = {tuple(sorted(p)) for p in read_pairs(out_dir / pairs_stage.PAIRS_NAME)}
    earlier = {tuple(sorted(p)) for p in kept}  # matched before the update
    return {"num_pairs_scored": scored, "num_pairs_kept": len(final & earlier),
            "num_pairs_dropped": len(earlier - final), "num_pairs_matched": len(final - earlier)}


def match_pairs(conf: PipelineConfig, pairs_path: Path, features_path: Path, out_dir: Path, *,
                executor: Executor | None = None, progress: bool = True, beside: bool = False,
                overwrite: bool = False, reserve: Path | None = None) -> Path:
    """Stage `match` with this run's matcher; returns the database that holds the matches (with
    `beside`, possibly a copy to `match.commit` once mapping succeeded; `reserve`: earlier matches
    to take pairs from, see `match.run`)."""
    return match.run(conf.match, pairs_path, out_dir / extract.DB_NAME, out_dir, features_path=features_path,
                     features_backend=conf.extract.backend, executor=executor, progress=progress, beside=beside,
                     overwrite=overwrite, reserve=reserve)


def map_model(conf: PipelineConfig, images_root: Path, out_dir: Path, *, db_path: Path | None = None,
              progress: bool = True, overwrite: bool = False, commit_round: Any = None,
              input_model: Path | None = None) -> Path:
    """Stage `map` on the matches of `db_path` (default the output's database; a copy made by the
    match stage is moved into place just before the new model, with `commit_round`, the pairs a
    round matched before mapping); returns `sparse/`. A failed mapping keeps the previous
    matches and model. `input_model`: a model to continue from (an incremental update's)."""
    db = out_dir / extract.DB_NAME
    work = Path(db_path or db)
    upstream = fingerprint(match.matches_digest(work))

    def commit() -> None:
        match.commit(work, db, out_dir)
        if commit_round is not None:
            commit_round()

    starved = advice.starved(records.done_info(out_dir, extract.STAGE) or {}, conf.extract.backend)
    try:
        return mapping.run(conf.map, work, images_root, out_dir, seed=conf.seed, upstream_key=upstream,
                           progress=progress, min_num_inliers=conf.match.min_num_inliers, commit=commit,
                           overwrite=overwrite, input_model=input_model, starved=starved)
    except NoResultError:
        if work != db:
            colmap.remove_database(work)  # the previous matches stay with the previous model
        (out_dir / ".sara" / rounds.STAGED_PAIRS).unlink(missing_ok=True)
        raise


def recover(out_dir: Path) -> None:
    """Finish or undo what a run killed between two swaps left (call it holding the lock): the
    previous `sparse/` when the new one never arrived; a round's `pairs.txt` whose ledger was
    already written, and the map stage of a round whose mapping was killed; image names aliased
    for COLMAP's pair importer (before any stage compares the database with its record)."""
    match.restore_names([out_dir / extract.DB_NAME, out_dir / ".sara" / match.NEXT_DB_NAME], out_dir)
    mapping.recover(out_dir)
    rounds.recover(out_dir)


def preflight(conf: PipelineConfig, *, extract_only: bool = False) -> None:
    """Check every name the run will look up (backends, descriptor, pair source), before any work.

    Values in range are checked when the config is made; this checks the names that only the
    registries know, and finds every weight file the run will load (file-system look-ups only):
    a missing one fails in well under a second, not after the stages before it. `extract_only`
    (`sara extract`): the feature backend alone, without importing the pair sources and matchers.
    """
    if conf.extract.backend not in FEATURE_BACKENDS:
        raise ValueError(f"extract.backend must be one of {', '.join(FEATURE_BACKENDS)}, got {conf.extract.backend!r}")
    needed = list(_weights_needed(FEATURE_BACKENDS.get(conf.extract.backend), conf.extract))
    if not extract_only:
        needed += _later_stages_checked(conf)
    for key, explicit in needed:
        weights.find(key, explicit)


def _later_stages_checked(conf: PipelineConfig) -> list[tuple[str, str]]:
    """Check the names the stages after extraction look up (pair source, matcher, descriptor);
    returns the weights they need."""
    pairs_stage.pair_source_file(conf.pairs.method)
    matcher = resolve_name(conf.match, conf.extract.backend)
    if matcher not in MATCHER_BACKENDS:
        raise ValueError(f"match.backend must be auto or one of {', '.join(MATCHER_BACKENDS)}, got {matcher!r}")
    uses_retrieval = "retrieval" in pairs_stage.source_sections(conf)
    if uses_retrieval and conf.retrieval.descriptor not in DESCRIPTORS:
        raise ValueError(f"retrieval.descriptor must be one of {', '.join(DESCRIPTORS)}, "
                         f"got {conf.retrieval.descriptor!r}")
    needed = _weights_needed(MATCHER_BACKENDS.get(matcher), conf.match, conf.extract.backend)
    if uses_retrieval:
        needed += _weights_needed(DESCRIPTORS.get(conf.retrieval.descriptor), conf.retrieval)
    return needed


def _weights_needed(backend: Any, *args: Any) -> list[tuple[str, str]]:
    """The (weights key, explicit path) a backend declares through its `weights_needed`, if any."""
    declare = getattr(backend, "weights_needed", None)
    return list(declare(*args)) if declare is not None else []


def _check_ground_truth(gt_dir: Path, images_root: Path, names: list[str] | None = None) -> None:
    """A ground truth that does not exist, holds no model, or shares no image name with the images
    fails before any work."""
    if not gt_dir.exists():
        raise FileNotFoundError(f"ground truth not found: {gt_dir} (a COLMAP model folder or a transforms.json)")
    if names is None:
        return
    from ..evaluation import gt_image_names

    common = gt_image_names(gt_dir, names)
    if not common:
        raise ValueError(f"the ground truth {gt_dir} shares no image name with {images_root}: is it the ground "
                         "truth of another scene?")


def _handle_orientation(mode: str, images: ImageSet, out_dir: Path, progress: bool) -> ImageSet:
    """The images the stages read: with `apply`, EXIF-rotated ones from upright copies; HEIC,
    WebP and AVIF images (which COLMAP cannot read) from JPEG copies, both in `out_dir/images_upright`."""
    if mode not in ("ignore", "apply"):
        raise ValueError(f"images.exif_orientation must be ignore or apply, not {mode!r}")
    rotate = mode == "apply" and bool(images.orientation)
    if rotate:
        logger.warning("%d images carry an EXIF rotation: reconstructing from upright copies in %s",
                       len(images.orientation), out_dir / "images_upright")
    elif images.orientation:
        logger.warning("%d images carry an EXIF rotation (e.g. %s); like COLMAP, sara uses the stored pixels. "
                       "Use -s images.exif_orientation=apply for upright copies", len(images.orientation),
                       next(iter(images.orientation)))
    if images.needs_copy:
        logger.info("%d images in formats COLMAP cannot read (HEIC, WebP, AVIF): reconstructing from JPEG copies "
                    "in %s", len(images.needs_copy), out_dir / "images_upright")
    if not rotate and not images.needs_copy:
        return images
    return upright_copy(images, out_dir / "images_upright", rotate=rotate, progress=progress)
