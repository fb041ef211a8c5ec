"""`PipelineConfig`: the sections in their order, where each key lives now and where it lived before."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar

from .rules import MAX_SEED, Rule, ints, option, validate
from .sara_sections import BudgetConfig, GraphConfig, RoundsConfig, ScoreConfig, SequenceConfig
from .sections import (
    ExecuteConfig,
    ExtractConfig,
    ImagesConfig,
    MapConfig,
    MatchConfig,
    PairsConfig,
    RetrievalConfig,
    SequentialConfig,
    VocabTreeConfig,
)


@dataclass(frozen=True, kw_only=True)
class PipelineConfig:
    SECTION: ClassVar[str] = ""

    images: ImagesConfig = field(default_factory=ImagesConfig)
    extract: ExtractConfig = field(default_factory=ExtractConfig)
    pairs: PairsConfig = field(default_factory=PairsConfig)
    sequential: SequentialConfig = field(default_factory=SequentialConfig)
    vocab_tree: VocabTreeConfig = field(default_factory=VocabTreeConfig)
    retrieval: RetrievalConfig = field(default_factory=RetrievalConfig)
    sequence: SequenceConfig = field(default_factory=SequenceConfig)
    score: ScoreConfig = field(default_factory=ScoreConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    budget: BudgetConfig = field(default_factory=BudgetConfig)
    rounds: RoundsConfig = field(default_factory=RoundsConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    map: MapConfig = field(default_factory=MapConfig)
    execute: ExecuteConfig = field(default_factory=ExecuteConfig)
    seed: int = option(0, ints(0, MAX_SEED), """Seed of the random choices (k-means codebooks, vocabulary trees,
        RANSAC, COLMAP's mapper): the same seed and inputs give the same result.""", advanced=False)

    def __post_init__(self) -> None:
        validate(self)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


#: keys renamed when the pair sources' options, the pair budget and SARA's rounds got sections of
#: their own: old name -> new name. Both `-s OLD=value` and run.json files with the old layout work.
RENAMED: dict[str, str] = {
    "pairs.sequential_overlap": "sequential.overlap",
    "pairs.sequential_quadratic": "sequential.quadratic",
    "pairs.sequential_loop_detection": "sequential.loop_detection",
    "pairs.sequential_loop_period": "sequential.loop_period",
    "pairs.sequential_loop_neighbors": "sequential.loop_neighbors",
    "pairs.vocab_tree_path": "vocab_tree.path",
    "pairs.vocab_num_images": "vocab_tree.num_images",
    "pairs.vocab_num_words": "vocab_tree.num_words",
    "graph.max_pairs_per_image": "budget.max_pairs_per_image",
    "graph.max_pairs_fraction": "budget.max_pairs_fraction",
    "graph.densify": "budget.densify",
    "graph.densify_pairs_per_image": "budget.densify_pairs_per_image",
    "pairs.repair_rounds": "rounds.repair_rounds",
    "pairs.repair_pairs_per_view": "rounds.repair_pairs_per_view",
    "pairs.min_view_inliers": "rounds.support_min_view_inliers",
    "pairs.support_pairs_per_view": "rounds.support_pairs_per_view",
    "graph.pose_guided_pairs_per_image": "rounds.pose_guided_pairs_per_image",
    "graph.pose_guided_min_points": "rounds.pose_guided_min_points",
    "graph.pose_guided_max_view_angle_deg": "rounds.pose_guided_max_view_angle_deg",
    "graph.pose_guided_max_per_view": "rounds.pose_guided_max_per_view",
    "graph.extend_tracks": "rounds.extend_tracks",
    "graph.extend_tracks_radius_px": "rounds.extend_tracks_radius_px",
    "graph.extend_tracks_scale_quantile": "rounds.extend_tracks_scale_quantile",
    "map.extend_model": "rounds.extend_model",
}


def sections() -> dict[str, type]:
    """Section name -> its dataclass, in `PipelineConfig`'s order."""
    return {f.name: f.default_factory for f in dataclasses.fields(PipelineConfig)
            if f.default_factory is not dataclasses.MISSING}


def _all_rules() -> dict[str, Rule]:
    out: dict[str, Rule] = {}
    for section, cls in sections().items():
        out.update({f"{section}.{f.name}": f.metadata["rule"] for f in dataclasses.fields(cls)})
    out["seed"] = next(f for f in dataclasses.fields(PipelineConfig) if f.name == "seed").metadata["rule"]
    return out


#: section.field -> (check, description of the valid values), read from the fields themselves
RULES: dict[str, Rule] = _all_rules()

#: the section name of each config class in `PipelineConfig`
SECTIONS: dict[str, str] = {cls.__name__: cls.SECTION for cls in sections().values()} | {"PipelineConfig": ""}
