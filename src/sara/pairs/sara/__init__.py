"""SARA, the Scene-Aware Reconstruction Accelerator, as a pair source.

`source.py` selects the first pairs (global-descriptor kNN candidates, a short pre-match scoring
overlap x parallax, the maximum spanning tree plus loops, anchors and weak-view pairs);
`rounds.py` adds pairs around mapping (support, repair, pose-guided) and refines the model;
`budget.py` owns the pair cap of all of them.
"""

from __future__ import annotations

from ...config import PipelineConfig
from .. import PairSource
from .extend import extend
from .rounds import SaraRounds
from .source import select


def _sections(conf: PipelineConfig) -> tuple[str, ...]:
    """The selection depends on the scorer, the graph and the budget it shares with the rounds."""
    return ("pairs", "retrieval", "sequence", "score", "graph", "budget", "rounds")


SOURCE = PairSource(select=select, sections=_sections, caches=("global-*.h5",), rounds=SaraRounds(),
                    extend=extend)
