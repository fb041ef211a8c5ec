"""SARA's pose-guided round: after the first model, match the unmatched pairs that add the most.

The first model's poses and points predict, for every unmatched pair of registered views, how
many of its points the two views share and how many of those are already tied to both views
through other pairs (`sara.selection.pose_guided`). The pairs whose matching adds the most
observations are matched, then the model is refined: re-triangulated with its poses held fixed
and bundle-adjusted (`refine`, used where the pipeline offers it; otherwise the pipeline maps
again from scratch with the added pairs).

Why: with the first model's poses, re-triangulating *all* of exhaustive
matching's verified pairs and bundle-adjusting reaches exhaustive matching's accuracy; the gap
left by a sparse selection is a lack of constraints, not wrong pairs nor the mapper's path. A few
pose-guided pairs per view recover most of it.

Every round takes its pairs from the one ledger, `budget.PairBudget`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path
from typing import Any

import numpy as np

from ... import colmap
from ...colmap import refine as colmap_refine
from ...features import scores_are_scales
from ...io import fingerprint, records
from ...io.pairs import Pair
from ...selection import pose_guided
from .. import PairContext
from .budget import PairBudget

logger = logging.getLogger(__name__)

STAGE = "pose_guided"


#: up to this many unmatched pairs of registered views the round predicts every one of them; above
#: it (about 200 views), each view's NEAREST_VIEWS nearest views only. Predicting a pair costs about
#: 0.5 ms: all 65,703 pairs of 363 views would take half a minute, 50 million (10,000 views) days.
MAX_ALL_PAIRS = 20_000
#: views nearest by camera centre (optical axes within 90 degrees) whose pairs the round predicts
#: on large models. On bm-moldGoldCape's model 32 already give the same choice as all 6,795 pairs
#: (24: 107 of the 114 pairs).
NEAREST_VIEWS = 48


def candidate_pairs(names: list[str], matched: list[Pair], centers: np.ndarray | None = None,
                    axes: np.ndarray | None = None) -> np.ndarray:
    """(K, 2) int64 rows of `names`, i < j: the pairs of registered views not matched yet; all of
    them up to MAX_ALL_PAIRS, else those among each view's NEAREST_VIEWS nearest views (`centers`,
    `axes`: (N, 3) camera centres and optical axes, required then)."""
    index = {n: i for i, n in enumerate(names)}
    done = {tuple(sorted((index[a], index[b]))) for a, b in matched if a in index and b in index}
    num = len(names)
    if num * (num - 1) // 2 - len(done) <= MAX_ALL_PAIRS:
        return np.array([p for p in combinations(range(num), 2) if p not in done],
                        dtype=np.int64).reshape(-1, 2)
    if centers is None or axes is None:
        raise ValueError(f"{num} views: the nearest views need the camera centres and axes")
    near = nearest_views(np.asarray(centers, np.float64), np.asarray(axes, np.float64), NEAREST_VIEWS)
    rows = np.unique(np.sort(near, axis=1), axis=0)  # never a view with itself
    keep = np.array([(int(a), int(b)) not in done for a, b in rows], dtype=bool)
    return rows[keep].reshape(-1, 2)


def nearest_views(centers: np.ndarray, axes: np.ndarray, k: int, block: int = 1024) -> np.ndarray:
    """(M, 2) int64 (view, other): each view's `k` nearest other views by centre distance among
    those whose optical axes are within 90 degrees of its own (ties: lower index), by blocks of
    rows so that memory stays O(block * N)."""
    num = len(centers)
    out = []
    for start in range(0, num, block):
        rows = np.arange(start, min(start + block, num))
        dist = ((centers[rows, None, :] - centers[None, :, :]) ** 2).sum(-1)
        dist[axes[rows] @ axes.T < 0] = np.inf
        dist[np.arange(len(rows)), rows] = np.inf
        order = np.argsort(dist, axis=1, kind="stable")[:, :k]
        for r, view in enumerate(rows):
            others = order[r][np.isfinite(dist[r, order[r]])]
            out.append(np.stack([np.full(len(others), view), others], axis=1))
    return np.concatenate(out).astype(np.int64) if out else np.zeros((0, 2), np.int64)


@dataclass
class Counts:
    """The scorer's counts (matches that fit one pose, `num_inliers_all`) of pairs whose two views it
    scores whole (no more keypoints than it uses): there the count, not a model's prediction, says
    what matching will find. `known`: pair (sorted names) -> count; `whole`: those views; `count`:
    scores more pairs of them (None: only `known`)."""

    known: dict[Pair, int]
    whole: set[str]
    count: Callable[[list[Pair]], dict[Pair, int]] | None = None

    def unknown(self, pairs: list[Pair]) -> list[Pair]:
        return [p for p in pairs if p not in self.known and self.whole.issuperset(p)]


#: rounds of counting the chosen pairs the scorer had not scored, choosing again after each (pairs still
#: not scored after the last are taken by the model's prediction)
COUNT_PASSES = 4


def select_extra(ctx: PairContext, pairs: list[Pair], model_dir: Path, counts: Counts | None = None,
                 ) -> tuple[list[Pair], dict[str, Any]]:
    """The pose-guided pairs to match next (sorted), and what the choice was based on.

    With `counts`, a pair's predicted covisible points are held to the scorer's count where it has
    one; a chosen pair of two such views that it has not scored is scored and the choice made again.
    On a low-texture stand-in (211 SIFT keypoints per image, every view scored whole) the model
    predicted 30 or more points for pairs the scorer had counted 15-37 matches in, and 18 of the
    round's 41 pairs did not verify; of the candidates counted 15-29, 17% verified under exhaustive
    matching, of those counted 45 or more all. Counted, 32 of its 33 pairs verified (lab/notes/CAPTURES.md,
    section 39)."""
    tic = time.perf_counter()
    geom = colmap_refine.read_geometry(model_dir)
    rounds, densify = ctx.conf.rounds, ctx.conf.budget.densify
    limit = PairBudget(len(ctx.names), ctx.conf.budget, rounds, ctx.max_round_pairs).pose_guided(
        len(pairs), len(geom.names))
    candidates = candidate_pairs(geom.names, pairs, geom.centers, geom.rotations[:, 2, :])
    if limit <= 0 or len(candidates) == 0:
        return [], {"budget": limit, "num_candidates": len(candidates)}
    predicted = pose_guided.covisibility(geom, candidates, max_view_angle_deg=rounds.pose_guided_max_view_angle_deg)
    named = [tuple(sorted((geom.names[a], geom.names[b]))) for a, b in candidates]
    score = ctx.conf.score
    counted = 0
    for passes in range(COUNT_PASSES + 1):  # the last choice is made with every count taken
        cov = predicted if counts is None else pose_guided.bounded_by(
            predicted, np.array([counts.known.get(p, np.inf) for p in named], dtype=np.float64))
        chosen = pose_guided.choose_pairs(candidates, cov, limit, rule="covisible" if densify else "weight",
                                          min_covisible=rounds.pose_guided_min_points,
                                          max_per_view=0 if densify else rounds.pose_guided_max_per_view,
                                          alpha=score.alpha, beta=score.beta,
                                          parallax_saturation_deg=score.parallax_saturation_deg)
        todo = counts.unknown([named[k] for k in chosen]) if counts is not None and counts.count else []
        if not todo or passes == COUNT_PASSES:
            break
        counts.known.update(counts.count(todo))
        counted += len(todo)
    floor = rounds.pose_guided_min_points
    extra = sorted(named[k] for k in chosen)
    info = {"budget": limit, "num_candidates": len(candidates), "num_chosen": len(extra),
            "rule": "covisible" if densify else "weight",
            "predicted_covisible_median": float(np.median(cov.covisible[chosen])) if len(chosen) else 0.0,
            "num_counted": counted,
            "num_counted_too_few": int(np.count_nonzero((predicted.covisible >= floor) & (cov.covisible < floor))),
            "time_s": time.perf_counter() - tic}
    return extra, info


def selection_key(first_round: list[Pair], conf: Any) -> str:
    """What a pose-guided round depends on: the first round's pairs and the settings of the graph,
    the pair budget and the pose-guided round (under "graph", the one section that held them all)."""
    rounds = {k: v for k, v in conf.rounds.__dict__.items() if k.startswith(("pose_guided_", "extend_tracks"))}
    settings = {**conf.graph.__dict__, **conf.budget.__dict__, **rounds}
    return fingerprint({"pairs": sorted(tuple(sorted(p)) for p in first_round), "graph": settings})


def recorded_pairs(out_dir: Path, key: str) -> list[Pair] | None:
    """The pairs a round with this key chose before (None when none did)."""
    record = records.read_record(out_dir, STAGE)
    if not record or record.get("key") != key or record.get("done") is not True:
        return None
    return [tuple(p) for p in record.get("info", {}).get("pairs", [])]


def mark_chosen(out_dir: Path, key: str, extra: list[Pair], info: dict[str, Any]) -> None:
    records.mark_done(out_dir, STAGE, key, {**info, "pairs": [list(p) for p in extra]})


def refine(ctx: PairContext, extra: list[Pair], db_path: Path, model_dir: Path,
           out_dir: Path) -> dict[str, Any] | None:
    """Refine the model after the pose-guided round instead of mapping again from scratch.

    Re-triangulates every match of `db_path` with the poses of `model_dir` held fixed and
    bundle-adjusts poses and points together, then extends the tracks (`rounds.extend_tracks`) and
    adjusts again, into `out_dir`. Returns its counts and time, or None when the round's pairs
    `extra` are not the pose-guided round's (views left out of the model need the mapper to
    register them) or there is no model: then map again.

    The pipeline calls this through `Rounds.refine` after every round; otherwise the round's pairs
    are mapped again from scratch.
    """
    record = records.read_record(ctx.out_dir, STAGE) or {}
    chosen = {tuple(p) for p in record.get("info", {}).get("pairs", [])}
    if record.get("done") is not True or not chosen or not colmap.has_model(model_dir):
        return None
    if chosen != {tuple(sorted(p)) for p in extra}:
        return None
    tic = time.perf_counter()
    rounds = ctx.conf.rounds
    extension = _extension(rounds, ctx.conf.extract.backend)
    counts = colmap_refine.triangulate_and_adjust(model_dir, db_path, ctx.images_root, out_dir,
                                                  num_threads=ctx.conf.map.num_threads, seed=ctx.conf.seed,
                                                  features_path=ctx.features_path,
                                                  extension=extension if rounds.extend_tracks else None,
                                                  refine_distortion=distortion_refined(ctx))
    elapsed = time.perf_counter() - tic
    logger.info("pose-guided round: re-triangulated, %d observations added to tracks, bundle-adjusted in %.1f s "
                "(%d points)", counts["observations_added"], elapsed, counts["num_points3d"])
    return {"time_s": elapsed, **counts}


def distortion_refined(ctx: PairContext) -> bool:
    """Whether a refinement's adjustment refines the cameras' distortion: not where
    `map.refine_distortion` is false. Where only the map stage's retry held it (`distortion_held`),
    the model is whole by the refinement and its adjustment refines it: on the low-texture stand-in
    holding it there too lowered AUC@1 / @5 under each of the three namings where the retry ran
    (0.0107 / 0.3025 -> 0.0078 / 0.2866 under the files' own names; lab/notes/CAPTURES.md 24)."""
    return ctx.conf.map.refine_distortion


def _extension(rounds: Any, backend: str) -> colmap_refine.TrackExtension:
    """The track extension of `rounds`; the scale test only where `backend`'s scores are scales."""
    return colmap_refine.TrackExtension(
        radius_px=rounds.extend_tracks_radius_px, max_view_angle_deg=rounds.pose_guided_max_view_angle_deg,
        scale_quantile=rounds.extend_tracks_scale_quantile if scores_are_scales(backend) else 0.0)


def finish(ctx: PairContext, model_dir: Path, out_dir: Path, *, refined: bool) -> dict[str, Any] | None:
    """Extend the tracks of the final model (`rounds.extend_tracks`) when no pose-guided refinement
    did (`refined` False: the round was skipped, the pair cap being spent, or every round mapped
    again), then bundle-adjust, into `out_dir`. None when there is nothing to do."""
    rounds = ctx.conf.rounds
    if refined or not rounds.extend_tracks or not colmap.has_model(model_dir):
        return None
    tic = time.perf_counter()
    counts = colmap_refine.extend_and_adjust(model_dir, out_dir, ctx.features_path,
                                             _extension(rounds, ctx.conf.extract.backend),
                                             refine_distortion=distortion_refined(ctx))
    elapsed = time.perf_counter() - tic
    logger.info("final model: %d observations added to tracks, bundle-adjusted in %.1f s",
                counts["observations_added"], elapsed)
    return {"time_s": elapsed, **counts}
