"""The ``colmap`` export: ``DEST/database.db``, ``DEST/sparse/N`` and ``DEST/project.ini``.

``project.ini`` names the database and the image folder, for ``colmap gui --project_path
DEST/project.ini`` (COLMAP 4.x: the database has COLMAP 4's rig and frame tables) or
``colmap gui --import_path DEST/sparse/0 --database_path DEST/database.db --image_path IMAGES``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from .. import colmap
from ..colmap import model
from ..io import read_json, write_text_atomic
from .common import ExportJob


def write(job: ExportJob) -> None:
    """For COLMAP's GUI, a copy of the run's database, every model in DEST/sparse, DEST/project.ini."""
    out_dir, dest = job.out_dir, job.dest
    db_src = out_dir / "database.db"
    if not db_src.exists():
        raise FileNotFoundError(f"{db_src} not found: the colmap export needs the run's database")
    colmap.copy_database(db_src, dest / "database.db")
    if (dest / "sparse").exists():
        shutil.rmtree(dest / "sparse")
    for src in model.find_models(out_dir / "sparse"):
        model.write_model(src, dest / "sparse" / src.name)
    config = read_json(out_dir / "run.json").get("config", {}) if (out_dir / "run.json").exists() else {}
    write_text_atomic(dest / "project.ini", project_ini(dest / "database.db", job.images_root, config))


def project_ini(database: Path, images_root: Path, config: dict) -> str:
    """A COLMAP project file: the database, the image folder and the mapper settings sara ran with.

    COLMAP rejects keys that a command does not register (boost program_options), so only the paths
    and `Mapper.*` options are written, which `colmap gui` and `colmap mapper` both register.
    """
    mapper = config.get("map", {})
    lines = [f"database_path={Path(database).resolve()}", f"image_path={Path(images_root).resolve()}",
             "[Mapper]", f"min_model_size={mapper.get('min_model_size', 10)}",
             f"abs_pose_min_num_inliers={mapper.get('abs_pose_min_num_inliers', 30)}",
             f"abs_pose_min_inlier_ratio={mapper.get('abs_pose_min_inlier_ratio', 0.25)}"]
    return "\n".join(lines) + "\n"
