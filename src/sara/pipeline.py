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

Nothing lost, nothing silently wrong:

- every option and name is checked before any work (`preflight`), so a bad option never touches
  the output folder;
- a stage trusts its record only while its outputs still hold what it wrote (`sara.io.records`):
  derived files (features, scores) that are damaged are made again; files a person may have
  edited (`pairs.txt`, `sparse/`) are never overwritten on resume, and a damaged database stops
  the run, each with a message that names the file and the fix;
- new pairs, matches and models are built beside the old ones (`.sara/`) and swapped in only when
  complete; a run that produces nothing (no pairs, no verified pair, no model) raises NoResultError
  and keeps the previous `pairs.txt`, matches, `sparse/`, `run.json` and `report.md`;
- `run.json` and `report.md` are written when a run finishes (and `run.json` once when a folder's
  first run has its features, so that `sara map OUT` finds the images);
- files left by killed runs are removed when a run starts and ends (`sara.io.clean_temporaries`).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import platform
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from . import __version__, colmap, extract, mapping, match, weights
from .config import PipelineConfig
from .execute import Executor, make_executor
from .features import BACKENDS as FEATURE_BACKENDS
from .features import features_file_name
from .io import (
    DamagedOutputError,
    IncompleteStageError,
    NoResultError,
    OutputLock,
    file_digest,
    fingerprint,
    link_or_copy,
    prepare_output_dir,
    read_json,
    records,
    write_json_atomic,
    write_text_atomic,
)
from .io.images import ImageSet, scan_images, upright_copy
from .io.pairs import read_pairs, write_pairs
from .matchers import BACKENDS as MATCHER_BACKENDS
from .matchers import resolve_name
from .pairs import SOURCES, PairContext, get_after_mapping, get_source
from .retrieval import DESCRIPTORS
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
    if _uses_retrieval(conf):
        data.update(retrieval=conf.retrieval.__dict__)
    if conf.pairs.method == "sara":  # the scorer and the graph: SARA's own
        data.update(score=conf.score.__dict__, graph=conf.graph.__dict__)
    if source_file is not None:
        data["file"] = source_file.read_text(encoding="utf-8", errors="replace")
    return fingerprint(data)


def _uses_retrieval(conf: PipelineConfig) -> bool:
    return conf.pairs.method in ("sara", "retrieval") or conf.pairs.sequential_loop_detection


def pair_source_file(method: str) -> Path | None:
    """None for a named pair source; the path for a pairs file (FileNotFoundError when neither)."""
    if method in SOURCES:
        return None
    path = Path(method)
    if path.is_dir():
        raise IsADirectoryError(f"--pairs {method}: a folder, not a pairs file ('name0 name1' per line) "
                                f"nor a pair source ({', '.join(SOURCES)})")
    if not path.is_file():
        raise FileNotFoundError(f"--pairs {method}: not a pair source ({', '.join(SOURCES)}) and no such pairs file")
    return path


def preflight(conf: PipelineConfig) -> None:
    """Check every name the run will look up (backends, descriptor, pair source), before any work.

    Values in range are checked when the config is made (`sara.config.validate`); this checks the
    names that only the registries know.
    """
    pair_source_file(conf.pairs.method)
    if conf.extract.backend not in FEATURE_BACKENDS:
        raise ValueError(f"extract.backend must be one of {', '.join(FEATURE_BACKENDS)}, got {conf.extract.backend!r}")
    matcher = resolve_name(conf.match, conf.extract.backend)
    if matcher not in MATCHER_BACKENDS:
        raise ValueError(f"match.backend must be auto or one of {', '.join(MATCHER_BACKENDS)}, got {matcher!r}")
    if _uses_retrieval(conf) and conf.retrieval.descriptor not in DESCRIPTORS:
        raise ValueError(f"retrieval.descriptor must be one of {', '.join(DESCRIPTORS)}, "
                         f"got {conf.retrieval.descriptor!r}")
    # every weight file the run will load, found now (file-system look-ups only): a missing one
    # fails in well under a second, not after the stages before it
    needed = list(_weights_needed(FEATURE_BACKENDS.get(conf.extract.backend), conf.extract))
    needed += _weights_needed(MATCHER_BACKENDS.get(matcher), conf.match, conf.extract.backend)
    if _uses_retrieval(conf):
        needed += _weights_needed(DESCRIPTORS.get(conf.retrieval.descriptor), conf.retrieval)
    for key, explicit in needed:
        weights.find(key, explicit)


