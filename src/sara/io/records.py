"""Per-stage records in `<out>/.sara/`, so a re-run skips finished work and redoes stale work.

Each stage stores the fingerprint of everything that determines its output (its config and its
inputs). A stage is done when its record exists with `done: true` and the same fingerprint.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from . import read_json, write_json_atomic


def _record_path(out_dir: Path, stage: str) -> Path:
    return Path(out_dir) / ".sara" / f"{stage}.json"


def read_record(out_dir: Path, stage: str) -> dict[str, Any] | None:
    path = _record_path(out_dir, stage)
    if not path.exists():
        return None
    try:
        return read_json(path)
    except ValueError:  # a record cut short: treat the stage as never run
        return None


def is_done(out_dir: Path, stage: str, key: str) -> bool:
    rec = read_record(out_dir, stage)
    return rec is not None and rec.get("done") is True and rec.get("key") == key


def mark_started(out_dir: Path, stage: str, key: str) -> None:
    write_json_atomic(_record_path(out_dir, stage), {"key": key, "done": False})


def mark_done(out_dir: Path, stage: str, key: str, info: dict[str, Any] | None = None) -> None:
    write_json_atomic(_record_path(out_dir, stage), {"key": key, "done": True, "info": info or {}})


def done_info(out_dir: Path, stage: str) -> dict[str, Any]:
    rec = read_record(out_dir, stage) or {}
    return rec.get("info", {})


def clear(out_dir: Path, stage: str) -> None:
    _record_path(out_dir, stage).unlink(missing_ok=True)
