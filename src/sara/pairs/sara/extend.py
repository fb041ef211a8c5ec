"""SARA's pairs for a collection whose earlier selection was matched, after images were added,
removed or changed.

The whole graph is selected again, as a run from scratch of the collection would: the candidates
are the kNN of the global descriptors of every image (recomputed for the whole collection: VLAD's
codebook is learned from the collection and not stored, and computing it again costs seconds),
and SARA's selection runs on all of them. What an update saves is the scoring: a candidate the
earlier selection scored between two images that did not change takes its score from
`scores.csv`; only the others are scored. The match stage then matches only the selected pairs
that are not matched yet, and removes from the database the earlier pairs that the selection no
longer holds, so the mapper sees the selected pairs' geometries and no others.

Keeping every earlier pair and adding the new images' pairs instead cost AUC@1 on Herz-Jesus
(0.623 against 0.652 from scratch, 20 -> 25 views): the earlier pairs were chosen for a graph
of 20 views, and remapping the same matches from scratch gave the same 0.623 (lab/notes/INCREMENTAL.md).
"""

from __future__ import annotations

import logging
import shutil

import numpy as np

from ...io.pairs import Pair
from ...io.scores import PairScores, older_columns, read_scores_csv, take_scores
from .. import Extension, PairContext, PairResult
from .source import SCORES_NAME, select

logger = logging.getLogger(__name__)


def extend(ctx: PairContext, extension: Extension) -> PairResult:
    """SARA's selection for all of `ctx.names`, reusing the earlier scores (see the module's docstring);
    where only names changed, the earlier selection as it stands, its rounds' pairs included (`kept`)."""
    if extension.renamed_only and extension.scores_path is not None:
        return kept(ctx, extension)
    cached = _kept_scores(extension, set(ctx.names) - set(extension.new_names))
    result = select(ctx, cached=cached)
    earlier = {_canonical(p) for p in extension.kept_pairs}
    chosen = {_canonical(p) for p in result.pairs}
    result.info.update(num_kept_pairs=len(chosen & earlier), num_dropped_pairs=len(earlier - chosen),
                       num_new_pairs=len(chosen - earlier), num_cached_scores=0 if cached is None else len(cached))
    logger.info("update: %d candidates scored (the others' scores reused); of the %d earlier pairs %d selected "
                "again and %d dropped, %d pairs new", result.info.get("num_candidates_scored", 0), len(earlier),
                len(chosen & earlier), len(earlier - chosen), len(chosen - earlier))
    return result


def kept(ctx: PairContext, extension: Extension) -> PairResult:
    """The earlier pairs and scores under the new names: selecting again would only break ties by the
    new names, and it drops the pairs the rounds after mapping added (bm-moldGoldCape with every file
    renamed: 72 dropped, chosen anew from the continued model, AUC@1 0.9343 against 0.9443 from
    scratch; lab/notes/INCREMENTAL.md)."""
    shutil.copyfile(extension.scores_path, ctx.out_dir / SCORES_NAME)
    pairs = list(extension.kept_pairs)
    logger.info("update: only names changed: the earlier %d pairs stand, none selected or scored again", len(pairs))
    return PairResult(pairs, info={"num_pairs": len(pairs), "num_kept_pairs": len(pairs), "num_dropped_pairs": 0,
                                   "num_new_pairs": 0, "num_candidates_scored": 0, "renamed_only": True})


def _canonical(pair: Pair) -> Pair:
    return (pair[0], pair[1]) if pair[0] <= pair[1] else (pair[1], pair[0])


def _kept_scores(extension: Extension, kept_names: set[str]) -> PairScores | None:
    """The earlier candidates' scores between images that stay unchanged (None when there are none)."""
    if extension.scores_path is None:
        return None
    older = older_columns(extension.scores_path)
    if older:  # what the selection now reads of a score (its direction, ...) is not there: score again
        logger.info("update: the earlier scores were written by an older release (no %s): every candidate "
                    "is scored again", ", ".join(older))
        return None
    scores, _ = read_scores_csv(extension.scores_path)
    rows = [k for k, (a, b) in enumerate(zip(scores.name0, scores.name1)) if a in kept_names and b in kept_names]
    return take_scores(scores, np.array(rows, dtype=np.int64)) if rows else None
