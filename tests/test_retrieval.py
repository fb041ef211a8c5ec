"""Tests of global retrieval (kNN pairs, VLAD, codebooks, global.h5) and of the gt overlap geometry."""

from __future__ import annotations

import itertools
from pathlib import Path

import h5py
import numpy as np
import pytest

import sara.retrieval.vlad  # noqa: F401
from sara import retrieval
from sara.config import RetrievalConfig
from sara.descriptors import l2_normalize, mutual_nearest_neighbours
from sara.gt_pairs import (
    GtView,
    count_consistent_matches,
    fundamental_from_poses,
    overlapping_pairs,
    strong_pairs,
)
from sara.io.h5 import Features, write_features
from sara.retrieval import get_descriptor, knn_pairs
from sara.retrieval.vlad import BowDescriptor, VladDescriptor, kmeans, vlad
from sara.scoring.twoview import sampson_distance as sampson_distance_px

# ----------------------------------------------------------------------------------------
# knn_pairs
# ----------------------------------------------------------------------------------------


def test_knn_pairs_exact_on_a_line() -> None:
    # five unit vectors on a circle at 0, 10, 25, 60 and 68 degrees: cosine follows the angle gap
    angles = np.deg2rad([0.0, 10.0, 25.0, 60.0, 68.0])
    desc = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    # top-1: 0->1, 1->0, 2->1, 3->4, 4->3
    assert knn_pairs(desc, 1).tolist() == [[0, 1], [1, 2], [3, 4]]
    # top-2: 0->{1,2}, 1->{0,2}, 2->{1,0}, 3->{4,2}, 4->{3,2}
    assert knn_pairs(desc, 2).tolist() == [[0, 1], [0, 2], [1, 2], [2, 3], [2, 4], [3, 4]]


def test_knn_pairs_symmetric_union_not_intersection() -> None:
    # image 3 is far from everyone; its nearest neighbour is 2, but 3 is nobody's nearest neighbour
    desc = np.array([[1.0, 0.0], [0.99, 0.14], [0.95, 0.31], [0.0, 1.0]])
    pairs = knn_pairs(desc, 1)
    assert [2, 3] in pairs.tolist()
    assert pairs.tolist() == [[0, 1], [1, 2], [2, 3]]


@pytest.mark.parametrize("k", [1, 3, 7, 8, 20])
def test_knn_pairs_invariants(k: int) -> None:
    rng = np.random.default_rng(k)
    desc = rng.normal(size=(9, 16))
    pairs = knn_pairs(desc, k)
    assert pairs.dtype == np.int64 and pairs.shape[1] == 2
    assert np.all(pairs[:, 0] < pairs[:, 1])  # no self pairs, canonical order
    assert len(np.unique(pairs, axis=0)) == len(pairs)
    assert pairs.tolist() == sorted(pairs.tolist())
    degree = np.bincount(pairs.ravel(), minlength=9)
    assert np.all(degree >= min(k, 8))  # every image keeps its own k neighbours
    if k >= 8:
        assert pairs.tolist() == [list(p) for p in itertools.combinations(range(9), 2)]


def test_knn_pairs_scale_invariant_and_edge_cases() -> None:
    rng = np.random.default_rng(0)
    desc = rng.normal(size=(6, 4))
    scaled = desc * rng.uniform(0.1, 10.0, size=(6, 1))
    assert np.array_equal(knn_pairs(desc, 2), knn_pairs(scaled, 2))
    assert knn_pairs(desc[:1], 5).shape == (0, 2)
    with pytest.raises(ValueError, match="at least 1"):
        knn_pairs(desc, 0)


# ----------------------------------------------------------------------------------------
# VLAD, k-means, bag of words
# ----------------------------------------------------------------------------------------


def clustered(rng: np.random.Generator, centre: np.ndarray, n: int, spread: float = 0.05) -> np.ndarray:
    return l2_normalize(centre + spread * rng.normal(size=(n, len(centre))))


