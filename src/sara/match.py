"""Stage `match`: full matching of the pairs of a pairs file with any matcher of `sara.matchers`,
then COLMAP's geometric verification, into the COLMAP database (so mapping is the same for all)."""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import colmap
from .config import MatchConfig
from .execute import Executor, SerialExecutor, single_threaded_torch_in_worker
from .io import fingerprint, read_json, records, write_json_atomic
from .io.h5 import FeatureCache
from .io.pairs import Pair, read_pairs, write_pairs
from .matchers import Matcher, make_matcher, resolve_name

logger = logging.getLogger(__name__)

STAGE = "match"
CONF_RECORD = "match-settings"
PROGRESS_RECORD = "match-progress"


def run(conf: MatchConfig, pairs_path: Path, db_path: Path, out_dir: Path, *, features_path: Path,
        features_backend: str = "sift", executor: Executor | None = None, progress: bool = True) -> Path:
    """Match every pair of `pairs_path` into the database; returns the database path (counts and
    the time taken go into the stage record).

    The database ends up holding the matches of exactly these pairs: matches left by another pairs
    file are removed first. An interrupted run resumes (COLMAP skips pairs already matched).
    """
    out_dir = Path(out_dir)
    restore_names(db_path, out_dir)  # after a run killed while names were aliased
    names = colmap.database_images(db_path)
    pairs = read_pairs(pairs_path, known_names=names)
    matcher_name = resolve_name(conf, features_backend)
    key = fingerprint({"pairs": pairs, "conf": {**conf.__dict__, "backend": matcher_name},
                       "features": Path(features_path).name})
    if records.is_done(out_dir, STAGE, key):
        logger.info("match: %d pairs already matched, skipping", len(pairs))
        return Path(db_path)
    matcher = make_matcher(conf, features_backend)  # loads weights: fails here, before any work
    conf_key = fingerprint({**conf.__dict__, "backend": matcher_name, "features": Path(features_path).name})
    if not records.is_done(out_dir, CONF_RECORD, conf_key):
        _clear_matches(db_path)  # a fresh start, or matches made with other settings
        records.mark_done(out_dir, CONF_RECORD, conf_key)
    else:
        _remove_other_pairs(db_path, pairs, names)  # keep the matches that are still wanted
    records.mark_started(out_dir, STAGE, key)

    todo = _unmatched(db_path, pairs, names)
    # time spent by earlier, interrupted runs on these very pairs counts too
    progress_record = records.read_record(out_dir, PROGRESS_RECORD) or {}
    earlier_s = float(progress_record.get("info", {}).get("time_s", 0.0)) if progress_record.get("key") == key else 0.0
    tic = time.perf_counter()
    chunk_path = out_dir / ".sara" / "match_chunk.txt"
    chunks = [todo[k:k + conf.chunk_size] for k in range(0, len(todo), conf.chunk_size)]
    with tqdm(total=len(pairs), initial=len(pairs) - len(todo), desc=f"match pairs ({matcher.name})", unit="pair",
              disable=not progress) as bar, space_free_names(db_path, out_dir) as alias:
        if hasattr(matcher, "match_in_database"):
            found: Iterator[list[np.ndarray] | None] = iter([None] * len(chunks))
        else:
            _MATCHERS[_matcher_key(conf, features_backend)] = matcher  # in this process, reuse it
            jobs = [_MatchJob(conf, features_backend, str(features_path), chunk) for chunk in chunks]
            found = (executor or SerialExecutor()).map(_match_chunk, jobs)
        for chunk, matches in zip(chunks, found):
            renamed = [(alias.get(a, a), alias.get(b, b)) for a, b in chunk]
            write_pairs(chunk_path, renamed)
            if matches is None:
                matcher.match_in_database(db_path, chunk_path)
            else:
                colmap.write_matches(db_path, dict(zip(renamed, matches)))
                colmap.verify_pairs(db_path, chunk_path, min_num_inliers=conf.min_num_inliers)
            bar.update(len(chunk))
            records.mark_done(out_dir, PROGRESS_RECORD, key, {"time_s": earlier_s + time.perf_counter() - tic})
    chunk_path.unlink(missing_ok=True)
    elapsed = earlier_s + time.perf_counter() - tic
    info = {"num_pairs": len(pairs), "num_matched_now": len(todo), "time_s": elapsed, "matcher": matcher.name,
            **verification_stats(db_path, conf.min_num_inliers)}
    records.mark_done(out_dir, STAGE, key, info)
    logger.info("match: %d pairs in %.1f s, %d verified", len(pairs), elapsed, info["num_verified_pairs"])
    return Path(db_path)


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


