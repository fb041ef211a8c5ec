"""Plain pycolmap exhaustive matching and incremental mapping, outside sara's pipeline code.

A cross-check of `sara bench`: the exhaustive row of the benchmark should agree, within run-to-run
noise, with what plain pycolmap makes of the very same features. Steps:

1. SIFT features by `sara extract` into OUT/features (or reuse a finished extract folder, e.g. the
   `features/` of a bench scene, with --features);
2. a copy of that database (features only, no matches) into OUT/plain/database.db;
3. `pycolmap.match_exhaustive` with pycolmap's default matching and verification options (the
   values sara's MatchConfig also uses), then `pycolmap.incremental_mapping` with default options
   (seeded) except the two registration thresholds that sara's MapConfig sets (so both pipelines
   ask COLMAP the same question), into OUT/plain/sparse;
4. evaluation of the largest model against SCENE/gt with `sara.evaluate`, printed with the columns
   of the bench table and saved to OUT/plain/metrics.json.

    python lab/scripts/plain_colmap_exhaustive.py SCENE OUT [--features DIR] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap

from sara import bench, evaluate
from sara.config import MapConfig, make_config
from sara.pipeline import run as sara_run

logger = logging.getLogger("plain_colmap_exhaustive")


def copy_database(src: Path, dst: Path) -> None:
    """A consistent copy of a SQLite database (its WAL included), without matches in it."""
    bench.copy_sqlite(src, dst)
    with pycolmap.Database.open(str(dst)) as db:
        if db.num_matched_image_pairs() or db.num_verified_image_pairs():
            raise ValueError(f"{src} already holds matches: give the database of a bare `sara extract`")


def inlier_stats(db_path: Path, min_num_inliers: int) -> dict:
    """Verified pairs and their mean inlier count, read straight from the database."""
    with pycolmap.Database.open(str(db_path)) as db:
        _, num_inliers = db.read_two_view_geometry_num_inliers()
    inliers = np.asarray(num_inliers, dtype=np.int64)
    verified = inliers[inliers >= min_num_inliers]
    return {"verified_pairs": int(len(verified)),
            "matches_per_pair": float(verified.mean()) if len(verified) else None}


def match_and_map(db_path: Path, images: Path, sparse: Path, seed: int) -> dict:
    """pycolmap's exhaustive matcher and incremental mapper with their defaults; returns times."""
    pycolmap.set_random_seed(seed)
    tic = time.perf_counter()
    pycolmap.match_exhaustive(str(db_path), device=pycolmap.Device.cpu)
    match_s = time.perf_counter() - tic
    verification = pycolmap.TwoViewGeometryOptions()
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    map_defaults = MapConfig()
    options.mapper.abs_pose_min_num_inliers = map_defaults.abs_pose_min_num_inliers
    options.mapper.abs_pose_min_inlier_ratio = map_defaults.abs_pose_min_inlier_ratio
    sparse.mkdir(parents=True, exist_ok=True)
    tic = time.perf_counter()
    recs = pycolmap.incremental_mapping(str(db_path), str(images), str(sparse), options=options)
    map_s = time.perf_counter() - tic
    with pycolmap.Database.open(str(db_path)) as db:
        num_images = db.num_images()
    return {"num_images": num_images, "pairs": num_images * (num_images - 1) // 2, "match_s": match_s,
            "map_s": map_s, "num_models": len(recs), **inlier_stats(db_path, verification.min_num_inliers)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", type=Path, help="scene folder holding images/ and gt/")
    parser.add_argument("out", type=Path, help="output folder")
    parser.add_argument("--features", type=Path, help="a finished `sara extract` folder to reuse")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(name)s] %(message)s")
    pycolmap.logging.minloglevel = 2
    images, gt = bench.scene_paths(args.scene)
    features = args.features or args.out / "features"
    if args.features is None:
        sara_run(make_config("sift-offline", {"seed": args.seed}), images, features, stop_after="extract")
    plain = args.out / "plain"
    plain.mkdir(parents=True, exist_ok=True)
    copy_database(features / "database.db", plain / "database.db")
    info = match_and_map(plain / "database.db", images, plain / "sparse", args.seed)
    metrics = evaluate.run(plain / "sparse", gt, plain / "metrics.json")
    row = {**bench.row_from_report({}, metrics), **info, "scene": args.scene.name, "method": "plain pycolmap"}
    row.update(select_s=None, tree_build_s=None, fraction_of_exhaustive=1.0)
    (plain / "row.json").write_text(json.dumps(row, indent=2) + "\n", encoding="utf-8")
    print(bench.markdown_table([row], bench.TABLE_COLUMNS[:14]))
    print(f"\n{info['num_models']} model(s); mapping {info['map_s']:.1f} s; verified pairs {info['verified_pairs']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
