"""Pair sources: each turns a collection into a list of image pairs to match.

Every source (SARA and the baselines) only produces pairs; matching, verification and mapping
are the same code for all of them, so comparisons measure pair selection and nothing else.

A source is one file that defines a `PairSource` plus one line in `SOURCES`. It declares the
configuration sections its pairs depend on (they key the pairs stage's cache) and the files it
keeps between runs; a source that wants more pairs once matches or a model exist (SARA) also
gives `Rounds`, which the pipeline drives without knowing the source.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from ..config import PipelineConfig
from ..io.pairs import Pair
from ..registry import Registry


@dataclass
class PairContext:
    names: list[str]  # the images of the run, sorted
    images_root: Path
    features_path: Path  # features.h5
    db_path: Path  # COLMAP database with keypoints and cameras
    out_dir: Path  # where a source may write its own files (scores.csv, global.h5, ...)
    conf: PipelineConfig
    progress: bool = True
    executor: Any = None  # a sara.execute.Executor for parallel work; None: this process
    #: the extract stage's focal-length estimate for a shared camera (`estimated_px`, `sound`,
    #: `prior_px`, ...; its record's `focal`), None when it made none
    focal_estimate: dict[str, Any] | None = None
    #: most pairs the round after mapping that is being asked for may add, from the rounds' time
    #: budget (set by the pipeline for that call; None: no limit beyond the source's own)
    max_round_pairs: int | None = None
    #: the round asked for is the one after the repairs used up `rounds.repair_rounds`: a source
    #: should give pairs its `refine` takes in (set by the pipeline for that call)
    last_round: bool = False
    #: where the pairs stage keeps the scores made so far (a `sara.scoring.ScoreJournal`): a source
    #: that scores pairs passes it to `score_pairs`, and a selection stopped part-way keeps them
    score_journal: Any = None


@dataclass
class PairResult:
    pairs: list[Pair]
    info: dict[str, Any] = field(default_factory=dict)  # stats that go into run.json
    timings_s: dict[str, float] = field(default_factory=dict)
    #: with no pairs: why, in words a user can act on ("" lets the pipeline say it generically)
    why_empty: str = ""


@dataclass
class Extension:
    """An earlier selection, matched, of a collection that images were added to, removed from or
    changed in since.

    kept_pairs: the earlier pairs between images that stay unchanged (already matched: a source
    that selects them again costs no matching); new_names: the images that are new or changed;
    scores_path: the earlier selection's scores file, if any (its candidates between unchanged
    images need no scoring again).
    """

    kept_pairs: list[Pair]
    new_names: list[str]
    scores_path: Path | None = None
    #: only names changed since (no image added, removed or changed): the earlier selection stands
    renamed_only: bool = False


@dataclass
class Round:
    """Pairs a round asks to match, and the role the report gives them."""

    pairs: list[Pair]
    role: str


class Rounds(Protocol):
    """What a pair source does around mapping; the pipeline calls, in this order:

    - `before_mapping(ctx, pairs, db_path)`: more pairs once the first pairs are matched (their
      verified geometries are in `db_path`), matched before the first mapping;
    - `after_mapping(ctx, pairs, model_dir)`: more pairs once a model exists (`model_dir`, the
      largest); matched, then the model is refined or mapped again; repeated up to
      `rounds.repair_rounds` times while it asks for pairs;
    - `refine(ctx, added, db_path, model_dir, out_model_dir)`: instead of mapping again after a
      round, write a refined model into `out_model_dir` (None: map again);
    - `finish(ctx, model_dir, out_model_dir, refined=...)`: a last improvement of the final model
      into `out_model_dir` (None: nothing to do).

    A round returns None or a Round without pairs when it has nothing to add; pairs are always
    `name0 name1` of images of the run, never pairs already matched.
    """

    def before_mapping(self, ctx: PairContext, pairs: list[Pair], db_path: Path) -> Round | None: ...

    def after_mapping(self, ctx: PairContext, pairs: list[Pair], model_dir: Path) -> Round | None: ...

    def refine(self, ctx: PairContext, added: Round, db_path: Path, model_dir: Path,
               out_model_dir: Path) -> dict[str, Any] | None: ...

    def finish(self, ctx: PairContext, model_dir: Path, out_model_dir: Path, *,
               refined: bool) -> dict[str, Any] | None: ...


class NoRounds:
    """Rounds that add nothing: a base for sources that implement only some of them."""

    def before_mapping(self, ctx: PairContext, pairs: list[Pair], db_path: Path) -> Round | None:
        return None

    def after_mapping(self, ctx: PairContext, pairs: list[Pair], model_dir: Path) -> Round | None:
        return None

    def refine(self, ctx: PairContext, added: Round, db_path: Path, model_dir: Path,
               out_model_dir: Path) -> dict[str, Any] | None:
        return None

    def finish(self, ctx: PairContext, model_dir: Path, out_model_dir: Path, *,
               refined: bool) -> dict[str, Any] | None:
        return None


def _only_pairs_section(conf: PipelineConfig) -> tuple[str, ...]:
    return ("pairs",)


@dataclass(frozen=True)
class PairSource:
    """A pair source: `select(ctx)` gives the pairs.

    sections(conf): the configuration sections its pairs depend on (the pairs stage's cache key;
    "retrieval" there also makes the run check the global descriptor and its weights up front).
    caches: file patterns it keeps in the output folder between runs (reused when their inputs
    did not change). rounds: its work around mapping, if any.
    """

    select: Callable[[PairContext], PairResult]
    sections: Callable[[PipelineConfig], tuple[str, ...]] = _only_pairs_section
    caches: tuple[str, ...] = ()
    rounds: Rounds | None = None
    extend: Callable[[PairContext, Extension], PairResult] | None = None

    def __call__(self, ctx: PairContext) -> PairResult:
        return self.select(ctx)


SOURCES: Registry[PairSource] = Registry("pair source", {
    "sara": "sara.pairs.sara:SOURCE",
    "exhaustive": "sara.pairs.exhaustive:SOURCE",
    "sequential": "sara.pairs.sequential:SOURCE",
    "vocab_tree": "sara.pairs.vocabtree:SOURCE",
    "vocabtree": "sara.pairs.vocabtree:SOURCE",  # the spelling of sara 0.1
    "retrieval": "sara.pairs.retrieval_only:SOURCE",
})


def get_source(name: str) -> PairSource:
    if name not in SOURCES:
        raise ValueError(
            f"unknown pair source {name!r}; choose one of {', '.join(SOURCES)} or give a pairs file path"
        )
    source = SOURCES.get(name)
    # a bare function registered by a plugin or a test: a source with no settings of its own
    return source if isinstance(source, PairSource) else PairSource(select=source)


def rounds_of(name: str) -> Rounds | None:
    """The rounds of the pair source `name` (None for a pairs file or a source without rounds)."""
    return get_source(name).rounds if name in SOURCES else None