def test_vlad_of_identical_sets_is_identical_and_unit_norm() -> None:
    rng = np.random.default_rng(1)
    codebook = l2_normalize(rng.normal(size=(4, 8)))
    desc = l2_normalize(rng.normal(size=(50, 8)))
    a, b = vlad(desc, codebook), vlad(desc[::-1].copy(), codebook)  # order does not matter
    assert a.shape == (32,) and a.dtype == np.float32
    np.testing.assert_allclose(a, b, atol=1e-6)
    assert np.linalg.norm(a) == pytest.approx(1.0, abs=1e-5)
    assert np.all(vlad(np.zeros((0, 8), np.float32), codebook) == 0)


def test_vlad_of_disjoint_clusters_differs() -> None:
    rng = np.random.default_rng(2)
    centres = np.eye(8)[:2]
    codebook = centres.astype(np.float32)
    a = vlad(clustered(rng, centres[0], 40), codebook)
    b = vlad(clustered(rng, centres[1], 40), codebook)
    # each image fills only the block of its own word: the VLADs are orthogonal
    assert np.count_nonzero(a[8:]) == 0 and np.count_nonzero(b[:8]) == 0
    assert float(a @ b) == pytest.approx(0.0, abs=1e-6)


def test_kmeans_finds_separated_clusters_and_is_deterministic() -> None:
    rng = np.random.default_rng(3)
    centres = np.eye(16)[:3] * 3.0
    x = np.concatenate([c + 0.1 * rng.normal(size=(100, 16)) for c in centres]).astype(np.float32)
    found = kmeans(x, 3, seed=7)
    assert np.array_equal(found, kmeans(x, 3, seed=7))
    nearest = np.argmin(((found[:, None] - centres[None]) ** 2).sum(-1), axis=1)
    assert sorted(nearest.tolist()) == [0, 1, 2]
    np.testing.assert_allclose(found, centres[nearest], atol=0.05)
    with pytest.raises(ValueError, match="at least k"):
        kmeans(x[:2], 3)


def test_bow_tfidf_ignores_words_in_every_image() -> None:
    counts = np.array([[5, 1, 0], [5, 0, 1], [5, 1, 1]])
    tfidf = retrieval.vlad.bow_tfidf(counts)
    assert np.all(tfidf[:, 0] == 0)  # idf = log(3/3) = 0
    np.testing.assert_allclose(np.linalg.norm(tfidf, axis=1), 1.0, atol=1e-6)


# ----------------------------------------------------------------------------------------
# Backends on a constructed collection in features.h5
# ----------------------------------------------------------------------------------------

GROUPS = 3
PER_GROUP = 4


def write_grouped_features(path: Path, seed: int = 0) -> list[str]:
    """12 images of 3 scenes (groups), uint8 RootSIFT-like descriptors as COLMAP stores them.

    All scenes share 6 generic descriptor clusters (visual words); each scene draws its 150 local
    "landmark" descriptors around its own scene-specific variant of those clusters. Every image sees
    a random 100 of its scene's landmarks, with a little noise. (With one cluster per scene, VLAD
    would see only noise: residuals to a word at the centre of a tight cluster are just noise.)
    """
    rng = np.random.default_rng(seed)
    names = []
    words = rng.uniform(0, 1, size=(6, 128)) ** 4
    variants = words[None] + 0.4 * rng.uniform(0, 1, size=(GROUPS, 6, 128)) ** 4
    landmarks = [variants[g][rng.integers(0, 6, 150)] + 0.05 * rng.uniform(0, 1, size=(150, 128))
                 for g in range(GROUPS)]
    with h5py.File(path, "w") as h5:
        for g, i in itertools.product(range(GROUPS), range(PER_GROUP)):
            seen = landmarks[g][rng.choice(150, 100, replace=False)]
            desc = seen + 0.01 * rng.uniform(size=seen.shape)
            desc = np.clip(512 * l2_normalize(desc), 0, 255).astype(np.uint8)
            name = f"g{g}/img{i}.jpg"
            write_features(h5, name, Features(
                keypoints=rng.uniform(0, 100, size=(100, 2)).astype(np.float32), descriptors=desc,
                scores=rng.uniform(1, 5, 100).astype(np.float32), image_size=(100, 100)))
            names.append(name)
    return names


