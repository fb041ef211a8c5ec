"""Sequential pairs, as COLMAP's sequential matcher makes them for video and ordered captures.

Images are ordered by name (COLMAP orders them the same way). Each image is paired with the next
`overlap` images; with `quadratic`, with the images 2^k ahead instead (k = 0 .. overlap - 1: offsets
1, 2, 4, 8, ...), as pycolmap 4.2's `SequentialPairingOptions.quadratic_overlap` does (COLMAP 3.x
used the union of both windows). With loop detection, every `loop_period`-th image (the first, then
every period: indices 0, period, 2 period, ...) is also paired with its `loop_neighbors` nearest
images by global descriptor (`retrieval.descriptor`), where COLMAP queries a vocabulary tree.
"""

from __future__ import annotations

import numpy as np

from ..config import PipelineConfig
from ..descriptors import top_k_cosine
from ..io.pairs import Pair, canonical_pairs
from . import PairContext, PairResult, PairSource


def sequential_offsets(overlap: int, *, quadratic: bool = False) -> list[int]:
    """Index offsets paired with each image: 1..overlap, or 2^0..2^(overlap-1) when quadratic."""
    if overlap < 1:
        raise ValueError(f"sequential overlap must be at least 1, got {overlap}")
    return [2**k for k in range(overlap)] if quadratic else list(range(1, overlap + 1))


def sequential_pairs(names: list[str], overlap: int, *, quadratic: bool = False) -> list[Pair]:
    """Canonical pairs of COLMAP's sequential matcher (no loop detection) over `names` sorted."""
    order = sorted(names)
    offsets = sequential_offsets(overlap, quadratic=quadratic)
    return canonical_pairs((order[i], order[i + d]) for i in range(len(order)) for d in offsets
                           if i + d < len(order))


def nearest_neighbours(desc: np.ndarray, queries: list[int], k: int) -> np.ndarray:
    """Top-k cosine neighbours (self excluded) of the `queries` rows of `desc`.

    desc: (N, D) float rows (normalised here); queries: Q row indices. Returns (Q, min(k, N - 1))
    int64 row indices, best first; ties go to the lower index.
    """
    return top_k_cosine(desc, k, np.asarray(queries, dtype=np.int64))


def loop_pairs(ctx: PairContext, order: list[str]) -> list[Pair]:
    """Loop-closure pairs: every `loop_period`-th image with its nearest images by global descriptor."""
    from .. import retrieval

    conf = ctx.conf.sequential
    if conf.loop_period < 1 or conf.loop_neighbors < 1:
        raise ValueError("sequential.loop_period and sequential.loop_neighbors must be at least 1")
    path = retrieval.run(ctx.conf.retrieval, ctx.features_path, order, ctx.out_dir, images_root=ctx.images_root,
                         progress=ctx.progress, seed=ctx.conf.seed)
    names, desc = retrieval.read_global(path)
    row = {name: i for i, name in enumerate(names)}
    desc = desc[[row[name] for name in order]]
    queries = list(range(0, len(order), conf.loop_period))
    nbrs = nearest_neighbours(desc, queries, conf.loop_neighbors)
    return [(order[q], order[int(j)]) for q, found in zip(queries, nbrs) for j in found]


def select(ctx: PairContext) -> PairResult:
    conf = ctx.conf.sequential
    pairs = sequential_pairs(ctx.names, conf.overlap, quadratic=conf.quadratic)
    info: dict = {"num_sequential": len(pairs)}
    if conf.loop_detection:
        pairs = canonical_pairs(pairs + loop_pairs(ctx, sorted(ctx.names)))
        info["num_loop_pairs_added"] = len(pairs) - info["num_sequential"]
    return PairResult(pairs, info)


def _sections(conf: PipelineConfig) -> tuple[str, ...]:
    """Loop detection retrieves with the global descriptors."""
    return ("pairs", "sequential", "retrieval") if conf.sequential.loop_detection else ("pairs", "sequential")


SOURCE = PairSource(select=select, sections=_sections, caches=("global-*.h5",))
