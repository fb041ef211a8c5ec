"""COLMAP's vocabulary tree: building a visual index from SIFT descriptors and retrieving, for every
image of a database, the images most like it (the `vocabtree` baseline pair source)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
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


def vocab_tree_retrieval(db_path: Path, tree_path: Path, num_images: int, *, queries: Sequence[str] | None = None,
                         on_query: Callable[[str, list[str]], None] | None = None,
                         num_threads: int = -1) -> list[tuple[str, str]]:
    """COLMAP's vocabulary-tree retrieval: database images query the index of all images.

    Returns (query name, retrieved name) for the `num_images` best-scoring images of each query;
    as in COLMAP's vocab_tree_matcher, the query itself is usually among them. `queries`: the images
    that query (None: every image; all are indexed either way). `on_query(name, retrieved)` is called
    after each query, in turn, so that a caller can keep its results as they come.

    It runs in a process of its own (`vocabtree_process`): COLMAP's generator queries ahead in
    threads that read its index and the database, and freeing it part-way (a Ctrl-C between two
    queries) crashes the process; a child is stopped whole.
    """
    from .vocabtree_process import run_queries

    job = {"db_path": str(db_path), "tree_path": str(tree_path), "num_images": int(num_images),
           "num_threads": int(num_threads)}
    retrieved: list[tuple[str, str]] = []

    def answer(query: str, names: list[str]) -> None:
        retrieved.extend((query, name) for name in names)
        if on_query is not None:
            on_query(query, names)

    run_queries(job, queries, answer)
    return retrieved


def query_all(job: dict, answer: Callable[[str, list[str]], None]) -> None:
    """The child's side: every query of the match list (or every image) in turn, each answered."""
    opts = pycolmap.VocabTreePairingOptions()
    opts.vocab_tree_path = job["tree_path"]
    opts.num_images = job["num_images"]
    opts.num_threads = job["num_threads"]
    if job.get("match_list_path"):
        opts.match_list_path = job["match_list_path"]
    with open_pycolmap_database(Path(job["db_path"])) as db:
        names = {im.image_id: im.name for im in db.read_all_images()}
        generator = pycolmap.VocabTreePairGenerator(opts, db)  # indexes every image
        while not generator.has_finished():
            block = [(names[int(a)], names[int(b)]) for a, b in generator.next()]  # one query's images
            if block:
                answer(block[0][0], [b for _, b in block])