@contextlib.contextmanager
def space_free_names(db_path: Path, out_dir: Path) -> Iterator[dict[str, str]]:
    """Rename images whose names hold spaces while COLMAP's pair importer runs.

    The importer splits lines at spaces, so such names become `sara-alias-<image_id>` in the
    database for the duration; the mapping is saved first, so a killed run is repaired on resume.
    Yields original name -> alias.
    """
    with colmap.open_database(db_path) as db:
        spaced = {im.name: im.image_id for im in db.read_all_images() if " " in im.name}
    if not spaced:
        yield {}
        return
    alias = {name: f"sara-alias-{image_id}" for name, image_id in spaced.items()}
    write_json_atomic(Path(out_dir) / ".sara" / ALIASES_NAME, alias)
    _rename(db_path, {image_id: alias[name] for name, image_id in spaced.items()})
    try:
        yield alias
    finally:
        restore_names(db_path, out_dir)


def restore_names(db_path: Path, out_dir: Path) -> None:
    path = Path(out_dir) / ".sara" / ALIASES_NAME
    if not path.exists():
        return
    original = {a: name for name, a in read_json(path).items()}
    with colmap.open_database(db_path) as db:
        ids = {im.image_id: original[im.name] for im in db.read_all_images() if im.name in original}
    _rename(db_path, ids)
    path.unlink()


def _rename(db_path: Path, new_names: dict[int, str]) -> None:
    with colmap.open_database(db_path) as db:
        for image_id, name in new_names.items():
            image = db.read_image(image_id)
            image.name = name
            db.update_image(image)


def _clear_matches(db_path: Path) -> None:
    with colmap.open_database(db_path) as db:
        db.clear_matches()
        db.clear_two_view_geometries()


def _remove_other_pairs(db_path: Path, pairs: list[Pair], ids: dict[str, int]) -> None:
    """Delete matches of pairs that are not in `pairs` (left by another pairs file)."""
    wanted = {tuple(sorted((ids[a], ids[b]))) for a, b in pairs}
    with colmap.open_database(db_path) as db:
        for i, j, _ in colmap.verified_image_pairs(db):
            if (i, j) not in wanted:
                db.delete_matches(i, j)
                db.delete_two_view_geometry(i, j)


def _unmatched(db_path: Path, pairs: list[Pair], ids: dict[str, int]) -> list[Pair]:
    with colmap.open_database(db_path) as db:
        return [(a, b) for a, b in pairs if not db.exists_two_view_geometry(ids[a], ids[b])]


def verification_stats(db_path: Path, min_num_inliers: int) -> dict:
    """Verified pairs and inlier matches per verified pair, from the database."""
    with colmap.open_database(db_path) as db:
        _, num_inliers = db.read_two_view_geometry_num_inliers()
    inliers = np.asarray(num_inliers, dtype=np.int64)
    verified = inliers[inliers >= min_num_inliers]
    return {
        "num_verified_pairs": int(len(verified)),
        "inlier_matches_per_pair_mean": float(verified.mean()) if len(verified) else 0.0,
        "inlier_matches_per_pair_median": float(np.median(verified)) if len(verified) else 0.0,
    }
