"""SARA's rounds around mapping, behind the `sara.pairs.Rounds` seam:

- before the first mapping, `support` pairs for views whose matched pairs hold few inliers;
- after it, `repair` pairs for views the mapper left out of the main model; where a repair left
  most of its views out, once, the `fill` pairs (the best unmatched candidates of all views, up to
  the cap); or else, once, the `pose-guided` pairs the first model predicts to add the most
  observations; the model is then refined with its poses fixed instead of mapped again
  (`pose_guided.refine`);
- on the final model, when no refinement did it, its tracks are extended (`pose_guided.finish`).

Every round takes its pairs from the one ledger, `budget.PairBudget`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ... import colmap
from ...io import fingerprint, records
from ...io.h5 import keypoint_counts
from ...io.pairs import Pair
from ...io.scores import read_scores_csv
from ...matchers import resolve_name
from .. import NoRounds, PairContext, Round
from . import pose_guided
from .budget import PairBudget
from .repair import fill_pairs, left_out_views, neighbour_pairs, repair_pairs
from .source import SCORES_NAME, is_selected, score_pairs_of, score_with_ratio_test
from .support import support_pairs, view_inliers

logger = logging.getLogger(__name__)

#: record of the last repair round: the views it was for and the pairs it led to
REPAIR_STAGE = "repair_views"
#: record of the pairs added before the first mapping for weakly matched views
SUPPORT_STAGE = "support"
#: record of the fill round's pairs (once per selection)
FILL_STAGE = "fill"
#: matchers whose matches are the mutual nearest neighbours the scorer counts (`_fully_scored`)
NEAREST_NEIGHBOUR_MATCHERS = ("colmap", "nearest")


def budget_of(ctx: PairContext) -> PairBudget:
    return PairBudget(len(ctx.names), ctx.conf.budget, ctx.conf.rounds, ctx.max_round_pairs)


class SaraRounds(NoRounds):
    """SARA's `sara.pairs.Rounds`."""

    def before_mapping(self, ctx: PairContext, pairs: list[Pair], db_path: Path) -> Round:
        return Round(before_mapping(ctx, pairs, db_path), "support")

    def after_mapping(self, ctx: PairContext, pairs: list[Pair], model_dir: Path) -> Round:
        return after_mapping(ctx, pairs, model_dir)

    def refine(self, ctx: PairContext, added: Round, db_path: Path, model_dir: Path,
               out_model_dir: Path) -> dict[str, Any] | None:
        return pose_guided.refine(ctx, added.pairs, db_path, model_dir, out_model_dir)

    def finish(self, ctx: PairContext, model_dir: Path, out_model_dir: Path, *, refined: bool) -> dict[str, Any] | None:
        return pose_guided.finish(ctx, model_dir, out_model_dir, refined=refined)


def after_mapping(ctx: PairContext, pairs: list[Pair], model_dir: Path) -> Round:
    """More pairs once a model exists, within the cap of all rounds (`BudgetConfig.pair_cap`):

    1. views that the mapper left out of the main model although the selected graph joins them to
       it: their best unselected candidates into the main model and pairs between their
       neighbours there (`repair.py`), unless the last round was such a repair and most of its
       views are still out (`_repair_stalled`; once the fill round's pairs are matched, one more
       repair may run);
    2. then, while views are still out (the repair stalled, or found no candidate into the model),
       once: the best unmatched candidates of all views by weight, up to the cap (`repair.fill_pairs`);
    3. otherwise, once: the pose-guided round (`pose_guided.py`), the unmatched pairs of registered
       views that the model predicts to add the most observations; also in the pipeline's last round
       (`ctx.last_round`, once the repairs used up theirs), whatever views are still out.

    Returns the pairs and their role (`repair`, `fill` or `pose-guided`).
    """
    if ctx.last_round:  # the repairs had their rounds: the pose-guided pairs only, refined in place
        return Round(pose_guided_round(ctx, pairs, model_dir), "pose-guided")
    main = colmap.registered_images(model_dir)
    left_out = left_out_views(ctx.names, pairs, main)
    key = _selection_key(ctx) if left_out else ""
    if left_out and not _repair_stalled(ctx, key, pairs, left_out):
        extra = _repair_round(ctx, pairs, main, left_out)
        if extra:
            logger.warning("%d views were left out of the main model: matching %d more pairs and mapping again",
                           len(left_out), len(extra))
            records.mark_done(ctx.out_dir, REPAIR_STAGE, key,
                              {"left_out": sorted(left_out), "pairs": _pairs_key(pairs + extra), "stalled": False,
                               "after_fill": _filled(ctx, key, pairs)})
            return Round(extra, "repair")
    if left_out and (extra := fill_round(ctx, pairs, key, len(left_out))):
        return Round(extra, "fill")
    return Round(pose_guided_round(ctx, pairs, model_dir), "pose-guided")


