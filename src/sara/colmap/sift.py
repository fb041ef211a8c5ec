"""COLMAP's SIFT: its image reader, its extraction into the database or of one image in memory, and
reading the stored features back as arrays.

Keypoints are in COLMAP's pixel convention (centre of the top-left pixel at (0.5, 0.5)); scales in
pixels; descriptors uint8 RootSIFT as COLMAP stores them.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Container
from pathlib import Path
from types import TracebackType
from typing import Self

import numpy as np
import pycolmap

from .database import CAMERA_MODES, image_ids_in, open_pycolmap_database
from .native import log_settings, native_errors


def image_read_problem(path: Path) -> str | None:
    """Why COLMAP's image reader (the one its SIFT extraction uses) cannot decode a file, or None."""
    try:
        bitmap = pycolmap.Bitmap.read(str(path), as_rgb=False)
    except (RuntimeError, ValueError, OSError) as exc:
        return f"COLMAP's image reader fails on it ({exc})"
    if bitmap is None or bitmap.width <= 0 or bitmap.height <= 0:
        return "COLMAP's image reader cannot decode it (a format COLMAP does not read, whatever its extension)"
    return None


def extract_sift(db_path: Path, image_dir: Path, names: list[str], *, max_image_size: int, max_num_features: int,
                 camera_model: str, camera_params: str = "", num_threads: int = -1, camera_mode: str = "auto",
                 existing_camera_id: int | None = None, default_focal_length_factor: float = 1.2,
                 watch: Callable[[int | None], None] | None = None) -> None:
    """SIFT (RootSIFT, COLMAP defaults) of `names`; images with features are skipped.

    Images not in the database yet are imported by the same pass of COLMAP's reader, each image
    decoded once (`camera_mode`, `existing_camera_id` for the images of a resumed run, and the
    focal prior's `default_focal_length_factor` as in `import_images`); an image the reader cannot
    decode is left out of the database. One call of COLMAP for all `names`: its reader, extractor
    and writer threads stay busy to the end (in chunks, they idled at the end of each). With
    `watch`, the call runs in a process of its own (`extract_process`) and `watch` is called about
    every `extract_process.WATCH_S` seconds with the number of images with keypoints in the
    database (None while it cannot be read); when `watch` raises (Ctrl-C included), the process is
    stopped and the error raised here. Images finished before stay in the database."""
    args = {"db_path": str(db_path), "image_dir": str(image_dir), "names": list(names),
            "max_image_size": max_image_size, "max_num_features": max_num_features,
            "camera_model": camera_model, "camera_params": camera_params, "num_threads": num_threads,
            "camera_mode": camera_mode, "existing_camera_id": existing_camera_id,
            "default_focal_length_factor": default_focal_length_factor}
    if watch is None:
        with native_errors("extract SIFT features", Path(db_path).parent):
            extract_now(**args)
        return
    from . import extract_process

    job = {"args": args, "db_path": str(db_path), "parent": os.getpid(), "verbose": log_settings["verbose"],
           "log_dir": str(log_settings["log_dir"]) if log_settings["log_dir"] else None}
    extract_process.run_watched(job, lambda: watch(count_with_keypoints(Path(db_path))))


def extract_now(db_path: str, image_dir: str, names: list[str], max_image_size: int, max_num_features: int,
                camera_model: str, camera_params: str, num_threads: int, camera_mode: str = "auto",
                existing_camera_id: int | None = None, default_focal_length_factor: float = 1.2) -> None:
    """pycolmap's extraction into the database, in this process and thread."""
    opts = pycolmap.FeatureExtractionOptions()
    opts.max_image_size = max_image_size
    opts.num_threads = num_threads
    opts.sift.max_num_features = max_num_features
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    reader.camera_params = camera_params
    reader.default_focal_length_factor = default_focal_length_factor
    if existing_camera_id is not None:
        reader.existing_camera_id = existing_camera_id
    pycolmap.extract_features(db_path, image_dir, image_names=names, camera_mode=CAMERA_MODES[camera_mode],
                              reader_options=reader, extraction_options=opts, device=pycolmap.Device.cpu)


