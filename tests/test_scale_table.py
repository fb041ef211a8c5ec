"""docs/results.md's table of thousands of images is the one `lab/scripts/scale_current.py` makes from
the committed rows (`lab/notes/scale_e2e_results.jsonl`), run here as the docs show it: every figure
of a row in the script's table is in the documented row of the same size and method."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COMMAND = "python lab/scripts/scale_current.py lab/notes/scale_e2e_results.jsonl OUT"
sys.path.insert(0, str(ROOT / "lab" / "scripts"))
from scale_current import LABELS  # noqa: E402  (the script's method names as the docs spell them)

#: cells compared as they are (the docs may only add bold); the registered / models cell is written
#: differently (a range, not a list)
COMPARED = ("runs", "pairs", "AUC@1 mean (range)", "AUC@5 mean (range)", "match s", "map s", "rounds s", "CPU s")


def _rows(markdown: str) -> dict[tuple[str, str], dict[str, str]]:
    """The first table of `markdown` whose header starts with N, as {(N, method): {column: cell}}."""
    lines = [line for line in markdown.splitlines() if line.startswith("|")]
    start = next(k for k, line in enumerate(lines) if line.startswith("| N |"))
    header = [c.strip() for c in lines[start].strip("|").split("|")]
    rows = {}
    for line in lines[start + 2:]:
        cells = [c.strip().replace("**", "") for c in line.strip("|").split("|")]
        if len(cells) != len(header) or not re.fullmatch(r"[\d,]+", cells[0]):
            break
        row = dict(zip(header, cells))
        rows[row["N"], re.sub(r" \(k = \d+\)$", "", row["method"])] = row  # the docs name k once
    return rows


def test_the_documented_scale_table_is_the_scripts(tmp_path: Path):
    results = (ROOT / "docs" / "results.md").read_text()
    assert COMMAND in results
    args = COMMAND.split()[1:-1] + [str(tmp_path)]
    subprocess.run([sys.executable, *args], cwd=ROOT, check=True, capture_output=True)
    made = _rows((tmp_path / "scale_current.md").read_text())
    documented = _rows(results[results.index("## Thousands of images"):])
    assert made and set(documented) == {(n, LABELS[m]) for n, m in made}
    for (n, method), row in made.items():
        shown = documented[n, LABELS[method]]
        for column in COMPARED:
            assert shown[column] == row[column], (n, method, column)
    assert (tmp_path / "scale_current.png").stat().st_size > 0
