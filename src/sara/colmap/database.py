"""A COLMAP database opened through pycolmap: the file's life (create, copy, replace, remove), its
images and cameras, the keypoints and matches that sara writes, and the edits of the matching stage.

Every function takes the database's path and returns sara's types (names, ids, arrays); pycolmap's
`Database` object stays inside the adapter. Read-only queries that must leave the file's bytes as
they are go through SQLite instead (`database_queries`).
"""

from __future__ import annotations

import contextlib
import functools
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from ..io import atomic_path
from .database_queries import camera_models
from .geometry import CameraInfo
from .native import native_errors

CAMERA_MODES = {
    "single": pycolmap.CameraMode.SINGLE,
    "per_image": pycolmap.CameraMode.PER_IMAGE,
    "per_folder": pycolmap.CameraMode.PER_FOLDER,
    "auto": pycolmap.CameraMode.AUTO,
}


@contextlib.contextmanager
def open_pycolmap_database(path: Path) -> Iterator[pycolmap.Database]:
    """pycolmap's `Database` of `path`, closed on exit; for the modules of this adapter only."""
    with native_errors(f"open the database {path}", Path(path).parent):
        db = pycolmap.Database.open(str(path))
    try:
        yield db
    finally:
        db.close()


# ---------------------------------------------------------------------------------------------
# The file
# ---------------------------------------------------------------------------------------------


def create_database(path: Path) -> None:
    """An empty COLMAP database at `path` (its tables, no images)."""
    with native_errors(f"create the database {path}", Path(path).parent):
        pycolmap.Database.open(str(path)).close()


def copy_database(src: Path, dst: Path) -> None:
    """Copy a COLMAP database consistently (its WAL included) through SQLite's backup API."""
    import sqlite3

    with atomic_path(dst) as tmp:
        source = sqlite3.connect(f"file:{src}?mode=rw", uri=True)  # rw: its log is merged and removed on close
        target = sqlite3.connect(tmp)
        try:
            source.backup(target)
        finally:
            target.close()
            source.close()


def remove_database(path: Path) -> None:
    """Delete a database with its SQLite write-ahead log and index (`-wal`, `-shm`): a log left by
    a killed run must never be replayed onto a newer file of the same name."""
    for suffix in ("", "-wal", "-shm", "-journal"):
        Path(f"{path}{suffix}").unlink(missing_ok=True)


def replace_database(src: Path, dst: Path) -> None:
    """Move a finished database (closed, so its log is merged) onto `dst`, dropping `dst`'s log."""
    for suffix in ("-wal", "-shm", "-journal"):
        Path(f"{dst}{suffix}").unlink(missing_ok=True)
    os.replace(src, dst)


# ---------------------------------------------------------------------------------------------
# Images and cameras
# ---------------------------------------------------------------------------------------------


def import_images(db_path: Path, image_dir: Path, names: list[str], *, camera_mode: str, camera_model: str,
                  camera_params: str = "", default_focal_length_factor: float = 1.2,
                  existing_camera_id: int | None = None) -> None:
    """Add images and their cameras to the database (no features yet); with `existing_camera_id`,
    the images share that camera of the database instead."""
    opts = pycolmap.ImageReaderOptions()
    if existing_camera_id is not None:
        opts.existing_camera_id = existing_camera_id
    opts.camera_model = camera_model
    opts.camera_params = camera_params
    opts.default_focal_length_factor = default_focal_length_factor
    with native_errors("import the images into the database", Path(db_path).parent):
        pycolmap.import_images(
            str(db_path), str(image_dir), camera_mode=CAMERA_MODES[camera_mode], image_names=names, options=opts
        )


def image_ids(db_path: Path) -> dict[str, int]:
    """name -> image_id of every image, in the database's order, read through pycolmap (which
    writes to the file: `database_images` reads the same without touching it)."""
    with open_pycolmap_database(db_path) as db:
        return image_ids_in(db)


def image_ids_in(db: pycolmap.Database) -> dict[str, int]:
    """`image_ids` of a database open in this adapter."""
    return {im.name: im.image_id for im in db.read_all_images()}


def rename_images(db_path: Path, new_names: dict[int, str]) -> None:
    """Give the images of `new_names` (image_id -> name) their new names."""
    with open_pycolmap_database(db_path) as db:
        for image_id, name in new_names.items():
            image = db.read_image(image_id)
            image.name = name
            db.update_image(image)


def cameras_by_image(db_path: Path) -> dict[str, CameraInfo]:
    """name -> its camera (intrinsics as imported: EXIF focal or COLMAP's prior)."""
    with open_pycolmap_database(db_path) as db:
        cams = {c.camera_id: CameraInfo.of(c) for c in db.read_all_cameras()}
        return {im.name: cams[im.camera_id] for im in db.read_all_images()}


