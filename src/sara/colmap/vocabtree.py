"""COLMAP's vocabulary tree: building a visual index from SIFT descriptors and retrieving, for every
image of a database, the images most like it (the `vocabtree` baseline pair source)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from .database import open_pycolmap_database


def build_visual_index(descriptors: np.ndarray, path: Path, *, num_words: int, num_iterations: int,
                       seed: int, num_threads: int = -1) -> None:
    """Build a pycolmap visual index (vocabulary tree) from SIFT descriptors and write it to `path`.

    descriptors: (N, 128) uint8 SIFT as COLMAP stores them; cast to float32 unscaled, as COLMAP
    does when it indexes or queries a database image. One clustering round; the same seed and
    input give the same file (pycolmap's global seed drives the clustering).
    """
    data = np.ascontiguousarray(np.asarray(descriptors), dtype=np.float32)
    index = pycolmap.VisualIndex.create(128, 64)
    opts = pycolmap.VisualIndex.BuildOptions()
    opts.num_visual_words = int(num_words)
    opts.num_iterations = int(num_iterations)
    opts.num_rounds = 1
    opts.num_threads = num_threads
    pycolmap.set_random_seed(seed)
    index.build(opts, pycolmap.FeatureDescriptorsFloat(type=pycolmap.FeatureExtractorType.SIFT, data=data))
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    index.write(str(path))


def vocab_tree_retrieval(db_path: Path, tree_path: Path, num_images: int, *,
                         num_threads: int = -1) -> list[tuple[str, str]]:
    """COLMAP's vocabulary-tree retrieval: every database image queries the index of all images.

    Returns (query name, retrieved name) for the `num_images` best-scoring images of each query;
    as in COLMAP's vocab_tree_matcher, the query itself is usually among them.
    """
    opts = pycolmap.VocabTreePairingOptions()
    opts.vocab_tree_path = str(tree_path)
    opts.num_images = int(num_images)
    opts.num_threads = num_threads
    with open_pycolmap_database(db_path) as db:
        names = {im.image_id: im.name for im in db.read_all_images()}
        id_pairs = pycolmap.VocabTreePairGenerator(opts, db).all_pairs()
    return [(names[int(a)], names[int(b)]) for a, b in id_pairs]
