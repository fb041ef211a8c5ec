"""Sequential pairs, as COLMAP's sequential matcher makes them for video and ordered captures.

Images are ordered by file name. Each image is paired with the next `overlap` images; with
`quadratic`, also with the images 2^k ahead (k < overlap). With loop detection, every
`loop_period`-th image is also paired with its nearest neighbours by global descriptor.
"""

from __future__ import annotations

from ..pairsfile import Pair, canonical_pairs
from . import PairContext, PairResult


def sequential_pairs(names: list[str], overlap: int, *, quadratic: bool = False) -> list[Pair]:
    if overlap < 1:
        raise ValueError(f"sequential overlap must be at least 1, got {overlap}")
    order = sorted(names)
    n = len(order)
    pairs = []
    for i in range(n):
        for d in range(1, overlap + 1):
            if i + d < n:
                pairs.append((order[i], order[i + d]))
        if quadratic:
            for k in range(overlap):
                j = i + 2**k
                if j < n:
                    pairs.append((order[i], order[j]))
    return canonical_pairs(pairs)


def select(ctx: PairContext) -> PairResult:
    conf = ctx.conf.pairs
    pairs = sequential_pairs(ctx.names, conf.sequential_overlap, quadratic=conf.sequential_quadratic)
    info: dict = {"num_sequential": len(pairs)}
    if conf.sequential_loop_detection:
        from ..retrieval import global_descriptors, knn_neighbours

        order = sorted(ctx.names)
        desc = global_descriptors(ctx.conf.retrieval, ctx.features_path, order, ctx.out_dir, progress=ctx.progress)
        queries = list(range(0, len(order), max(1, conf.sequential_loop_period)))
        nbrs = knn_neighbours(desc, conf.sequential_loop_neighbors, queries=queries)
        loops = [(order[q], order[j]) for q, row in zip(queries, nbrs) for j in row]
        pairs = canonical_pairs(pairs + loops)
        info["num_loop_pairs_added"] = len(pairs) - info["num_sequential"]
    return PairResult(pairs, info)