def _weights_needed(backend: Any, *args: Any) -> list[tuple[str, str]]:
    """The (weights key, explicit path) a backend declares through its `weights_needed`, if any."""
    declare = getattr(backend, "weights_needed", None)
    return list(declare(*args)) if declare is not None else []


def pair_context(conf: PipelineConfig, images: ImageSet, features_path: Path, out_dir: Path, *,
                 executor: Executor | None = None, progress: bool = True, work_dir: Path | None = None) -> PairContext:
    return PairContext(names=images.names, images_root=images.root, features_path=features_path,
                       db_path=out_dir / extract.DB_NAME, out_dir=work_dir or out_dir, conf=conf, progress=progress,
                       executor=executor)


#: files that pair sources keep between runs (reused when their inputs did not change)
PAIR_CACHES = ("global-*.h5", "vocab_tree.bin", "vocab_tree.json")
STAGING = "pairs.next"


def select_pairs(conf: PipelineConfig, images: ImageSet, features_path: Path, out_dir: Path, *,
                 executor: Executor | None = None, overwrite: bool = False, progress: bool = True) -> Path:
    """Stage `pairs`: write `pairs.txt` from the configured source; returns its path.

    The source writes its files (scores.csv, global descriptors) into `.sara/pairs.next/`; they and
    `pairs.txt` replace the previous ones only when it selected at least one pair (else
    NoResultError, and the previous pairs, matches and model stay).
    """
    method = conf.pairs.method
    source_file = pair_source_file(method)
    key = pairs_key(conf, (records.read_record(out_dir, extract.STAGE) or {}).get("key", ""), source_file)
    pairs_path = out_dir / PAIRS_NAME
    if not overwrite and records.is_done(out_dir, PAIRS_STAGE, key) and _pairs_intact(out_dir):
        logger.info("pairs: %s up to date, skipping", pairs_path)
        return pairs_path
    tic = time.perf_counter()
    staging = out_dir / ".sara" / STAGING
    shutil.rmtree(staging, ignore_errors=True)
    try:
        if source_file is not None:
            pairs = read_pairs(source_file, known_names=images.names)
            info: dict[str, Any] = {"source": str(source_file)}
        else:
            _seed_caches(out_dir, staging)
            ctx = pair_context(conf, images, features_path, out_dir, executor=executor, progress=progress,
                               work_dir=staging)
            result = get_source(method)(ctx)
            pairs, info = result.pairs, {**result.info, "timings_s": result.timings_s}
        if not pairs:
            raise NoResultError(_no_pairs_reason(method, source_file, info, len(images.names), out_dir))
        produced = _swap_in_pair_files(staging, out_dir, key)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    write_pairs(pairs_path, pairs)
    n = len(images.names)
    exhaustive = n * (n - 1) // 2
    info.update(method=method, num_pairs=len(pairs), num_selected=len(pairs), time_s=time.perf_counter() - tic,
                num_exhaustive_pairs=exhaustive, fraction_of_exhaustive=len(pairs) / max(1, exhaustive))
    outputs = {name: file_digest(out_dir / name) for name in [PAIRS_NAME, *produced] if name in _TRACKED_PAIR_FILES}
    records.mark_done(out_dir, PAIRS_STAGE, key, info, outputs=outputs)
    return pairs_path


#: outputs of the pairs stage whose digests the record keeps (caches check themselves)
_TRACKED_PAIR_FILES = (PAIRS_NAME, "scores.csv")


def _seed_caches(out_dir: Path, staging: Path) -> None:
    """Copy the caches of earlier pair selections into the staging folder (a source reuses them)."""
    staging.mkdir(parents=True, exist_ok=True)
    for pattern in PAIR_CACHES:
        for path in out_dir.glob(pattern):
            if path.is_file():
                shutil.copy2(path, staging / path.name)


def _swap_in_pair_files(staging: Path, out_dir: Path, key: str) -> list[str]:
    """Move what the source wrote into the output folder; returns the file names."""
    records.mark_started(out_dir, PAIRS_STAGE, key)
    records.clear(out_dir, AFTER_MAPPING_STAGE)
    produced = []
    if staging.is_dir():
        for path in sorted(staging.iterdir()):
            if path.is_file():
                os.replace(path, out_dir / path.name)
                produced.append(path.name)
    return produced