def count_with_keypoints(db_path: Path) -> int | None:
    """Images with keypoints in a database that COLMAP may be writing: None while it is locked."""
    import sqlite3

    try:
        con = sqlite3.connect(f"file:{db_path}?mode=ro", uri=True, timeout=0.2)
        try:
            return int(con.execute("SELECT COUNT(*) FROM keypoints").fetchone()[0])
        finally:
            con.close()
    except sqlite3.Error:
        return None


def read_sift_rows(db_path: Path, known: Container[int] = (), *, limit: int | None = None,
                   ) -> dict[str, tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    """name -> (image_id, keypoints, scales, descriptors) as `FeatureReader.read_sift`, of the images
    with keypoints and descriptors whose image_id is not in `known` (at most `limit` of them, the
    lowest ids first). Read with SQLite alone, so also from a database that COLMAP is writing in
    another process."""
    import sqlite3

    con = sqlite3.connect(f"file:{db_path}?mode=ro", uri=True, timeout=5.0)
    try:
        ids = con.execute("SELECT image_id, name FROM images JOIN keypoints USING (image_id) "
                          "JOIN descriptors USING (image_id) ORDER BY image_id").fetchall()
        new = [(int(image_id), name) for image_id, name in ids if int(image_id) not in known][:limit]
        out = {}
        for image_id, name in new:
            (k_rows, k_data), = con.execute("SELECT rows, data FROM keypoints WHERE image_id = ?", (image_id,))
            (d_rows, d_data), = con.execute("SELECT rows, data FROM descriptors WHERE image_id = ?", (image_id,))
            kp = np.frombuffer(k_data, np.float32).reshape(k_rows, -1) if k_rows else np.zeros((0, 2), np.float32)
            desc = np.frombuffer(d_data, np.uint8).reshape(d_rows, -1) if d_rows else np.zeros((0, 128), np.uint8)
            out[name] = (image_id, *_split_keypoints(kp, desc))
        return out
    finally:
        con.close()


def sift_of_image(image: np.ndarray, *, max_num_features: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """COLMAP's SIFT of one (H, W, 3) or (H, W) uint8 image: as :meth:`FeatureReader.read_sift`."""
    gray = np.asarray(image, dtype=np.float32)
    if gray.ndim == 3:
        gray = gray @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    opts = pycolmap.SiftExtractionOptions()
    opts.max_num_features = max_num_features
    sift = pycolmap.Sift(opts, device=pycolmap.Device.cpu)
    kp, desc = sift.extract(gray / 255.0)
    kp = np.asarray(kp, dtype=np.float32)
    return _split_keypoints(kp, np.asarray(desc))


class FeatureReader:
    """The SIFT features stored in a database, read as arrays: ``with FeatureReader(db_path) as r:``.

    The database is opened once for all the images read (each open checks its schema).
    """

    def __init__(self, db_path: Path):
        self.path = Path(db_path)
        self._stack = contextlib.ExitStack()
        self._db: pycolmap.Database | None = None

    def __enter__(self) -> Self:
        self._db = self._stack.enter_context(open_pycolmap_database(self.path))
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._db = None
        self._stack.close()

    def _open(self) -> pycolmap.Database:
        if self._db is None:
            raise RuntimeError("FeatureReader is read inside its `with` block only")
        return self._db

    def image_ids(self) -> dict[str, int]:
        """name -> image_id of every image of the database, in its order."""
        return image_ids_in(self._open())

    def read_sift(self, image_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Keypoints (N, 2) float32 COLMAP pixels, scales (N,) float32 px, descriptors (N, 128) uint8."""
        db = self._open()
        kp = np.asarray(db.read_keypoints(image_id), dtype=np.float32)
        desc = np.asarray(db.read_descriptors(image_id).data)
        return _split_keypoints(kp, desc)


def _split_keypoints(kp: np.ndarray, desc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """COLMAP's keypoint rows (x, y[, scale[, orientation]] or x, y, a11, a12, a21, a22) -> xy, scale."""
    if len(kp) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros((0, 128), np.uint8)
    if kp.shape[1] >= 6:  # affine shape a11 a12 a21 a22: scale = sqrt(|det|)
        scale = np.sqrt(np.abs(kp[:, 2] * kp[:, 5] - kp[:, 3] * kp[:, 4]))
    elif kp.shape[1] >= 3:
        scale = kp[:, 2]
    else:
        scale = np.ones(len(kp), np.float32)
    return kp[:, :2].copy(), scale.astype(np.float32), desc.astype(np.uint8, copy=False)
