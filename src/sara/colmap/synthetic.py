"""pycolmap's synthetic scenes: rendered images and their true model, for tests and the demo."""

from __future__ import annotations

from pathlib import Path

import pycolmap


def synthesize_scene(images_dir: Path, gt_dir: Path, *, num_images: int, num_points: int, width: int,
                     height: int, seed: int) -> None:
    """pycolmap's synthetic scene: rendered PNGs into `images_dir`, the true model (text) into `gt_dir`.

    One PINHOLE camera with focal 1.2 * max(width, height); cameras surround one point cloud.
    """
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
    pycolmap.synthesize_images(pycolmap.SyntheticImageOptions(), rec, str(images_dir))
    rec.write_text(str(gt_dir))
