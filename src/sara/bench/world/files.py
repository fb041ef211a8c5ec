"""The world on disk: a normal sara output folder (features file, database.db) plus truth.h5 and
world.json, written once per config, and what the pair selection needs to run on it."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import time
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from tqdm import tqdm

from ...io import read_json, write_json_atomic
from ...io.h5 import Features, write_features
from ...io.images import ImageSet
from .city import City, build_city
from .config import DB_NAME, IMAGES_DIR, TRUTH_NAME, WORLD_JSON, WorldConfig, features_name, image_name
from .observe import observe_image
from .walk import camera_poses

logger = logging.getLogger(__name__)


def _complete(out_dir: Path, conf: WorldConfig) -> dict[str, Any] | None:
    path = out_dir / WORLD_JSON
    if not path.exists():
        return None
    try:
        info = read_json(path)
    except ValueError:
        return None
    if info.get("key") != conf.key() or not info.get("complete"):
        return None
    if not all((out_dir / n).exists() for n in (info.get("features_file", ""), DB_NAME, TRUTH_NAME)):
        return None
    return info


def make_world(out_dir: Path, conf: WorldConfig, *, db_features: bool = False, progress: bool = True,
               overwrite: bool = False) -> dict[str, Any]:
    """Write a world into `out_dir` (features-sift.h5, database.db, truth.h5, world.json); returns world.json.

    Skipped when `out_dir` already holds this world (same config and generator version).
    db_features: also write keypoints and descriptors into the database (COLMAP matching could run
    on it; the selection stage reads only the cameras), which doubles the disk used.
    """
    from ...colmap.build import DatabaseBuilder  # pycolmap stays in sara.colmap

    out_dir = Path(out_dir)
    if not overwrite and (info := _complete(out_dir, conf)) is not None:
        logger.info("world: %s is up to date, skipping", out_dir)
        return info
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / WORLD_JSON).unlink(missing_ok=True)
    tic = time.perf_counter()
    city = build_city(conf)
    poses = camera_poses(conf, city.grid)
    names = [image_name(i) for i in range(conf.num_images)]
    features_file = features_name()
    tmp = {name: out_dir / f".{name}.tmp" for name in (features_file, DB_NAME, TRUTH_NAME)}
    for path in tmp.values():
        path.unlink(missing_ok=True)
    with h5py.File(tmp[features_file], "w") as feats_h5, h5py.File(tmp[TRUTH_NAME], "w") as truth_h5, \
            DatabaseBuilder(tmp[DB_NAME], model="PINHOLE", width=conf.width, height=conf.height,
                            params=conf.camera_params()) as db:
        # the truth's point ids grow image by image; the dataset stays open until the file closes
        ids_ds = truth_h5.create_dataset("point_ids", shape=(0,), maxshape=(None,), dtype=np.int32,
                                         chunks=(1 << 16,))
        num_kp, num_in = _write_images(feats_h5, truth_h5, ids_ds, db, city, poses, names,
                                       db_features=db_features, progress=progress)
        _write_truth_arrays(truth_h5, names, poses, city)
    for name, path in tmp.items():
        os.replace(path, out_dir / name)
    info = {
        "key": conf.key(),
        "complete": True,
        "config": conf.to_dict(),
        **_walk_summary(city, poses, conf),
        "keypoints_mean": float(num_kp.mean()),
        "keypoints_min": int(num_kp.min()),
        "inlier_keypoints_mean": float(num_in.mean()),
        "features_file": features_file,
        "db_features": db_features,
        "synthesis_s": time.perf_counter() - tic,
        "disk_bytes": {name: (out_dir / name).stat().st_size for name in tmp},
    }
    write_json_atomic(out_dir / WORLD_JSON, info)
    return info


def _write_images(feats_h5: h5py.File, truth_h5: h5py.File, ids_ds: h5py.Dataset, db: Any, city: City,
                  poses: dict[str, np.ndarray], names: list[str], *, db_features: bool,
                  progress: bool) -> tuple[np.ndarray, np.ndarray]:
    """Synthesise every image into the features file and the database, and its observed point ids
    into the truth (one image in memory at a time); returns (N,) keypoints and (N,) inliers per image."""
    conf = city.conf
    n = len(names)
    num_kp = np.zeros(n, np.int64)
    num_in = np.zeros(n, np.int64)
    offsets = np.zeros(n + 1, np.int64)
    for i in tqdm(range(n), desc="synthesise images", unit="img", disable=not progress):
        rng = np.random.default_rng([conf.seed, 5, i])
        obs = observe_image(city, poses["R"][i], poses["centers"][i], rng)
        write_features(feats_h5, names[i], Features(obs.keypoints, obs.descriptors, obs.scores,
                                                    (conf.width, conf.height)))
        if db_features:
            db.add_image(names[i], obs.keypoints + 0.5, obs.scores, obs.descriptors)
        else:
            db.add_image(names[i])
        seen = np.sort(obs.point_ids[obs.point_ids >= 0]).astype(np.int32)
        offsets[i + 1] = offsets[i] + len(seen)
        ids_ds.resize((offsets[i + 1],))
        ids_ds[offsets[i]:offsets[i + 1]] = seen
        num_kp[i], num_in[i] = len(obs.point_ids), len(seen)
    truth_h5.create_dataset("offsets", data=offsets)
    return num_kp, num_in


def _write_truth_arrays(truth_h5: h5py.File, names: list[str], poses: dict[str, np.ndarray], city: City) -> None:
    """The names, true poses, walk, points and blocks that `Truth` and the plots read."""
    conf = city.conf
    truth_h5.create_dataset("names", data=np.array(names, dtype=object), dtype=h5py.string_dtype())
    truth_h5.create_dataset("cam_from_world_R", data=poses["R"])
    truth_h5.create_dataset("cam_from_world_t", data=poses["t"])
    truth_h5.create_dataset("centers", data=poses["centers"])
    truth_h5.create_dataset("heading", data=poses["heading"])
    truth_h5.create_dataset("arc_m", data=poses["arc_m"])
    truth_h5.create_dataset("crossings", data=poses["path"])
    truth_h5.create_dataset("points_xyz", data=city.xyz)
    truth_h5.create_dataset("points_facade", data=city.facade)
    truth_h5.create_dataset("blocks", data=city.blocks)
    truth_h5.attrs["camera_model"] = "PINHOLE"
    truth_h5.attrs["camera_params"] = conf.camera_params()
    truth_h5.attrs["config"] = json.dumps(conf.to_dict())


def _walk_summary(city: City, poses: dict[str, np.ndarray], conf: WorldConfig) -> dict[str, Any]:
    """The city's and the walk's size for world.json: streets, how often walked, in which directions."""
    n = conf.num_images
    visits = _street_visits(poses["path"])
    return {
        "grid_blocks": city.grid,
        "num_images": n,
        "num_points3D": city.num_points,
        "walk_length_m": float(n * conf.step_m),
        "streets": 2 * city.grid * (city.grid + 1),
        "streets_walked": len(visits),
        "streets_walked_twice_or_more": int(sum(v >= 2 for v in visits.values())),
        "street_walks_opposite_direction": int(sum(1 for v in _street_directions(poses["path"]).values()
                                                   if len(v) > 1)),
    }


def _street_visits(path: np.ndarray) -> dict[tuple, int]:
    visits: dict[tuple, int] = {}
    for a, b in zip(map(tuple, path[:-1]), map(tuple, path[1:])):
        key = (min(a, b), max(a, b))
        visits[key] = visits.get(key, 0) + 1
    return visits


def _street_directions(path: np.ndarray) -> dict[tuple, set]:
    dirs: dict[tuple, set] = {}
    for a, b in zip(map(tuple, path[:-1]), map(tuple, path[1:])):
        dirs.setdefault((min(a, b), max(a, b)), set()).add(a < b)
    return dirs


def remove_world(out_dir: Path) -> None:
    """Delete a world's files (and whatever a selection run left in the folder)."""
    shutil.rmtree(out_dir, ignore_errors=True)


