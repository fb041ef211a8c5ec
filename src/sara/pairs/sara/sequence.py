"""Ordered captures: frames of a video, a burst or a drive, recognised by their names and confirmed
by what they look like.

A name numbers a frame when it ends in digits before its extension (`frame_000123.png`,
`IMG_0042.JPG`, `cam0/000051.png`); the names sharing everything but that number (folder, prefix,
extension) form one sequence, ordered by the number. A phone's photo names number every capture
too, so in `auto` mode the order counts only when the images' looks agree with it: most of each
image's nearest global descriptors must be frames within `window` places of it, which a shuffled
collection reaches by chance with probability about 2 window / N per neighbour. In a long capture
"most" asks too much: a walk that passes places twice, or turns the camera left and right by turns,
has nearest neighbours from the other pass or a few windows on (a 1,000-frame walk: 39%, 39 times
what chance gives, and its retrieval neighbours missed 3,011 of the 4,985 window pairs). So the
bar is the lower of `min_agreement` and AGREEMENT_LIFT times the chance share: ten times chance is
far beyond what a shuffled collection reaches, and for fewer than about 200 frames the bar stays
`min_agreement`.

In a sequence, each frame is also a candidate pair with the `window` frames that follow it; the
retrieval neighbours stay candidates too and close the loops. The candidates are scored and the
pairs chosen as for any capture. `auto` (the default) uses the window only from `auto_min_frames`
frames: in a long walk the window's frames, which look different from each other (the same place
from another side, the next stretch), linked the views that retrieval alone left out of the model;
in the shared scenes' short sequences they gained nothing (see SequenceConfig).
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ...config import SequenceConfig
from ...descriptors import top_k_cosine
from ...io.numbered import numbered

#: fewest frames of a sequence; shorter runs of numbered names are not an order worth using
MIN_FRAMES = 3
#: share of the names a set of sequences must cover to order the capture
MIN_COVERED = 0.9
#: nearest global descriptors per image that test the order in `auto` mode
AGREEMENT_NEIGHBOURS = 4
#: `auto`: an agreement this many times the chance share always counts (see the module docstring)
AGREEMENT_LIFT = 10.0


@dataclass
class Sequences:
    """The frame orders found among the names.

    orders: one list of indices into the names per sequence, in capture order (empty: no order).
    agreement: share of the nearest global descriptors that are neighbouring frames (None: not tested).
    needed: the share `auto` asked for (`needed_agreement`; None: not tested).
    used: whether the order feeds the candidates (mode yes, or auto, the looks agree and it is long enough).
    too_short: auto found fewer frames than `auto_min_frames` (whatever the agreement).
    """

    orders: list[list[int]] = field(default_factory=list)
    agreement: float | None = None
    needed: float | None = None
    used: bool = False
    too_short: bool = False

    @property
    def num_frames(self) -> int:
        return sum(map(len, self.orders))

    def summary(self, mode: str, num_window: int) -> dict[str, Any]:
        rounded = {key: None if value is None else round(value, 4)
                   for key, value in (("agreement", self.agreement), ("agreement_needed", self.needed))}
        return {"mode": mode, "used": self.used, "num_sequences": len(self.orders),
                "num_frames": self.num_frames, **rounded, "num_window_candidates": num_window}


def frame_orders(names: list[str]) -> list[list[int]]:
    """Sequences of frames among `names` (indices, in frame-number order), or [] when numbered
    names cover less than MIN_COVERED of them."""
    groups: dict[tuple[str, str], list[tuple[int, int]]] = defaultdict(list)
    for i, name in enumerate(names):
        found = numbered(name)
        if found is not None:
            groups[found[0]].append((found[1], i))
    orders = [[i for _, i in sorted(group)] for _, group in sorted(groups.items()) if len(group) >= MIN_FRAMES]
    covered = sum(map(len, orders))
    return orders if names and covered >= MIN_COVERED * len(names) else []


def agreement(orders: list[list[int]], desc: np.ndarray, window: int) -> float:
    """Share of each frame's AGREEMENT_NEIGHBOURS nearest global descriptors (rows of `desc`, one per
    name) that lie in its sequence within `window` frames of it."""
    place = {i: (s, p) for s, order in enumerate(orders) for p, i in enumerate(order)}
    rows = np.array([i for order in orders for i in order], dtype=np.int64)
    k = min(AGREEMENT_NEIGHBOURS, len(desc) - 1)
    if k < 1 or len(rows) == 0:
        return 0.0
    near = total = 0
    for i, found in zip(rows, top_k_cosine(desc, k, rows)):
        seq, pos = place[int(i)]
        for j in found:
            other = place.get(int(j))
            near += other is not None and other[0] == seq and abs(other[1] - pos) <= window
            total += 1
    return near / total if total else 0.0


def chance_agreement(orders: list[list[int]], num_names: int, window: int) -> float:
    """The agreement a shuffled order would have on average: per frame, the share of the other
    images that lie within `window` places of it in its sequence."""
    if num_names < 2:
        return 1.0
    counts = [min(p, window) + min(len(order) - 1 - p, window) for order in orders for p in range(len(order))]
    return float(np.mean(counts)) / (num_names - 1) if counts else 0.0


def needed_agreement(orders: list[list[int]], num_names: int, conf: SequenceConfig) -> float:
    """The agreement `auto` asks for: `min_agreement`, or AGREEMENT_LIFT times chance where lower."""
    return min(conf.min_agreement, AGREEMENT_LIFT * chance_agreement(orders, num_names, conf.window))


def detect(names: list[str], desc: np.ndarray | None, conf: SequenceConfig) -> Sequences:
    """The sequences of a capture under `conf.mode` (see the module docstring)."""
    if conf.mode == "no":
        return Sequences()
    orders = frame_orders(names)
    if conf.mode == "yes":
        if not orders:
            raise ValueError("sequence.mode is yes (--sequence yes), but the image names do not number frames: "
                             "name them in capture order with a frame number (frame_000001.png, ...)")
        return Sequences(orders, used=True)
    if not orders or desc is None:
        return Sequences(orders)
    found = Sequences(orders, agreement(orders, desc, conf.window), needed_agreement(orders, len(names), conf))
    found.too_short = found.num_frames < conf.auto_min_frames
    found.used = not found.too_short and found.agreement >= found.needed
    return found


def window_pairs(orders: list[list[int]], window: int) -> np.ndarray:
    """(E, 2) int64 pairs i < j: each frame with the `window` frames after it in its sequence."""
    pairs = [(min(a, b), max(a, b)) for order in orders for p, a in enumerate(order)
             for b in order[p + 1:p + 1 + window]]
    return np.array(sorted(set(pairs)), dtype=np.int64).reshape(-1, 2)
