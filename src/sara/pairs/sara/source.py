"""The SARA pair source: retrieval -> pre-matching scores -> information-weighted spanning tree
-> loop, anchor and weak-view augmentation.

Beyond the paper: views whose every candidate was rejected for low parallax (near-duplicates,
pure rotations) are not dropped. They carry no new geometry, but a user still wants them posed,
so the best such pair by overlap "rescues" them, and likewise joins components of the selected
graph that only low-parallax pairs connect. Views with no overlapping candidate at all (another
scene) stay apart: the selected graph's components are reported and each maps to its own model.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from itertools import combinations
from typing import Any

import numpy as np

from ... import retrieval, scoring, selection
from ...config import SequenceConfig
from ...descriptors import top_k_cosine
from ...io.pairs import Pair
from ...io.scores import PairScores, concat_scores, take_scores, write_scores_csv
from ...rotations import matrix_from_rotvec
from .. import PairContext, PairResult
from . import sequence
from .budget import PairBudget
from .field_of_view import axial_motion, moving_ahead, resolve_tree_overlap

logger = logging.getLogger(__name__)

SCORES_NAME = "scores.csv"
#: candidates with less parallax than this "match at the same pixels"; from this share of them on, a warning
STILL_PARALLAX_DEG = 0.05
STILL_SHARE = 0.8
RESCUE_REASON = "low_parallax"


def select(ctx: PairContext, cached: PairScores | None = None) -> PairResult:
    """SARA's pairs of `ctx.names`. `cached`: scores of earlier candidates (an incremental update's,
    between images that did not change): a candidate found there is not scored again."""
    conf = ctx.conf
    timings: dict[str, float] = {}
    tic = time.perf_counter()
    names, edges, desc = _candidates(ctx)
    sequences = sequence.detect(names, desc, conf.sequence)
    edges, num_window = _with_window(edges, sequences, conf.sequence)
    timings["retrieval"] = time.perf_counter() - tic

    tic = time.perf_counter()
    candidates: list[Pair] = [(names[i], names[j]) for i, j in edges]
    scores, num_scored = _score_or_reuse(ctx, candidates, cached)
    timings["scoring"] = time.perf_counter() - tic
    _warn_if_still(scores)

    tic = time.perf_counter()
    axial = axial_motion(scores)
    tree_overlap, field_of_view = resolve_tree_overlap(ctx, axial)
    conf = replace(conf, score=replace(conf.score, tree_overlap=tree_overlap))
    roles, chosen_graph, rescued = _choose(len(names), edges, scores, conf)
    timings["graph"] = time.perf_counter() - tic

    widened = 0
    for neighbors in _widen_schedule(conf.retrieval.widen_neighbors, len(names)):
        labels = selection.connected_components(len(names), _selected_edges(edges, roles))
        new_edges = widen_candidates(desc, edges, labels, neighbors) if desc is not None else edges[:0]
        if len(new_edges) == 0:
            break
        tic = time.perf_counter()
        logger.info("the selected graph has %d components: scoring %d more candidates from %d neighbours of "
                    "the views outside the largest one", int(labels.max()) + 1, len(new_edges), neighbors)
        new_candidates = [(names[i], names[j]) for i, j in new_edges]
        more, num_more = _score_or_reuse(ctx, new_candidates, cached)
        scores, num_scored = concat_scores(scores, more), num_scored + num_more
        edges, candidates = np.concatenate([edges, new_edges]), candidates + new_candidates
        widened += len(new_edges)
        timings["scoring"] += time.perf_counter() - tic
        tic = time.perf_counter()
        roles, chosen_graph, rescued = _choose(len(names), edges, scores, conf)
        timings["graph"] += time.perf_counter() - tic

    labels = selection.connected_components(len(names), _selected_edges(edges, roles))
    tic = time.perf_counter()
    scores, num_ratio = rescore_outside(ctx, candidates, edges, labels, scores)
    timings["scoring"] += time.perf_counter() - tic
    if num_ratio:
        roles, chosen_graph, rescued = _choose(len(names), edges, scores, conf)

    num_chain = chain_through_time(edges, roles, scores, sequences.orders, conf.sequence) if sequences.used else 0
    write_scores_csv(ctx.out_dir / SCORES_NAME, scores, roles)
    chosen = [candidates[e] for e, role in enumerate(roles) if is_selected(role)]
    labels = selection.connected_components(len(names), _selected_edges(edges, roles))
    info = {
        "num_candidates": len(candidates),
        "num_candidates_scored": num_scored,
        "num_widened": widened,
        "num_ratio_accepted": num_ratio,
        "num_accepted": int(scores.accepted.sum()),
        "rejected": _count(r for r in scores.reason if r),
        "num_rescued": rescued,
        "num_chain": num_chain,
        "tree_overlap": tree_overlap,
        "tree_overlap_setting": ctx.conf.score.tree_overlap,
        "field_of_view_deg": field_of_view,
        "axial_motion": axial,
        "moving_ahead": moving_ahead(axial),
        "graph": chosen_graph.stats(),
        "selected_components": _component_sizes(labels),
        "sequence": sequences.summary(conf.sequence.mode, num_window),
    }
    sizes = info["selected_components"]
    if len(sizes) > 1:
        logger.warning("the selected view graph has %d components of sizes %s: they share no reliable geometry "
                       "and will map to separate models", len(sizes), sizes)
    return PairResult(chosen, info, timings, why_empty="" if chosen else _why_empty(info))


def _warn_if_still(scores: PairScores) -> None:
    """Most candidates matching at the same pixels (no parallax at all) say that the camera stood
    still, or that something moving with it fills the views; the second has a remedy (--masks)."""
    still = np.count_nonzero(np.asarray(scores.parallax_deg) < STILL_PARALLAX_DEG)
    if len(scores) >= 10 and still >= STILL_SHARE * len(scores):
        logger.warning("%d of %d candidate pairs match at the same pixels (parallax under %g degrees): the camera "
                       "stood still, or something that moves with it fills the views (a hand, a car's bonnet, a "
                       "mount): leave it out with --masks", still, len(scores), STILL_PARALLAX_DEG)


def _why_empty(info: dict[str, Any]) -> str:
    rejected = ", ".join(f"{k} {v}" for k, v in sorted(info.get("rejected", {}).items())) or "none"
    return (f"the sara pair source selected no pairs: {info.get('num_accepted', 0)} of {info['num_candidates']} "
            f"candidate pairs accepted (rejected: {rejected}); the images may not overlap, or relax the score.* "
            "thresholds")


def rescore_outside(ctx: PairContext, candidates: list[Pair], edges: np.ndarray, labels: np.ndarray,
                    scores: PairScores) -> tuple[PairScores, int]:
    """The rejected candidates of the views outside the largest component of the selected graph
    (`labels` 0), scored again with Lowe's ratio test (`rounds.repair_descriptor_ratio`); those it
    accepts replace their first scores. Returns the scores and how many it accepted.

    The scorer pre-matches by raw descriptor similarity. Across a wide baseline most of its best
    matches are wrong, so a view whose true partners share plenty of matches can have every
    candidate rejected (an orbit video picked sparsely: 10 inliers among the 50 best matches for
    a pair that exhaustive matching verifies with 154). The ratio test finds those matches; it is
    kept to the views that are cut off, because across the whole selection it changes pairs that
    were fine (bm-moldGoldCape: AUC@1 0.944 -> 0.925, lab/notes/CAPTURES.md section 10).
    """
    ratio = ctx.conf.rounds.repair_descriptor_ratio
    if ratio >= 1.0 or len(edges) == 0 or labels.max(initial=0) == 0:
        return scores, 0
    outside = labels != 0
    todo = np.flatnonzero((outside[edges[:, 0]] | outside[edges[:, 1]]) & ~scores.accepted)
    if len(todo) == 0:
        return scores, 0
    again = score_with_ratio_test(ctx, [candidates[e] for e in todo])
    better = np.flatnonzero(again.accepted)
    logger.info("%d rejected candidates of %d views outside the largest part of the selected graph scored again "
                "with a ratio test of %.2f: %d accepted", len(todo), int(outside.sum()), ratio, len(better))
    if len(better) == 0:
        return scores, 0
    order = np.arange(len(scores))
    order[todo[better]] = len(scores) + better
    return take_scores(concat_scores(scores, again), order), len(better)


def score_with_ratio_test(ctx: PairContext, candidates: list[Pair], *, progress: bool | None = None
                          ) -> scoring.PairScores:
    """`candidates` scored with Lowe's ratio test (`rounds.repair_descriptor_ratio`) in the pre-match."""
    ratio = ctx.conf.rounds.repair_descriptor_ratio
    return _score(ctx, candidates, replace(ctx.conf.score, max_descriptor_ratio=ratio), progress=progress)


