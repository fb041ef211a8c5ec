"""Before the first mapping: more pairs for the views whose matched pairs are weak.

The scorer sees at most `score.num_matches` matches per pair, so it cannot tell a pair of 60 inlier
matches from one of 2,000. Full matching can: on a low-texture scene (a few hundred features per
image) a view of the selection may end up with two or three verified pairs of a few dozen inliers.
COLMAP's mapper then fails to register it, starts new models, and the repair round after mapping
maps everything again (docs/ACCURACY.md, "Time, and mapping a sparse graph"). Here each view's
verified inlier matches are summed over its pairs; a view below `pairs.min_view_inliers` gets up to
`pairs.support_pairs_per_view` more of its accepted candidates (the scorer's best weight first),
matched before the mapper runs. It takes at most half of the room that the
pair cap of all rounds leaves after the first round; the pose-guided round keeps the rest. Views of
well-textured scenes sum hundreds to thousands of inliers and get nothing (docs/ACCURACY.md, section 14).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from ..io.pairs import Pair
from ..io.scores import read_scores_csv


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
                  per_view: int, room: int) -> list[Pair]:
    """Unselected accepted candidates of the views whose `support` is below `min_inliers`, best
    scorer weight first, up to `per_view` for each such view and `room` in all; sorted.

    A pair counts for both of its views. The order is the scorer's (deterministic), not the
    views' support: verified inlier counts vary by a few between identical runs (COLMAP's
    multi-threaded RANSAC), which may only move a view across `min_inliers`.
    """
    weak = {v for v, s in support.items() if s < min_inliers}
    if not weak or per_view <= 0 or room <= 0:
        return []
    chosen = {tuple(sorted(p)) for p in pairs}
    scores, _ = read_scores_csv(scores_csv)
    options = sorted((-float(scores.weight[k]), tuple(sorted((a, b))))
                     for k, (a, b) in enumerate(zip(scores.name0, scores.name1))
                     if scores.accepted[k] and (a in weak or b in weak))
    added: dict[str, int] = defaultdict(int)
    extra: list[tuple[str, str]] = []
    for _, pair in options:
        if len(extra) >= room:
            break
        if pair in chosen or not any(v in weak and added[v] < per_view for v in pair):
            continue
        chosen.add(pair)
        extra.append(pair)
        for view in pair:
            added[view] += 1
    return sorted(extra)