def _repair_round(ctx: PairContext, pairs: list[Pair], main: set[str], left_out: list[str]) -> list[Pair]:
    """The repair's pairs, within its room: for each left-out view its best candidates into the main
    model (`repair_pairs`) and pairs between its neighbours in the model (`neighbour_pairs`), taken
    one of each per view in turn, so that a short room still reaches every view."""
    per_view = ctx.conf.rounds.repair_pairs_per_view
    own = repair_pairs(ctx.out_dir / SCORES_NAME, pairs, main, left_out, per_view, rescore=_ratio_rescore(ctx),
                       min_inliers=ctx.conf.match.min_num_inliers,
                       fully_scored=_fully_scored(ctx, main | set(left_out)))
    own_by_view: dict[str, list[Pair]] = {v: [] for v in left_out}
    targets = set(left_out)
    for pair in own:
        own_by_view[pair[0] if pair[0] in targets else pair[1]].append(pair)
    linked = colmap.verified_inliers(ctx.db_path, ctx.conf.match.min_num_inliers)
    near = neighbour_pairs(ctx.out_dir / SCORES_NAME, pairs, main, left_out, linked, per_view)
    ordered: list[Pair] = []
    for k in range(per_view):
        for view in left_out:
            ordered += [p[k] for p in (own_by_view[view], near[view]) if len(p) > k]
    room = budget_of(ctx).repair(len(pairs), len(left_out))
    taken = ordered[:room]
    num_near = len(set(taken) & {p for v in left_out for p in near[v]})
    logger.info("repair: %d pairs into the main model, %d between the left-out views' neighbours in it",
                len(taken) - num_near, num_near)
    return sorted(taken)


def _fully_scored(ctx: PairContext, views: set[str]) -> set[str]:
    """The `views` whose every keypoint the scorer used (no more than `score.num_keypoints`); none where
    the matcher is not a nearest-neighbour one: LightGlue finds matches the scorer's nearest
    neighbours miss, so their count does not tell whether its matching of the pair will verify."""
    if resolve_name(ctx.conf.match, ctx.conf.extract.backend) not in NEAREST_NEIGHBOUR_MATCHERS:
        return set()
    counts = keypoint_counts(ctx.features_path, sorted(views))
    return {view for view, num in counts.items() if num <= ctx.conf.score.num_keypoints}


def _ratio_rescore(ctx: PairContext) -> Callable[[list[Pair]], dict[Pair, int]] | None:
    """The repair's scoring of candidates with Lowe's ratio test (`rounds.repair_descriptor_ratio`):
    pair -> inliers of its pose among all mutual matches; None when the ratio is 1 (off)."""
    ratio = ctx.conf.rounds.repair_descriptor_ratio
    if ratio >= 1.0:
        return None

    def rescore(candidates: list[Pair]) -> dict[Pair, int]:
        scores = score_with_ratio_test(ctx, candidates, progress=False)
        logger.info("repair: %d candidates of the left-out views scored again with a ratio test of %.2f",
                    len(candidates), ratio)
        return {pair: int(n) for pair, n in zip(candidates, scores.num_inliers_all)}

    return rescore


def fill_round(ctx: PairContext, pairs: list[Pair], key: str, num_left_out: int) -> list[Pair]:
    """The fill pairs, once per selection (`key`, `_selection_key`): [] once they are matched, the
    same pairs again after an interruption."""
    record = records.read_record(ctx.out_dir, FILL_STAGE)
    if record and record.get("done") is True and record.get("key") == key:
        return _still_to_match([(a, b) for a, b in record.get("info", {}).get("pairs", [])], pairs)
    extra = fill_pairs(ctx.out_dir / SCORES_NAME, pairs, budget_of(ctx).fill(len(pairs)))
    records.mark_done(ctx.out_dir, FILL_STAGE, key, {"left_out": num_left_out, "pairs": [list(p) for p in extra]})
    if extra:
        logger.warning("%d views are still out of the main model after a repair for them: the graph is too sparse "
                       "there; matching the %d best remaining candidates and mapping again", num_left_out, len(extra))
    return extra


