"""`sara export OUT DEST --format NAME`: a sara model in the layout another tool reads.

Formats are registered by name in `FORMATS`, each one module with a `write(job)` function:

- ``3dgs`` (`gaussian_splatting.py`): what 3D Gaussian Splatting's ``train.py -s DEST`` loads:
  undistorted images and a PINHOLE model in ``DEST/sparse/0``.
- ``nerfstudio`` (`nerfstudio.py`): ``DEST/transforms.json``, ``DEST/images`` and
  ``DEST/sparse_pc.ply``, as ``ns-process-data`` writes them.
- ``colmap`` (`colmap_project.py`): ``DEST/database.db``, ``DEST/sparse/N`` and ``DEST/project.ini``
  for ``colmap gui``.

`export` reads the model `OUT/sparse/<model_index>` of a `sara run` and the image folder recorded in
`OUT/run.json`. A format replaces what it writes in DEST and leaves anything else there. A new
format is one module with `write(job: ExportJob) -> None` plus one line in `FORMATS`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from .. import colmap
from ..registry import Registry
from .common import ExportJob, check_destination, find_model, recorded_images_root

logger = logging.getLogger(__name__)

ExportFormat = Callable[[ExportJob], None]

#: name -> the format's writer; the CLI's `--format` choices are these names
FORMATS: Registry[ExportFormat] = Registry("export format", {
    "3dgs": "sara.export.gaussian_splatting:write",
    "nerfstudio": "sara.export.nerfstudio:write",
    "colmap": "sara.export.colmap_project:write",
})

__all__ = ["FORMATS", "ExportFormat", "ExportJob", "export", "find_model", "recorded_images_root"]


def export(out_dir: Path, dest: Path, fmt: str = "3dgs", *, model_index: int = 0, images: Path | None = None,
           undistort: bool = False, max_image_size: int = -1, progress: bool = True,
           verbose_colmap: bool = False) -> Path:
    """Export model `OUT/sparse/<model_index>` of a sara run to `dest` in format `fmt`; returns `dest`.

    images: the image folder (default: the one recorded in `OUT/run.json`).
    undistort: nerfstudio only (3dgs always undistorts, colmap never does).
    max_image_size: with undistortion, also downscale the longer image side to this (px; -1: keep).
    progress: progress bars over the images.
    verbose_colmap: COLMAP's own log (the undistorter's) on the console instead of `OUT/logs`.
    Raises FileNotFoundError when OUT has no model or the images are missing, ValueError for a bad format.
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    out_dir, dest = Path(out_dir), Path(dest)
    model_dir = find_model(out_dir, model_index)
    images_root = Path(images) if images is not None else recorded_images_root(out_dir)
    if not images_root.is_dir():
        raise FileNotFoundError(f"image folder {images_root} not found; pass the images the model was made from")
    check_destination(out_dir, dest, images_root)
    dest.mkdir(parents=True, exist_ok=True)
    colmap.send_log_to(out_dir / "logs", verbose=verbose_colmap)
    job = ExportJob(out_dir=out_dir, model_dir=model_dir, images_root=images_root, dest=dest, undistort=undistort,
                    max_image_size=max_image_size, progress=progress)
    FORMATS.get(fmt)(job)
    logger.info("exported %s (%s) to %s", model_dir, fmt, dest)
    return dest
