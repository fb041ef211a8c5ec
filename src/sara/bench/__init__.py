"""`sara bench`: every pair source side by side on scenes with known poses (`run.py`), and the
tables and plot of the results (`tables.py`)."""

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
    render_markdown,
)

__all__ = [
    "ABLATION_COLUMNS", "ABLATION_NOTE", "ABLATION_TITLE", "ABLATION_VARIANTS", "DEFAULT_METHODS", "TABLE_COLUMNS",
    "TABLE_TITLE", "BenchResult", "parse_methods", "render_markdown", "run_bench", "run_method",
]
