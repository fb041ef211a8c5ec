"""Taking images out of a database and out of a model, for an incremental update of an output
folder (images removed from the collection, or changed and extracted again); images made to share
one camera; keypoints taken out (an overlay's, before matching).

COLMAP's database tables have no cascade for matches (they are keyed by pair id), and pycolmap's
`Database` has no call that deletes an image, so the rows go through SQLite in one transaction:
the file holds either every row of an image or none. Image and camera ids are AUTOINCREMENT, so
an id of a deleted image is never given to another one.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pycolmap

#: COLMAP's pair id of two image ids: smaller * 2^31 - 1 + larger (`pycolmap.image_pair_to_pair_id`)
_MAX_IMAGE_ID = 2147483647
_CAMERA_SENSOR = int(pycolmap.SensorType.CAMERA.value)  # sensor_type of a camera in the rig tables


def delete_images(db_path: Path, names: list[str]) -> list[str]:
    """Delete the images `names` from the database with their keypoints, descriptors, matches,
    two-view geometries, frames, and their cameras and rigs when no other image uses them.
    Names not in the database are ignored; returns the names deleted."""
    con = sqlite3.connect(str(db_path))
    try:
        with con:  # one transaction: all or nothing
            rows = con.execute("SELECT image_id, name, camera_id FROM images").fetchall()
            drop = {int(i): (n, int(c)) for i, n, c in rows if n in set(names)}
            if not drop:
                return []
            _delete_pairs_of(con, set(drop))
            for image_id, (_, camera_id) in drop.items():
                frames = [r[0] for r in con.execute(
                    "SELECT frame_id FROM frame_data WHERE data_id = ? AND sensor_type = ?",
                    (image_id, _CAMERA_SENSOR))]
                for table in ("keypoints", "descriptors", "images"):
                    con.execute(f"DELETE FROM {table} WHERE image_id = ?", (image_id,))
                con.execute("DELETE FROM frame_data WHERE data_id = ? AND sensor_type = ?", (image_id, _CAMERA_SENSOR))
                con.execute("DELETE FROM pose_priors WHERE corr_data_id = ? AND corr_sensor_type = ?",
                            (image_id, _CAMERA_SENSOR))
                for frame_id in frames:
                    if not con.execute("SELECT 1 FROM frame_data WHERE frame_id = ?", (frame_id,)).fetchone():
                        con.execute("DELETE FROM frames WHERE frame_id = ?", (frame_id,))
                _delete_unused_camera(con, camera_id)
            return sorted(name for name, _ in drop.values())
    finally:
        con.close()


def _delete_pairs_of(con: sqlite3.Connection, image_ids: set[int]) -> None:
    """Delete the matches and two-view geometries of every pair that involves one of `image_ids`."""
    for table in ("matches", "two_view_geometries"):
        doomed = []
        for (pair_id,) in con.execute(f"SELECT pair_id FROM {table}"):
            first, second = divmod(int(pair_id), _MAX_IMAGE_ID)
            if first in image_ids or second in image_ids:
                doomed.append((int(pair_id),))
        con.executemany(f"DELETE FROM {table} WHERE pair_id = ?", doomed)


def share_cameras(db_path: Path, groups: list[list[str]]) -> int:
    """Give each group of images (names) the camera of its first image in the database, as COLMAP's
    import gives one camera to a folder: the images join that camera's rig, and the cameras and rigs
    no image uses any more are deleted. The images of a group must have cameras of the same size
    and prior. Idempotent; returns the number of images that changed camera."""
    con = sqlite3.connect(str(db_path))
    try:
        with con:  # one transaction: all or nothing
            rows = {n: (int(i), int(c)) for i, n, c in con.execute("SELECT image_id, name, camera_id FROM images")}
            changed = 0
            for names in groups:
                members = sorted(rows[n] for n in names if n in rows)
                if len(members) < 2:
                    continue
                keep = members[0][1]
                rig = con.execute("SELECT rig_id FROM rigs WHERE ref_sensor_id = ? AND ref_sensor_type = ?",
                                  (keep, _CAMERA_SENSOR)).fetchone()
                for image_id, camera_id in members[1:]:
                    if camera_id == keep:
                        continue
                    con.execute("UPDATE images SET camera_id = ? WHERE image_id = ?", (keep, image_id))
                    con.execute("UPDATE frame_data SET sensor_id = ? WHERE data_id = ? AND sensor_type = ?",
                                (keep, image_id, _CAMERA_SENSOR))
                    if rig is not None:
                        con.execute("UPDATE frames SET rig_id = ? WHERE frame_id IN (SELECT frame_id FROM frame_data "
                                    "WHERE data_id = ? AND sensor_type = ?)", (rig[0], image_id, _CAMERA_SENSOR))
                    _delete_unused_camera(con, camera_id)
                    changed += 1
            return changed
    finally:
        con.close()


def keep_keypoints(db_path: Path, static: Callable[[str, np.ndarray], np.ndarray | None]) -> int:
    """Take out of every image's keypoints (and descriptors, where the database holds them) those
    that `static(name, xy)` marks (xy: (N, 2) in COLMAP's pixel convention; a boolean mask, or None
    for none), in one transaction; for images not matched yet. Returns the keypoints taken out."""
    con = sqlite3.connect(str(db_path))
    removed = 0
    try:
        with con:  # one transaction: all or nothing
            images = con.execute("SELECT image_id, name FROM images JOIN keypoints USING (image_id)").fetchall()
            for image_id, name in images:
                rows, cols, data = con.execute("SELECT rows, cols, data FROM keypoints WHERE image_id = ?",
                                               (image_id,)).fetchone()
                if not rows:
                    continue
                kp = np.frombuffer(data, np.float32).reshape(rows, cols)
                drop = static(name, kp[:, :2])
                if drop is None or not drop.any():
                    continue
                keep = ~drop
                con.execute("UPDATE keypoints SET rows = ?, data = ? WHERE image_id = ?",
                            (int(keep.sum()), np.ascontiguousarray(kp[keep]).tobytes(), image_id))
                found = con.execute("SELECT rows, cols, data FROM descriptors WHERE image_id = ?",
                                    (image_id,)).fetchone()
                if found and found[0] == rows:
                    desc = np.frombuffer(found[2], np.uint8).reshape(found[0], found[1])
                    con.execute("UPDATE descriptors SET rows = ?, data = ? WHERE image_id = ?",
                                (int(keep.sum()), np.ascontiguousarray(desc[keep]).tobytes(), image_id))
                removed += int(drop.sum())
        return removed
    finally:
        con.close()


def _delete_unused_camera(con: sqlite3.Connection, camera_id: int) -> None:
    """Delete a camera (and the rig it alone makes up) that no image uses any more."""
    if con.execute("SELECT 1 FROM images WHERE camera_id = ?", (camera_id,)).fetchone():
        return
    rigs = [r[0] for r in con.execute("SELECT rig_id FROM rigs WHERE ref_sensor_id = ? AND ref_sensor_type = ?",
                                      (camera_id, _CAMERA_SENSOR))]
    for rig_id in rigs:
        if con.execute("SELECT 1 FROM frames WHERE rig_id = ?", (rig_id,)).fetchone():
            return  # still the rig of some frame: keep it and its camera
    for rig_id in rigs:
        con.execute("DELETE FROM rig_sensors WHERE rig_id = ?", (rig_id,))
        con.execute("DELETE FROM rigs WHERE rig_id = ?", (rig_id,))
    con.execute("DELETE FROM rig_sensors WHERE sensor_id = ? AND sensor_type = ?", (camera_id, _CAMERA_SENSOR))
    con.execute("DELETE FROM cameras WHERE camera_id = ?", (camera_id,))


def prune_model(model_dir: Path, names: set[str], out_dir: Path) -> int:
    """Write the model of `model_dir` without the images `names` (their poses, observations and
    the points left with fewer than two views are removed) to `out_dir`; returns the number of
    images it still registers."""
    rec = pycolmap.Reconstruction(str(model_dir))
    for image in list(rec.images.values()):
        if image.name in names and image.has_pose:
            rec.deregister_frame(image.frame_id)
    rec.tear_down()  # drops the images without a pose and the cameras no image uses
    for point_id in list(rec.point3D_ids()):
        if rec.points3D[point_id].track.length() < 2:
            rec.delete_point3D(point_id)
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    rec.write(str(out_dir))
    return int(rec.num_reg_images())
