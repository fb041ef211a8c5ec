"""The ``3dgs`` export: what 3D Gaussian Splatting's ``train.py -s DEST`` loads.

Its ``scene/dataset_readers.py`` reads ``DEST/sparse/0`` (``cameras.bin``, ``images.bin``,
``points3D.bin``), accepts only PINHOLE / SIMPLE_PINHOLE cameras and opens
``DEST/images/<basename of the name>``. So the images are undistorted with COLMAP's undistorter,
and images in sub-folders are renamed ``sub_name.jpg``.
"""

from __future__ import annotations

from .common import ExportJob, undistort_flat


def write(job: ExportJob) -> None:
    """For 3D Gaussian Splatting, undistorted images in DEST/images and a PINHOLE model in DEST/sparse/0."""
    undistort_flat(job.model_dir, job.images_root, job.dest, job.max_image_size, job.progress)
