"""Stage `match`: full matching of the pairs of a pairs file with any matcher of `sara.matchers`,
then COLMAP's geometric verification, into the COLMAP database (so mapping is the same for all)."""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import colmap, eta
from .config import MatchConfig
from .execute import Executor, SerialExecutor, for_device, single_threaded_torch_in_worker
from .io import DamagedOutputError, NoResultError, ensure_free_space, fingerprint, read_json, records, write_json_atomic
from .io.h5 import FeatureCache
from .io.pairs import Pair, read_pairs, write_pairs
from .matchers import Matcher, make_matcher, resolve_name

logger = logging.getLogger(__name__)

STAGE = "match"
CONF_RECORD = "match-settings"
PROGRESS_RECORD = "match-progress"


NEXT_DB_NAME = "database.next.db"
#: about what one matched pair adds to the database, bytes: matches and inlier matches, 8 bytes
#: each, for 4,096 of each (SIFT pairs of large images reach that; most hold far fewer)
BYTES_PER_PAIR = 64 * 1024


def run(conf: MatchConfig, pairs_path: Path, db_path: Path, out_dir: Path, *, features_path: Path,
        features_backend: str = "sift", executor: Executor | None = None, progress: bool = True,
        beside: bool = False, overwrite: bool = False, reserve: Path | None = None) -> Path:
    """Match every pair of `pairs_path` into the database; returns the database that holds the
    matches (counts and the time taken go into the stage record).

    The database ends up holding the matches of exactly these pairs: matches left by another pairs
    file are removed first. An interrupted run resumes (pairs already matched are skipped).

    With `beside`, a database that already holds matches is not changed: the work is done in a
    copy, `.sara/database.next.db`, which is returned; the caller moves it into place with
    `commit` once what follows succeeded, so a failed run keeps the previous matches. When no pair
    gets a verified geometry, NoResultError is raised and the previous matches are kept.

    `reserve`: a database of the same images and keypoints whose matches were made with the same
    settings (an incremental update's earlier matches): a pair it holds is copied, not matched.
    """
    out_dir = Path(out_dir)
    next_db = out_dir / ".sara" / NEXT_DB_NAME
    _checked_summary(db_path)
    restore_names([db_path, next_db], out_dir)  # after a run killed while names were aliased
    before = _checked_summary(db_path)
    names = colmap.database_images(db_path)
    pairs = read_pairs(pairs_path, known_names=names)
    if not pairs:
        raise NoResultError(f"{pairs_path} lists no pairs: nothing to match (the previous matches are kept)")
    matcher_name = resolve_name(conf, features_backend)
    key = fingerprint({"pairs": pairs, "conf": {**_result_settings(conf), "backend": matcher_name},
                       "features": Path(features_path).name, "keypoints": before["keypoints_digest"]})
    ready = None if overwrite else _finished_database(out_dir, key, db_path, next_db, before)
    if ready is not None:
        logger.info("match: %d pairs already matched, skipping", len(pairs))
        return ready
    matcher = make_matcher(conf, features_backend)  # loads weights: fails here, before any work
    conf_key = fingerprint({**_result_settings(conf), "backend": matcher_name, "features": Path(features_path).name})
    same_settings = not overwrite and records.is_done(out_dir, CONF_RECORD, conf_key)  # of `db_path`'s matches
    # room for the stage's new matches (and the copy of the database beside) before COLMAP writes
    # any: it aborts the process when the database cannot grow
    todo = len(_unmatched(db_path, pairs, names)) if same_settings else len(pairs)
    copy_bytes = Path(db_path).stat().st_size if beside and before["num_matched_pairs"] > 0 else 0
    ensure_free_space(out_dir, BYTES_PER_PAIR * todo + copy_bytes)
    kept = {stage: records.read_record(out_dir, stage) for stage in (STAGE, PROGRESS_RECORD)}
    work = _work_database(db_path, next_db, out_dir, key, conf_key, pairs, names, same_settings=same_settings,
                          beside=beside and before["num_matched_pairs"] > 0)
    _remove_other_pairs(work, pairs, names)  # keep the matches that are still wanted
    if reserve is not None and same_settings:
        _restore(reserve, work, pairs, names)
    records.mark_started(out_dir, STAGE, key)
    elapsed, num_done, estimate = _match_all(conf, matcher, features_backend, features_path, pairs, names, work,
                                             out_dir, key, conf_key, executor, progress)
    info = {"num_pairs": len(pairs), "num_matched_now": num_done, "time_s": elapsed, "matcher": matcher.name,
            **_estimate_info(estimate, num_done, elapsed), **verification_stats(work, conf.min_num_inliers)}
    if info["num_verified_pairs"] == 0:
        if work != Path(db_path):
            colmap.remove_database(work)
        for stage, record in kept.items():  # they describe the database that is kept
            records.restore(out_dir, stage, record)
        raise NoResultError(
            f"none of the {len(pairs)} pairs has {conf.min_num_inliers} or more verified matches "
            f"(match.min_num_inliers): the images do not overlap, or the pairs are wrong"
            + ("; the previous matches are kept" if before["num_matched_pairs"] else ""))
    records.mark_done(out_dir, STAGE, key, info, outputs={DB_NAME: matches_digest(work)})
    logger.info("match: %d pairs in %.1f s, %d verified", len(pairs), elapsed, info["num_verified_pairs"])
    return work


