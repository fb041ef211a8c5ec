"""Vocabulary-tree pairs, as COLMAP's `vocab_tree_matcher` makes them (the paper's VocabTree baseline).

Every image queries a pycolmap visual index of all images and is paired with its
`vocab_tree.num_images` best-scoring images (the query itself usually among them, as in COLMAP).

The index needs a vocabulary tree: a saved one (`-s vocab_tree.path=FILE`, e.g. one of
COLMAP's pre-built trees or the `vocab_tree.bin` of an earlier run), or, when none is given, one
built from this collection's own SIFT descriptors and saved as `<out>/vocab_tree.bin` for reuse.
Building is kept short (a capped, seeded sample of descriptors, one clustering round of few
iterations) and is timed apart ("build_tree") from the retrieval itself ("retrieve"), since users
normally load a ready tree.

The queries are kept as they come (`vocab_tree_queries.jsonl`, one line per query): a selection
stopped part-way, at 10,000 images an hour in, queries only the images left when run again.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TextIO

import numpy as np
from tqdm import tqdm

from .. import colmap
from ..colmap.vocabtree_process import UnreadableTreeError
from ..io import fingerprint, read_json, write_json_atomic
from ..io.h5 import read_features
from ..io.pairs import Pair, canonical_pairs
from . import PairContext, PairResult, PairSource

logger = logging.getLogger(__name__)

TREE_NAME = "vocab_tree.bin"
TREE_RECORD_NAME = "vocab_tree.json"  # what the saved tree was built from, so a re-run reuses it
QUERIES_NAME = "vocab_tree_queries.jsonl"  # each query's retrieved images, kept while the queries run
MAX_TREE_DESCRIPTORS = 80_000  # descriptors sampled from the whole collection to build the tree
MIN_DESCRIPTORS_PER_WORD = 16  # fewer visual words than asked when the sample is small
TREE_ITERATIONS = 8  # k-means iterations of the single clustering round


def sample_sift(features_path: Path, names: Sequence[str], max_total: int, *, seed: int = 0,
                progress: bool = True) -> np.ndarray:
    """A seeded sample of about `max_total` SIFT descriptors, the same share from every image.

    Returns (M, 128) uint8 descriptors in COLMAP's scale (RootSIFT times 512), as COLMAP indexes
    them: unit-length float descriptors (sara's and hloc's files) are scaled back.
    """
    rng = np.random.default_rng(seed)
    per_image = max(1, math.ceil(max_total / max(len(names), 1)))
    parts = []
    for name in tqdm(names, desc="sample SIFT for the vocabulary tree", unit="img", disable=not progress):
        desc = np.asarray(read_features(features_path, name).descriptors)
        if desc.dtype != np.uint8:
            desc = np.clip(np.round(desc.astype(np.float32) * 512.0), 0, 255)
        if len(desc) > per_image:
            desc = desc[np.sort(rng.choice(len(desc), per_image, replace=False))]
        parts.append(desc)
    if not parts:
        return np.zeros((0, 128), np.uint8)
    return np.concatenate(parts).astype(np.uint8, copy=False)


def num_tree_words(num_descriptors: int, requested: int) -> int:
    """Visual words for a tree built from `num_descriptors`: `requested`, or fewer for small samples."""
    return max(1, min(int(requested), num_descriptors // MIN_DESCRIPTORS_PER_WORD))


def retrieval_pairs(retrieved: Sequence[Pair], names: Sequence[str]) -> list[Pair]:
    """(query, retrieved) name pairs -> canonical pairs, self pairs and unknown names dropped."""
    known = set(names)
    return canonical_pairs((a, b) for a, b in retrieved if a in known and b in known)


def build_tree(ctx: PairContext) -> tuple[Path, dict]:
    """Build (or reuse, when built earlier from the same inputs) `<out>/vocab_tree.bin`."""
    conf = ctx.conf.vocab_tree
    tree_path, record_path = Path(ctx.out_dir) / TREE_NAME, Path(ctx.out_dir) / TREE_RECORD_NAME
    stat = Path(ctx.features_path).stat()
    key = fingerprint({"names": list(ctx.names), "features": [stat.st_size, stat.st_mtime_ns],
                       "words": conf.num_words, "max_descriptors": MAX_TREE_DESCRIPTORS,
                       "iterations": TREE_ITERATIONS, "seed": ctx.conf.seed})
    if tree_path.exists() and record_path.exists() and read_json(record_path).get("key") == key:
        logger.info("vocabtree: reusing %s", tree_path)
        return tree_path, {**read_json(record_path)["info"], "tree_reused": True}
    sample = sample_sift(ctx.features_path, ctx.names, MAX_TREE_DESCRIPTORS, seed=ctx.conf.seed,
                         progress=ctx.progress)
    words = num_tree_words(len(sample), conf.num_words)
    if words < 2:
        raise ValueError(f"only {len(sample)} SIFT descriptors in the collection: too few to build a "
                         "vocabulary tree; give a ready one with -s vocab_tree.path=FILE")
    if words < conf.num_words:
        logger.warning("vocabtree: %d descriptors sampled, building %d visual words instead of %d",
                       len(sample), words, conf.num_words)
    logger.info("vocabtree: building a tree of %d words from %d descriptors", words, len(sample))
    colmap.build_visual_index(sample, tree_path, num_words=words, num_iterations=TREE_ITERATIONS,
                              seed=ctx.conf.seed)
    info = {"tree_num_words": words, "tree_num_descriptors": int(len(sample))}
    write_json_atomic(record_path, {"key": key, "info": info})
    return tree_path, {**info, "tree_reused": False}


class QueryJournal:
    """Each finished query's retrieved images, one JSON line per query, under the first line's key
    (the tree, the images, the features, `num_images`): a line the stop cut short is not read."""

    def __init__(self, path: Path, key: str) -> None:
        self.path, self.key = path, key
        self._file: TextIO | None = None

    def read(self) -> dict[str, list[str]]:
        try:
            lines = self.path.read_text(encoding="utf-8").split("\n")
        except (OSError, UnicodeDecodeError):
            return {}
        if not lines or lines[0] != json.dumps({"key": self.key}):
            return {}
        done: dict[str, list[str]] = {}
        for line in lines[1:-1]:  # the last piece follows the last newline: empty, or cut short
            try:
                query, retrieved = json.loads(line)
            except ValueError:
                continue
            done[str(query)] = [str(name) for name in retrieved]
        return done

    def start(self, done: dict[str, list[str]]) -> None:
        """Write the journal again with what was read (a journal of other inputs is dropped)."""
        body = "".join(json.dumps([query, retrieved]) + "\n" for query, retrieved in done.items())
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.write_text(json.dumps({"key": self.key}) + "\n" + body, encoding="utf-8")
        self._file = self.path.open("a", encoding="utf-8")

    def add(self, query: str, retrieved: list[str]) -> None:
        self._file.write(json.dumps([query, retrieved]) + "\n")
        self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def _queries_key(ctx: PairContext, tree_path: Path) -> str:
    tree = Path(tree_path).stat()
    features = Path(ctx.features_path).stat()
    return fingerprint({"tree": [str(tree_path), tree.st_size, tree.st_mtime_ns],
                        "names": list(ctx.names), "features": [features.st_size, features.st_mtime_ns],
                        "num_images": ctx.conf.vocab_tree.num_images})


def retrieve(ctx: PairContext, tree_path: Path) -> tuple[list[tuple[str, str]], int]:
    """Every image's `num_images` best-scoring images, the queries of a stopped selection kept;
    returns them and how many queries were kept."""
    journal = QueryJournal(Path(ctx.out_dir) / QUERIES_NAME, _queries_key(ctx, tree_path))
    known = set(ctx.names)
    done = {query: retrieved for query, retrieved in journal.read().items() if query in known}
    kept = len(done)
    left = [name for name in ctx.names if name not in done]
    if kept:
        logger.info("vocabtree: %d of %d queries kept from a stopped selection", kept, len(ctx.names))
    journal.start(done)
    try:
        if left:
            with tqdm(total=len(ctx.names), initial=kept, desc="vocabulary-tree queries", unit="img",
                      disable=not ctx.progress) as bar:
                def keep(query: str, retrieved: list[str]) -> None:
                    journal.add(query, retrieved)
                    done[query] = retrieved
                    bar.update()

                listable = all(name == name.strip() and "\n" not in name for name in left)  # a match list's lines
                colmap.vocab_tree_retrieval(ctx.db_path, tree_path, ctx.conf.vocab_tree.num_images,
                                            queries=left if kept and listable else None, on_query=keep)
    finally:
        journal.close()
    journal.path.unlink(missing_ok=True)  # every query answered: pairs.txt holds them now
    return [(query, name) for query, retrieved in done.items() for name in retrieved], kept


def select(ctx: PairContext) -> PairResult:
    conf = ctx.conf.vocab_tree
    if conf.num_images < 1:
        raise ValueError(f"vocab_tree.num_images must be at least 1, got {conf.num_images}")
    timings: dict[str, float] = {}
    if conf.path:
        tree_path = Path(conf.path).expanduser()
        if not tree_path.is_file():
            raise FileNotFoundError(
                f"vocabulary tree not found: {tree_path} (vocab_tree.path); give a saved pycolmap "
                f"visual index, e.g. the {TREE_NAME} of an earlier run, or leave it empty to build one")
        info: dict = {"tree": str(tree_path), "tree_built": False}
    else:
        tic = time.perf_counter()
        tree_path, info = build_tree(ctx)
        timings["build_tree"] = time.perf_counter() - tic
        info.update(tree=str(tree_path), tree_built=not info["tree_reused"])
    tic = time.perf_counter()
    try:
        retrieved, kept = retrieve(ctx, tree_path)
    except UnreadableTreeError as exc:
        if not conf.path:  # sara's own tree: damaged, not the user's input
            raise colmap.ColmapError(str(exc)) from exc
        raise ValueError(f"{exc}; give a saved pycolmap visual index with vocab_tree.path, or leave it "
                         "empty to build one") from exc
    except colmap.ColmapError as exc:
        if not conf.path:
            raise
        raise colmap.ColmapError(f"{exc} (the tree given: vocab_tree.path={tree_path})") from exc
    pairs = retrieval_pairs(retrieved, ctx.names)
    timings["retrieve"] = time.perf_counter() - tic
    info.update(num_images=conf.num_images, num_retrieved=len(retrieved), num_queries_kept=kept)
    return PairResult(pairs, info, timings)


SOURCE = PairSource(select=select, sections=lambda conf: ("pairs", "vocab_tree"),
                    caches=(TREE_NAME, TREE_RECORD_NAME, QUERIES_NAME))
