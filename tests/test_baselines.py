"""The baseline pair sources: exact pairs on hand-built collections, and agreement with COLMAP."""

from __future__ import annotations

import itertools
from pathlib import Path

import h5py
import numpy as np
import pycolmap
import pytest

from harness import assert_error
from sara.config import make_config
from sara.io.h5 import Features, write_features
from sara.pairs import PairContext, get_source
from sara.pairs.sequential import nearest_neighbours, sequential_offsets, sequential_pairs
from sara.pairs.vocabtree import QUERIES_NAME, TREE_NAME, QueryJournal, num_tree_words, retrieval_pairs


def names(n: int) -> list[str]:
    return [f"img{i:03d}.jpg" for i in range(n)]


def context(tmp_path: Path, image_names: list[str], overrides: dict | None = None) -> PairContext:
    return PairContext(names=sorted(image_names), images_root=tmp_path, features_path=tmp_path / "features.h5",
                       db_path=tmp_path / "database.db", out_dir=tmp_path, conf=make_config("sift-offline", overrides),
                       progress=False)


def as_index_pairs(pairs: list[tuple[str, str]]) -> set[tuple[int, int]]:
    return {(int(a[3:6]), int(b[3:6])) for a, b in pairs}


# ---------------------------------------------------------------------------------------------
# A tiny collection: each image draws its SIFT descriptors from the visual "words" of its group,
# so images of one group share content and images of different groups share none.
# ---------------------------------------------------------------------------------------------


def write_collection(folder: Path, groups: list[int], *, per_image: int = 200, words_per_group: int = 30,
                     seed: int = 0) -> list[str]:
    """database.db (cameras, images, keypoints, descriptors) and features.h5 with the same features."""
    rng = np.random.default_rng(seed)
    num_groups = max(groups) + 1
    sparse = rng.random((num_groups, words_per_group, 128)) < 0.3
    centres = rng.integers(20, 256, size=(num_groups, words_per_group, 128)) * sparse
    image_names = names(len(groups))
    db = pycolmap.Database.open(str(folder / "database.db"))
    camera_id = db.write_camera(pycolmap.Camera.create_from_model_name(1, "SIMPLE_RADIAL", 600.0, 640, 480))
    with h5py.File(folder / "features.h5", "w") as h5:
        for name, group in zip(image_names, groups):
            words = rng.integers(0, words_per_group, size=per_image)
            noise = rng.normal(0.0, 3.0, size=(per_image, 128))
            desc = np.clip(centres[group, words] + noise, 0, 255).astype(np.uint8)
            xy = (rng.random((per_image, 2)) * [640, 480]).astype(np.float32)
            image_id = db.write_image(pycolmap.Image(name=name, camera_id=camera_id))
            db.write_keypoints(image_id, xy)
            db.write_descriptors(image_id, pycolmap.FeatureDescriptors(type=pycolmap.FeatureExtractorType.SIFT,
                                                                       data=desc))
            write_features(h5, name, Features(keypoints=xy - 0.5, descriptors=desc,
                                              scores=rng.random(per_image).astype(np.float32) + 1.0,
                                              image_size=(640, 480)))
    db.close()
    return image_names


@pytest.fixture(scope="module")
def three_pairs(tmp_path_factory) -> Path:
    """Six images in three groups: {0, 3}, {1, 4}, {2, 5}."""
    folder = tmp_path_factory.mktemp("three_pairs")
    write_collection(folder, [0, 1, 2, 0, 1, 2])
    return folder


# ---------------------------------------------------------------------------------------------
# Exhaustive and sequential
# ---------------------------------------------------------------------------------------------


def test_exhaustive_source_exact(tmp_path: Path):
    result = get_source("exhaustive")(context(tmp_path, names(12)))
    assert len(result.pairs) == 66
    assert len(set(result.pairs)) == 66 and all(a < b for a, b in result.pairs)


