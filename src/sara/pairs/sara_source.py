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
from pathlib import Path
from typing import Any

import numpy as np

from .. import colmap, extract, retrieval, scoring, selection
from ..descriptors import top_k_cosine
from ..io import fingerprint, records
from ..io.pairs import Pair
from ..io.scores import concat_scores, read_scores_csv, write_scores_csv
from ..scoring import focal
from . import PairContext, PairResult, pose_guided
from .repair import left_out_views, repair_pairs
from .support import support_pairs, view_inliers

logger = logging.getLogger(__name__)

SCORES_NAME = "scores.csv"
RESCUE_REASON = "low_parallax"
#: record of the last repair round: the views it was for and the pairs it led to
REPAIR_STAGE = "repair_views"
#: record of the pairs added before the first mapping for weakly matched views
SUPPORT_STAGE = "support"


def select(ctx: PairContext) -> PairResult:
    conf = ctx.conf
    timings: dict[str, float] = {}
    tic = time.perf_counter()
    names, edges, desc = _candidates(ctx)
    timings["retrieval"] = time.perf_counter() - tic

    tic = time.perf_counter()
    candidates: list[Pair] = [(names[i], names[j]) for i, j in edges]
    scores = _score(ctx, candidates)
    timings["scoring"] = time.perf_counter() - tic

    tic = time.perf_counter()
    tree_overlap, field_of_view = resolve_tree_overlap(ctx)
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
        scores = concat_scores(scores, _score(ctx, new_candidates))
        edges, candidates = np.concatenate([edges, new_edges]), candidates + new_candidates
        widened += len(new_edges)
        timings["scoring"] += time.perf_counter() - tic
        tic = time.perf_counter()
        roles, chosen_graph, rescued = _choose(len(names), edges, scores, conf)
        timings["graph"] += time.perf_counter() - tic

    write_scores_csv(ctx.out_dir / SCORES_NAME, scores, roles)
    chosen = [candidates[e] for e, role in enumerate(roles) if role in selection.SELECTED_ROLES or role == "rescue"]
    labels = selection.connected_components(len(names), _selected_edges(edges, roles))
    info = {
        "num_candidates": len(candidates),
        "num_widened": widened,
        "num_accepted": int(scores.accepted.sum()),
        "rejected": _count(r for r in scores.reason if r),
        "num_rescued": rescued,
        "tree_overlap": tree_overlap,
        "tree_overlap_setting": ctx.conf.score.tree_overlap,
        "field_of_view_deg": field_of_view,
        "graph": chosen_graph.stats(),
        "selected_components": _component_sizes(labels),
    }
    sizes = info["selected_components"]
    if len(sizes) > 1:
        logger.warning("the selected view graph has %d components of sizes %s: they share no reliable geometry "
                       "and will map to separate models", len(sizes), sizes)
    return PairResult(chosen, info, timings)


def _score(ctx: PairContext, candidates: list[Pair]) -> scoring.PairScores:
    conf = ctx.conf
    return scoring.score_pairs(candidates, ctx.features_path, ctx.db_path, conf.score, executor=ctx.executor,
                               shard_size=conf.execute.shard_size, work_dir=ctx.out_dir / ".sara",
                               progress=ctx.progress, seed=conf.seed)


#: a known field of view at least this wide (degrees, across the larger image side) makes the
#: spanning tree of the most overlapping pairs (`score.tree_overlap=auto`; see `resolve_tree_overlap`).
#: Measured (docs/ACCURACY.md 19): at 31-33 degrees (half-size centre crops of Strecha scenes) and
#: at 58 that tree gains or both pass; at 27 (bm-moldGoldCape) it costs 0.004 AUC@1, at 16 (quarter
#: crops) 0.16-0.40
WIDE_FIELD_OF_VIEW_DEG = 30.0


def resolve_tree_overlap(ctx: PairContext) -> tuple[str, float | None]:
    """The overlap the spanning tree ranks by (`ScoreConfig.tree_overlap`), and the images' known
    field of view (None where unknown).

    ``auto`` takes ``all`` (the inliers among all mutual matches: trees of the nearest, most
    overlapping views) when the images' field of view is known and at least WIDE_FIELD_OF_VIEW_DEG,
    else ``best`` (the paper's weight, which prefers wider baselines). With a wide lens a short
    baseline still fixes the relative pose well; with a long lens (or a turntable, whose focal
    length the images cannot tell) it does not, and the trees of the nearest views lost up to 0.4
    AUC@1 on long-lens crops (docs/ACCURACY.md 16.3, 19).
    """
    mode = ctx.conf.score.tree_overlap
    fov = known_field_of_view(ctx.db_path, ctx.names, ctx.features_path)
    if mode != "auto":
        return mode, fov
    return ("all" if fov is not None and fov >= WIDE_FIELD_OF_VIEW_DEG else "best"), fov