def score_pairs_of(ctx: PairContext, candidates: list[Pair]) -> scoring.PairScores:
    """`candidates` scored as the selection scores them, quietly."""
    return _score(ctx, candidates, progress=False)


def _score(ctx: PairContext, candidates: list[Pair], score_conf: Any = None, *,
           progress: bool | None = None) -> scoring.PairScores:
    conf = ctx.conf
    return scoring.score_pairs(candidates, ctx.features_path, ctx.db_path, score_conf or conf.score,
                               executor=ctx.executor,
                               shard_size=conf.execute.shard_size, work_dir=ctx.out_dir / ".sara",
                               progress=ctx.progress if progress is None else progress, seed=conf.seed,
                               journal=ctx.score_journal)


def _score_or_reuse(ctx: PairContext, candidates: list[Pair],
                    cached: PairScores | None) -> tuple[PairScores, int]:
    """The scores of `candidates` in their order, those of `cached` reused (a pair found there the
    other way round gets its inverse pose), the others scored; and how many were scored."""
    if cached is None:
        return _score(ctx, candidates), len(candidates)
    row = {(a, b): k for k, (a, b) in enumerate(zip(cached.name0, cached.name1))}
    todo = [(a, b) for a, b in candidates if (a, b) not in row and (b, a) not in row]
    known = len(cached)
    pool = concat_scores(cached, _score(ctx, todo)) if todo else cached
    fresh = {pair: known + k for k, pair in enumerate(todo)}
    order = [row.get((a, b), row.get((b, a), fresh.get((a, b)))) for a, b in candidates]
    scores = take_scores(pool, order)
    for k, (a, b) in enumerate(candidates):
        if scores.name0[k] != a:  # stored as (b, a)
            scores.name0[k], scores.name1[k] = a, b
            scores.direction[k] = -matrix_from_rotvec(scores.rotvec[k]).T @ scores.direction[k]
            scores.rotvec[k] = -scores.rotvec[k]
    return scores, len(todo)