@pytest.mark.parametrize("backend", [VladDescriptor(), BowDescriptor(num_words=16)])
def test_backend_neighbours_stay_in_their_group(tmp_path: Path, backend: retrieval.GlobalDescriptor) -> None:
    names = write_grouped_features(tmp_path / "features.h5")
    conf = RetrievalConfig(codebook_size=8, features_per_image=100)
    desc = backend.compute(tmp_path / "features.h5", names, conf, progress=False, seed=0)
    assert desc.dtype == np.float32 and desc.shape[0] == len(names)
    np.testing.assert_allclose(np.linalg.norm(desc, axis=1), 1.0, atol=1e-5)
    group = np.repeat(np.arange(GROUPS), PER_GROUP)
    pairs = knn_pairs(desc, PER_GROUP - 1)
    assert np.all(group[pairs[:, 0]] == group[pairs[:, 1]])
    assert len(pairs) == GROUPS * PER_GROUP * (PER_GROUP - 1) // 2  # every within-group pair


def test_vlad_backend_deterministic_with_seed(tmp_path: Path) -> None:
    names = write_grouped_features(tmp_path / "features.h5")
    conf = RetrievalConfig(codebook_size=8, features_per_image=100)
    backend = VladDescriptor(sample_size=500)
    a = backend.compute(tmp_path / "features.h5", names, conf, progress=False, seed=3)
    b = backend.compute(tmp_path / "features.h5", names, conf, progress=False, seed=3)
    c = backend.compute(tmp_path / "features.h5", names, conf, progress=False, seed=4)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_get_descriptor_registry() -> None:
    assert isinstance(get_descriptor("vlad"), retrieval.GlobalDescriptor)
    with pytest.raises(ValueError, match="vlad, bow"):
        get_descriptor("netvlad")


def test_run_writes_global_h5_and_skips_when_up_to_date(tmp_path: Path, monkeypatch) -> None:
    features = tmp_path / "features.h5"
    names = write_grouped_features(features)
    conf = RetrievalConfig(codebook_size=8, features_per_image=100)
    path = retrieval.run(conf, features, names, tmp_path / "out", progress=False)
    stored_names, desc = retrieval.read_global(path)
    assert stored_names == names and desc.shape == (len(names), 8 * 128)
    pairs = retrieval.pairs_from_global(path, PER_GROUP - 1)
    assert all(a.split("/")[0] == b.split("/")[0] for a, b in pairs)

    shuffled = names[::-1]
    assert retrieval.run(conf, features, shuffled, tmp_path / "out", progress=False) == path
    assert retrieval.read_global(path)[0] == names  # rows stay in name order

    calls = []
    monkeypatch.setattr(retrieval.vlad, "learn_codebook", lambda *a, **k: calls.append(1) or np.eye(8, 128))
    retrieval.run(RetrievalConfig(codebook_size=8, features_per_image=100, num_neighbors=5), features, names,
                  tmp_path / "out", progress=False)
    assert calls == []  # same descriptors: num_neighbors does not invalidate global.h5
    retrieval.run(RetrievalConfig(codebook_size=8, features_per_image=50), features, names,
                  tmp_path / "out", progress=False)
    assert calls == [1]  # another config: recomputed
    with pytest.raises(ValueError, match="unknown global descriptor"):
        retrieval.run(RetrievalConfig(descriptor="nope"), features, names, tmp_path / "out", progress=False)


# ----------------------------------------------------------------------------------------
# Ground-truth geometry
# ----------------------------------------------------------------------------------------


def rot_y(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
VIEW1 = GtView(K=K, R=np.eye(3), t=np.zeros(3), size=(640, 480))
VIEW2 = GtView(K=K, R=rot_y(-10.0), t=rot_y(-10.0) @ -np.array([1.0, 0.0, 0.0]), size=(640, 480))


def project(view: GtView, points: np.ndarray) -> np.ndarray:
    cam = points @ view.R.T + view.t
    uv = cam @ view.K.T
    return uv[:, :2] / uv[:, 2:]


def test_sampson_distance_zero_for_exact_projections_and_grows_off_the_line() -> None:
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-1, 1, 20), rng.uniform(-1, 1, 20), rng.uniform(4, 8, 20)])
    x1, x2 = project(VIEW1, points), project(VIEW2, points)
    F = fundamental_from_poses(VIEW1, VIEW2)
    np.testing.assert_allclose(sampson_distance_px(F, x1, x2), 0.0, atol=1e-8)
    # translation along x, small rotation about y: epipolar lines are close to horizontal, so a
    # vertical shift of 3 px in image 2 gives a distance of about 3 / sqrt(2) px (both images share it)
    shifted = sampson_distance_px(F, x1, x2 + [0.0, 3.0])
    assert np.all(shifted > 1.5) and np.all(shifted < 3.0)


