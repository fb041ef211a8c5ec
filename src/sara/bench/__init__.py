"""`sara bench`: every pair source side by side on scenes with known poses (`run.py`), the
tables and plot of the results (`tables.py`), scenes under random file names (`names.py`), and
synthetic street worlds of any size with true poses, to measure pair selection at scale (`world/`,
imported on its own as `sara.bench.world`)."""

from .kinds import kind_summary, parse_kinds, render_kinds
from .names import renamed_scene
from .run import (
    ABLATION_VARIANTS,
    DEFAULT_METHODS,
    BenchResult,
    parse_methods,
    run_bench,
    run_method,
)
from .tables import (
    ABLATION_COLUMNS,
    ABLATION_NOTE,
    ABLATION_TITLE,
    TABLE_COLUMNS,
    TABLE_TITLE,
    names_summary,
    render_markdown,
    render_names,
)

__all__ = [
    "ABLATION_COLUMNS", "ABLATION_NOTE", "ABLATION_TITLE", "ABLATION_VARIANTS", "DEFAULT_METHODS", "TABLE_COLUMNS",
    "TABLE_TITLE", "BenchResult", "names_summary", "parse_methods", "render_markdown", "render_names",
    "kind_summary", "parse_kinds", "render_kinds", "renamed_scene", "run_bench", "run_method",
]
