"""Weight-free global descriptors learned from the collection itself: VLAD (the default) and a
tf-idf bag of visual words, over each image's own local descriptors (RootSIFT, or any learned ones).

VLAD: Jegou et al. 2010, intra-normalisation as in Arandjelovic & Zisserman 2013, with a codebook
learned by k-means on a capped random sample of the collection's descriptors. Measured against
ground-truth overlaps (`lab/scripts/retrieval_recall.py`) the variants: PCA-whitening learned from the collection
lowered the recall of strong overlaps on every scene (k = 5 and 10), so it is off; the order of
intra-normalisation and signed square root made no difference.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..config import RetrievalConfig
from ..descriptors import l2_normalize
from ..io.h5 import read_features

logger = logging.getLogger(__name__)

CODEBOOK_SAMPLE_SIZE = 100_000  # descriptors sampled from the whole collection to learn the codebook
KMEANS_ITERATIONS = 20
BOW_CODEBOOK_SIZE = 1024  # visual words of the `bow` backend (VLAD uses conf.codebook_size)
_EPS = 1e-12


# ---------------------------------------------------------------------------------------------
# Pure cores: arrays in, arrays out
# ---------------------------------------------------------------------------------------------


def squared_distances(x: np.ndarray, centers: np.ndarray, x_sq: np.ndarray | None = None) -> np.ndarray:
    """(N, D), (K, D) -> (N, K) float32 squared Euclidean distances (clipped at 0); `x_sq`: the
    rows' squared norms, `(x * x).sum(1)`, when already known (k-means computes them once)."""
    x_sq = (x * x).sum(1) if x_sq is None else x_sq
    d2 = x_sq[:, None] - 2.0 * (x @ centers.T) + (centers * centers).sum(1)[None, :]
    return np.maximum(d2, 0.0, out=d2)


def assign_words(x: np.ndarray, codebook: np.ndarray) -> np.ndarray:
    """(N, D) descriptors -> (N,) int64 index of the nearest codebook row (ties: lowest index)."""
    if len(x) == 0:
        return np.zeros(0, dtype=np.int64)
    return np.argmin(squared_distances(x, codebook), axis=1).astype(np.int64)


