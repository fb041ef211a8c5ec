"""The map stage's model folders: what they hold (`colmap_models`, `model_digest`) and how a new
`sparse/` replaces the old one without a moment where neither exists (`swap_in`, `recover`)."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from . import colmap
from .io import file_digest

#: where `swap_in` keeps the previous models until the new ones are in place
OLD = "sparse.old"


def swap_in(new: Path, sparse: Path) -> None:
    """Replace `sparse` by the folder `new`; a run killed in between leaves the old one in
    `.sara/sparse.old`, which `recover` puts back."""
    old = new.parent / OLD
    shutil.rmtree(old, ignore_errors=True)
    if sparse.exists():
        sparse.rename(old)
    new.rename(sparse)
    shutil.rmtree(old, ignore_errors=True)


def recover(out_dir: Path) -> None:
    """After a run killed while swapping models: put the previous `sparse/` back when the new one
    never arrived (call it while holding the output folder's lock)."""
    out_dir = Path(out_dir)
    old = out_dir / ".sara" / OLD
    if old.is_dir():
        if (out_dir / "sparse").exists():
            shutil.rmtree(old, ignore_errors=True)
        else:
            old.rename(out_dir / "sparse")


def colmap_models(sparse: Path) -> list[Path]:
    sparse = Path(sparse)
    if not sparse.is_dir():
        return []
    return sorted((p for p in sparse.iterdir() if p.is_dir() and colmap.has_model(p)), key=lambda p: p.name)


def model_digest(sparse: Path) -> dict[str, Any]:
    """Size and hash of every file of every model folder under `sparse/`."""
    sparse = Path(sparse)
    if not sparse.is_dir():
        return {}
    return {f"{sub.name}/{f.name}": file_digest(f) for sub in sorted(sparse.iterdir()) if sub.is_dir()
            for f in sorted(sub.iterdir()) if f.is_file()}
