"""hloc round trip: hloc-layout SuperPoint-like features -> SARA pairs -> hloc-style matching -> model.

hloc itself is not installed (it pulls CUDA torch); its file layouts are mirrored here from
hloc/extract_features.py (`main`: one group per image, `keypoints` shifted to hloc's pixel
convention, float32 arrays stored as float16 with `as_half`, `uncertainty` attribute),
hloc/match_features.py (`writer_fn`: `matches0` int16, `matching_scores0` float16, group
`names_to_pair(name0, name1)`), hloc/utils/parsers.py (`parse_retrieval`: `q, r = p.split()`)
and hloc/pairs_from_retrieval.py (`get_descriptors`: `fd[name]["global_descriptor"]`).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import h5py
import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from sara import hloc
from sara.config import make_config
from sara.io.pairs import read_pairs

DESCRIPTOR_DIM = 256  # SuperPoint's
NUM_DISTRACTORS = 150


def parse_retrieval(path: Path) -> dict[str, list[str]]:
    """hloc/utils/parsers.py parse_retrieval."""
    retrieval = defaultdict(list)
    for line in path.read_text().rstrip("\n").split("\n"):
        if len(line) == 0:
            continue
        q, r = line.split()
        retrieval[q].append(r)
    return dict(retrieval)


def write_superpoint_like(gt_dir: Path, path: Path, *, seed: int = 0) -> None:
    """hloc features of the true observations of a synthetic model, plus random distractors.

    Each 3D point has a random unit descriptor; its observations carry that descriptor plus noise.
    Keypoints and descriptors are float16 (hloc's as_half), descriptors stored (D, N).
    """
    rng = np.random.default_rng(seed)
    rec = pycolmap.Reconstruction()
    rec.read_text(str(gt_dir))
    point_desc = {pid: rng.normal(size=DESCRIPTOR_DIM) for pid in rec.points3D}
    with h5py.File(path, "w") as h5:
        for image in rec.images.values():
            cam = rec.cameras[image.camera_id]
            obs = [(p2d.xy, point_desc[p2d.point3D_id]) for p2d in image.points2D if p2d.has_point3D()]
            xy = np.array([o[0] for o in obs]) - 0.5  # COLMAP -> hloc pixel convention
            desc = np.array([o[1] for o in obs]) + rng.normal(scale=0.1, size=(len(obs), DESCRIPTOR_DIM))
            xy = np.concatenate([xy, rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (NUM_DISTRACTORS, 2))])
            desc = np.concatenate([desc, rng.normal(size=(NUM_DISTRACTORS, DESCRIPTOR_DIM))])
            desc /= np.linalg.norm(desc, axis=1, keepdims=True)
            order = rng.permutation(len(xy))
            grp = h5.create_group(image.name)
            grp.create_dataset("keypoints", data=xy[order].astype(np.float16))
            grp["keypoints"].attrs["uncertainty"] = 1.0
            grp.create_dataset("descriptors", data=desc[order].T.astype(np.float16))
            grp.create_dataset("scores", data=rng.uniform(0.1, 1.0, len(xy)).astype(np.float16))
            grp.create_dataset("image_size", data=np.array([cam.width, cam.height]))


def match_mutual_nn(features: Path, pairs: Path, matches: Path) -> Path:
    """A tiny hloc-style matcher: mutual nearest neighbours of the descriptors, hloc's matches layout."""
    with h5py.File(features, "r") as feats, h5py.File(matches, "w") as out:
        for name0, refs in parse_retrieval(pairs).items():
            for name1 in refs:
                d0 = feats[name0]["descriptors"][()].astype(np.float32).T
                d1 = feats[name1]["descriptors"][()].astype(np.float32).T
                sim = d0 @ d1.T
                nn01, nn10 = sim.argmax(1), sim.argmax(0)
                mutual = nn10[nn01] == np.arange(len(d0))
                matches0 = np.where(mutual, nn01, -1)
                grp = out.create_group(hloc.names_to_pair(name0, name1))
                grp.create_dataset("matches0", data=matches0.astype(np.int16))
                grp.create_dataset("matching_scores0", data=np.where(mutual, sim.max(1), 0).astype(np.float16))
    return matches


def connected(names: list[str], pairs: dict[str, list[str]]) -> bool:
    parent = {n: n for n in names}

    def find(n: str) -> str:
        while parent[n] != n:
            n = parent[n]
        return n

    for q, refs in pairs.items():
        for r in refs:
            parent[find(q)] = find(r)
    return len({find(n) for n in names}) == 1


def test_hloc_round_trip(synthetic_scene, tmp_path: Path):
    images, gt = synthetic_scene
    features = tmp_path / "feats-superpoint-n4096-r1024.h5"
    write_superpoint_like(gt, features)

    # k = 5 < N - 1: SARA computes global descriptors (with k >= N - 1 every pair is a candidate anyway)
    conf = make_config("sift-offline", {"retrieval.num_neighbors": 5})
    pairs_path = hloc.select_pairs(features, tmp_path / "pairs-sara.txt", conf=conf, progress=False)
    pairs = parse_retrieval(pairs_path)
    names = sorted(p.name for p in images.iterdir())
    num_pairs = sum(len(r) for r in pairs.values())
    assert 0 < num_pairs < len(names) * (len(names) - 1) // 2
    assert connected(names, pairs)
    assert (tmp_path / "pairs-sara-sara" / "scores.csv").exists()
    global_path = hloc.global_descriptors(tmp_path / "pairs-sara-sara")
    with h5py.File(global_path, "r") as fd:  # pairs_from_retrieval.get_descriptors
        desc = np.stack([fd[n]["global_descriptor"].__array__() for n in names])
    assert desc.shape[0] == len(names) and np.allclose(np.linalg.norm(desc, axis=1), 1, atol=1e-3)

    matches = match_mutual_nn(features, pairs_path, tmp_path / "matches.h5")
    model_dir = hloc.reconstruct(images, features, matches, pairs_path, tmp_path / "sfm", progress=False)

    rec = pycolmap.Reconstruction(str(model_dir))
    truth = pycolmap.Reconstruction()
    truth.read_text(str(gt))
    assert rec.num_reg_images() == len(names)
    est = {im.name: im.cam_from_world().rotation.matrix() for im in rec.images.values()}
    ref = {im.name: im.cam_from_world().rotation.matrix() for im in truth.images.values()}
    errors = [np.degrees(Rotation.from_matrix(est[a] @ est[b].T @ (ref[a] @ ref[b].T).T).magnitude())
              for a in names for b in names if a < b]
    assert np.max(errors) < 1.0


def test_reads_hloc_variants(tmp_path: Path):
    """DISK/ALIKED `keypoint_scores`, (N, D) descriptors, flipped and old-style ('_') pair keys."""
    path = tmp_path / "feats.h5"
    with h5py.File(path, "w") as h5:
        grp = h5.create_group("sub/a.jpg")
        grp.create_dataset("keypoints", data=np.array([[1, 2], [3, 4], [5, 6]], np.float16))
        grp.create_dataset("descriptors", data=np.eye(3, 128, dtype=np.float16))  # (N, D)
        grp.create_dataset("keypoint_scores", data=np.array([0.1, 0.9, 0.5], np.float16))
        grp.create_dataset("image_size", data=np.array([640, 480]))
        m = h5.create_group(hloc.names_to_pair("b.jpg", "sub/a.jpg"))
        m.create_dataset("matches0", data=np.array([2, -1, 0], np.int16))
        m.create_dataset("matching_scores0", data=np.array([0.9, 0, 0.2], np.float16))
        old = h5.create_group(hloc.names_to_pair("c.jpg", "d.jpg", "_"))
        old.create_dataset("matches0", data=np.array([-1, 1], np.int16))
    with h5py.File(path, "r") as h5:
        feats = hloc.read_hloc_features(h5, "sub/a.jpg")
        assert feats.descriptors.shape == (3, 128) and feats.keypoints.dtype == np.float32
        np.testing.assert_allclose(feats.scores, [0.1, 0.9, 0.5], atol=1e-3)
        assert feats.image_size == (640, 480)
        np.testing.assert_array_equal(hloc.read_hloc_matches(h5, "sub/a.jpg", "b.jpg"), [[2, 0], [0, 2]])
        np.testing.assert_array_equal(hloc.read_hloc_matches(h5, "b.jpg", "sub/a.jpg", min_score=0.5), [[0, 2]])
        np.testing.assert_array_equal(hloc.read_hloc_matches(h5, "c.jpg", "d.jpg"), [[1, 1]])
        with pytest.raises(ValueError, match="another pairs file"):
            hloc.read_hloc_matches(h5, "a.jpg", "c.jpg")


def test_names_with_spaces_are_refused(tmp_path: Path):
    path = tmp_path / "feats.h5"
    with h5py.File(path, "w") as h5:
        for name in ("my photo.jpg", "b.jpg"):
            grp = h5.create_group(name)
            grp.create_dataset("keypoints", data=np.zeros((1, 2), np.float32))
    with pytest.raises(ValueError, match="whitespace"):
        hloc.select_pairs(path, tmp_path / "pairs.txt")
    with pytest.raises(FileNotFoundError):
        hloc.select_pairs(tmp_path / "missing.h5", tmp_path / "pairs.txt")


def test_pairs_file_with_a_byte_order_mark(synthetic_scene, tmp_path: Path):
    """A pairs file saved by a Windows editor starts with a UTF-8 byte-order mark: it is not part
    of the first name, neither for sara's reader nor for COLMAP's verification (issue 30)."""
    from sara.colmap import model as colmap_model

    images, gt = synthetic_scene
    names = sorted(p.name for p in images.iterdir())
    features = tmp_path / "feats.h5"
    write_superpoint_like(gt, features)
    plain = tmp_path / "pairs.txt"
    plain.write_text("".join(f"{a} {b}\n" for a, b in zip(names, names[1:])))
    with_bom = tmp_path / "pairs-bom.txt"
    with_bom.write_bytes(b"\xef\xbb\xbf" + plain.read_bytes())
    assert read_pairs(with_bom, known_names=names) == read_pairs(plain, known_names=names)
    assert read_pairs(with_bom)[0] == (names[0], names[1])
    matches = match_mutual_nn(features, plain, tmp_path / "matches.h5")
    model_dir = hloc.reconstruct(images, features, matches, with_bom, tmp_path / "sfm", progress=False)
    verified = colmap_model.database_pairs(tmp_path / "sfm" / "database.db")[1]
    assert len(verified) == len(names) - 1  # the first pair too
    assert pycolmap.Reconstruction(str(model_dir)).num_reg_images() == len(names)
    assert not (tmp_path / "sfm" / ".pairs-verified.txt").exists()
