"""Retrieval-only pairs: SARA's own candidates, matched as they are (no pre-matching geometry).

Every image is paired with its `retrieval.num_neighbors` nearest images by the same global
descriptor SARA uses (`retrieval.descriptor`, cosine similarity); the pairs are the symmetric
union. Against SARA this isolates what the geometric scoring and the graph selection add.
"""

from __future__ import annotations

import time

from .. import retrieval
from ..io.pairs import canonical_pairs
from . import PairContext, PairResult, PairSource


def select(ctx: PairContext) -> PairResult:
    rconf = ctx.conf.retrieval
    tic = time.perf_counter()
    global_path = retrieval.run(rconf, ctx.features_path, ctx.names, ctx.out_dir, images_root=ctx.images_root,
                                progress=ctx.progress, seed=ctx.conf.seed)
    names, desc = retrieval.read_global(global_path)
    describe_s = time.perf_counter() - tic
    tic = time.perf_counter()
    pairs = canonical_pairs((names[i], names[j]) for i, j in retrieval.knn_pairs(desc, rconf.num_neighbors))
    knn_s = time.perf_counter() - tic
    info = {"descriptor": rconf.descriptor, "num_neighbors": rconf.num_neighbors}
    return PairResult(pairs, info, {"global_descriptors": describe_s, "knn": knn_s})


SOURCE = PairSource(select=select, sections=lambda conf: ("pairs", "retrieval"), caches=("global-*.h5",))