def test_sequential_source_exact(tmp_path: Path):
    result = get_source("sequential")(context(tmp_path, names(10), {"sequential.overlap": "3"}))
    # image i with i+1..i+3: 3 * 7 + 2 + 1
    assert len(result.pairs) == 24
    assert as_index_pairs(result.pairs) == {(i, j) for i in range(10) for j in range(i + 1, min(i + 4, 10))}
    quadratic = get_source("sequential")(context(tmp_path, names(20), {"sequential.overlap": "3",
                                                                       "sequential.quadratic": "true"}))
    # offsets 1, 2, 4 (2^k, k < 3): 19 + 18 + 16
    assert len(quadratic.pairs) == 53
    assert (0, 4) in as_index_pairs(quadratic.pairs) and (0, 3) not in as_index_pairs(quadratic.pairs)


def test_sequential_offsets_and_errors():
    assert sequential_offsets(4) == [1, 2, 3, 4]
    assert sequential_offsets(4, quadratic=True) == [1, 2, 4, 8]
    with pytest.raises(ValueError, match="at least 1"):
        sequential_pairs(names(5), 0)
    assert sequential_pairs(names(1), 3) == []


def colmap_sequential(db_path: Path, overlap: int, quadratic: bool) -> set[tuple[str, str]]:
    opts = pycolmap.SequentialPairingOptions()
    opts.overlap, opts.quadratic_overlap = overlap, quadratic
    db = pycolmap.Database.open(str(db_path))
    try:
        ids = {im.image_id: im.name for im in db.read_all_images()}
        pairs = pycolmap.SequentialPairGenerator(opts, db).all_pairs()
    finally:
        db.close()
    return {tuple(sorted((ids[a], ids[b]))) for a, b in pairs}


def test_sequential_agrees_with_colmap(tmp_path: Path):
    shuffled = [names(13)[i] for i in np.random.default_rng(1).permutation(13)]  # COLMAP sorts by name too
    db = pycolmap.Database.open(str(tmp_path / "database.db"))
    camera_id = db.write_camera(pycolmap.Camera.create_from_model_name(1, "SIMPLE_RADIAL", 600.0, 640, 480))
    for name in shuffled:
        db.write_image(pycolmap.Image(name=name, camera_id=camera_id))
    db.close()
    for overlap, quadratic in itertools.product((1, 3, 5, 20), (False, True)):
        ours = set(sequential_pairs(shuffled, overlap, quadratic=quadratic))
        assert ours == colmap_sequential(tmp_path / "database.db", overlap, quadratic), (overlap, quadratic)


def test_nearest_neighbours_exact():
    desc = np.array([[1, 0], [0.9, 0.1], [0, 1], [0.1, 0.9], [0.7, 0.7]], dtype=np.float32)
    assert nearest_neighbours(desc, [0, 2], 1).tolist() == [[1], [3]]
    assert nearest_neighbours(desc, [4], 10).shape == (1, 4)  # k capped at N - 1, self excluded
    assert nearest_neighbours(desc, [], 2).shape == (0, 0)


def test_sequential_loop_detection(tmp_path: Path):
    # groups: {0, 5}, {1, 2}, {3, 7}, {4, 6}; queries 0 and 4 (period 4) find 5 and 6
    write_collection(tmp_path, [0, 1, 1, 2, 3, 0, 3, 2])
    ctx = context(tmp_path, names(8), {"sequential.overlap": "1", "sequential.loop_detection": "true",
                                       "sequential.loop_period": "4", "sequential.loop_neighbors": "1",
                                       "retrieval.codebook_size": "16"})
    result = get_source("sequential")(ctx)
    assert as_index_pairs(result.pairs) == {(i, i + 1) for i in range(7)} | {(0, 5), (4, 6)}
    assert result.info == {"num_sequential": 7, "num_loop_pairs_added": 2}


# ---------------------------------------------------------------------------------------------
# Retrieval only and the vocabulary tree
# ---------------------------------------------------------------------------------------------


