"""Exhaustive pairs: every image with every other, n (n - 1) / 2 pairs."""

from __future__ import annotations

import itertools

from ..io.pairs import Pair
from . import PairContext, PairResult, PairSource


def exhaustive_pairs(names: list[str]) -> list[Pair]:
    return list(itertools.combinations(sorted(names), 2))


def select(ctx: PairContext) -> PairResult:
    return PairResult(exhaustive_pairs(ctx.names))


SOURCE = PairSource(select=select)