def shared_camera(db_path: Path, names: list[str] | None = None) -> CameraInfo | None:
    """The camera of the images `names` (None: every image of the database) when they use one and
    the same, else None."""
    with open_pycolmap_database(db_path) as db:
        if names is None:
            cameras = db.read_all_cameras()
            return CameraInfo.of(cameras[0]) if len(cameras) == 1 else None
        wanted = set(names)
        ids = {im.camera_id for im in db.read_all_images() if im.name in wanted}
        return CameraInfo.of(db.read_camera(ids.pop())) if len(ids) == 1 else None


def set_focal_length(db_path: Path, camera_id: int, focal_px: float) -> None:
    """Replace the focal length of one camera of the database (other parameters kept, still a guess
    for bundle adjustment to refine: `has_prior_focal_length` stays as it was)."""
    with open_pycolmap_database(db_path) as db:
        camera = db.read_camera(camera_id)
        for index in camera.focal_length_idxs():
            camera.params[index] = focal_px
        db.update_camera(camera)


def fisheye_focal_priors(db_path: Path) -> list[int]:
    """Mark the focal length of every fisheye camera (`extract.camera_model` OPENCV_FISHEYE, ...)
    as a prior, its guess included; returns the cameras marked now. COLMAP 4 verifies the pairs of
    a fisheye camera only where its focal length is a prior: the fundamental matrix it falls back
    to otherwise assumes a pinhole, so it marks every such pair degenerate and no model is built.
    Told it is a prior, it verifies on the cameras' rays, and the guess hardly matters there (a
    fisheye drive's 97 pairs: the same inlier matches to 0.01% with focal lengths from 0.56 to 1.7
    times the true one); bundle adjustment still refines it."""
    fisheye = _fisheye_model_ids()
    marked = [camera_id for camera_id, (model, prior) in camera_models(db_path).items()
              if model in fisheye and not prior]
    if marked:  # pycolmap's open writes to the file: only where there is something to change
        with open_pycolmap_database(db_path) as db:
            for camera_id in marked:
                camera = db.read_camera(camera_id)
                camera.has_prior_focal_length = True
                db.update_camera(camera)
    return marked


def fisheye_cameras(db_path: Path) -> list[int]:
    """The database's cameras of a fisheye model (read with SQLite alone)."""
    fisheye = _fisheye_model_ids()
    return [camera_id for camera_id, (model, _) in camera_models(db_path).items() if model in fisheye]


@functools.lru_cache(maxsize=1)
def _fisheye_model_ids() -> frozenset[int]:
    """COLMAP's camera model ids of its fisheye models (pycolmap's `is_perspective_fisheye`)."""
    ids = set()
    for name, model_id in pycolmap.CameraModelId.__members__.items():
        if int(model_id) >= 0 and pycolmap.Camera.create_from_model_name(0, name, 1.0, 2, 2).is_perspective_fisheye():
            ids.add(int(model_id))
    return frozenset(ids)


# ---------------------------------------------------------------------------------------------
# Keypoints, matches and two-view geometries
# ---------------------------------------------------------------------------------------------


def write_keypoints(db_path: Path, keypoints: dict[str, np.ndarray]) -> None:
    """Store (N, 2) float32 keypoints (COLMAP's pixel convention) of images already in the database."""
    with open_pycolmap_database(db_path) as db:
        ids = image_ids_in(db)
        for name, xy in keypoints.items():
            if db.exists_keypoints(ids[name]):
                continue
            db.write_keypoints(ids[name], np.ascontiguousarray(xy, dtype=np.float32).reshape(-1, 2))


def write_matches(db_path: Path, matches: dict[tuple[str, str], np.ndarray]) -> None:
    """Store (K, 2) index matches of image pairs (by name), replacing unverified ones left by a killed run."""
    with open_pycolmap_database(db_path) as db:
        ids = image_ids_in(db)
        for (name0, name1), m in matches.items():
            id0, id1 = ids[name0], ids[name1]
            if db.exists_two_view_geometry(id0, id1):
                db.delete_two_view_geometry(id0, id1)
            if db.exists_matches(id0, id1):
                db.delete_matches(id0, id1)
            db.write_matches(id0, id1, np.ascontiguousarray(m, dtype=np.uint32).reshape(-1, 2))


def verified_image_pairs(db_path: Path) -> list[tuple[int, int, int]]:
    """(image_id0, image_id1, num_inliers) of every pair with a two-view geometry, id0 < id1."""
    with open_pycolmap_database(db_path) as db:
        return _verified_image_pairs(db)


def _verified_image_pairs(db: pycolmap.Database) -> list[tuple[int, int, int]]:
    pair_ids, num_inliers = db.read_two_view_geometry_num_inliers()
    out = []
    for pair_id, n in zip(pair_ids, num_inliers):
        i, j = sorted(pycolmap.pair_id_to_image_pair(int(pair_id)))
        out.append((int(i), int(j), int(n)))
    return out


def two_view_inlier_counts(db_path: Path) -> np.ndarray:
    """(P,) int64 inlier matches of every pair with a two-view geometry (zero where it failed)."""
    with open_pycolmap_database(db_path) as db:
        _, num_inliers = db.read_two_view_geometry_num_inliers()
    return np.asarray(num_inliers, dtype=np.int64)


