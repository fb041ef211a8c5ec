"""The code passes ruff with the rules of pyproject.toml ([tool.ruff]). CI runs the README's
`python -m pytest -q`, so the linter runs as this test (skipped where ruff is not installed; the
`test` extra installs it)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(importlib.util.find_spec("ruff") is None, reason="ruff is not installed (pip install -e '.[test]')")
def test_ruff_finds_nothing() -> None:
    proc = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "src", "tests"], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, f"ruff check src tests:\n{proc.stdout}{proc.stderr}"
