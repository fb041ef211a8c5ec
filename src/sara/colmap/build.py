"""Writing a COLMAP database from arrays: one camera, its rig, and one frame and image per name.

Used where the features come from elsewhere (the synthetic worlds of `sara.bench.world`), so that the
rest of sara reads the database as if COLMAP's own extraction had written it. pycolmap stays
inside `sara.colmap`, like every other call into it.

Keypoints go in COLMAP's pixel convention (centre of the top-left pixel at (0.5, 0.5)) as
6-column affine shapes ``x y a11 a12 a21 a22`` (scale times a rotation), which
`sara.colmap.FeatureReader.read_sift` turns back into a scale; descriptors as uint8 SIFT (128 columns).
"""

from __future__ import annotations

from pathlib import Path
from types import TracebackType
from typing import Self

import numpy as np
import pycolmap

#: Images written per SQLite transaction (one commit per image is ~100x slower).
COMMIT_EVERY = 256


class DatabaseBuilder:
    """Write a fresh database: ``with DatabaseBuilder(path, ...) as db: db.add_image(name)``.

    One camera (``model`` with ``params`` in COLMAP's order, e.g. PINHOLE ``fx, fy, cx, cy``)
    shared by every image, one rig holding that camera, and one frame per image, as
    `pycolmap.import_images` with a single camera writes them. Image ids are 1, 2, ... in the
    order of `add_image`. The file must not exist yet.
    """

    def __init__(self, path: Path, *, model: str, width: int, height: int, params: list[float]):
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"{self.path} exists; the builder writes new databases only")
        self._db = pycolmap.Database.open(str(self.path))
        camera = pycolmap.Camera(model=model, width=int(width), height=int(height),
                                 params=[float(p) for p in params], camera_id=1)
        self.camera_id = self._db.write_camera(camera, use_camera_id=True)
        rig = pycolmap.Rig(rig_id=1)
        rig.add_ref_sensor(camera.sensor_id)
        self.rig_id = self._db.write_rig(rig, use_rig_id=True)
        self._next_id = 1
        self._transaction: pycolmap.DatabaseTransaction | None = None
        self._in_transaction = 0

    def add_image(self, name: str, keypoints: np.ndarray | None = None, scales: np.ndarray | None = None,
                  descriptors: np.ndarray | None = None) -> int:
        """Add an image (and optionally its features); returns its image id.

        keypoints: (K, 2) COLMAP pixels; scales: (K,) pixels (1 when omitted);
        descriptors: (K, 128) uint8. Both or neither of keypoints and descriptors.
        """
        if (keypoints is None) != (descriptors is None):
            raise ValueError("give both keypoints and descriptors, or neither")
        if self._transaction is None:
            self._transaction = pycolmap.DatabaseTransaction(self._db)
            self._transaction.__enter__()
        image_id = self._next_id
        image = pycolmap.Image(name=name, camera_id=self.camera_id, image_id=image_id)
        frame = pycolmap.Frame(rig_id=self.rig_id, frame_id=image_id)
        frame.add_data_id(image.data_id)
        image.frame_id = self._db.write_frame(frame, use_frame_id=True)
        self._db.write_image(image, use_image_id=True)
        if keypoints is not None:
            xy = np.asarray(keypoints, dtype=np.float32).reshape(-1, 2)
            scale = np.ones(len(xy), np.float32) if scales is None else np.asarray(scales, np.float32)
            zeros = np.zeros(len(xy), np.float32)
            affine = np.stack([xy[:, 0], xy[:, 1], scale, zeros, zeros, scale], axis=1)
            self._db.write_keypoints(image_id, np.ascontiguousarray(affine))
            desc = np.ascontiguousarray(np.asarray(descriptors, dtype=np.uint8))
            if desc.shape != (len(xy), 128):
                raise ValueError(f"descriptors must be ({len(xy)}, 128) uint8, got {desc.shape}")
            self._db.write_descriptors(
                image_id, pycolmap.FeatureDescriptors(type=pycolmap.FeatureExtractorType.SIFT, data=desc))
        self._next_id += 1
        self._in_transaction += 1
        if self._in_transaction >= COMMIT_EVERY:
            self._commit()
        return image_id

    def _commit(self) -> None:
        if self._transaction is not None:
            self._transaction.__exit__(None, None, None)
            self._transaction = None
        self._in_transaction = 0

    def close(self) -> None:
        self._commit()
        self._db.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
