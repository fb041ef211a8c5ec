"""The one table renderer: Markdown (GitHub) or aligned plain text, from rows of strings. A leaf."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any


def format_number(value: Any, spec: str = "") -> str:
    """`value` with a format spec ("d", ".3f", ...); None and non-finite floats print as "-"."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if spec == "d":
        return str(int(value))
    if spec:
        return format(float(value), spec)
    return f"{value:.4f}" if isinstance(value, float) else str(value)


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]], *, numeric: bool = True) -> str:
    """A Markdown table; with `numeric`, every column but the first is right-aligned."""
    align = "|---|" + ("---:|" if numeric else "---|") * (len(header) - 1)
    lines = ["| " + " | ".join(header) + " |", align]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def text_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """An aligned plain-text table: the first column left-aligned, the others right-aligned."""
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]

    def line(cells: Sequence[str]) -> str:
        first = f"{cells[0]:<{widths[0]}}"
        return "  ".join([first] + [f"{c:>{w}}" for c, w in zip(cells[1:], widths[1:])])

    return "\n".join([line(header), line(["-" * w for w in widths]), *(line(r) for r in rows)])