DB_NAME = "database.db"

#: settings that change how the matching runs, never which matches it finds: a run that only
#: changes them keeps (and resumes) the matches made so far
_RUN_ONLY_SETTINGS = ("chunk_size", "num_threads", "device")


def _result_settings(conf: MatchConfig) -> dict:
    return {k: v for k, v in conf.__dict__.items() if k not in _RUN_ONLY_SETTINGS}


def commit(work: Path, db_path: Path, out_dir: Path) -> None:
    """Move the database returned by `run` onto `db_path` (nothing to do when it is `db_path`);
    the settings its matches were made with become those of `db_path`."""
    if Path(work) == Path(db_path):
        return
    conf_key = (records.read_record(out_dir, PROGRESS_RECORD) or {}).get("info", {}).get("conf_key")
    colmap.replace_database(work, db_path)
    if conf_key:
        records.mark_done(out_dir, CONF_RECORD, conf_key)


def matches_digest(db_path: Path) -> dict:
    """What identifies the matches of a database: counts and a digest of every pair's match and
    inlier counts."""
    summary = colmap.database_summary(db_path) or {}
    return {k: summary.get(k) for k in ("num_matched_pairs", "num_verified_pairs", "matches_digest")}


def _checked_summary(db_path: Path) -> dict:
    try:
        summary = colmap.database_summary(db_path)
    except DamagedOutputError as exc:
        raise DamagedOutputError(f"{exc}; run again with --overwrite to redo extraction and matching") from None
    if summary is None:
        raise FileNotFoundError(f"{db_path} not found: run the extract stage first")
    return summary


def _finished_database(out_dir: Path, key: str, db_path: Path, next_db: Path, summary: dict) -> Path | None:
    """The database that holds the finished matches of `key`: `db_path`, or a copy that a run killed
    before moving it into place left in `.sara/` (None when the stage must run)."""
    if not records.is_done(out_dir, STAGE, key):
        return None
    recorded = records.recorded_outputs(out_dir, STAGE).get(DB_NAME)
    now = {k: summary.get(k) for k in ("num_matched_pairs", "num_verified_pairs", "matches_digest")}
    if recorded is None or recorded == now:
        return Path(db_path)
    if next_db.exists():
        try:
            if matches_digest(next_db) == recorded:
                return next_db
        except DamagedOutputError:
            pass
    logger.warning("%s no longer holds the matches that the match stage recorded (changed, damaged, or a "
                   "run stopped before it was updated): matching again", db_path)
    return None


