"""The synthetic street worlds of `sara.bench.world`: determinism, truth, readers, and selection on them."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from sara import colmap
from sara.bench.world import (
    TRUTH_NAME,
    Truth,
    WorldConfig,
    build_city,
    camera_poses,
    features_path,
    image_set,
    make_world,
    observe_image,
    world_info,
)
from sara.io.h5 import list_names, read_features

SMALL = 120


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    out = tmp_path_factory.mktemp("world")
    make_world(out, WorldConfig(num_images=SMALL, seed=3), progress=False)
    return out


def _h5_equal(path_a, path_b, names):
    with h5py.File(path_a, "r") as a, h5py.File(path_b, "r") as b:
        for name in names:
            for key in ("keypoints", "descriptors", "scores", "image_size"):
                if not np.array_equal(a[name][key][()], b[name][key][()]):
                    return False
    return True


def test_same_seed_same_world_other_seed_other_world(tmp_path):
    conf = WorldConfig(num_images=30, seed=5)
    make_world(tmp_path / "a", conf, progress=False)
    make_world(tmp_path / "b", conf, progress=False)
    make_world(tmp_path / "c", WorldConfig(num_images=30, seed=6), progress=False)
    names = image_set(tmp_path / "a").names
    assert _h5_equal(features_path(tmp_path / "a"), features_path(tmp_path / "b"), names)
    assert not _h5_equal(features_path(tmp_path / "a"), features_path(tmp_path / "c"), names[:3])
    ta, tb = Truth(tmp_path / "a"), Truth(tmp_path / "b")
    assert np.array_equal(ta.point_ids, tb.point_ids) and np.array_equal(ta.R, tb.R)
    # a second call finds the world complete and leaves it alone
    mtime = features_path(tmp_path / "a").stat().st_mtime_ns
    make_world(tmp_path / "a", conf, progress=False)
    assert features_path(tmp_path / "a").stat().st_mtime_ns == mtime


def test_files_load_with_sara_readers(world):
    info = world_info(world)
    names = image_set(world).names
    assert names == sorted(names) and len(names) == SMALL
    assert list_names(features_path(world)) == names
    cameras = colmap.cameras_by_image(world / "database.db")
    assert sorted(cameras) == names
    cam = cameras[names[0]]
    assert cam.model == "PINHOLE" and colmap.mean_focal_px(cam) == pytest.approx(900.0)
    conf = info["config"]
    for name in names[::17]:
        feats = read_features(features_path(world), name)
        assert feats.descriptors.dtype == np.uint8 and feats.descriptors.shape == (len(feats.keypoints), 128)
        assert feats.image_size == (conf["width"], conf["height"])
        assert np.all(feats.keypoints >= -0.5) and np.all(feats.keypoints[:, 0] < conf["width"])
        assert np.all(feats.keypoints[:, 1] < conf["height"])
        assert 100 < len(feats.keypoints) <= conf["max_keypoints"]
        top = read_features(features_path(world), name, top_k=50)
        assert top.scores.min() >= np.sort(feats.scores)[-50]  # "top M by score" is well defined
    assert 1000 < info["keypoints_mean"] < conf["max_keypoints"]


def test_truth_matches_the_geometry(world):
    """The points an image observes project into it with the true pose, in front of the camera."""
    truth = Truth(world)
    with h5py.File(world / TRUTH_NAME, "r") as h5:
        xyz = h5["points_xyz"][()]
        f, _, cx, cy = h5.attrs["camera_params"]
    for i in range(0, SMALL, 23):
        cam = xyz[truth.observed(i)] @ truth.R[i].T + truth.t[i]
        assert np.all(cam[:, 2] > 0)
        u, v = f * cam[:, 0] / cam[:, 2] + cx, f * cam[:, 1] / cam[:, 2] + cy
        assert np.all((u >= 0) & (u < 2 * cx) & (v >= 0) & (v < 2 * cy))


def test_true_overlap_is_symmetric_and_sensible(world):
    truth = Truth(world, min_common=20)
    n = len(truth.names)
    rng = np.random.default_rng(0)
    for a, b in rng.integers(0, n, size=(20, 2)):
        assert truth.common_points(int(a), int(b)) == truth.common_points(int(b), int(a))
    assert truth.common_points(7, 7) == len(truth.observed(7))
    # neighbours along the walk overlap: the same image side (every 4th image) and the forward views
    near = [(i, i + 4) for i in range(0, n - 4, 3)]
    assert truth.overlaps(near).mean() > 0.9
    # images far apart (and not a revisit of the same street) never do
    dist = np.linalg.norm(truth.centers[:, None, :2] - truth.centers[None, :, :2], axis=2)
    far = np.argwhere(dist > 80)
    assert len(far) > 100
    assert truth.common_counts(far[:: max(1, len(far) // 300)]).max() == 0
    assert truth.common_points(truth.names[0], truth.names[4]) == truth.common_points(0, 4)


def test_image_observation_ids_are_the_truth(world):
    """What observe_image returns is what make_world stored (same seed and generator)."""
    conf = WorldConfig(**{**world_info(world)["config"], "facade_height_m": tuple(
        world_info(world)["config"]["facade_height_m"]), "yaw_pattern_deg": tuple(
        world_info(world)["config"]["yaw_pattern_deg"])})
    city = build_city(conf)
    poses = camera_poses(conf, city.grid)
    obs = observe_image(city, poses["R"][5], poses["centers"][5], np.random.default_rng([conf.seed, 5, 5]))
    assert np.array_equal(np.sort(obs.point_ids[obs.point_ids >= 0]), Truth(world).observed(5))
    assert np.mean(obs.point_ids < 0) == pytest.approx(conf.outlier_fraction, abs=0.05)


@pytest.mark.slow  # 11 s; the selection at scale is measured by lab/scripts/scale_bench.py
def test_selection_on_a_small_world_is_connected_and_true(world, tmp_path):
    """SARA's pair selection, called as the pipeline calls it, on the world."""
    from sara.bench.world import selection_context
    from sara.config import make_config
    from sara.pairs import get_source

    names = image_set(world).names
    # the default settings but a smaller k-means sample for the codebook (its cost does not depend on N)
    conf = make_config(overrides={"retrieval.features_per_image": "400"})
    result = get_source("sara")(selection_context(conf, world, tmp_path / "run", progress=False))
    pairs = result.pairs
    assert set(result.timings_s) >= {"retrieval", "scoring"}
    # one connected component
    parent = {n: n for n in names}

    def find(x):
        while parent[x] != x:
            x = parent[x]
        return x

    for a, b in pairs:
        parent[find(a)] = find(b)
    assert len({find(n) for n in names}) == 1
    assert len(pairs) / len(names) < 2.5
    truly = Truth(world, min_common=20).overlaps(pairs)
    assert truly.mean() >= 0.95, [p for p, ok in zip(pairs, truly) if not ok][:10]
