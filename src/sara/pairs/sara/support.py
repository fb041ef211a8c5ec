"""Before the first mapping: more pairs for the views whose matched pairs are weak.

The scorer sees at most `score.num_matches` matches per pair, so it cannot tell a pair of 60 inlier
matches from one of 2,000. Full matching can: on a low-texture scene (a few hundred features per
image) a view of the selection may end up with two or three verified pairs of a few dozen inliers.
COLMAP's mapper then fails to register it, starts new models, and the repair round after mapping
maps everything again. Here each view's
verified inlier matches are summed over its pairs; a view below `rounds.support_min_view_inliers` gets up to
`rounds.support_pairs_per_view` more of its best accepted candidates (by the scorer's weight),
weakest views first (fewest matches before verification), matched before the mapper runs. It
takes at most half of the room that the pair cap of all rounds leaves after the first round; the
pose-guided round keeps the rest. Views of well-textured scenes sum hundreds to thousands of
inliers and get nothing.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from ...io.pairs import Pair
from ...io.scores import read_scores_csv


def view_inliers(names: list[str], pairs: list[Pair], inliers: dict[tuple[str, str], int]) -> dict[str, int]:
    """Each view's verified inlier matches summed over its pairs (0 for a view without any)."""
    total = dict.fromkeys(names, 0)
    for a, b in pairs:
        count = inliers.get(tuple(sorted((a, b))), 0)
        for view in (a, b):
            if view in total:
                total[view] += count
    return total


def support_pairs(scores_csv: Path, pairs: list[Pair], support: dict[str, int], min_inliers: int,
                  per_view: int, room: int, order: dict[str, int] | None = None) -> list[Pair]:
    """Up to `per_view` unselected accepted candidates (best scorer weight first) for each view whose
    `support` is below `min_inliers`, weakest views first, at most `room` pairs in all; sorted.

    A pair added for one view counts for the other view of the pair too. Weakest means the lowest
    `order` (default: `support`); the source passes the views' matches before verification, which
    were repeatable when the verified counts were not (COLMAP's RANSAC without a seed).
    """
    rank = order if order is not None else support
    weak = sorted((v for v, s in support.items() if s < min_inliers), key=lambda v: (rank.get(v, 0), v))
    if not weak or per_view <= 0 or room <= 0:
        return []
    chosen = {tuple(sorted(p)) for p in pairs}
    targets = set(weak)
    options: dict[str, list[tuple[float, tuple[str, str]]]] = defaultdict(list)
    scores, _ = read_scores_csv(scores_csv)
    for k, (a, b) in enumerate(zip(scores.name0, scores.name1)):
        pair = tuple(sorted((a, b)))
        if not scores.accepted[k] or pair in chosen:
            continue
        for view in pair:
            if view in targets:
                options[view].append((-float(scores.weight[k]), pair))
    added: dict[str, int] = defaultdict(int)
    extra: list[tuple[str, str]] = []
    for view in weak:
        for _, pair in sorted(options[view]):
            if added[view] >= per_view or len(extra) >= room:
                break
            if pair in chosen:
                continue
            chosen.add(pair)
            extra.append(pair)
            for end in pair:
                added[end] += 1
    return sorted(extra)