def _work_database(db_path: Path, next_db: Path, out_dir: Path, key: str, conf_key: str, pairs: list[Pair],
                   names: dict[str, int], *, same_settings: bool, beside: bool) -> Path:
    """Where to match: `db_path` itself when nothing in it can be lost (no matches, or only
    additions made with the same settings), else with `beside` a copy in `.sara/` (resumed when a
    killed run of the same pairs and settings left one). Matches made with other settings are
    cleared first."""
    progress = records.read_record(out_dir, PROGRESS_RECORD) or {}
    info = progress.get("info", {})
    if beside and next_db.exists() and progress.get("key") == key and info.get("conf_key") == conf_key:
        try:
            same = (colmap.database_summary(next_db) or {}).get("keypoints_digest") == \
                (colmap.database_summary(db_path) or {}).get("keypoints_digest")
        except DamagedOutputError:
            same = False
        if same:
            return next_db
    colmap.remove_database(next_db)
    if not beside or (same_settings and _only_additions(db_path, pairs, names)):
        if not same_settings:
            colmap.clear_matches(db_path)  # a fresh start, or matches made with other settings
            records.mark_done(out_dir, CONF_RECORD, conf_key)
        return Path(db_path)
    ensure_free_space(out_dir, Path(db_path).stat().st_size)
    colmap.copy_database(db_path, next_db)
    if not same_settings:
        colmap.clear_matches(next_db)
    records.mark_done(out_dir, PROGRESS_RECORD, key, {"time_s": 0.0, "beside": True, "conf_key": conf_key})
    return next_db


def _only_additions(db_path: Path, pairs: list[Pair], ids: dict[str, int]) -> bool:
    """Whether matching `pairs` only adds to the database (every pair it holds is wanted)."""
    wanted = {tuple(sorted((ids[a], ids[b]))) for a, b in pairs}
    return all((i, j) in wanted for i, j, _ in colmap.verified_image_pairs(db_path))


#: chunks per worker at least, when there are few pairs for the executor's workers
CHUNKS_PER_WORKER = 4