def has_two_view_geometry(db_path: Path, id_pairs: list[tuple[int, int]]) -> list[bool]:
    """Whether each (image_id0, image_id1) pair has a two-view geometry (in either order)."""
    with open_pycolmap_database(db_path) as db:
        return [bool(db.exists_two_view_geometry(i, j)) for i, j in id_pairs]


def copy_pairs(src_db: Path, dst_db: Path, id_pairs: list[tuple[int, int]]) -> int:
    """Copy the matches and two-view geometry of every (image_id0, image_id1) pair of `id_pairs`
    that `src_db` has a geometry of into `dst_db` (a database of the same images and keypoints,
    without a geometry of these pairs); returns how many pairs were copied."""
    with open_pycolmap_database(src_db) as src:
        found = [(i, j, src.read_matches(i, j), src.read_two_view_geometry(i, j)) for i, j in id_pairs
                 if src.exists_two_view_geometry(i, j)]
    with open_pycolmap_database(dst_db) as dst:
        for i, j, matches, geometry in found:
            if dst.exists_matches(i, j):  # unverified matches a killed run left
                dst.delete_matches(i, j)
            dst.write_matches(i, j, matches)
            dst.write_two_view_geometry(i, j, geometry)
    return len(found)


def clear_matches(db_path: Path) -> None:
    """Delete every match and two-view geometry (images, cameras and features kept)."""
    with open_pycolmap_database(db_path) as db:
        db.clear_matches()
        db.clear_two_view_geometries()


def delete_pairs_except(db_path: Path, keep: set[tuple[int, int]]) -> None:
    """Delete the matches and two-view geometry of every pair with a geometry that is not in `keep`
    ((image_id0, image_id1) with id0 < id1)."""
    with open_pycolmap_database(db_path) as db:
        for i, j, _ in _verified_image_pairs(db):
            if (i, j) not in keep:
                db.delete_matches(i, j)
                db.delete_two_view_geometry(i, j)


def number_images_by_name(db_path: Path) -> bool:
    """Give the images of a database without matches their ids in name order, and their frames the
    same order, as an import of the images in name order does. COLMAP's extraction, importing the
    images as its threads finish them, numbers them in an order that changes from run to run, and
    the mapper's ties follow the ids. Returns whether anything was renumbered."""
    import sqlite3

    con = sqlite3.connect(db_path)
    try:
        rows = con.execute("SELECT image_id, name FROM images").fetchall()
        ids = sorted(image_id for image_id, _ in rows)
        new = {old: ids[k] for k, (old, _) in enumerate(sorted(rows, key=lambda r: r[1]))}
        if all(old == now for old, now in new.items()):
            return False
        if con.execute("SELECT COUNT(*) FROM matches").fetchone()[0]:
            raise RuntimeError(f"{db_path}: images can be renumbered only before matching")
        frames = dict(con.execute("SELECT data_id, frame_id FROM frame_data WHERE sensor_type = ?", (_CAMERA_SENSOR,)))
        frame_new = {frames[old]: frames[now] for old, now in new.items() if old in frames and now in frames}
        shift = max([*ids, *frames.values(), 0]) + 1
        with con:
            _renumber(con, new, shift, [("images", "image_id", ""), ("keypoints", "image_id", ""),
                                        ("descriptors", "image_id", ""),
                                        ("frame_data", "data_id", f" AND sensor_type = {_CAMERA_SENSOR}"),
                                        ("pose_priors", "corr_data_id", f" AND corr_sensor_type = {_CAMERA_SENSOR}")])
            _renumber(con, frame_new, shift, [("frames", "frame_id", ""), ("frame_data", "frame_id", "")])
        return True
    finally:
        con.close()


#: `sensor_type` of a camera in COLMAP's rig tables
_CAMERA_SENSOR = 0


def _renumber(con: Any, new: dict[int, int], shift: int, columns: list[tuple[str, str, str]]) -> None:
    """Move ids old -> new in each (table, column, extra condition), through ids shifted past all
    of them so that no two rows share an id on the way. Only the rows that change move: COLMAP's
    threads finish the images nearly in order, and a row moved is its features copied."""
    con.execute("CREATE TEMP TABLE IF NOT EXISTS renumber (old INTEGER PRIMARY KEY, new INTEGER)")
    con.execute("DELETE FROM renumber")
    con.executemany("INSERT INTO renumber VALUES (?, ?)", [(a, b) for a, b in new.items() if a != b])
    for table, column, where in columns:
        con.execute(f"UPDATE {table} SET {column} = {column} + ? WHERE {column} IN (SELECT old FROM renumber){where}",
                    (shift,))
        con.execute(f"UPDATE {table} SET {column} = (SELECT new FROM renumber WHERE old = {column} - ?) "
                    f"WHERE {column} >= ?{where}", (shift, shift))
