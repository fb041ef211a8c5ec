"""Per-stage records in `<out>/.sara/`, so a re-run skips finished work and redoes stale work.

Each stage stores the fingerprint of everything that determines its output (its config and its
inputs) and, when done, what it produced: a digest of each output file (sizes and content hashes of
small files; counts and a cheap digest of large ones, see `sara.io.file_digest`). A stage is done
when its record exists with `done: true`, the same fingerprint, and outputs that still match what
is on disk now: a file cut short, emptied, edited or damaged since is never trusted.
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
        record = read_json(path)
    except (ValueError, UnicodeDecodeError):  # a record cut short: treat the stage as never run
        return None
    return record if isinstance(record, dict) else None


def is_done(out_dir: Path, stage: str, key: str) -> bool:
    rec = read_record(out_dir, stage)
    return rec is not None and rec.get("done") is True and rec.get("key") == key


def mark_started(out_dir: Path, stage: str, key: str) -> None:
    write_json_atomic(_record_path(out_dir, stage), {"key": key, "done": False})


def mark_done(out_dir: Path, stage: str, key: str, info: dict[str, Any] | None = None, *,
              outputs: dict[str, Any] | None = None) -> None:
    """Record a finished stage; `outputs` maps each output (a file name) to its digest."""
    record: dict[str, Any] = {"key": key, "done": True, "info": info or {}}
    if outputs is not None:
        record["outputs"] = outputs
    write_json_atomic(_record_path(out_dir, stage), record)


def restore(out_dir: Path, stage: str, record: dict[str, Any] | None) -> None:
    """Put back a record read before a failed attempt (None: remove the stage's record)."""
    if record is None:
        clear(out_dir, stage)
    else:
        write_json_atomic(_record_path(out_dir, stage), record)


def done_info(out_dir: Path, stage: str) -> dict[str, Any]:
    rec = read_record(out_dir, stage) or {}
    return rec.get("info", {})


def recorded_outputs(out_dir: Path, stage: str) -> dict[str, Any]:
    """The output digests of a finished stage ({} when none were recorded)."""
    rec = read_record(out_dir, stage) or {}
    return rec.get("outputs", {}) if rec.get("done") is True else {}


def changed_output(out_dir: Path, stage: str, current: dict[str, Any]) -> str | None:
    """The first output whose digest now differs from the one recorded when the stage finished
    (None when all agree). `current` maps output names to their digests as they are now; an output
    that is recorded but not in `current` is not checked."""
    recorded = recorded_outputs(out_dir, stage)
    for name, digest in current.items():
        if name in recorded and recorded[name] != digest:
            return name
    return None


def clear(out_dir: Path, stage: str) -> None:
    _record_path(out_dir, stage).unlink(missing_ok=True)
