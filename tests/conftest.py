from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "2")

DATA_ROOT = Path(os.environ.get("SARA_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def scene_dir(name: str) -> Path:
    path = DATA_ROOT / name
    if not (path / "images").is_dir():
        pytest.skip(f"real scene {name} not available at {path} (set SARA_DATA to its parent folder)")
    return path


@pytest.fixture(scope="session")
def synthetic_scene(tmp_path_factory):
    """A small rendered scene with known poses: (images folder, gt folder)."""
    from sara.synthetic import make_scene

    return make_scene(tmp_path_factory.mktemp("synthetic"), num_images=10)
