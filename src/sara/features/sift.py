"""COLMAP's SIFT (RootSIFT, COLMAP's defaults): the default backend, extracted straight into the
COLMAP database by COLMAP itself, then copied into `features-sift.h5`.

In the database descriptors stay as COLMAP stores them, (N, 128) uint8 RootSIFT scaled by 512; in
`features-sift.h5` they are unit-length float16, as hloc stores them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from .. import colmap
from ..config import ExtractConfig
from ..io import ensure_free_space
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

    def extract_to_database(self, db_path: Path, images: ImageSet, names: list[str], *, progress: bool) -> None:
        """COLMAP's extraction of `names` (already imported into the database) in one call, the
        progress read from the database meanwhile; a disk that another program fills during the
        extraction stops it cleanly (COLMAP would abort the process when the database cannot grow)."""
        conf, db_path = self.conf, Path(db_path)
        start = colmap.count_with_keypoints(db_path) or 0
        with tqdm(total=len(names), desc="extract SIFT", unit="img", disable=not progress) as bar:

            def watch(done: int | None) -> None:
                if done is not None:
                    bar.update(max(0, min(len(names), done - start) - bar.n))
                # the images on their way into the database at most: one per thread, a few queued
                ensure_free_space(db_path.parent, DB_BYTES_PER_KEYPOINT * conf.max_num_features * IN_FLIGHT)

            colmap.extract_sift(db_path, images.root, names, max_image_size=conf.max_image_size,
                                max_num_features=conf.max_num_features, camera_model=conf.camera_model,
                                camera_params=conf.camera_params, num_threads=conf.num_threads, watch=watch)
            bar.update(len(names) - bar.n)


def make(conf: ExtractConfig) -> ColmapSift:
    return ColmapSift(conf)
