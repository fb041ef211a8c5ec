"""The one ledger of SARA's pairs: the cap of all rounds together and each round's share of it.

Every round (the first selection, support before mapping, repair and pose-guided after it) asks
this object how many pairs it may add; no other module splits `budget.max_pairs_per_image`. The
rounds after mapping are also held to the pairs their time budget leaves (`time_limit`, which the
pipeline works out from `rounds.max_time_fraction` and the first round's matching rate).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...config import BudgetConfig, RoundsConfig


@dataclass(frozen=True)
class PairBudget:
    """The pair caps of one collection of `num_images` images."""

    num_images: int
    budget: BudgetConfig
    rounds: RoundsConfig
    #: most pairs of the round after mapping being chosen, from the rounds' time budget (the
    #: pipeline's `PairContext.max_round_pairs`; None: no limit)
    time_limit: int | None = None

    @property
    def cap(self) -> int:
        """Most pairs of every round together (`BudgetConfig.pair_cap`, or `densify_cap` with densify)."""
        budget, num = self.budget, self.num_images
        return budget.densify_cap(num) if budget.densify else budget.pair_cap(num)

    def first_round(self) -> int:
        """Most pairs of the first selection: the cap less what the pose-guided round after mapping
        keeps for itself (`rounds.pose_guided_pairs_per_image` per image); the spanning forest is
        kept regardless. With densify the first round is the usual selection within the usual cap,
        and the pose-guided round adds to it up to the densify cap."""
        cap = self.budget.pair_cap(self.num_images)
        if self.budget.densify:
            return cap
        reserve = math.ceil(self.rounds.pose_guided_pairs_per_image * self.num_images - 1e-9)
        # where the cap leaves little beyond the spanning tree (small collections, where 25% of the
        # exhaustive pairs binds), the round keeps at most half of that room: a first model built on
        # the bare tree leaves views out, and mapping again for them costs more than the round saves
        room = max(0, cap - max(self.num_images - 1, 0))
        return max(0, cap - min(reserve, room // 2))

    def support(self, num_matched: int) -> int:
        """Pairs the support round before mapping may add: half of the room the cap leaves; the
        pose-guided round after mapping keeps the rest."""
        return (self.cap - num_matched) // 2

    def repair(self, num_matched: int, num_left_out: int) -> int:
        """Pairs a repair round may add: the room under the usual cap, and at least two per view
        left out of the model: one into the model (a view without a pair into it cannot be
        registered) and one between its neighbours there (without it their keypoints it sees may
        have no 3D point)."""
        return self._in_time(max(self.budget.pair_cap(self.num_images) - num_matched, 2 * num_left_out))

    def fill(self, num_matched: int) -> int:
        """Pairs the fill round may add (after a repair that left its views out): a repair's room,
        with no view left to guarantee a pair."""
        return self.repair(num_matched, num_left_out=0)

    def pose_guided(self, num_matched: int, num_registered: int) -> int:
        """Pairs the pose-guided round may add: its own share per registered view
        (`rounds.pose_guided_pairs_per_image`, or `budget.densify_pairs_per_image` with densify),
        within the cap."""
        ratio = self.budget.densify_pairs_per_image if self.budget.densify else self.rounds.pose_guided_pairs_per_image
        own = int(np.ceil(ratio * num_registered - 1e-9))
        return self._in_time(max(0, min(own, self.cap - num_matched)))

    def _in_time(self, pairs: int) -> int:
        """`pairs`, or fewer where the rounds' time budget leaves less (it wins over the pair caps:
        a repair that does not fit in time is not worth its mapping)."""
        return pairs if self.time_limit is None else max(0, min(pairs, self.time_limit))