def known_field_of_view(db_path: Path, names: list[str], features_path: Path | None = None) -> float | None:
    """The median field of view (degrees, larger image side) of `names`, over the images whose
    focal length is known: from EXIF or `extract.camera_params` (the camera's prior focal length),
    or a sound estimate from the images (`sara.scoring.focal`, the extract stage's record). None
    when it is known for fewer than half of them.

    Features extracted by sara 0.1 before the estimate's soundness was recorded get it estimated
    again from `features_path` (a few seconds), so a resumed run chooses as a new one does."""
    cameras = colmap.cameras_by_image(db_path)
    estimate = records.done_info(db_path.parent, extract.STAGE).get("focal") or {}
    if estimate.get("estimated_px") and "sound" not in estimate and features_path is not None:
        estimate = _estimate_again(cameras, features_path, names, estimate) or {}
    estimated = estimate.get("estimated_px") if estimate.get("sound") else None
    fovs = []
    for name in names:
        camera = cameras.get(name)
        if camera is None:
            continue
        if camera.has_prior_focal_length:
            fovs.append(focal.field_of_view_deg(float(camera.mean_focal_length()), camera.width, camera.height))
        elif estimated:  # only ever for one shared camera
            fovs.append(focal.field_of_view_deg(float(estimated), camera.width, camera.height))
    if not names or 2 * len(fovs) < len(names):
        return None
    return float(np.median(fovs))


def _estimate_again(cameras: dict[str, Any], features_path: Path, names: list[str], recorded: dict) -> dict | None:
    """The focal estimate's length and soundness, from the features, for one camera shared by all images."""
    shared = {camera.camera_id: camera for camera in cameras.values()}
    if len(shared) != 1 or not Path(features_path).is_file():
        return None
    camera = next(iter(shared.values()))
    found = focal.estimate_from_features(Path(features_path), names, camera.width, camera.height,
                                         float(recorded.get("prior_px") or camera.mean_focal_length()))
    return {"estimated_px": found.focal_px, "sound": found.sound} if found is not None else None


def _choose(num_images: int, edges: np.ndarray, scores: scoring.PairScores, conf: Any):
    """Roles of the candidates (spanning tree, augmentation, low-parallax rescue)."""
    chosen_graph = selection.select_pairs(num_images, edges, scores.weight, scores.parallax_deg, scores.accepted,
                                          conf.graph, max_pairs=selection.first_round_cap(num_images, conf.graph),
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


def after_mapping(ctx: PairContext, pairs: list[Pair], model_dir: Path) -> list[Pair]:
    """More pairs once a model exists, within the cap of all rounds (`GraphConfig.pair_cap`):

    1. views that the mapper left out of the main model although the selected graph joins them to
       it: their best unselected candidates into the main model (`repair.py`), unless the last
       round was such a repair and most of its views are still out (`_repair_stalled`);
    2. otherwise, once: the pose-guided round (`pose_guided.py`), the unmatched pairs of registered
       views that the model predicts to add the most observations.
    """
    main = colmap.registered_images(model_dir)
    left_out = left_out_views(ctx.names, pairs, main)
    key = _selection_key(ctx) if left_out else ""
    if left_out and not _repair_stalled(ctx, key, pairs, left_out):
        extra = repair_pairs(ctx.out_dir / SCORES_NAME, pairs, main, left_out, ctx.conf.pairs.repair_pairs_per_view)
        room = max(ctx.conf.graph.pair_cap(len(ctx.names)) - len(pairs), len(left_out))
        extra = extra[:room] if len(extra) > room else extra
        if extra:
            logger.warning("%d views were left out of the main model: matching %d more pairs and mapping again",
                           len(left_out), len(extra))
            records.mark_done(ctx.out_dir, REPAIR_STAGE, key,
                              {"left_out": sorted(left_out), "pairs": _pairs_key(pairs + extra), "stalled": False})
        return extra
    return pose_guided_round(ctx, pairs, model_dir)


def before_mapping(ctx: PairContext, pairs: list[Pair], db_path: Path) -> list[Pair]:
    """More pairs, matched before the first mapping, for the views whose verified pairs in `db_path`
    hold few inlier matches (`support.py`); once per selection: [] once they are matched, the same
    pairs again after an interruption."""
    conf = ctx.conf.pairs
    if conf.min_view_inliers <= 0 or conf.support_pairs_per_view <= 0:
        return []
    key = fingerprint({"selection": _selection_key(ctx), "min_view_inliers": conf.min_view_inliers,
                       "per_view": conf.support_pairs_per_view})
    record = records.read_record(ctx.out_dir, SUPPORT_STAGE)
    if record and record.get("done") is True and record.get("key") == key:
        return _still_to_match([(a, b) for a, b in record.get("info", {}).get("pairs", [])], pairs)
    support = view_inliers(ctx.names, pairs, colmap.verified_inliers(db_path, ctx.conf.match.min_num_inliers))
    graph = ctx.conf.graph
    cap = graph.densify_cap(len(ctx.names)) if graph.densify else graph.pair_cap(len(ctx.names))
    weak = sum(1 for s in support.values() if s < conf.min_view_inliers)
    # at most half of the room the cap leaves: the pose-guided round after mapping keeps the rest
    extra = support_pairs(ctx.out_dir / SCORES_NAME, pairs, support, conf.min_view_inliers,
                          conf.support_pairs_per_view, (cap - len(pairs)) // 2,
                          order=view_inliers(ctx.names, pairs, colmap.match_counts(db_path))) if weak else []
    records.mark_done(ctx.out_dir, SUPPORT_STAGE, key, {
        "num_weak_views": weak, "view_inliers_median": float(np.median(list(support.values()) or [0])),
        "pairs": [list(p) for p in extra]})
    if extra:
        logger.info("%d views have fewer than %d verified inlier matches in all: matching %d more pairs before "
                    "mapping", weak, conf.min_view_inliers, len(extra))
    return extra


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
    stand-in, 4 s a round against 2.7 s for exhaustive matching's whole mapping, which leaves the
    same views out). The views stay out, with a warning, and the rounds go to the pose-guided
    pairs of the views in the model.
    """
    record = records.read_record(ctx.out_dir, REPAIR_STAGE)
    if not record or record.get("done") is not True or record.get("key") != key:
        return False
    info = record.get("info", {})
    before = set(info.get("left_out", []))
    if info.get("stalled"):
        return set(left_out) <= before
    still = before & set(left_out)
    if info.get("pairs") != _pairs_key(pairs) or set(left_out) - before or 2 * len(still) <= len(before):
        return False
    records.mark_done(ctx.out_dir, REPAIR_STAGE, key, {**info, "stalled": True})
    logger.warning("%d of the %d views of the last repair round are still out of the main model: leaving them out",
                   len(still), len(before))
    return True


def _selection_key(ctx: PairContext) -> str:
    """The first round's pairs: a record of another selection does not apply."""
    scores = ctx.out_dir / SCORES_NAME
    return _pairs_key(_first_round(scores)) if scores.exists() else ""


