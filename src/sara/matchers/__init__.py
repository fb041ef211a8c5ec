"""Matchers: one small Protocol, one file per matcher, one registry.

A matcher turns the features of two images into index pairs. The match stage (`sara.match`)
does everything else for every matcher alike: chunks of pairs, resuming pair by pair, writing the
matches into the COLMAP database and COLMAP's geometric verification, so mapping is unchanged.

COLMAP's SIFT matcher is the one that matches inside the database itself (its fastest path for
SIFT); it implements `match_in_database` instead of `match`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, runtime_checkable

import numpy as np

from ..config import MatchConfig
from ..io.h5 import Features
from ..registry import Registry


@runtime_checkable
class Matcher(Protocol):
    """A matcher of two images' features (hloc convention keypoints, (N, D) descriptors).

    `match` returns (K, 2) int32 indices (i0, i1) and (K,) float32 scores (larger is better).
    A matcher may also define `match_batch(pairs: list[tuple[Features, Features]])` returning a
    list of such results (used in chunks when present). A matcher that runs on an accelerator says
    so with a `device` attribute (a torch.device or "cuda", ...): the stage then calls it in the
    driver process instead of loading it in every worker (`sara.execute.for_device`). A matcher
    that pays a cost per image and call says how much with `image_cost_in_pairs` (in pairs'
    matching time), which the stage's time estimate counts (`sara.eta.chunk_work`).
    """

    name: str

    def match(self, feats0: Features, feats1: Features) -> tuple[np.ndarray, np.ndarray]: ...


#: factory(conf, features_backend_name) -> Matcher
MatcherFactory = Callable[[MatchConfig, str], Matcher]

BACKENDS: Registry[MatcherFactory] = Registry("matcher", {
    "colmap": "sara.matchers.colmap_sift:make",
    "nearest": "sara.matchers.nearest:make",
    "lightglue": "sara.matchers.lightglue:make",
    "lighterglue": "sara.matchers.lightglue:make",
})

#: the matcher `backend = "auto"` picks for each local-feature backend (others: "nearest")
AUTO: dict[str, str] = {
    "sift": "colmap",
    "aliked-n16": "lightglue",
    "aliked-n16rot": "lightglue",
    "aliked-n32": "lightglue",
    "disk": "lightglue",
    "xfeat": "lighterglue",
}


def resolve_name(conf: MatchConfig, features: str) -> str:
    """The matcher a run uses: `conf.backend`, or for "auto" the usual one for these features."""
    return AUTO.get(features, "nearest") if conf.backend == "auto" else conf.backend


def make_matcher(conf: MatchConfig, features: str) -> Matcher:
    return BACKENDS.get(resolve_name(conf, features))(conf, features)