def _choose(num_images: int, edges: np.ndarray, scores: scoring.PairScores, conf: Any):
    """Roles of the candidates (spanning tree, augmentation, low-parallax rescue)."""
    selection.mark_inconsistent(num_images, edges, scores, conf.graph)  # in place: reason "inconsistent"
    max_pairs = PairBudget(num_images, conf.budget, conf.rounds).first_round()
    chosen_graph = selection.select_pairs(num_images, edges, scores.weight, scores.parallax_deg, scores.accepted,
                                          conf.graph, max_pairs=max_pairs,
                                          tree_weight=scoring.tree_weights(scores, conf.score))
    roles = list(chosen_graph.role)
    rescued = rescue_low_parallax(num_images, edges, roles, scores)
    return roles, chosen_graph, rescued


def _widen_schedule(neighbors: int, num_images: int) -> list[int]:
    """Neighbour counts of the widening rounds: `neighbors`, then four times as many (each at most
    N - 1; none when 0)."""
    if neighbors <= 0:
        return []
    out: list[int] = []
    for k in (neighbors, 4 * neighbors):
        k = min(k, num_images - 1)
        if not out or k > out[-1]:
            out.append(k)
    return out


def widen_candidates(desc: np.ndarray, edges: np.ndarray, labels: np.ndarray, neighbors: int) -> np.ndarray:
    """New candidate pairs for the views outside the largest component of the selected graph.

    Views whose candidates were all rejected (weak texture, hard illumination) or missed by the kNN
    are cut off from the model. Their `neighbors` nearest global descriptors give more candidates,
    views of the smallest components first, at most as many new pairs as there are candidates
    already (each of the two rounds at most doubles the scoring). Returns (E', 2) int64 pairs i < j, none of
    them in `edges`, in a deterministic order.
    """
    sizes = np.bincount(labels)
    outside = np.flatnonzero(labels != 0)
    if len(outside) == 0 or len(sizes) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    outside = outside[np.argsort(sizes[labels[outside]], kind="stable")]  # smallest components first
    known = {(int(a), int(b)) for a, b in edges}
    budget = max(len(edges), neighbors)
    new: list[tuple[int, int]] = []
    for start in range(0, len(outside), 256):
        rows = outside[start:start + 256]
        nbrs = top_k_cosine(desc, neighbors, queries=rows)
        for i, row in zip(rows, nbrs):
            for j in row:
                pair = (min(int(i), int(j)), max(int(i), int(j)))
                if pair not in known:
                    known.add(pair)
                    new.append(pair)
        if len(new) >= budget:
            break
    return np.array(new[:budget], dtype=np.int64).reshape(-1, 2)


