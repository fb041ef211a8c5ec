"""Stage `match`: COLMAP's SIFT matching and geometric verification of the pairs in a pairs file."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import colmap, state
from .config import MatchConfig
from .io import fingerprint
from .pairsfile import Pair, read_pairs, write_pairs

logger = logging.getLogger(__name__)

STAGE = "match"


def run(conf: MatchConfig, pairs_path: Path, db_path: Path, out_dir: Path, *,
        progress: bool = True) -> dict:
    """Match every pair of `pairs_path` into the database; returns counts and the time taken.

    The database ends up holding the matches of exactly these pairs: matches left by another pairs
    file are removed first. An interrupted run resumes (COLMAP skips pairs already matched).
    """
    out_dir = Path(out_dir)
    names = colmap.database_images(db_path)
    pairs = read_pairs(pairs_path, known_names=names)
    if any(" " in n for pair in pairs for n in pair):
        raise ValueError("image names with spaces cannot be matched by COLMAP's pair importer; "
                         "rename the files (spaces -> '_') and run again")
    key = fingerprint({"pairs": pairs, "conf": conf.__dict__})
    if state.is_done(out_dir, STAGE, key):
        logger.info("match: %d pairs already matched, skipping", len(pairs))
        return state.done_info(out_dir, STAGE)
    record = state.read_record(out_dir, STAGE)
    if record is None or record.get("key") != key:
        _clear_matches(db_path)  # a fresh start, or matches of other pairs / settings
    state.mark_started(out_dir, STAGE, key)

    todo = _unmatched(db_path, pairs, names)
    tic = time.perf_counter()
    chunk_path = out_dir / ".sara" / "match_chunk.txt"
    with tqdm(total=len(pairs), initial=len(pairs) - len(todo), desc="match pairs", unit="pair",
              disable=not progress) as bar:
        for start in range(0, len(todo), conf.chunk_size):
            chunk = todo[start:start + conf.chunk_size]
            write_pairs(chunk_path, chunk)
            colmap.match_pairs(db_path, chunk_path, conf)
            bar.update(len(chunk))
    chunk_path.unlink(missing_ok=True)
    elapsed = time.perf_counter() - tic
    info = {"num_pairs": len(pairs), "num_matched_now": len(todo), "time_s": elapsed,
            **verification_stats(db_path, conf.min_num_inliers)}
    state.mark_done(out_dir, STAGE, key, info)
    logger.info("match: %d pairs in %.1f s, %d verified", len(pairs), elapsed, info["num_verified_pairs"])
    return info


def _clear_matches(db_path: Path) -> None:
    with colmap.open_database(db_path) as db:
        db.clear_matches()
        db.clear_two_view_geometries()


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
