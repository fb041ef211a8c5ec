"""Pair sources: each turns a collection into a list of image pairs to match.

Every source (SARA and the baselines) only produces pairs; matching, verification and mapping
are the same code for all of them, so comparisons measure pair selection and nothing else.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

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


@dataclass
class PairResult:
    pairs: list[Pair]
    info: dict[str, Any] = field(default_factory=dict)  # stats that go into run.json
    timings_s: dict[str, float] = field(default_factory=dict)


PairSource = Callable[[PairContext], PairResult]
#: after_mapping(ctx, pairs, model_dir) -> more pairs to match (empty: the model is as good as it gets)
AfterMapping = Callable[[PairContext, list[Pair], Path], list[Pair]]

SOURCES: Registry[PairSource] = Registry("pair source", {
    "sara": "sara.pairs.sara_source:select",
    "exhaustive": "sara.pairs.exhaustive:select",
    "sequential": "sara.pairs.sequential:select",
    "vocab_tree": "sara.pairs.vocabtree:select",
    "vocabtree": "sara.pairs.vocabtree:select",  # the spelling of sara 0.1
    "retrieval": "sara.pairs.retrieval_only:select",
})

#: sources that look at the first model and ask for more pairs (matched, then mapped again)
AFTER_MAPPING: Registry[AfterMapping] = Registry("post-mapping step", {
    "sara": "sara.pairs.sara_source:after_mapping",
})


def get_source(name: str) -> PairSource:
    if name not in SOURCES:
        raise ValueError(
            f"unknown pair source {name!r}; choose one of {', '.join(SOURCES)} or give a pairs file path"
        )
    return SOURCES.get(name)


def get_after_mapping(name: str) -> AfterMapping | None:
    return AFTER_MAPPING.get(name) if name in AFTER_MAPPING else None