def before_mapping(ctx: PairContext, pairs: list[Pair], db_path: Path) -> list[Pair]:
    """More pairs, matched before the first mapping, for the views whose verified pairs in `db_path`
    hold few inlier matches (`support.py`), within half of the room the pair budget leaves (the
    pose-guided round after mapping keeps the rest); from `rounds.fill_before_map_images` images
    also the best remaining candidates up to the cap (`repair.fill_pairs`). Once per selection: []
    once they are matched, the same pairs again after an interruption."""
    conf = ctx.conf.rounds
    supports = conf.support_min_view_inliers > 0 and conf.support_pairs_per_view > 0
    fills = 0 < conf.fill_before_map_images <= len(ctx.names)
    if not supports and not fills:
        return []
    key = fingerprint({"selection": _selection_key(ctx), "min_view_inliers": conf.support_min_view_inliers,
                       "per_view": conf.support_pairs_per_view} | ({"fill": True} if fills else {}))
    record = records.read_record(ctx.out_dir, SUPPORT_STAGE)
    if record and record.get("done") is True and record.get("key") == key:
        return _still_to_match([(a, b) for a, b in record.get("info", {}).get("pairs", [])], pairs)
    support = view_inliers(ctx.names, pairs, colmap.verified_inliers(db_path, ctx.conf.match.min_num_inliers))
    weak = sum(1 for s in support.values() if s < conf.support_min_view_inliers)
    extra = support_pairs(ctx.out_dir / SCORES_NAME, pairs, support, conf.support_min_view_inliers,
                          conf.support_pairs_per_view, budget_of(ctx).support(len(pairs)),
                          order=view_inliers(ctx.names, pairs, colmap.match_counts(db_path))) \
        if weak and supports else []
    filled = fill_pairs(ctx.out_dir / SCORES_NAME, pairs + extra, budget_of(ctx).cap - len(pairs) - len(extra)) \
        if fills else []
    records.mark_done(ctx.out_dir, SUPPORT_STAGE, key, {
        "num_weak_views": weak, "view_inliers_median": float(np.median(list(support.values()) or [0])),
        "num_fill": len(filled), "pairs": [list(p) for p in extra + filled]})
    if extra:
        logger.info("%d views have fewer than %d verified inlier matches in all: matching %d more pairs before "
                    "mapping", weak, conf.support_min_view_inliers, len(extra))
    if filled:
        logger.info("%d images (rounds.fill_before_map_images: %d): matching the %d best remaining candidates, up "
                    "to the pair cap, before the first mapping", len(ctx.names), conf.fill_before_map_images,
                    len(filled))
    return extra + filled


def _still_to_match(chosen: list[Pair], pairs: list[Pair]) -> list[Pair]:
    """Pairs a round chose before: none once they are all matched, all of them again when a run
    stopped before they were."""
    matched = {tuple(sorted(p)) for p in pairs}
    return [] if all(tuple(sorted(p)) in matched for p in chosen) else chosen


def _pairs_key(pairs: list[Pair]) -> str:
    return fingerprint(sorted(tuple(sorted(p)) for p in pairs))


def _repair_stalled(ctx: PairContext, key: str, pairs: list[Pair], left_out: list[str]) -> bool:
    """True when most views of the last repair round are still out of the main model (and no other
    view has dropped out since); `key`: the selection the record must belong to (`_selection_key`).

    That round's pairs, each left-out view's best candidates into the model, did not tie them to
    it; the next best are weaker still, and every repair round maps again (on a low-texture
    scene, 4 s a round against 2.7 s for exhaustive matching's whole mapping, which leaves the
    same views out). The views stay out, with a warning, and the rounds go to the pose-guided
    pairs of the views in the model.
    """
    record = records.read_record(ctx.out_dir, REPAIR_STAGE)
    if not record or record.get("done") is not True or record.get("key") != key:
        return False
    info = record.get("info", {})
    before = set(info.get("left_out", []))
    if info.get("stalled"):
        # the fill round's pairs came after this verdict: the part is denser now, one more repair may tie
        # the views in (with pairs between their new neighbours); a repair after the fill stalls for good
        return set(left_out) <= before and (info.get("after_fill", False) or not _filled(ctx, key, pairs))
    still = before & set(left_out)
    if info.get("pairs") != _pairs_key(pairs) or set(left_out) - before or 2 * len(still) <= len(before):
        return False
    records.mark_done(ctx.out_dir, REPAIR_STAGE, key, {**info, "stalled": True})
    logger.warning("%d of the %d views of the last repair round are still out of the main model: leaving them out",
                   len(still), len(before))
    return True


