"""Stage `map`: pycolmap's incremental (or global) mapper into `sparse/0`, `sparse/1`, ...

Components are numbered by decreasing size, so `sparse/0` is always the largest model, the one
that 3DGS, nerfstudio and COLMAP's GUI open by default.
"""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path

from tqdm import tqdm

from . import colmap
from .config import MapConfig
from .io import records

logger = logging.getLogger(__name__)

STAGE = "map"


def run(conf: MapConfig, db_path: Path, images_root: Path, out_dir: Path, *, seed: int = 0,
        upstream_key: str = "", progress: bool = True) -> Path:
    """Map the matched database into `out_dir/sparse/N`; returns `sparse/` (component sizes and the
    time taken go into the stage record)."""
    out_dir = Path(out_dir)
    sparse = out_dir / "sparse"
    key = state_key(conf, seed, upstream_key)
    if records.is_done(out_dir, STAGE, key) and sparse.exists():
        logger.info("map: model up to date, skipping")
        return sparse
    records.mark_started(out_dir, STAGE, key)
    tmp = out_dir / ".sara" / "sparse.partial"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    num_images = len(colmap.database_images(db_path))
    colmap.set_seed(seed)
    tic = time.perf_counter()
    if conf.mapper == "incremental":
        with tqdm(total=num_images, desc="map (incremental)", unit="img", disable=not progress) as bar:
            recs = colmap.incremental_mapping(
                db_path, images_root, tmp, seed=seed, min_model_size=conf.min_model_size,
                abs_pose_min_num_inliers=conf.abs_pose_min_num_inliers,
                abs_pose_min_inlier_ratio=conf.abs_pose_min_inlier_ratio, num_threads=conf.num_threads,
                on_next_image=lambda: bar.update())
    elif conf.mapper == "global":
        recs = colmap.global_mapping(db_path, images_root, tmp, seed=seed, num_threads=conf.num_threads)
    else:
        raise ValueError(f"unknown mapper {conf.mapper!r}; choose incremental or global")
    elapsed = time.perf_counter() - tic
    sizes = colmap.write_models_by_size(tmp, recs)
    if sparse.exists():
        shutil.rmtree(sparse)
    tmp.rename(sparse)
    info = {"time_s": elapsed, "num_components": len(sizes), "component_sizes": sizes,
            "num_registered": sizes[0] if sizes else 0, "num_images": num_images}
    records.mark_done(out_dir, STAGE, key, info)
    if not sizes:
        logger.warning("map: no model could be built (too few verified matches)")
    elif len(sizes) > 1:
        logger.warning("map: the scene split into %d models of %s images", len(sizes), sizes)
    return sparse


def state_key(conf: MapConfig, seed: int, upstream_key: str) -> str:
    from .io import fingerprint

    return fingerprint({"conf": conf.__dict__, "seed": seed, "upstream": upstream_key})
