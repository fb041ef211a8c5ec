"""How long work will take: the matching time estimated from its first chunk, durations in words,
and the time budget of the rounds after the first mapping. A leaf (standard library only).

The first chunk of a matching (about 5% of its pairs, `sara.match.chunked`) is a sample of its
pairs in the order of the pairs file, so its rate predicts the rest; it also carries the fixed costs
of a start (loading the matcher, opening files), so the estimate errs on the long side for short
matchings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Estimate:
    """A matching's expected time, from the rate of its first chunk."""

    num_pairs: int  # pairs this run matches (pairs matched by an earlier, interrupted run excluded)
    rate_pairs_per_s: float
    seconds: float  # the whole matching, time of earlier interrupted runs included
    earlier_s: float = 0.0  # of which earlier interrupted runs took

    def line(self, stage: str = "match") -> str:
        """"match: 1,225 pairs, about 3 min 10 s at 6.4 pairs/s (first chunk)"."""
        return (f"{stage}: {self.num_pairs:,} pairs, about {format_duration(self.seconds)} at "
                f"{self.rate_pairs_per_s:.{1 if self.rate_pairs_per_s < 100 else 0}f} pairs/s (first chunk)")


def from_first_chunk(num_pairs: int, chunk_pairs: int, chunk_s: float, *, concurrency: int = 1,
                     earlier_s: float = 0.0, work_ratio: float | None = None) -> Estimate:
    """The estimate once the first chunk of `chunk_pairs` pairs came back after `chunk_s` seconds.

    concurrency: chunks that run at the same time (a pool's workers, at most the number of chunks):
    when the first one comes back, about that many are done. earlier_s: time that interrupted runs
    already spent on these pairs, counted in the whole. work_ratio: the work of all chunks over
    the first one's where it is not in proportion to the pairs (`chunk_work`); default
    num_pairs / chunk_pairs.
    """
    if chunk_pairs <= 0 or num_pairs < 0:
        raise ValueError(f"a first chunk needs pairs (got {chunk_pairs} of {num_pairs})")
    ratio = num_pairs / chunk_pairs if work_ratio is None else work_ratio
    seconds = max(chunk_s, 1e-6) * ratio / max(1, concurrency)
    return Estimate(num_pairs, num_pairs / seconds if seconds > 0 else 0.0, earlier_s + seconds, earlier_s)


def chunk_work(chunks: list[list[tuple[str, str]]], image_cost: float) -> list[float]:
    """The work of each chunk in pairs' matching time: its pairs, plus `image_cost` pairs for each
    image it touches where the matcher pays once per image and call (COLMAP's SIFT matcher builds
    each image's search index anew in every call)."""
    return [len(chunk) + image_cost * len({name for pair in chunk for name in pair}) for chunk in chunks]


def format_duration(seconds: float) -> str:
    """A duration as people say it: "0.4 s", "45 s", "3 min 10 s", "2 h 5 min"."""
    if not math.isfinite(seconds) or seconds < 0:
        raise ValueError(f"not a duration: {seconds}")
    if seconds < 10:
        return f"{seconds:.1f} s"
    whole = round(seconds)
    if whole < 60:
        return f"{whole} s"
    if whole < 3600:
        minutes, secs = divmod(whole, 60)
        return f"{minutes} min {secs} s" if secs else f"{minutes} min"
    hours, minutes = divmod(round(seconds / 60), 60)
    return f"{hours} h {minutes} min" if minutes else f"{hours} h"


@dataclass(frozen=True)
class TimeBudget:
    """The time the rounds after the first mapping may take: `fraction` of the first round's match
    + map time (0: no limit). `spent_s` is what they took so far; `rate_pairs_per_s` the first
    matching's rate (0: unknown, then no pair cut)."""

    fraction: float
    first_match_s: float
    first_map_s: float
    spent_s: float = 0.0
    rate_pairs_per_s: float = 0.0

    @property
    def total_s(self) -> float:
        if self.fraction <= 0:
            return math.inf
        return self.fraction * (self.first_match_s + self.first_map_s)

    @property
    def left_s(self) -> float:
        return max(0.0, self.total_s - self.spent_s)

    def pairs_that_fit(self) -> int | None:
        """Most pairs the next round may match in the time left, at the first round's rate (None:
        the rate is unknown, no cut; 0: the time is spent)."""
        if self.left_s <= 0:
            return 0
        if self.rate_pairs_per_s <= 0 or math.isinf(self.left_s):
            return None
        return math.floor(self.left_s * self.rate_pairs_per_s + 1e-9)