def test_retrieval_only_finds_the_group_partner(three_pairs: Path, tmp_path: Path):
    ctx = context(three_pairs, names(6), {"retrieval.num_neighbors": "1", "retrieval.codebook_size": "16"})
    ctx.out_dir = tmp_path
    result = get_source("retrieval")(ctx)
    assert as_index_pairs(result.pairs) == {(0, 3), (1, 4), (2, 5)}
    assert set(result.timings_s) == {"global_descriptors", "knn"}
    ctx.conf = make_config("sift-offline", {"retrieval.num_neighbors": "5", "retrieval.codebook_size": "16"})
    assert len(get_source("retrieval")(ctx).pairs) == 15  # k >= N - 1: every pair


def test_vocabtree_finds_the_group_partner_and_reuses_its_tree(three_pairs: Path, tmp_path: Path):
    ctx = context(three_pairs, names(6), {"vocab_tree.num_images": "2"})  # the query itself and one more
    ctx.out_dir = tmp_path / "built"
    built = get_source("vocabtree")(ctx)
    assert as_index_pairs(built.pairs) == {(0, 3), (1, 4), (2, 5)}
    assert set(built.timings_s) == {"build_tree", "retrieve"}
    tree = tmp_path / "built" / TREE_NAME
    assert tree.is_file() and built.info["tree_built"] is True
    again = get_source("vocabtree")(ctx)  # same inputs: the saved tree is reused, same pairs
    assert again.info["tree_built"] is False and again.pairs == built.pairs
    loaded_ctx = context(three_pairs, names(6), {"vocab_tree.num_images": "2", "vocab_tree.path": str(tree)})
    loaded_ctx.out_dir = tmp_path / "loaded"
    loaded = get_source("vocabtree")(loaded_ctx)
    assert loaded.pairs == built.pairs and set(loaded.timings_s) == {"retrieve"}
    assert not (tmp_path / "loaded" / TREE_NAME).exists()


def test_vocabtree_missing_tree_is_a_clear_error(three_pairs: Path, tmp_path: Path):
    ctx = context(three_pairs, names(6), {"vocab_tree.path": str(tmp_path / "nope.bin")})
    with pytest.raises(FileNotFoundError, match="vocabulary tree not found"):
        get_source("vocabtree")(ctx)


def test_vocabtree_helpers():
    assert num_tree_words(80_000, 4096) == 4096
    assert num_tree_words(1_600, 4096) == 100
    retrieved = [("b", "a"), ("a", "a"), ("a", "b"), ("a", "zz"), ("c", "a")]
    assert retrieval_pairs(retrieved, ["a", "b", "c"]) == [("a", "b"), ("a", "c")]


def test_baseline_pairs_do_not_depend_on_saras_own_settings():
    """Changing the scorer or the graph (a learned preset's budget, say) redoes SARA's pairs only."""
    from sara.config import make_config
    from sara.pipeline import pairs_key

    changed = {"budget.max_pairs_per_image": 2.5, "score.min_inliers": 12}
    for method in ("exhaustive", "retrieval", "sequential"):
        base = make_config("sift-offline", {"pairs.method": method})
        other = make_config("sift-offline", {"pairs.method": method, **changed})
        assert pairs_key(base, "x", None) == pairs_key(other, "x", None)
    sara = make_config("sift-offline")
    assert pairs_key(sara, "x", None) != pairs_key(make_config("sift-offline", changed), "x", None)
    retrieval = make_config("sift-offline", {"pairs.method": "retrieval"})
    assert pairs_key(retrieval, "x", None) != pairs_key(
        make_config("sift-offline", {"pairs.method": "retrieval", "retrieval.num_neighbors": 5}), "x", None)


