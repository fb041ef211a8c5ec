"""Synthetic scenes with known poses and rendered images (no download), for the demo and tests."""

from __future__ import annotations

import shutil
from pathlib import Path

import pycolmap


def make_scene(out_dir: Path, *, num_images: int = 24, num_points: int = 300, width: int = 1024,
               height: int = 768, seed: int = 0) -> tuple[Path, Path]:
    """Render a scene into `out_dir/images` and write its true model to `out_dir/gt` (COLMAP text).

    Returns (images folder, gt folder). Cameras surround one point cloud, as pycolmap places them.
    """
    out_dir = Path(out_dir)
    images, gt = out_dir / "images", out_dir / "gt"
    if (gt / "images.txt").exists() and images.exists() and len(list(images.iterdir())) == num_images:
        return images, gt
    for folder in (images, gt):
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
    pycolmap.set_random_seed(seed)
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs = 1
    opts.num_cameras_per_rig = 1
    opts.num_frames_per_rig = num_images
    opts.num_points3D = num_points
    opts.camera_width, opts.camera_height = width, height
    opts.camera_model_id = pycolmap.CameraModelId.PINHOLE
    focal = 1.2 * max(width, height)
    opts.camera_params = [focal, focal, width / 2, height / 2]
    rec = pycolmap.synthesize_dataset(opts)
    pycolmap.synthesize_images(pycolmap.SyntheticImageOptions(), rec, str(images))
    rec.write_text(str(gt))
    return images, gt