def world_info(out_dir: Path) -> dict[str, Any]:
    """The world.json of a world folder."""
    return read_json(Path(out_dir) / WORLD_JSON)


def features_path(out_dir: Path) -> Path:
    """The features file of a world folder."""
    return Path(out_dir) / world_info(out_dir)["features_file"]


def image_set(out_dir: Path) -> ImageSet:
    """The world's images as sara's ImageSet (the folder `images/` does not exist: no pixels)."""
    out_dir = Path(out_dir)
    info = read_json(out_dir / WORLD_JSON)
    conf = info["config"]
    names = [image_name(i) for i in range(info["num_images"])]
    size = (int(conf["width"]), int(conf["height"]))
    return ImageSet(root=out_dir / IMAGES_DIR, names=names, sizes=dict.fromkeys(names, size))


def selection_context(conf: Any, out_dir: Path, run_dir: Path, *, progress: bool = True,
                      executor: Any = None) -> Any:
    """The `sara.pairs.PairContext` the pipeline would build to select pairs on this world.

    The selection writes into `run_dir` (global descriptors, scores.csv), which gets a copy of the
    world's database (a link when it holds features), so runs never share cached results.
    `executor`: where the work runs, for a sara that has executors (None: its default).
    """
    from ...pairs import PairContext

    out_dir, run_dir = Path(out_dir), Path(run_dir)
    (run_dir / ".sara").mkdir(parents=True, exist_ok=True)  # the pipeline's records folder exists by then
    images = image_set(out_dir)
    feats = features_path(out_dir)
    db = run_dir / DB_NAME
    if not db.exists():
        if world_info(out_dir).get("db_features"):
            db.symlink_to((out_dir / DB_NAME).resolve())
        else:
            shutil.copyfile(out_dir / DB_NAME, db)
    try:
        from ...pipeline import pair_context
    except ImportError:
        pair_context = None
    if pair_context is not None:
        for kwargs in ({"executor": executor, "progress": progress}, {"progress": progress}):
            if executor is None:
                kwargs.pop("executor", None)
            try:
                return pair_context(conf, images, feats, run_dir, **kwargs)
            except TypeError:  # another signature: try without the executor, then from the fields
                continue
    values = {"names": images.names, "images_root": images.root, "features_path": feats, "db_path": db,
              "out_dir": run_dir, "conf": conf, "progress": progress, "executor": executor}
    fields = {f.name for f in dataclasses.fields(PairContext)}
    return PairContext(**{k: v for k, v in values.items() if k in fields})

