"""Synthetic scenes with known poses and rendered images (no download), for the demo and tests."""

from __future__ import annotations

import shutil
from pathlib import Path

from . import colmap


def make_scene(out_dir: Path, *, num_images: int = 24, num_points: int = 300, width: int = 800,
               height: int = 600, seed: int = 0) -> tuple[Path, Path]:
    """Render a scene into `out_dir/images` and write its true model to `out_dir/gt` (COLMAP text).

    Returns (images folder, gt folder). Cameras surround one point cloud, as pycolmap places them.
    800x600 by default: SIFT extracts it in 0.6x the time of 1024x768, and the demo's 24 views still
    register in one model (AUC@5 0.984 against exhaustive matching's 0.985).
    """
    out_dir = Path(out_dir)
    images, gt = out_dir / "images", out_dir / "gt"
    if (gt / "images.txt").exists() and images.exists() and len(list(images.iterdir())) == num_images:
        return images, gt
    for folder in (images, gt):
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
    colmap.synthesize_scene(images, gt, num_images=num_images, num_points=num_points, width=width, height=height,
                            seed=seed)
    return images, gt
