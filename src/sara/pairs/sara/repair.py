"""Closing the loop after mapping: when the model splits although SARA's view graph is connected,
match a few more candidate pairs that link the left-out views to the main model, then map again.

A sparse selection can leave a group of views hanging on one or two pairs; COLMAP may then fail
to register them into the main model and start a separate one. The candidates that the scorer
ranked below the selection (scores.csv) name the next best links; a handful per left-out view
usually suffices. Views that SARA itself found unconnected (another scene) are left alone.

A left-out view may also already have verified pairs into the model and still not register: the
mapper poses a view from its keypoints whose matches reach a 3D point, and the keypoints its
registered neighbours share with it were matched to no other registered view, so they were never
triangulated (1,000-image synthetic world: a view with 154, 125 and 99 inliers to three registered
views, none of those keypoints with a 3D point). Matching those neighbours with each other
triangulates them (`neighbour_pairs`); there, 7 such pairs took the model from 979 views to 988.

When such a repair leaves most of its views out (the round is not repeated), the views' links
were not what was missing: the part they belong to is too sparse for the mapper. On a
200-image synthetic street the mapper joined the parts only once the graph held 4-6 pairs per
view, whichever pairs they were, while pairs added only at the left-out views left it in two
(lab/notes/SCALE.md). So the room the pair cap leaves then goes, once, to the best unmatched
candidates of all views by the scorer's weight (`fill_pairs`).
"""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ...io.pairs import Pair
from ...io.scores import read_scores_csv
from ...selection import connected_components

logger = logging.getLogger(__name__)


def left_out_views(names: list[str], pairs: list[Pair], main: set[str]) -> list[str]:
    """Views outside the main model but in the selected graph's component of the main model."""
    if not main:
        return []
    index = {n: i for i, n in enumerate(names)}
    edges = np.array([sorted((index[a], index[b])) for a, b in pairs], dtype=np.int64).reshape(-1, 2)
    labels = connected_components(len(names), edges)
    main_labels = np.bincount([labels[index[n]] for n in main if n in index])
    main_label = int(np.argmax(main_labels))
    return [n for n in names if labels[index[n]] == main_label and n not in main]


def repair_pairs(scores_csv: Path, pairs: list[Pair], main: set[str], left_out: list[str],
                 per_view: int, rescore: Callable[[list[Pair]], dict[Pair, int]] | None = None,
                 min_inliers: int = 0, fully_scored: set[str] | None = None) -> list[Pair]:
    """For each left-out view, its best unselected candidates into the main model: by the RANSAC
    pose's inliers among all mutual matches (`num_inliers_all`, which does not saturate at the b
    best matches and predicts a full matching's inliers better).

    `rescore(pairs)` gives that count anew for the candidates of the left-out views (pair -> inliers;
    the round's ratio-tested scoring); a pair it leaves out keeps its first score.

    A candidate between two `fully_scored` views (None: every view) whose count is under
    `min_inliers` (the round passes verification's own minimum) is not taken. The scorer saw every
    keypoint of such views (no more than its `score.num_keypoints`), so its count is what matching
    will find, up to RANSAC: the pair would not verify, and a pair spent on it is one the fill round
    after a stalled repair no longer has. On a low-texture turntable (211 SIFT keypoints per image, 47
    views) 43 of a repair's 62 pairs were such candidates, none verified (ratio-tested counts up to
    25 for pairs that do not verify, at least 41 for nine in ten of those that do), and the repair
    used up the cap's room. Where the scorer saw a fraction of the keypoints the counts say little: on
    an orbit video picked sparsely (mold50, thousands of keypoints per image) links counted 6-14
    verified with 16-119 inliers, and the repair needs them."""
    chosen = {tuple(sorted(p)) for p in pairs}
    targets = set(left_out)
    found: list[tuple[str, int, Pair]] = []
    scores, _ = read_scores_csv(scores_csv)
    for k, (a, b) in enumerate(zip(scores.name0, scores.name1)):
        pair = tuple(sorted((a, b)))
        if pair in chosen:
            continue
        for view, other in ((a, b), (b, a)):
            if view in targets and other in main:
                found.append((view, k, pair))
    again = rescore(sorted({pair for _, _, pair in found})) if rescore is not None and found else {}
    options: dict[str, list[tuple[int, Pair]]] = defaultdict(list)
    for view, k, pair in found:
        if pair in again:
            count = again[pair]
        elif scores.reason[k] != "no_model":
            count = int(scores.num_inliers_all[k])
        else:
            continue
        if count >= min_inliers or (fully_scored is not None and not fully_scored.issuperset(pair)):
            options[view].append((count, pair))
    extra: list[Pair] = []
    for view in left_out:
        ranked = sorted(options[view], key=lambda item: (-item[0], item[1]))
        extra += [pair for _, pair in ranked[:per_view]]
    return sorted(set(extra))


def fill_pairs(scores_csv: Path, pairs: list[Pair], room: int) -> list[Pair]:
    """The `room` best accepted candidates not among `pairs`, by the scorer's weight (then by name); sorted."""
    if room <= 0:
        return []
    chosen = {tuple(sorted(p)) for p in pairs}
    scores, _ = read_scores_csv(scores_csv)
    ranked = sorted((-float(scores.weight[k]), tuple(sorted((a, b))))
                    for k, (a, b) in enumerate(zip(scores.name0, scores.name1)) if scores.accepted[k])
    return sorted([pair for _, pair in ranked if pair not in chosen][:room])


def neighbour_pairs(scores_csv: Path, pairs: list[Pair], main: set[str], left_out: list[str],
                    linked: dict[Pair, int], per_view: int) -> dict[str, list[Pair]]:
    """For each left-out view, up to `per_view` unmatched accepted candidates between two of its
    neighbours in the main model, best weight first: `linked` holds the verified pairs (sorted
    names -> inliers) and says who its neighbours are. Returns view -> its pairs (a pair goes to
    the first view that names it)."""
    neighbours: dict[str, set[str]] = defaultdict(set)
    for a, b in linked:
        neighbours[a].add(b)
        neighbours[b].add(a)
    chosen = {tuple(sorted(p)) for p in pairs}
    scores, _ = read_scores_csv(scores_csv)
    weight = {tuple(sorted((a, b))): float(scores.weight[k])
              for k, (a, b) in enumerate(zip(scores.name0, scores.name1)) if scores.accepted[k]}
    out: dict[str, list[Pair]] = {}
    for view in left_out:
        near = sorted(neighbours.get(view, set()) & main)
        options = sorted((-weight[(a, b)], (a, b)) for i, a in enumerate(near) for b in near[i + 1:]
                         if (a, b) in weight and (a, b) not in chosen)
        out[view] = [pair for _, pair in options[:per_view]]
        chosen.update(out[view])
    return out
