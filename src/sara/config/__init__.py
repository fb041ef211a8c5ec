"""Configuration: one frozen dataclass per concern, nested in `PipelineConfig`.

The CLI takes a preset name plus `section.field=value` overrides; the resolved configuration is
written to `run.json` in the output folder. Unknown keys are errors that list the valid ones; the
keys renamed when the sections were split (`RENAMED`) still work, with a warning naming the new key.
Each field's default, valid values, everyday/advanced flag and description are written beside it
(`sections`, `sara_sections`); `describe_markdown()` turns them into docs/configuration.md.
"""

from __future__ import annotations

from .describe import describe_markdown, everyday_keys
from .layout import RENAMED, RULES, SECTIONS, PipelineConfig
from .overrides import apply_overrides, config_from_dict, make_config, parse_override_args, renamed_keys
from .presets import PRESETS
from .rules import CAMERA_MODELS, MAX_SEED, ConfigError, validate
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

__all__ = [
    "CAMERA_MODELS", "MAX_SEED", "PRESETS", "RENAMED", "RULES", "SECTIONS", "BudgetConfig", "ConfigError",
    "ExecuteConfig", "ExtractConfig", "GraphConfig", "ImagesConfig", "MapConfig", "MatchConfig", "PairsConfig",
    "PipelineConfig", "RetrievalConfig", "RoundsConfig", "ScoreConfig", "SequenceConfig", "SequentialConfig",
    "VocabTreeConfig",
    "apply_overrides", "config_from_dict", "describe_markdown", "everyday_keys", "make_config",
    "parse_override_args", "renamed_keys", "validate",
]
