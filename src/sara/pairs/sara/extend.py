"""SARA's pairs for images added to a collection whose pairs are already selected and matched.

The earlier pairs between images that stay are kept as they are (their matches too). The new
images get candidates from the global descriptors (recomputed for the whole collection: VLAD's
codebook is learned from the collection and not stored, and computing it again costs seconds);
only their candidates are scored, the earlier candidates' scores are read back from
`scores.csv`. SARA's selection then runs on all the candidates with the same per-image budget,
and the update takes from it the pairs that touch a new image (a spanning tree of all candidates
reaches each new image through such pairs), plus, where removing images split the kept pairs,
the selected pairs that join the pieces again.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from itertools import combinations

import numpy as np

from ... import retrieval, selection
from ...descriptors import top_k_cosine
from ...io.pairs import Pair
from ...io.scores import PairScores, concat_scores, read_scores_csv, write_scores_csv
from .. import Extension, PairContext, PairResult
from .field_of_view import resolve_tree_overlap
from .source import SCORES_NAME, _choose, _score, _selected_edges

logger = logging.getLogger(__name__)


def extend(ctx: PairContext, extension: Extension) -> PairResult:
    """The kept pairs plus SARA's pairs for `extension.new_names` (see the module's docstring)."""
    timings: dict[str, float] = {}
    names = list(ctx.names)
    index = {n: i for i, n in enumerate(names)}
    tic = time.perf_counter()
    new_rows = np.array(sorted(index[n] for n in extension.new_names if n in index), dtype=np.int64)
    old = _kept_scores(extension, set(names) - set(extension.new_names))
    known = {tuple(sorted((index[a], index[b]))) for a, b in zip(old.name0, old.name1)} if old is not None else set()
    new_edges = [e for e in _new_candidates(ctx, names, new_rows) if e not in known]
    timings["retrieval"] = time.perf_counter() - tic
    tic = time.perf_counter()
    new_candidates: list[Pair] = [(names[i], names[j]) for i, j in new_edges]
    scored = _score(ctx, new_candidates) if new_candidates else None
    timings["scoring"] = time.perf_counter() - tic
    parts = [s for s in (old, scored) if s is not None]
    if not parts:  # nothing to choose from: the kept pairs as they are
        kept_only = sorted({(min(a, b), max(a, b)) for a, b in extension.kept_pairs})
        return PairResult(kept_only, {"num_candidates_scored": 0, "num_kept_pairs": len(kept_only)}, timings)
    scores = parts[0] if len(parts) == 1 else concat_scores(*parts)
    edges = np.array([(index[a], index[b]) for a, b in zip(scores.name0, scores.name1)], dtype=np.int64).reshape(-1, 2)
    tic = time.perf_counter()
    tree_overlap, field_of_view = resolve_tree_overlap(ctx)
    conf = replace(ctx.conf, score=replace(ctx.conf.score, tree_overlap=tree_overlap))
    roles, chosen_graph, rescued = _choose(len(names), edges, scores, conf)
    kept = [(min(a, b), max(a, b)) for a, b in extension.kept_pairs]
    added = _pairs_for_new(names, edges, roles, new_rows, kept, index)
    timings["graph"] = time.perf_counter() - tic
    write_scores_csv(ctx.out_dir / SCORES_NAME, scores, roles)
    pairs = sorted(set(kept) | set(added))
    labels = selection.connected_components(len(names), np.array([(index[a], index[b]) for a, b in pairs],
                                                                 dtype=np.int64).reshape(-1, 2))
    info = {"num_candidates": len(scores), "num_candidates_scored": len(new_candidates), "num_kept_pairs": len(kept),
            "num_new_pairs": len(added), "num_accepted": int(scores.accepted.sum()), "num_rescued": rescued,
            "tree_overlap": tree_overlap, "tree_overlap_setting": ctx.conf.score.tree_overlap,
            "field_of_view_deg": field_of_view, "graph": chosen_graph.stats(),
            "selected_components": sorted(np.bincount(labels).tolist(), reverse=True) if len(labels) else []}
    logger.info("update: %d pairs kept, %d candidates of %d new images scored, %d pairs added", len(kept),
                len(new_candidates), len(new_rows), len(added))
    why = "" if pairs else "the sara pair source selected no pairs for the updated collection"
    return PairResult([tuple(p) for p in pairs], info, timings, why_empty=why)


def _kept_scores(extension: Extension, kept_names: set[str]) -> PairScores | None:
    """The earlier candidates' scores between images that stay (None when there are none)."""
    if extension.scores_path is None:
        return None
    scores, _ = read_scores_csv(extension.scores_path)
    rows = [k for k, (a, b) in enumerate(zip(scores.name0, scores.name1)) if a in kept_names and b in kept_names]
    if not rows:
        return None
    pick = np.array(rows, dtype=np.int64)
    return PairScores(name0=[scores.name0[k] for k in rows], name1=[scores.name1[k] for k in rows],
                      **{f: getattr(scores, f)[pick] for f in ("num_matches", "num_inliers", "num_inliers_all",
                                                                "overlap", "parallax_deg", "weight", "accepted")},
                      reason=[scores.reason[k] for k in rows])


def _new_candidates(ctx: PairContext, names: list[str], new_rows: np.ndarray) -> list[tuple[int, int]]:
    """Candidate pairs (i < j) of the new images: their k nearest global descriptors (every pair
    with them when k >= N - 1, as the first selection does)."""
    if len(new_rows) == 0:
        return []
    conf = ctx.conf
    if conf.retrieval.num_neighbors >= len(names) - 1:
        new = set(new_rows.tolist())
        return [(i, j) for i, j in combinations(range(len(names)), 2) if i in new or j in new]
    global_path = retrieval.run(conf.retrieval, ctx.features_path, names, ctx.out_dir, images_root=ctx.images_root,
                                progress=ctx.progress, seed=conf.seed)
    stored, desc = retrieval.read_global(global_path)
    position = {n: k for k, n in enumerate(stored)}
    desc = desc[[position[n] for n in names]]
    found = set()
    for i, row in zip(new_rows, top_k_cosine(desc, conf.retrieval.num_neighbors, queries=new_rows)):
        found.update((min(int(i), int(j)), max(int(i), int(j))) for j in row)
    return sorted(found)


def _pairs_for_new(names: list[str], edges: np.ndarray, roles: list[str], new_rows: np.ndarray,
                   kept: list[tuple[str, str]], index: dict[str, int]) -> list[Pair]:
    """The selected pairs that touch a new image, then the selected pairs that join components of
    the kept and new pairs (in the candidates' order)."""
    new = set(new_rows.tolist())
    selected = _selected_edges(edges, roles)
    touching = [(int(i), int(j)) for i, j in selected if int(i) in new or int(j) in new]
    parent = list(range(len(names)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in [(index[a], index[b]) for a, b in kept] + touching:
        parent[find(i)] = find(j)
    joining = []
    for i, j in ((int(a), int(b)) for a, b in selected):
        if find(i) != find(j):
            parent[find(i)] = find(j)
            joining.append((i, j))
    return [tuple(sorted((names[i], names[j]))) for i, j in touching + joining]