def _no_pairs_reason(method: str, source_file: Path | None, info: dict[str, Any], num_images: int,
                     out_dir: Path) -> str:
    kept = " (the previous pairs, matches and model are kept)" if (out_dir / PAIRS_NAME).exists() else ""
    if source_file is not None:
        return f"{source_file} lists no pairs: nothing to match{kept}"
    if num_images < 2:
        return f"only {num_images} usable image: a reconstruction needs at least 2{kept}"
    extracted = records.read_record(out_dir, extract.STAGE) or {}
    featureless = (extracted.get("info") or {}).get("images_without_features") or []
    if num_images - len(featureless) < 2:
        return (f"{len(featureless)} of {num_images} images have no features (flat or featureless): a "
                f"reconstruction needs at least 2 with features{kept}")
    if "num_candidates" in info:
        rejected = ", ".join(f"{k} {v}" for k, v in sorted(info.get("rejected", {}).items())) or "none"
        return (f"the {method} pair source selected no pairs: {info.get('num_accepted', 0)} of "
                f"{info['num_candidates']} candidate pairs accepted (rejected: {rejected}); the images may not "
                f"overlap, or relax the score.* thresholds{kept}")
    return f"the {method} pair source selected no pairs{kept}"


def _pairs_intact(out_dir: Path) -> bool:
    """Whether the pairs stage's files still hold what it wrote.

    `pairs.txt` missing: select again (False). Changed (edited, emptied, cut short): never
    overwritten, DamagedOutputError says what to do. `scores.csv` changed or damaged: made again
    (False, with a warning).
    """
    pairs_path = out_dir / PAIRS_NAME
    if not pairs_path.exists():
        return False
    recorded = records.recorded_outputs(out_dir, PAIRS_STAGE)
    if PAIRS_NAME in recorded and recorded[PAIRS_NAME] != file_digest(pairs_path):
        raise DamagedOutputError(
            f"{pairs_path} was changed after the pairs stage wrote it (edited, emptied or cut short); delete it to "
            f"select the pairs again, or match your own pairs with `sara match {out_dir} --pairs FILE`")
    for name in _TRACKED_PAIR_FILES[1:]:
        if name in recorded and recorded[name] != file_digest(out_dir / name):
            logger.warning("%s differs from what the pairs stage wrote (changed, damaged or missing): selecting "
                           "the pairs again", out_dir / name)
            return False
    return True


# ---------------------------------------------------------------------------------------------
# Matching and mapping, and the rounds after mapping
# ---------------------------------------------------------------------------------------------


def match_pairs(conf: PipelineConfig, pairs_path: Path, features_path: Path, out_dir: Path, *,
                executor: Executor | None = None, progress: bool = True, beside: bool = False,
                overwrite: bool = False) -> Path:
    """Stage `match` with this run's matcher; returns the database that holds the matches (with
    `beside`, possibly a copy to `match.commit` once mapping succeeded)."""
    return match.run(conf.match, pairs_path, out_dir / extract.DB_NAME, out_dir, features_path=features_path,
                     features_backend=conf.extract.backend, executor=executor, progress=progress, beside=beside,
                     overwrite=overwrite)


def map_model(conf: PipelineConfig, images_root: Path, out_dir: Path, *, db_path: Path | None = None,
              progress: bool = True, overwrite: bool = False, staged: Path | None = None,
              num_staged: int = 0) -> Path:
    """Stage `map` on the matches of `db_path` (default the output's database; a copy made by the
    match stage is moved into place just before the new model); returns `sparse/`. `staged`: the
    pairs file those matches were made from when it is not yet `pairs.txt` (`num_staged` pairs
    added before mapping), moved into place with them."""
    db = out_dir / extract.DB_NAME
    work = Path(db_path or db)
    upstream = fingerprint(match.matches_digest(work))

    def commit() -> None:
        match.commit(work, db, out_dir)
        if staged is not None:
            _add_to_pairs_record(out_dir, num_staged, file_digest(staged), field="num_added_before_mapping")
            os.replace(staged, out_dir / PAIRS_NAME)

    return mapping.run(conf.map, work, images_root, out_dir, seed=conf.seed, upstream_key=upstream,
                       progress=progress, min_num_inliers=conf.match.min_num_inliers, commit=commit,
                       overwrite=overwrite)