def _match_all(conf: MatchConfig, matcher: Matcher, features_backend: str, features_path: Path, pairs: list[Pair],
               names: dict[str, int], work: Path, out_dir: Path, key: str, conf_key: str, executor: Executor | None,
               progress: bool) -> tuple[float, int, eta.Estimate | None]:
    """Match and verify the pairs not yet in `work`, chunk by chunk; returns (seconds, pairs done,
    the estimate made from the first chunk, None when nothing was matched)."""
    todo = _unmatched(work, pairs, names)
    # time spent by earlier, interrupted runs on these very pairs counts too
    progress_record = records.read_record(out_dir, PROGRESS_RECORD) or {}
    earlier = progress_record.get("info", {}) if progress_record.get("key") == key else {}
    earlier_s, beside = float(earlier.get("time_s", 0.0)), work.name == NEXT_DB_NAME
    tic = time.perf_counter()
    chunk_path = out_dir / ".sara" / "match_chunk.txt"
    size = conf.chunk_size
    executor = for_device(executor, getattr(matcher, "device", "cpu"))
    workers = getattr(executor, "workers", 1) if executor is not None else 1
    if not hasattr(matcher, "match_in_database") and workers > 1:
        # a few chunks per worker, so that no worker idles at the end while another finishes a
        # chunk of harder pairs (LightGlue's time per pair varies several-fold with the overlap)
        size = max(1, min(size, math.ceil(len(todo) / (workers * CHUNKS_PER_WORKER))))
    chunks = chunked(todo, size)
    if len(chunks) > 1:
        logger.info("match: %s pairs to match%s; an estimate of the time follows the first chunk", f"{len(todo):,}",
                    f" ({len(pairs) - len(todo):,} matched before)" if len(todo) < len(pairs) else "")
    # chunks in flight at once: when the first comes back, about that many are done
    concurrency = 1 if hasattr(matcher, "match_in_database") else min(workers, len(chunks))
    estimate = None
    with tqdm(total=len(pairs), initial=len(pairs) - len(todo), desc=f"match pairs ({matcher.name})", unit="pair",
              disable=not progress) as bar, space_free_names(work, out_dir) as alias:
        if hasattr(matcher, "match_in_database"):
            found: Iterator[list[np.ndarray] | None] = iter([None] * len(chunks))
        else:
            _MATCHERS[_matcher_key(conf, features_backend)] = matcher  # in this process, reuse it
            jobs = [_MatchJob(conf, features_backend, str(features_path), chunk) for chunk in chunks]
            found = (executor or SerialExecutor()).map(_match_chunk, jobs)
        for chunk, matches in zip(chunks, found):
            ensure_free_space(out_dir, BYTES_PER_PAIR * len(chunk))  # SQLite inside COLMAP on a full disk: unclear
            renamed = [(alias.get(a, a), alias.get(b, b)) for a, b in chunk]
            write_pairs(chunk_path, renamed)
            if matches is None:
                matcher.match_in_database(work, chunk_path)
            else:
                colmap.write_matches(work, dict(zip(renamed, matches)))
                colmap.verify_pairs(work, chunk_path, min_num_inliers=conf.min_num_inliers)
            bar.update(len(chunk))
            if estimate is None:
                costs = eta.chunk_work(chunks, getattr(matcher, "image_cost_in_pairs", 0.0))
                estimate = eta.from_first_chunk(len(todo), len(chunk), time.perf_counter() - tic,
                                                concurrency=concurrency, earlier_s=earlier_s,
                                                work_ratio=sum(costs) / costs[0])
                if len(chunks) > 1:
                    logger.info(estimate.line(STAGE))
            records.mark_done(out_dir, PROGRESS_RECORD, key, {"time_s": earlier_s + time.perf_counter() - tic,
                                                              "beside": beside, "conf_key": conf_key})
    chunk_path.unlink(missing_ok=True)
    return earlier_s + time.perf_counter() - tic, len(todo), estimate


def _estimate_info(estimate: eta.Estimate | None, num_done: int, elapsed_s: float) -> dict:
    """The record's figures of the estimate against the time taken (with one chunk, the estimate is
    the time taken: it was made as the matching ended)."""
    if estimate is None:
        return {}
    return {"estimate_s": estimate.seconds, "estimate_rate_pairs_per_s": estimate.rate_pairs_per_s,
            "rate_pairs_per_s": num_done / max(elapsed_s - estimate.earlier_s, 1e-6)}


#: the first chunk, whose rate gives the estimate of the time: about this share of the pairs, at
#: least MIN_FIRST_CHUNK pairs, at most a chunk, so that the estimate comes within seconds
FIRST_CHUNK_SHARE = 0.05
MIN_FIRST_CHUNK = 8


def chunked(todo: list[Pair], size: int) -> list[list[Pair]]:
    """`todo` in chunks of `size` pairs after a smaller first chunk (`FIRST_CHUNK_SHARE`)."""
    first = min(size, max(MIN_FIRST_CHUNK, math.ceil(FIRST_CHUNK_SHARE * len(todo))))
    return [todo[:first]] + [todo[k:k + size] for k in range(first, len(todo), size)] if todo else []


@dataclass(frozen=True)
class _MatchJob:
    """A chunk of pairs for a worker: it opens the features file and loads the matcher once."""

    conf: MatchConfig
    features_backend: str
    features_path: str
    pairs: list[Pair]


_MATCHERS: dict[tuple, Matcher] = {}  # per process
_READERS: dict[str, FeatureCache] = {}  # per process


def _matcher_key(conf: MatchConfig, features_backend: str) -> tuple:
    return (tuple(sorted(conf.__dict__.items())), features_backend)