def _filled(ctx: PairContext, key: str, pairs: list[Pair]) -> bool:
    """True when the fill round of this selection (`key`) chose pairs and all of them are matched."""
    record = records.read_record(ctx.out_dir, FILL_STAGE)
    if not record or record.get("done") is not True or record.get("key") != key:
        return False
    chosen = [tuple(p) for p in record.get("info", {}).get("pairs", [])]
    return bool(chosen) and not _still_to_match(chosen, pairs)


def _selection_key(ctx: PairContext) -> str:
    """The first round's pairs: a record of another selection does not apply."""
    scores = ctx.out_dir / SCORES_NAME
    return _pairs_key(_first_round(scores)) if scores.exists() else ""


def pose_guided_round(ctx: PairContext, pairs: list[Pair], model_dir: Path) -> list[Pair]:
    """The pose-guided pairs (once per selection; [] when done, disabled or nothing is worth it)."""
    conf = ctx.conf
    if (conf.rounds.pose_guided_pairs_per_image <= 0 and not conf.budget.densify) or not colmap.has_model(model_dir):
        return []
    key = pose_guided.selection_key(_first_round(ctx.out_dir / SCORES_NAME), conf)
    done = pose_guided.recorded_pairs(ctx.out_dir, key)
    if done is not None:
        return _still_to_match(done, pairs)
    extra, info = pose_guided.select_extra(ctx, pairs, model_dir, counts=_counts(ctx))
    pose_guided.mark_chosen(ctx.out_dir, key, extra, info)
    if info.get("num_counted_too_few"):
        logger.info("pose-guided round: %d pairs the model predicts enough points for are left out: the scorer, "
                    "which saw every keypoint of both views, counted fewer matches", info["num_counted_too_few"])
    if extra:
        logger.info("pose-guided round: matching %d more pairs (predicted covisible points, median %.0f)",
                    len(extra), info.get("predicted_covisible_median", 0.0))
    return extra


def _counts(ctx: PairContext) -> pose_guided.Counts | None:
    """The scorer's counts for the pose-guided round (`pose_guided.Counts`): those of `scores.csv`
    between views it scored whole (`_fully_scored`), and its scoring for others of them; None where
    no view was scored whole."""
    whole = _fully_scored(ctx, set(ctx.names))
    if not whole:  # the ordinary case: no second reading of scores.csv
        return None
    scores, _ = read_scores_csv(ctx.out_dir / SCORES_NAME)
    if scores.num_inliers_all is None:
        return None
    known = {tuple(sorted((a, b))): int(n) for a, b, n in zip(scores.name0, scores.name1, scores.num_inliers_all)
             if a in whole and b in whole}

    def count(pairs: list[Pair]) -> dict[Pair, int]:
        found = score_pairs_of(ctx, pairs)
        return {tuple(sorted(p)): int(n) for p, n in zip(pairs, found.num_inliers_all)}

    return pose_guided.Counts(known, whole, count)


def _first_round(scores_csv: Path) -> list[Pair]:
    scores, roles = read_scores_csv(scores_csv)
    roles = roles or [""] * len(scores)
    return [(a, b) for a, b, r in zip(scores.name0, scores.name1, roles) if is_selected(r)]


#: the pipeline may refine the model after the pose-guided round instead of mapping again
after_mapping.refine = pose_guided.refine  # type: ignore[attr-defined]
#: and extend the final model's tracks when no refinement did
after_mapping.finish = pose_guided.finish  # type: ignore[attr-defined]
#: before the first mapping: more pairs for weakly matched views
after_mapping.before_mapping = before_mapping  # type: ignore[attr-defined]
