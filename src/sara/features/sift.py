"""COLMAP's SIFT (RootSIFT, COLMAP's defaults): the default backend, extracted straight into the
COLMAP database by COLMAP itself, then copied into `features-sift.h5`.

In the database descriptors stay as COLMAP stores them, (N, 128) uint8 RootSIFT scaled by 512; in
`features-sift.h5` they are unit-length float16, as hloc stores them.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
from tqdm import tqdm

from .. import colmap
from ..config import ExtractConfig
from ..descriptors import l2_normalize
from ..io import ensure_free_space
from ..io.h5 import Features, read_open, write_features
from ..io.images import ImageSet
from . import Keypoints

#: at most what one keypoint adds to COLMAP's database: (x, y, a11, a12, a21, a22) float32, 128 bytes
DB_BYTES_PER_KEYPOINT = 6 * 4 + 128
#: images whose features may be on their way into the database at once (threads and write queue)
IN_FLIGHT = 16


class ColmapSift:
    name = "sift"

    def __init__(self, conf: ExtractConfig) -> None:
        self.conf = conf

    def extract(self, image: np.ndarray) -> Keypoints:
        """SIFT of one (H, W, 3) uint8 image, for callers outside the extract stage."""
        xy, scale, desc = colmap.sift_of_image(image, max_num_features=self.conf.max_num_features)
        return Keypoints(xy=colmap.colmap_to_hloc_keypoints(xy), scores=scale, descriptors=desc)

    def extract_to_database(self, db_path: Path, images: ImageSet, names: list[str], *, progress: bool,
                            camera_mode: str = "auto", existing_camera_id: int | None = None,
                            on_watch: Callable[[], None] | None = None) -> None:
        """COLMAP's extraction of `names` in one call (those not in the database yet imported by
        the same pass, with `camera_mode` and `existing_camera_id`: `colmap.extract_sift`), the
        progress read from the database meanwhile and `on_watch` called at each look; a disk that
        another program fills during the extraction stops it cleanly (COLMAP would abort the
        process when the database cannot grow)."""
        conf, db_path = self.conf, Path(db_path)
        start = colmap.count_with_keypoints(db_path) or 0
        with tqdm(total=len(names), desc="extract SIFT", unit="img", disable=not progress) as bar:

            def watch(done: int | None) -> None:
                if done is not None:
                    bar.update(max(0, min(len(names), done - start) - bar.n))
                # the images on their way into the database at most: one per thread, a few queued
                ensure_free_space(db_path.parent, DB_BYTES_PER_KEYPOINT * conf.max_num_features * IN_FLIGHT)
                if on_watch is not None:
                    on_watch()

            colmap.extract_sift(db_path, images.root, names, max_image_size=conf.max_image_size,
                                max_num_features=conf.max_num_features, camera_model=conf.camera_model,
                                camera_params=conf.camera_params, num_threads=conf.num_threads,
                                camera_mode=camera_mode, existing_camera_id=existing_camera_id,
                                default_focal_length_factor=conf.default_focal_length_factor, watch=watch)
            bar.update(len(names) - bar.n)


class DatabaseToH5:
    """Copies the SIFT features that COLMAP writes into the database to an open `features-sift.h5`
    (hloc's layout, unit-length float16 descriptors) image by image: `update` from the extraction's
    watch copies what COLMAP finished since the last look, so that little is left to copy when it
    ends. The database is read with SQLite alone, from this process while COLMAP writes in its own.
    """

    #: images read from the database at once (a resumed run may find thousands there)
    BATCH = 32

    def __init__(self, db_path: Path, h5: h5py.File, sizes: dict[str, tuple[int, int]]) -> None:
        self.db_path, self.h5, self.sizes = Path(db_path), h5, sizes
        self.counts: dict[str, int] = {}  # name -> keypoints, of the images copied
        self._ids: set[int] = set()

    def update(self) -> list[str]:
        """Copy the images of `sizes` that have features in the database and are not copied yet."""
        if not self.db_path.exists():
            return []
        new = []
        while batch := colmap.read_sift_rows(self.db_path, self._ids, limit=self.BATCH):
            for name, (image_id, kp, scale, desc) in batch.items():
                self._ids.add(image_id)
                if name not in self.sizes:
                    continue
                # HDF5 crashes on a full disk: make sure the image fits before writing it
                ensure_free_space(self.db_path.parent, len(kp) * (8 + 4 + 2 * desc.shape[-1]) + 4096)
                write_features(self.h5, name, Features(keypoints=colmap.colmap_to_hloc_keypoints(kp),
                                                       descriptors=hloc_descriptors(desc), scores=scale,
                                                       image_size=self.sizes[name]))
                self.counts[name] = len(kp)
                new.append(name)
        return new

    def read(self, name: str, top_k: int | None = None) -> Features:
        """The features of a copied image, as a reader of the finished file gets them."""
        return read_open(self.h5, name, top_k=top_k)


def not_extracted(images: ImageSet, with_keypoints: set[str], todo: list[str]) -> dict[str, str]:
    """The images of `todo` that COLMAP's extraction left without features, name -> why: a file its
    reader cannot decode, or one gone or changed since the scan."""
    out = {}
    for name in todo:
        if name in with_keypoints:
            continue
        path = images.root / name
        if not path.exists():
            out[name] = "the file disappeared during extraction"
        else:
            out[name] = colmap.image_read_problem(path) or "COLMAP's extraction skipped it (see its log in logs/)"
    return out


def hloc_descriptors(desc: np.ndarray) -> np.ndarray:
    """COLMAP's uint8 RootSIFT (norm about 512) -> unit-length float16, as hloc's extractors store
    descriptors, so that hloc's ratio and distance tests work on sara's files."""
    return l2_normalize(desc, axis=1).astype(np.float16)


def make(conf: ExtractConfig) -> ColmapSift:
    return ColmapSift(conf)