def _candidates(ctx: PairContext) -> tuple[list[str], np.ndarray, np.ndarray | None]:
    """Image names, (E, 2) int64 candidate pairs and the global descriptors: the kNN of the global
    descriptors, or every pair when k >= N - 1 (then kNN would return them all: the descriptors are
    not computed, None)."""
    conf = ctx.conf
    if conf.retrieval.num_neighbors >= len(ctx.names) - 1:
        names = list(ctx.names)
        pairs = np.array(list(combinations(range(len(names)), 2)), dtype=np.int64).reshape(-1, 2)
        return names, pairs, None
    global_path = retrieval.run(conf.retrieval, ctx.features_path, ctx.names, ctx.out_dir,
                                images_root=ctx.images_root, progress=ctx.progress, seed=conf.seed)
    names, desc = retrieval.read_global(global_path)
    return names, retrieval.knn_pairs(desc, conf.retrieval.num_neighbors).astype(np.int64), desc


def _with_window(edges: np.ndarray, sequences: sequence.Sequences, conf: SequenceConfig) -> tuple[np.ndarray, int]:
    """The candidates and, in a sequence, each frame's `conf.window` following frames (appended, kNN
    pairs first); returns them and how many the window added."""
    if not sequences.used:
        frames = sequences.num_frames
        if sequences.too_short:
            logger.info("sequence: the names number %d frames, fewer than sequence.auto_min_frames (%d): the "
                        "retrieval neighbours alone (--sequence yes adds the window)", frames, conf.auto_min_frames)
        elif sequences.agreement is not None:
            logger.info("sequence: the names number %d frames, but only %.0f%% of the images' nearest global "
                        "descriptors are neighbouring frames (%.0f%% needed): not used as an order (--sequence yes "
                        "uses it)", frames, 100 * sequences.agreement,
                        100 * (sequences.needed or 0.0))
        return edges, 0
    known = {(int(a), int(b)) for a, b in edges}
    window = sequence.window_pairs(sequences.orders, conf.window).tolist()
    extra = np.array([p for p in window if tuple(p) not in known], dtype=np.int64).reshape(-1, 2)
    if len(extra):
        logger.info("sequence: %d frames in %d sequence(s); %d candidate pairs of neighbouring frames added to "
                    "the retrieval neighbours", sequences.num_frames, len(sequences.orders), len(extra))
    return np.concatenate([edges.reshape(-1, 2), extra]), len(extra)