def sum_by_label(x: np.ndarray, labels: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Row sums per label: (N, D), (N,) labels in [0, k) -> (k, D) sums (x's dtype), (k,) int64 counts.

    Each label's rows are gathered in their order and summed along a contiguous axis: the same
    pairwise sums, bit for bit, as numpy's `reduceat` over the rows sorted by label (what this
    did before), in a quarter of the time; k-means spent most of its time here.
    """
    counts = np.bincount(labels, minlength=k).astype(np.int64)
    sums = np.zeros((k, x.shape[1]), dtype=x.dtype)
    if len(x):
        order = np.argsort(labels, kind="stable")
        ends = np.cumsum(counts)
        # (D, rows) contiguous: a column gather when x is stored transposed (hloc's descriptors are)
        transposed = x.T.flags.c_contiguous
        for label in np.flatnonzero(counts):
            index = order[ends[label] - counts[label]:ends[label]]
            block = x.T.take(index, axis=1) if transposed else np.ascontiguousarray(x.take(index, axis=0).T)
            sums[label] = np.add.reduceat(block, [0], axis=1)[:, 0]
    return sums, counts


def _kmeans_pp_init(x: np.ndarray, k: int, rng: np.random.Generator, x_sq: np.ndarray) -> np.ndarray:
    """k-means++ seeding: (k, D) float32 rows chosen from `x` (`x_sq`: its rows' squared norms)."""
    centers = np.empty((k, x.shape[1]), dtype=np.float32)
    centers[0] = x[rng.integers(len(x))]
    d2 = squared_distances(x, centers[:1], x_sq)[:, 0]
    for i in range(1, k):
        total = float(d2.sum())
        idx = int(rng.choice(len(x), p=d2 / total)) if total > 0 else int(rng.integers(len(x)))
        centers[i] = x[idx]
        d2 = np.minimum(d2, squared_distances(x, centers[i:i + 1], x_sq)[:, 0])
    return centers


def kmeans(x: np.ndarray, k: int, *, seed: int = 0, iterations: int = KMEANS_ITERATIONS) -> np.ndarray:
    """Lloyd's k-means with k-means++ seeding: (N, D) -> (k, D) float32 centres.

    Deterministic for a given seed. A cluster that empties is re-seeded with the point farthest
    from its centre. Needs at least `k` points.
    """
    x = np.asarray(x, dtype=np.float32)
    if k < 1 or len(x) < k:
        raise ValueError(f"k-means needs at least k={k} >= 1 points, got {len(x)}")
    rng = np.random.default_rng(seed)
    x_sq = (x * x).sum(1)
    centers = _kmeans_pp_init(x, k, rng, x_sq)
    labels = np.full(len(x), -1, dtype=np.int64)
    for _ in range(iterations):
        d2 = squared_distances(x, centers, x_sq)
        new_labels = np.argmin(d2, axis=1)
        if np.array_equal(new_labels, labels):
            break
        labels = new_labels
        sums, counts = sum_by_label(x, labels, k)
        nonempty = counts > 0
        centers[nonempty] = sums[nonempty] / counts[nonempty, None]
        if not nonempty.all():
            far = np.argsort(-d2[np.arange(len(x)), labels], kind="stable")
            centers[~nonempty] = x[far[: int((~nonempty).sum())]]
    return centers


def vlad(desc: np.ndarray, codebook: np.ndarray) -> np.ndarray:
    """VLAD of one image: (N, D) local descriptors, (K, D) codebook -> (K * D,) float32.

    Residuals to the nearest word are summed per word, each word's block is L2-normalised
    (intra-normalisation), then signed square root, then global L2 normalisation. An image
    without descriptors gives the zero vector.
    """
    k, dim = codebook.shape
    out = np.zeros((k, dim), dtype=np.float32)
    if len(desc):
        words = assign_words(desc, codebook)
        out = sum_by_label(np.asarray(desc - codebook[words], dtype=np.float32), words, k)[0]
    out = l2_normalize(out, axis=1)
    out = np.sign(out) * np.sqrt(np.abs(out))
    return l2_normalize(out.reshape(-1))


def bow_tfidf(word_counts: np.ndarray) -> np.ndarray:
    """(N, K) visual-word counts per image -> (N, K) float32 tf-idf vectors, rows L2-normalised.

    tf = count / number of words in the image; idf = log(N / number of images with the word).
    """
    counts = np.asarray(word_counts, dtype=np.float64)
    num_images = len(counts)
    doc_freq = (counts > 0).sum(0)
    idf = np.log(num_images / np.maximum(doc_freq, 1))
    tf = counts / np.maximum(counts.sum(1, keepdims=True), 1.0)
    return l2_normalize(tf * idf)


def pca_whiten(desc: np.ndarray, *, dims: int | None = None, eps: float = 1e-6) -> np.ndarray:
    """PCA-whitening learned from the rows themselves: (N, D) -> (N, d) float32, rows L2-normalised.

    Keeps d = min(dims, N - 1, D) principal components and divides each by the square root of its
    eigenvalue (plus `eps` times the largest, to keep noise directions from exploding).
    """
    x = np.asarray(desc, dtype=np.float64)
    centred = x - x.mean(0, keepdims=True)
    _, sing, vt = np.linalg.svd(centred, full_matrices=False)
    keep = max(1, min(dims or vt.shape[0], len(x) - 1, vt.shape[0]))
    var = sing[:keep] ** 2 / max(len(x) - 1, 1)
    proj = centred @ vt[:keep].T / np.sqrt(var + eps * var.max() + _EPS)
    return l2_normalize(proj)


# ---------------------------------------------------------------------------------------------
# Local descriptors of the collection and the codebook learned from them
# ---------------------------------------------------------------------------------------------


def local_descriptors(features_path: Path, name: str, features_per_image: int) -> np.ndarray:
    """(M, D) float32 unit local descriptors of one image: its `features_per_image` best-scoring ones
    (for SIFT, the largest scales; uint8 RootSIFT and float descriptors alike).

    `features_per_image` <= 0 takes them all.
    """
    feats = read_features(features_path, name, top_k=features_per_image if features_per_image > 0 else None)
    return l2_normalize(feats.descriptors, axis=1)


def sample_descriptors(features_path: Path, names: Sequence[str], features_per_image: int,
                       sample_size: int, *, seed: int = 0, progress: bool = True) -> np.ndarray:
    """A random sample of about `sample_size` descriptors, the same share from every image.

    Draws from each image's `features_per_image` largest-scale descriptors; (M, 128) float32.
    """
    rng = np.random.default_rng(seed)
    per_image = max(1, math.ceil(sample_size / max(len(names), 1)))
    parts = []
    for name in tqdm(names, desc="sample descriptors", unit="img", disable=not progress):
        desc = local_descriptors(features_path, name, features_per_image)
        if len(desc) > per_image:
            desc = desc[np.sort(rng.choice(len(desc), per_image, replace=False))]
        parts.append(desc)
    return np.concatenate(parts) if parts else np.zeros((0, 0), np.float32)


def learn_codebook(features_path: Path, names: Sequence[str], num_words: int, features_per_image: int, *,
                   sample_size: int = CODEBOOK_SAMPLE_SIZE, seed: int = 0, progress: bool = True) -> np.ndarray:
    """(K, 128) float32 visual words: k-means on a capped sample of the collection's descriptors.

    K is `num_words`, or fewer (with a warning) when the collection has fewer descriptors.
    """
    sample = sample_descriptors(features_path, names, features_per_image, sample_size, seed=seed,
                                progress=progress)
    if len(sample) == 0:
        raise ValueError("no local descriptors in the collection: cannot learn a codebook")
    k = min(num_words, len(sample))
    if k < num_words:
        logger.warning("only %d descriptors in the collection: codebook of %d words instead of %d",
                       len(sample), k, num_words)
    return kmeans(sample, k, seed=seed)


# ---------------------------------------------------------------------------------------------
# Backends
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class VladDescriptor:
    """VLAD over the image's own RootSIFT, codebook from the collection (no weights needed).

    D = codebook_size * 128. `whiten` adds PCA-whitening learned from the collection's VLADs.
    """

    name: str = "vlad"
    whiten: bool = False
    sample_size: int = CODEBOOK_SAMPLE_SIZE

    def compute(self, features_path: Path, names: Sequence[str], conf: RetrievalConfig, *,
                images_root: Path | None = None, progress: bool = True, seed: int = 0) -> np.ndarray:
        codebook = learn_codebook(features_path, names, conf.codebook_size, conf.features_per_image,
                                  sample_size=self.sample_size, seed=seed, progress=progress)
        out = np.zeros((len(names), codebook.size), dtype=np.float32)
        for i, name in enumerate(tqdm(names, desc="vlad", unit="img", disable=not progress)):
            out[i] = vlad(local_descriptors(features_path, name, conf.features_per_image), codebook)
        return pca_whiten(out) if self.whiten and len(names) > 2 else out


@dataclasses.dataclass(frozen=True)
class BowDescriptor:
    """tf-idf bag of visual words (hard assignment) over a codebook learned from the collection."""

    name: str = "bow"
    num_words: int = BOW_CODEBOOK_SIZE
    sample_size: int = CODEBOOK_SAMPLE_SIZE

    def compute(self, features_path: Path, names: Sequence[str], conf: RetrievalConfig, *,
                images_root: Path | None = None, progress: bool = True, seed: int = 0) -> np.ndarray:
        codebook = learn_codebook(features_path, names, self.num_words, conf.features_per_image,
                                  sample_size=self.sample_size, seed=seed, progress=progress)
        counts = np.zeros((len(names), len(codebook)), dtype=np.int64)
        for i, name in enumerate(tqdm(names, desc="bag of words", unit="img", disable=not progress)):
            words = assign_words(local_descriptors(features_path, name, conf.features_per_image), codebook)
            counts[i] = np.bincount(words, minlength=len(codebook))
        return bow_tfidf(counts)