def _match_chunk(job: _MatchJob) -> list[np.ndarray]:
    """(K, 2) matches of every pair of the job, in order."""
    key = _matcher_key(job.conf, job.features_backend)
    if key not in _MATCHERS:
        single_threaded_torch_in_worker()
        colmap.quiet_signals_in_worker()
        _MATCHERS.clear()
        _MATCHERS[key] = make_matcher(job.conf, job.features_backend)
    if job.features_path not in _READERS:
        for reader in _READERS.values():
            reader.close()
        _READERS.clear()
        _READERS[job.features_path] = FeatureCache(Path(job.features_path))
    matcher, reader = _MATCHERS[key], _READERS[job.features_path]
    return [np.asarray(matcher.match(reader.get(a), reader.get(b))[0], dtype=np.int32) for a, b in job.pairs]


ALIASES_NAME = "name_aliases.json"


def needs_alias(name: str) -> bool:
    """Whether COLMAP's pair importer would misread a name: it trims each line, skips lines that
    start with '#' and splits at the first space."""
    return name.startswith("#") or any(c.isspace() for c in name)


@contextlib.contextmanager
def space_free_names(db_path: Path, out_dir: Path) -> Iterator[dict[str, str]]:
    """Rename images whose names COLMAP's pair importer would misread while it runs.

    Names with spaces (anywhere, leading and trailing included) or a leading '#' become
    `sara-alias-<image_id>` in the database for the duration; the mapping is saved first, so a
    killed run is repaired on resume. Yields original name -> alias.
    """
    odd = {name: image_id for name, image_id in colmap.image_ids(db_path).items() if needs_alias(name)}
    if not odd:
        yield {}
        return
    alias = {name: f"sara-alias-{image_id}" for name, image_id in odd.items()}
    write_json_atomic(Path(out_dir) / ".sara" / ALIASES_NAME, alias)
    colmap.rename_images(db_path, {image_id: alias[name] for name, image_id in odd.items()})
    try:
        yield alias
    finally:
        restore_names([db_path], out_dir)


def restore_names(db_paths: list[Path], out_dir: Path) -> None:
    """Give aliased images their names back in each existing database of `db_paths`."""
    path = Path(out_dir) / ".sara" / ALIASES_NAME
    if not path.exists():
        return
    original = {a: name for name, a in read_json(path).items()}
    for db_path in db_paths:
        if not Path(db_path).exists():
            continue
        ids = {image_id: original[name] for name, image_id in colmap.image_ids(db_path).items() if name in original}
        colmap.rename_images(db_path, ids)
    path.unlink()


def _remove_other_pairs(db_path: Path, pairs: list[Pair], ids: dict[str, int]) -> None:
    """Delete matches of pairs that are not in `pairs` (left by another pairs file)."""
    wanted = {tuple(sorted((ids[a], ids[b]))) for a, b in pairs}
    colmap.delete_pairs_except(db_path, wanted)


def _restore(reserve: Path, work: Path, pairs: list[Pair], ids: dict[str, int]) -> None:
    """Copy the matches of the pairs not yet in `work` that `reserve` holds."""
    missing = [(ids[a], ids[b]) for a, b in _unmatched(work, pairs, ids)]
    restored = colmap.copy_pairs(reserve, work, missing) if missing else 0
    if restored:
        logger.info("match: %d pairs matched before taken from the earlier matches", restored)


def _unmatched(db_path: Path, pairs: list[Pair], ids: dict[str, int]) -> list[Pair]:
    done = colmap.has_two_view_geometry(db_path, [(ids[a], ids[b]) for a, b in pairs])
    return [pair for pair, matched in zip(pairs, done) if not matched]


def verification_stats(db_path: Path, min_num_inliers: int) -> dict:
    """Verified pairs and inlier matches per verified pair, from the database."""
    inliers = colmap.two_view_inlier_counts(db_path)
    verified = inliers[inliers >= min_num_inliers]
    return {
        "num_verified_pairs": int(len(verified)),
        "inlier_matches_per_pair_mean": float(verified.mean()) if len(verified) else 0.0,
        "inlier_matches_per_pair_median": float(np.median(verified)) if len(verified) else 0.0,
    }