def test_a_setting_added_later_keys_the_pairs_only_away_from_its_default():
    """A finished run keeps its key (and is not redone) when a release adds a setting at its default;
    setting it otherwise redoes the pairs."""
    from sara.config import make_config
    from sara.io import fingerprint
    from sara.pipeline import pairs_key
    from sara.pipeline.pairs_stage import ADDED_LATER, source_sections

    conf = make_config("sift-offline")
    before = {"extract": "x", "seed": conf.seed}  # the key as a release without the added settings made it
    for section in source_sections(conf):
        values = dict(getattr(conf, section).__dict__)
        for name in ADDED_LATER.get(section, {}):
            del values[name]
        before[section] = values
    assert pairs_key(conf, "x", None) == fingerprint(before)
    off = make_config("sift-offline", {"rounds.repair_descriptor_ratio": 1.0})
    assert pairs_key(off, "x", None) != pairs_key(conf, "x", None)


def test_a_stopped_vocabtree_selection_queries_only_the_images_left(five_view_scene, tmp_path, run_cli,
                                                                    monkeypatch):
    """Ctrl-C after two of five queries: the run again queries the three left (the index is built
    again, the tree reused), and its pairs are an uninterrupted run's; nothing of the queries stays."""
    from sara import colmap
    from sara.pipeline import share_features

    images, _ = five_view_scene
    whole, out = tmp_path / "whole", tmp_path / "out"
    args = ("--method", "vocabtree", "-q")
    assert run_cli("pairs", images, whole, *args).code == 0
    share_features(whole, out)
    original, asked = colmap.vocab_tree_retrieval, []

    def two_then_stop(*a, on_query, **kw):
        answered = []

        def answer(query, retrieved):
            on_query(query, retrieved)
            answered.append(query)
            if len(answered) == 2:
                raise KeyboardInterrupt

        return original(*a, on_query=answer, **kw)

    monkeypatch.setattr(colmap, "vocab_tree_retrieval", two_then_stop)
    assert run_cli("pairs", images, out, *args).code == 130

    def recorded(*a, queries=None, **kw):
        asked.append(queries)
        return original(*a, queries=queries, **kw)

    monkeypatch.setattr(colmap, "vocab_tree_retrieval", recorded)
    result = run_cli("pairs", images, out, *args)
    assert result.code == 0, result.err
    assert len(asked) == 1 and asked[0] is not None and len(asked[0]) == 3
    assert (out / "pairs.txt").read_bytes() == (whole / "pairs.txt").read_bytes()
    assert not list(out.rglob(QUERIES_NAME))


def test_the_query_journal_reads_whole_lines_of_its_own_inputs(tmp_path):
    path = tmp_path / QUERIES_NAME
    journal = QueryJournal(path, "key-a")
    journal.start({"a.jpg": ["a.jpg", "b.jpg"]})
    journal.add("b.jpg", ["b.jpg", "a.jpg"])
    journal.close()
    with path.open("a", encoding="utf-8") as f:
        f.write('["c.jpg", ["c.j')  # a stop in the middle of a line
    assert journal.read() == {"a.jpg": ["a.jpg", "b.jpg"], "b.jpg": ["b.jpg", "a.jpg"]}
    assert QueryJournal(path, "key-b").read() == {}  # other tree, images, features or num_images
    path.write_bytes(b"\xff\xfe")
    assert journal.read() == {}


def test_a_file_that_is_no_vocabulary_tree_is_a_bad_input_in_one_line(five_view_scene, tmp_path, run_cli):
    """The queries run in a child process; a tree file COLMAP cannot read is the user's input (exit 2),
    named with the setting that gave it, COLMAP's own reason beside it."""
    images, _ = five_view_scene
    bad = tmp_path / "tree.bin"
    bad.write_bytes(bytes(range(256)) * 4)
    result = run_cli("pairs", images, tmp_path / "out", "--pairs", "vocabtree", "-q", "-s", f"vocab_tree.path={bad}")
    assert_error(result, 2, f"not a vocabulary tree COLMAP can read: {bad}", "faiss index", "vocab_tree.path")