def test_sampson_distance_hand_computed() -> None:
    # pure translation along x with identity intrinsics: F = [t]x, epipolar lines are rows y = const
    F = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    d = sampson_distance_px(F, np.array([[5.0, 2.0]]), np.array([[1.0, 4.0]]))
    assert d[0] == pytest.approx(2.0 / np.sqrt(2.0))


def test_mutual_nearest_neighbors_and_consistent_count() -> None:
    rng = np.random.default_rng(0)
    desc = l2_normalize(rng.normal(size=(6, 32)))
    perm = np.array([3, 0, 5, 1, 2, 4])
    matches, _ = mutual_nearest_neighbours(desc, desc[perm])
    assert sorted(map(tuple, matches.tolist())) == sorted((int(perm[j]), j) for j in range(6))

    points = np.column_stack([rng.uniform(-1, 1, 6), rng.uniform(-1, 1, 6), rng.uniform(4, 8, 6)])
    x1, x2 = project(VIEW1, points), project(VIEW2, points)
    x2_bad = x2.copy()
    x2_bad[:2, 1] += 40.0  # two matches off their epipolar lines
    F = fundamental_from_poses(VIEW1, VIEW2)
    assert count_consistent_matches(x1, desc, x2, desc, F, 2.0) == 6
    assert count_consistent_matches(x1, desc, x2_bad, desc, F, 2.0) == 4


def test_overlapping_and_strong_pairs() -> None:
    counts = {("a", "b"): 100, ("a", "c"): 40, ("b", "c"): 5, ("a", "d"): 30, ("c", "d"): 80}
    assert overlapping_pairs(counts, 30) == {("a", "b"), ("a", "c"), ("a", "d"), ("c", "d")}
    assert strong_pairs(counts, 30) == {("a", "b"), ("c", "d")}


def test_sum_by_label_matches_unbuffered_add() -> None:
    rng = np.random.default_rng(5)
    x = rng.normal(size=(40, 3)).astype(np.float32)
    labels = rng.integers(0, 6, 40)
    labels[labels == 4] = 5  # label 4 stays empty
    expected = np.zeros((6, 3), np.float32)
    np.add.at(expected, labels, x)
    sums, counts = retrieval.vlad.sum_by_label(x, labels, 6)
    np.testing.assert_allclose(sums, expected, atol=1e-5)
    assert counts.tolist() == np.bincount(labels, minlength=6).tolist() and counts[4] == 0


@pytest.mark.parametrize("layout", ["rows", "transposed"])
def test_sum_by_label_gives_the_sums_of_the_sorted_rows_bit_for_bit(layout) -> None:
    """The per-label gather gives exactly the sums of numpy's reduceat over the rows sorted by
    label (the codebooks of earlier runs), whether the descriptors are stored row by row or
    transposed as hloc's files hold them."""
    rng = np.random.default_rng(11)
    x = rng.random((5000, 128), dtype=np.float32)
    if layout == "transposed":
        x = np.ascontiguousarray(x.T).T
        assert not x.flags.c_contiguous
    labels = rng.integers(0, 64, len(x))
    labels[labels == 7] = 8  # an empty label
    counts = np.bincount(labels, minlength=64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])[counts > 0]
    expected = np.zeros((64, 128), np.float32)
    expected[counts > 0] = np.add.reduceat(x[np.argsort(labels, kind="stable")], starts, axis=0)
    sums, _ = retrieval.vlad.sum_by_label(x, labels, 64)
    assert sums.tobytes() == expected.tobytes()