def support_round(conf: PipelineConfig, images: ImageSet, features_path: Path, out_dir: Path, work: Path, *,
                  executor: Executor | None = None, progress: bool = True) -> tuple[Path, Path | None, int]:
    """Before the first mapping, let the pair source add pairs for weakly matched views (SARA:
    `sara.pairs.support`) and match them. Returns the database to map, the pairs file it was matched
    from when that is not yet `pairs.txt` (None when nothing was added) and the number of pairs added.
    The matching time of these pairs is added to the match stage's."""
    step = get_after_mapping(conf.pairs.method)
    before = getattr(step, "before_mapping", None) if step is not None else None
    if before is None:
        return work, None, 0
    ctx = pair_context(conf, images, features_path, out_dir, executor=executor, progress=progress)
    pairs = read_pairs(out_dir / PAIRS_NAME, known_names=images.names)
    extra = before(ctx, pairs, work)
    if not extra:
        return work, None, 0
    first = records.read_record(out_dir, match.STAGE) or {}
    staged = out_dir / ".sara" / STAGED_PAIRS
    write_pairs(staged, pairs + extra)
    work = match_pairs(conf, staged, features_path, out_dir, executor=executor, progress=progress, beside=True)
    record = records.read_record(out_dir, match.STAGE) or {}
    if record.get("key") != first.get("key") and first.get("done") is True:  # matched now: both times count
        info = {**record.get("info", {}),
                "time_s": record.get("info", {}).get("time_s", 0.0) + first.get("info", {}).get("time_s", 0.0)}
        records.mark_done(out_dir, match.STAGE, record.get("key", ""), info, outputs=record.get("outputs"))
    return work, staged, len(extra)


