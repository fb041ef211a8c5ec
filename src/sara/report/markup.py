"""Small HTML helpers shared by the report's modules: escaping, number formatting, a section, a table."""

from __future__ import annotations

import html
import math
from collections.abc import Sequence

import numpy as np


def esc(text: object) -> str:
    """`text` escaped for HTML text and attribute values."""
    return html.escape(str(text), quote=True)


def fmt(value: object, digits: int = 3) -> str:
    """A value for a table cell: `digits` significant digits, thousands separators from 1000 on."""
    if value is None:
        return "&ndash;"
    if isinstance(value, bool | int | np.integer):
        return str(value)
    if isinstance(value, float | np.floating):
        if not math.isfinite(float(value)):
            return esc(value)
        return f"{float(value):.{digits}g}" if abs(float(value)) < 1e3 else f"{float(value):,.0f}"
    return esc(value)


def section(title: str, body: str, note: str = "") -> str:
    """A titled box of the page; `note` (HTML) is the grey line under the title."""
    note_html = f"<p class=\"note\">{note}</p>" if note else ""
    return f"<section><h2>{esc(title)}</h2>{note_html}{body}</section>"


def table(rows: Sequence[tuple[str, str]]) -> str:
    """A two-column table of (escaped key, HTML value) rows."""
    return "<table>" + "".join(f"<tr><th>{esc(k)}</th><td>{v}</td></tr>" for k, v in rows) + "</table>"