def rescue_low_parallax(num_images: int, edges: np.ndarray, roles: list[str], scores: scoring.PairScores) -> int:
    """Join components of the selected graph with pairs rejected only for low parallax.

    A maximum spanning forest over the components, weighted by overlap; sets their role to
    "rescue" in place and returns how many were added.
    """
    selected = _selected_edges(edges, roles)
    labels = selection.connected_components(num_images, selected)
    pool = np.array([e for e, r in enumerate(scores.reason) if r == RESCUE_REASON and roles[e] == "rejected"
                     and labels[edges[e, 0]] != labels[edges[e, 1]]], dtype=np.int64)
    if len(pool) == 0:
        return 0
    pool = pool[np.argsort(-scores.overlap[pool], kind="stable")]
    comp_edges = np.sort(np.stack([labels[edges[pool, 0]], labels[edges[pool, 1]]], axis=1), axis=1)
    _, first = np.unique(comp_edges, axis=0, return_index=True)  # the best pair per two components
    first = np.sort(first)
    pool, comp_edges = pool[first], comp_edges[first]
    chosen = selection.maximum_spanning_forest(int(labels.max()) + 1, comp_edges, scores.overlap[pool])
    for e in pool[chosen]:
        roles[e] = "rescue"
    return len(chosen)


def chain_through_time(edges: np.ndarray, roles: list[str], scores: scoring.PairScores, orders: list[list[int]],
                       conf: SequenceConfig) -> int:
    """In each sequence, each frame's `conf.chain` best accepted candidates (by weight; on a tie the
    candidate listed first) among the `conf.window` frames after it that the selection left out:
    their role becomes "chain" in place; returns how many.

    The spanning tree and its loops follow the weight, which does not prefer near frames: on a
    1,000-frame walk that passes places again, 480 of the tree's 999 edges joined frames 9 or more
    apart, and the first graph mapped to 815 views. The incremental mapper needs the chain between
    the loops: with each frame's best candidate among the next 8 frames added (797 pairs), 995 views
    in one model; as many pairs by weight alone, 918. End to end (window 5, the same pair cap, one run each):
    AUC@1 0.920 -> 0.930 at 1,000 images, 0.908 -> 0.921 at 3,000 (lab/notes/SCALE.md, thirty-ninth
    session)."""
    if conf.chain <= 0 or len(edges) == 0:
        return 0
    position = {int(view): (k, i) for k, order in enumerate(orders) for i, view in enumerate(order)}
    forward: dict[int, list[tuple[float, int]]] = {}
    for e, (a, b) in enumerate(edges.tolist()):
        if roles[e] != "unselected" or a not in position or b not in position:
            continue
        (seq_a, at_a), (seq_b, at_b) = position[a], position[b]
        if seq_a == seq_b and 0 < abs(at_b - at_a) <= conf.window:
            first = a if at_a < at_b else b
            forward.setdefault(first, []).append((-float(scores.weight[e]), e))
    added = 0
    for options in forward.values():
        for _, e in sorted(options)[:conf.chain]:
            roles[e] = "chain"
            added += 1
    if added:
        logger.info("sequence: %d pairs between near frames added to the selection (the chain through time)", added)
    return added


#: roles of pairs chosen besides the selection's own (`selection.SELECTED_ROLES`)
CHOSEN_ROLES = ("rescue", "chain")


def is_selected(role: str) -> bool:
    """Whether a candidate of this role is one of the selection's pairs."""
    return role in selection.SELECTED_ROLES or role in CHOSEN_ROLES


def _selected_edges(edges: np.ndarray, roles: list[str]) -> np.ndarray:
    mask = np.array([is_selected(r) for r in roles], dtype=bool)
    return edges[mask] if len(edges) else edges.reshape(0, 2)


def _component_sizes(labels: np.ndarray) -> list[int]:
    return sorted(np.bincount(labels).tolist(), reverse=True) if len(labels) else []


def _count(items) -> dict[str, int]:
    out: dict[str, int] = {}
    for item in items:
        out[item] = out.get(item, 0) + 1
    return out