def after_mapping_rounds(conf: PipelineConfig, images: ImageSet, features_path: Path, out_dir: Path, *,
                         executor: Executor | None = None, progress: bool = True) -> dict[str, Any] | None:
    """Let the pair source look at the model and ask for more pairs; match them and map again.

    Up to `pairs.repair_rounds` rounds. `pairs.txt` then lists every pair matched, and the pairs
    record says how many were added. A round whose mapping fails keeps the previous round's pairs,
    matches and model. Returns the round record's info (None when no round ran).
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
        staged = out_dir / ".sara" / STAGED_PAIRS
        write_pairs(staged, pairs + extra)
        try:
            work = match_pairs(conf, staged, features_path, out_dir, executor=ctx.executor, progress=progress,
                               beside=True)
            refined = _refine_round(conf, ctx, getattr(step, "refine", None), extra, out_dir, work, staged)
            if refined is None:
                _map_round(conf, images.root, out_dir, work, staged, len(extra), progress)
        except NoResultError as exc:
            logger.warning("the %d pairs added after mapping gave no better model (%s): keeping the model as it "
                           "was", len(extra), exc)
            colmap.remove_database(out_dir / ".sara" / match.NEXT_DB_NAME)
            staged.unlink(missing_ok=True)
            break
        info["rounds"] += 1
        info["pairs_added"] += len(extra)
        info["time_s"] += time.perf_counter() - tic
        info["match_time_s"] += records.done_info(out_dir, match.STAGE).get("time_s", 0.0)
        info["map_time_s"] += (refined["time_s"] if refined is not None
                               else records.done_info(out_dir, mapping.STAGE).get("time_s", 0.0))
        info["refined_rounds"] = info.get("refined_rounds", 0) + (refined is not None)
        records.mark_done(out_dir, AFTER_MAPPING_STAGE, "", info)
    finish = getattr(step, "finish", None)
    if finish is not None:
        finished = _finish_round(ctx, finish, out_dir, refined=info.get("refined_rounds", 0) > 0)
        if finished is not None:
            info["extension"] = finished
            info["time_s"] += finished["time_s"]
            info["map_time_s"] += finished["time_s"]
            records.mark_done(out_dir, AFTER_MAPPING_STAGE, "", info)
    return info if info["rounds"] or info.get("extension") else None


def _copy_other_models(sparse: Path, new: Path) -> None:
    """Into `new`, whose main model (0) replaces `sparse/0`: the other components as they are."""
    for other in sorted(sparse.iterdir()):
        if other.is_dir() and other.name != "0":
            shutil.copytree(other, new / other.name)


#: the last step after mapping (`_finish_round`)
FINISH_STAGE = "finish"


def _finish_round(ctx: PairContext, finish: Any, out_dir: Path, *, refined: bool) -> dict[str, Any] | None:
    """The pair source's last word on the final model (SARA: extend its tracks when no pose-guided
    refinement did); once per model: a model it already finished is left as it is."""
    sparse = out_dir / "sparse"
    done = records.done_info(out_dir, FINISH_STAGE)
    if done and done.get("model") == mapping.model_digest(sparse):
        return None
    tmp = out_dir / ".sara" / "sparse.finished"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        result = finish(ctx, sparse / "0", tmp / "0", refined=refined)
    except (OSError, ValueError, KeyError, RuntimeError) as exc:  # an improvement only: the model stays
        logger.warning("the last step on the final model failed (%s): keeping the model as it is", exc)
        result = None
    if result is None:
        shutil.rmtree(tmp, ignore_errors=True)
        return None
    _copy_other_models(sparse, tmp)
    mapping.swap_in(tmp, sparse)
    digest = mapping.model_digest(sparse)
    # the map stage now describes the finished model: a re-run keeps it
    mapped = records.read_record(out_dir, mapping.STAGE) or {}
    records.mark_done(out_dir, mapping.STAGE, mapped.get("key", ""), records.done_info(out_dir, mapping.STAGE),
                      outputs={"sparse": digest})
    records.mark_done(out_dir, FINISH_STAGE, "", {**result, "model": digest})
    return result


def _refine_round(conf: PipelineConfig, ctx: PairContext, refine: Any, extra: list, out_dir: Path, work: Path,
                  staged: Path) -> dict[str, Any] | None:
    """A round whose pairs only add constraints between posed views: the pair source refines the
    main model (re-triangulation with the poses fixed, then bundle adjustment) instead of mapping
    again from scratch. None when the source has no refinement or declines it for this round."""
    if refine is None:
        return None
    sparse = out_dir / "sparse"
    tmp = out_dir / ".sara" / "sparse.refined"
    shutil.rmtree(tmp, ignore_errors=True)
    result = refine(ctx, extra, work, sparse / "0", tmp / "0")
    if result is None:
        shutil.rmtree(tmp, ignore_errors=True)
        return None
    _copy_other_models(sparse, tmp)
    match.commit(work, out_dir / extract.DB_NAME, out_dir)
    _add_to_pairs_record(out_dir, len(extra), file_digest(staged))
    os.replace(staged, out_dir / PAIRS_NAME)
    mapping.swap_in(tmp, sparse)
    # the map stage now describes the refined model of the committed matches: a re-run skips it
    key = mapping.state_key(conf.map, conf.seed, fingerprint(match.matches_digest(out_dir / extract.DB_NAME)))
    info = {**(records.done_info(out_dir, mapping.STAGE) or {}), "refined": True, "time_s": result["time_s"]}
    records.mark_done(out_dir, mapping.STAGE, key, info, outputs={"sparse": mapping.model_digest(sparse)})
    return result


#: the pairs of a round after mapping, until its model replaces the previous one
STAGED_PAIRS = "pairs.next.txt"


def _map_round(conf: PipelineConfig, images_root: Path, out_dir: Path, work: Path, staged: Path,
               num_added: int, progress: bool) -> None:
    """Map a round's matches; when it gives a model, its database, `pairs.txt` and records replace
    the previous ones just before the model does."""
    db = out_dir / extract.DB_NAME

    def commit() -> None:
        match.commit(work, db, out_dir)
        _add_to_pairs_record(out_dir, num_added, file_digest(staged))
        os.replace(staged, out_dir / PAIRS_NAME)

    upstream = fingerprint(match.matches_digest(work))
    main = out_dir / "sparse" / "0"
    extend = conf.map.extend_model and conf.map.mapper == "incremental" and colmap.has_model(main)
    mapping.run(conf.map, work, images_root, out_dir, seed=conf.seed, upstream_key=upstream, progress=progress,
                min_num_inliers=conf.match.min_num_inliers, commit=commit, input_model=main if extend else None)


def _add_to_pairs_record(out_dir: Path, num_added: int, pairs_digest: dict[str, Any] | None, *,
                         field: str = "num_added_after_mapping") -> None:
    record = records.read_record(out_dir, PAIRS_STAGE) or {}
    info = record.get("info", {})
    info[field] = info.get(field, 0) + num_added
    selected = info.get("num_selected", info.get("num_pairs", 0))
    info["num_pairs"] = selected + info.get("num_added_after_mapping", 0) + info.get("num_added_before_mapping", 0)
    if info.get("num_exhaustive_pairs"):  # the pairs of all rounds, as the report counts them
        info["fraction_of_exhaustive"] = info["num_pairs"] / info["num_exhaustive_pairs"]
    outputs = {**record.get("outputs", {}), PAIRS_NAME: pairs_digest}
    records.mark_done(out_dir, PAIRS_STAGE, record.get("key", ""), info, outputs=outputs)


def recover(out_dir: Path) -> None:
    """Finish or undo what a run killed between two swaps left (call it holding the lock): the
    previous `sparse/` when the new one never arrived; a round's `pairs.txt` whose record was
    already written."""
    mapping.recover(out_dir)
    staged = out_dir / ".sara" / STAGED_PAIRS
    if staged.exists():
        if records.recorded_outputs(out_dir, PAIRS_STAGE).get(PAIRS_NAME) == file_digest(staged):
            os.replace(staged, out_dir / PAIRS_NAME)
        else:
            staged.unlink()


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
    preflight(conf)  # a bad option or --pairs fails before any work
    if gt_dir is not None:
        _check_ground_truth(Path(gt_dir), images_root)
    images = scan_images(images_root, recursive=conf.images.recursive, progress=progress)
    if stop_after != "extract" and len(images.names) < 2:
        raise ValueError(f"only one usable image in {images_root} ({images.names[0]}): a reconstruction needs "
                         "at least 2")
    if gt_dir is not None:
        _check_ground_truth(Path(gt_dir), images_root, images.names)
    prepare_output_dir(out_dir)
    executor = make_executor(conf.execute.executor, conf.execute.workers, conf.execute.ray_address)
    try:
        with OutputLock(out_dir, clean=True):
            recover(out_dir)
            return _run_stages(conf, images, images_root, out_dir, executor, gt_dir=gt_dir, overwrite=overwrite,
                               progress=progress, verbose_colmap=verbose_colmap, stop_after=stop_after)
    finally:
        executor.close()


def _check_ground_truth(gt_dir: Path, images_root: Path, names: list[str] | None = None) -> None:
    """A ground truth that does not exist, holds no model, or shares no image name with the images
    fails before any work."""
    if not gt_dir.exists():
        raise FileNotFoundError(f"ground-truth folder not found: {gt_dir}")
    if names is None:
        return
    from .evaluation import gt_image_names

    common = gt_image_names(gt_dir) & set(names)
    if not common:
        raise ValueError(f"the ground truth {gt_dir} shares no image name with {images_root}: is it the ground "
                         "truth of another scene?")


def _run_stages(conf: PipelineConfig, images: ImageSet, images_root: Path, out_dir: Path, executor: Executor, *,
                gt_dir: Path | None, overwrite: bool, progress: bool, verbose_colmap: bool,
                stop_after: str | None) -> RunReport:
    images = _handle_orientation(conf.images.exif_orientation, images, out_dir, progress)
    colmap.send_log_to(out_dir / "logs", verbose=verbose_colmap)
    colmap.set_seed(conf.seed)
    first_run = not (out_dir / "run.json").exists()
    features = extract.run(conf.extract, images, out_dir, executor=executor, overwrite=overwrite, progress=progress)
    images = extract.usable(images, out_dir)
    report = RunReport(out_dir, images_root, conf.to_dict(), skipped_images=images.skipped)
    report.stages["images"] = {"num_images": len(images.names), "num_skipped": len(images.skipped)}
    report.stages["extract"] = records.done_info(out_dir, extract.STAGE)  # its time_s: when it really ran
    if first_run or stop_after == "extract":
        report.save()  # `sara map OUT` finds the images through run.json
    if stop_after == "extract":
        return report
    pairs_path = select_pairs(conf, images, features, out_dir, executor=executor, overwrite=overwrite,
                              progress=progress)
    report.stages["pairs"] = records.done_info(out_dir, PAIRS_STAGE)
    if stop_after == "pairs":
        report.save()
        return report
    work = match_pairs(conf, pairs_path, features, out_dir, executor=executor, progress=progress, beside=True,
                       overwrite=overwrite)
    work, staged, num_staged = support_round(conf, images, features, out_dir, work, executor=executor,
                                             progress=progress)
    report.stages["match"] = records.done_info(out_dir, match.STAGE)
    try:
        map_model(conf, images.root, out_dir, db_path=work, progress=progress, overwrite=overwrite, staged=staged,
                  num_staged=num_staged)
    except NoResultError:
        if work != out_dir / extract.DB_NAME:
            colmap.remove_database(work)  # the previous matches stay with the previous model
        if staged is not None:
            staged.unlink(missing_ok=True)
        raise
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
    if info and (info.get("rounds") or info.get("extension")):
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


def _require_finished(out_dir: Path, stage: str, command: str) -> dict[str, Any]:
    record = records.read_record(out_dir, stage)
    if record is None or record.get("done") is not True:
        state = "never ran" if record is None else "did not finish (stopped or killed)"
        raise IncompleteStageError(f"the {stage} stage in {out_dir} {state}: run `{command}` first")
    return record


def match_only(conf: PipelineConfig, out_dir: Path, pairs_path: Path | None = None, *, progress: bool = True,
               verbose_colmap: bool = False) -> dict[str, Any]:
    """`sara match OUT`: match a pairs file (default OUT/pairs.txt) into OUT's database."""
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
        if pairs_path == out_dir / PAIRS_NAME and records.read_record(out_dir, PAIRS_STAGE) is not None:
            _pairs_intact(out_dir)  # a changed pairs.txt of the pairs stage is not matched silently
        colmap.send_log_to(out_dir / "logs", verbose=verbose_colmap)
        features = out_dir / features_file_name(conf.extract)
        work = match_pairs(conf, pairs_path, features, out_dir, progress=progress, beside=True)
        match.commit(work, db, out_dir)
    return records.done_info(out_dir, match.STAGE)