def pose_guided_round(ctx: PairContext, pairs: list[Pair], model_dir: Path) -> list[Pair]:
    """The pose-guided pairs (once per selection; [] when done, disabled or nothing is worth it)."""
    graph = ctx.conf.graph
    if (graph.pose_guided_pairs_per_image <= 0 and not graph.densify) or not colmap.has_model(model_dir):
        return []
    key = pose_guided.selection_key(_first_round(ctx.out_dir / SCORES_NAME), graph)
    done = pose_guided.recorded_pairs(ctx.out_dir, key)
    if done is not None:
        return _still_to_match(done, pairs)
    extra, info = pose_guided.select_extra(ctx, pairs, model_dir)
    pose_guided.mark_chosen(ctx.out_dir, key, extra, info)
    if extra:
        logger.info("pose-guided round: matching %d more pairs (predicted covisible points, median %.0f)",
                    len(extra), info.get("predicted_covisible_median", 0.0))
    return extra


def _first_round(scores_csv: Path) -> list[Pair]:
    scores, roles = read_scores_csv(scores_csv)
    roles = roles or [""] * len(scores)
    return [(a, b) for a, b, r in zip(scores.name0, scores.name1, roles)
            if r in selection.SELECTED_ROLES or r == "rescue"]


#: the pipeline may refine the model after the pose-guided round instead of mapping again
after_mapping.refine = pose_guided.refine  # type: ignore[attr-defined]
#: and extend the final model's tracks when no refinement did
after_mapping.finish = pose_guided.finish  # type: ignore[attr-defined]
#: before the first mapping: more pairs for weakly matched views
after_mapping.before_mapping = before_mapping  # type: ignore[attr-defined]


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


def _selected_edges(edges: np.ndarray, roles: list[str]) -> np.ndarray:
    mask = np.array([r in selection.SELECTED_ROLES or r == "rescue" for r in roles], dtype=bool)
    return edges[mask] if len(edges) else edges.reshape(0, 2)


def _component_sizes(labels: np.ndarray) -> list[int]:
    return sorted(np.bincount(labels).tolist(), reverse=True) if len(labels) else []


def _count(items) -> dict[str, int]:
    out: dict[str, int] = {}
    for item in items:
        out[item] = out.get(item, 0) + 1
    return out