def map_only(conf: PipelineConfig, out_dir: Path, images_root: Path | None = None, *, progress: bool = True,
             verbose_colmap: bool = False) -> dict[str, Any]:
    """`sara map OUT`: map OUT's database into OUT/sparse (images: the folder recorded in run.json).

    Refuses when the match stage did not finish, or when the database no longer holds the matches
    it recorded: an unfinished match is never mapped as if it were complete.
    """
    out_dir = Path(out_dir)
    db = _require_database(out_dir, "run `sara extract` and `sara match` first")
    images_root = Path(images_root or load_run(out_dir)["images_root"])
    if not images_root.is_dir():
        raise FileNotFoundError(f"image folder {images_root} not found: give it with --images")
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
    colmap.remove_database(out_dir / extract.DB_NAME)
    colmap.copy_database(features_dir / extract.DB_NAME, out_dir / extract.DB_NAME)
    link_or_copy(features_dir / features_name, out_dir / features_name)
    records.mark_done(out_dir, extract.STAGE, source["key"], source.get("info", {}), outputs=source.get("outputs"))
    return True


# ---------------------------------------------------------------------------------------------
# report.md
# ---------------------------------------------------------------------------------------------


def _tree_note(pairs_info: dict[str, Any]) -> str:
    """How the SARA selection ranked its spanning tree, for the report ('' for other sources)."""
    tree = pairs_info.get("tree_overlap")
    if tree is None:
        return ""
    fov = pairs_info.get("field_of_view_deg")
    view = f"{fov:.0f}-degree field of view" if fov is not None else "field of view unknown"
    rank = "the inliers among all matches" if tree == "all" else "the paper's weight"
    how = "" if pairs_info.get("tree_overlap_setting", "auto") == "auto" else ", as set by score.tree_overlap"
    return f"; spanning tree by {rank} ({view}{how})"


def render_report(report: RunReport) -> str:
    """A short human-readable summary of a run (Markdown)."""
    s = report.stages
    ex, pr, ma, mp = s.get("extract", {}), s.get("pairs", {}), s.get("match", {}), s.get("map", {})
    added, before = pr.get("num_added_after_mapping", 0), pr.get("num_added_before_mapping", 0)
    rows = [
        [f"extract ({ex.get('backend', 'sift')})", f"{ex.get('time_s', 0):.1f}",
         f"{ex.get('keypoints_mean', 0):.0f} keypoints per image"],
        [f"pairs ({pr.get('method')})", f"{pr.get('time_s', 0):.1f}",
         f"{pr.get('num_pairs', 0)} pairs ({100 * pr.get('fraction_of_exhaustive', 0):.1f}% of exhaustive)"
         + (f", {before} of them added before mapping for weakly matched views" if before else "")
         + (f", {added} of them added after mapping" if added else "") + _tree_note(pr)],
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
