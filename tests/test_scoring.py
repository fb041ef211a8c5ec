"""Tests of the pre-matching scorer on hand-built geometry with exactly known answers."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import h5py
import numpy as np
import pycolmap
import pytest

import sara.scoring.scorer as scorer_module
from model_utils import PinholeCamera, look_at, rotation_about_axis
from sara.config import ScoreConfig
from sara.io.h5 import Features, write_features
from sara.scoring import (
    FOCAL_SCALES,
    PairScores,
    ViewFeatures,
    estimate_relative_pose,
    explained_by_rotation,
    mutual_matches_from_similarity,
    mutual_nearest_neighbours,
    pair_weight,
    read_scores_csv,
    rotation_focal_scale,
    score_pair,
    score_pairs,
    tree_weights,
    triangulation_angles_deg,
    write_scores_csv,
)

CAMERA = PinholeCamera()  # 640 x 480, f = 500 px
CENTER0 = np.array([0.0, -8.0, 0.0])


# ----------------------------------------------------------------------------------------
# Triangulation angles
# ----------------------------------------------------------------------------------------


def normalized(R: np.ndarray, t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 2) normalised coordinates of world points (N, 3) in the camera x = R X + t."""
    cam = points @ R.T + t
    return cam[:, :2] / cam[:, 2:]


def relative(pose0: tuple[np.ndarray, np.ndarray], pose1: tuple[np.ndarray, np.ndarray]):
    """cam1_from_cam0 (R, t) of two cam_from_world poses."""
    (R0, t0), (R1, t1) = pose0, pose1
    R = R1 @ R0.T
    return R, t1 - R @ t0


def true_angles_deg(center0: np.ndarray, center1: np.ndarray, points: np.ndarray) -> np.ndarray:
    to0, to1 = center0 - points, center1 - points
    cos = np.sum(to0 * to1, axis=1) / np.linalg.norm(to0, axis=1) / np.linalg.norm(to1, axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def test_triangulation_angle_of_a_point_on_the_bisector():
    # Cameras 1 unit apart, both looking along +z; the point is 1 unit in front of the midpoint.
    R, t = np.eye(3), np.array([-1.0, 0.0, 0.0])  # camera 1 sits at x = 1
    angles, in_front = triangulation_angles_deg(R, t, [[0.5, 0.0]], [[-0.5, 0.0]])
    assert angles == pytest.approx([math.degrees(2 * math.atan(0.5))], abs=1e-9)
    assert in_front.tolist() == [True]


def test_triangulation_angles_of_converging_cameras_match_the_geometry():
    rng = np.random.default_rng(0)
    points = rng.uniform(-1.0, 1.0, (20, 3))
    pose0 = look_at(np.array([-2.0, -6.0, 0.5]), np.zeros(3))
    pose1 = look_at(np.array([3.0, -5.0, -0.5]), np.zeros(3))
    R, t = relative(pose0, pose1)
    angles, in_front = triangulation_angles_deg(
        R, 3.7 * t, normalized(*pose0, points), normalized(*pose1, points)  # any baseline length
    )
    expected = true_angles_deg(-pose0[0].T @ pose0[1], -pose1[0].T @ pose1[1], points)
    np.testing.assert_allclose(angles, expected, atol=1e-7)
    assert in_front.all()


def test_a_pure_rotation_has_no_triangulation_angle():
    rng = np.random.default_rng(1)
    x0 = rng.uniform(-0.5, 0.5, (30, 2))
    R = rotation_about_axis([0.2, 1.0, 0.1], 15.0)
    rays1 = np.concatenate([x0, np.ones((30, 1))], axis=1) @ R.T
    x1 = rays1[:, :2] / rays1[:, 2:]
    # Whatever baseline a solver returns, the rays stay parallel: points at infinity.
    for t in ([1.0, 0.0, 0.0], [0.3, -0.2, 0.9], [0.0, 0.0, 0.0]):
        angles, in_front = triangulation_angles_deg(R, np.array(t), x0, x1)
        assert np.all(angles < 1e-5)
        assert not in_front.any()


def test_points_behind_a_camera_are_not_in_front():
    rng = np.random.default_rng(2)
    points = rng.uniform(-1.0, 1.0, (10, 3))
    pose0, pose1 = look_at(CENTER0, np.zeros(3)), look_at(np.array([2.0, -7.0, 0.0]), np.zeros(3))
    R, t = relative(pose0, pose1)
    x0, x1 = normalized(*pose0, points), normalized(*pose1, points)
    assert triangulation_angles_deg(R, t, x0, x1)[1].all()
    # The opposite baseline puts every intersection behind both cameras.
    assert not triangulation_angles_deg(R, -t, x0, x1)[1].any()


def test_triangulation_rejects_mismatched_lengths():
    with pytest.raises(ValueError, match="differ in length"):
        triangulation_angles_deg(np.eye(3), [1.0, 0, 0], np.zeros((3, 2)), np.zeros((2, 2)))


# ----------------------------------------------------------------------------------------
# Mutual nearest neighbours
# ----------------------------------------------------------------------------------------


def test_mutual_nearest_neighbours_drops_a_one_sided_match():
    desc1 = np.eye(4, dtype=np.float32)
    desc0 = np.array([
        [0.9, 0.1, 0.0, 0.0],  # -> e0, and e0's best: mutual
        [0.8, 0.0, 0.2, 0.0],  # -> e0 too, but e0 prefers row 0: dropped
        [0.0, 0.0, 0.3, 0.7],  # -> e3, mutual
    ], dtype=np.float32)
    matches, similarity = mutual_nearest_neighbours(desc0, desc1)
    assert matches.dtype == np.int32
    assert matches.tolist() == [[0, 0], [2, 3]]
    np.testing.assert_allclose(similarity, [0.9 / math.sqrt(0.82), 0.7 / math.sqrt(0.58)], rtol=1e-6)
    best, _ = mutual_nearest_neighbours(desc0, desc1, max_matches=1)
    assert best.tolist() == [[0, 0]]


def test_mutual_nearest_neighbours_of_uint8_descriptors_are_scale_free():
    rng = np.random.default_rng(3)
    desc = rng.integers(0, 256, (40, 128)).astype(np.uint8)
    shuffled = rng.permutation(40)
    matches, similarity = mutual_nearest_neighbours(desc, desc[shuffled] // 2)
    assert len(matches) == 40
    np.testing.assert_array_equal(shuffled[matches[:, 1]], matches[:, 0])
    assert np.all(np.diff(similarity) <= 0)


def test_mutual_matches_break_ties_by_lowest_index():
    matches, similarity = mutual_matches_from_similarity(np.array([[1.0, 0.2], [1.0, 0.2], [0.1, 0.5]]))
    assert matches.tolist() == [[0, 0], [2, 1]]
    assert similarity.tolist() == [1.0, 0.5]
    empty, values = mutual_nearest_neighbours(np.zeros((0, 8)), np.ones((3, 8)))
    assert empty.shape == (0, 2) and values.shape == (0,)


# ----------------------------------------------------------------------------------------
# One pair, synthetic correspondences
# ----------------------------------------------------------------------------------------


@dataclasses.dataclass
class SyntheticPair:
    view0: ViewFeatures
    view1: ViewFeatures
    true_angles_deg: np.ndarray  # triangulation angles of the true correspondences
    num_true: int


def synthetic_pair(
    pose1: tuple[np.ndarray, np.ndarray], *, num_true: int = 40, num_wrong: int = 10,
    num_other: int = 100, noise_px: float = 0.3, seed: int = 0, focal_scale: float = 1.0,
) -> SyntheticPair:
    """Views of one point cloud from camera 0 (at CENTER0, looking at the origin) and ``pose1``.

    ``num_true`` correspondences with pixel noise, ``num_wrong`` whose descriptors match equally
    well but whose keypoint in image 1 lies 40 px off its epipolar line (in a random direction
    for a pure rotation), ``num_other``
    unrelated keypoints per image. ``focal_scale`` scales the normalised coordinates (a wrong focal).
    """
    rng = np.random.default_rng(seed)
    pose0 = look_at(CENTER0, np.zeros(3))
    num = num_true + num_wrong
    points = rng.uniform(-2.0, 2.0, (num, 3))
    noise = noise_px / CAMERA.fx
    x0 = normalized(*pose0, points) + rng.normal(0, noise, (num, 2))
    x1 = normalized(*pose1, points) + rng.normal(0, noise, (num, 2))
    R, t = relative(pose0, pose1)
    skew = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    lines = np.concatenate([x0, np.ones((num, 1))], axis=1) @ (skew @ R).T
    if np.linalg.norm(t) < 1e-9:  # a pure rotation: any direction leaves the rotation model
        lines = np.concatenate([rng.normal(size=(num, 2)), np.zeros((num, 1))], axis=1)
    normals = lines[:, :2] / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    x1[num_true:] += 40.0 / CAMERA.fx * normals[num_true:]
    desc = rng.normal(size=(num, 128))
    views = []
    for x in (x0, x1):
        other = rng.uniform(-0.6, 0.6, (num_other, 2))
        views.append(ViewFeatures(
            descriptors=np.concatenate([desc + rng.normal(0, 0.01, desc.shape),
                                        rng.normal(size=(num_other, 128))]).astype(np.float32),
            points_norm=focal_scale * np.concatenate([x, other]),
            focal_px=CAMERA.fx,
        ))
    center1 = -pose1[0].T @ pose1[1]
    angles = true_angles_deg(CENTER0, center1, points[:num_true])
    return SyntheticPair(views[0], views[1], angles, num_true)


def test_score_pair_with_a_known_pose():
    pair = synthetic_pair(look_at(np.array([3.0, -8.0, 1.0]), np.zeros(3)))
    conf = ScoreConfig()
    score = score_pair(pair.view0, pair.view1, conf)
    assert score.num_matches == conf.num_matches
    assert score.num_inliers == pair.num_true  # the 10 wrong matches lie 40 px off
    assert score.num_inliers_all == pair.num_true  # all mutual matches: none of the others fits
    assert score.overlap == pytest.approx(pair.num_true / 150)
    assert score.parallax_deg == pytest.approx(np.median(pair.true_angles_deg), abs=0.3)
    assert score.parallax_deg > conf.parallax_saturation_deg
    assert score.weight == pytest.approx(score.overlap)  # g(P) = 1 beyond saturation
    assert (score.accepted, score.reason) == (True, "")
    assert score_pair(pair.view0, pair.view1, conf) == score  # deterministic


@pytest.mark.parametrize("center1, axial", [((0.0, -5.0, 0.0), True), ((3.0, -8.0, 0.0), False)])
def test_the_direction_is_camera_0s_centre_seen_from_camera_1(center1, axial):
    """A step straight ahead (along both optical axes) and one to the side: the pose's unit
    translation points at camera 0's centre in camera 1's frame, along its axis only in the first."""
    pose1 = look_at(np.array(center1), np.zeros(3))
    pair = synthetic_pair(pose1, num_true=60)
    score = score_pair(pair.view0, pair.view1, ScoreConfig())
    seen = pose1[0] @ (CENTER0 - np.array(center1))
    assert np.degrees(np.arccos(np.dot(score.direction, seen) / np.linalg.norm(seen))) < 3.0
    assert (abs(score.direction[2]) > 0.99) == axial and (abs(score.direction[2]) < 0.5) == (not axial)


def test_a_pure_rotation_is_rejected_for_low_parallax():
    rotation = rotation_about_axis([0.3, 1.0, 0.2], 12.0) @ look_at(CENTER0, np.zeros(3))[0]
    pair = synthetic_pair((rotation, -rotation @ CENTER0))
    score = score_pair(pair.view0, pair.view1, ScoreConfig())
    assert score.num_inliers >= pair.num_true
    assert score.parallax_deg < 0.5
    assert (score.accepted, score.reason) == (False, "low_parallax")
    assert score.weight == 0.0


@pytest.mark.parametrize("focal_scale", [0.67, 1.5])
def test_a_pure_rotation_with_a_wrong_focal_length_has_no_parallax(focal_scale):
    rotation = rotation_about_axis([1.0, 0.4, 0.0], 15.0) @ look_at(CENTER0, np.zeros(3))[0]
    pair = synthetic_pair((rotation, -rotation @ CENTER0), focal_scale=focal_scale, seed=4)
    score = score_pair(pair.view0, pair.view1, ScoreConfig())
    assert score.parallax_deg == 0.0
    assert score.reason == "low_parallax"


def test_motion_with_parallax_is_not_taken_for_a_rotation():
    pair = synthetic_pair(look_at(np.array([1.0, -8.0, 0.3]), np.zeros(3)), seed=5)
    matches, _ = mutual_nearest_neighbours(pair.view0.descriptors, pair.view1.descriptors, 50)
    x0, x1 = pair.view0.points_norm[matches[:, 0]], pair.view1.points_norm[matches[:, 1]]
    pose = estimate_relative_pose(x0, x1, max_error=2 / CAMERA.fx, iterations=32)
    assert pose is not None
    inl = pose.inliers
    assert not explained_by_rotation(pose, x0[inl], x1[inl], max_error=2 / CAMERA.fx, iterations=32)


def test_rotation_focal_scale_recovers_the_scale_of_a_rotation_homography():
    scale = FOCAL_SCALES[31]
    R = rotation_about_axis([0.2, 1.0, 0.3], 20.0)
    C = np.diag([scale, scale, 1.0])
    homography = np.linalg.inv(C) @ R @ C * 2.5
    assert rotation_focal_scale(homography) == scale


def test_unrelated_images_have_few_inliers():
    pair = synthetic_pair(look_at(np.array([3.0, -8.0, 1.0]), np.zeros(3)), num_true=0,
                          num_wrong=0, num_other=300, seed=6)
    score = score_pair(pair.view0, pair.view1, ScoreConfig())
    assert score.num_inliers < ScoreConfig().min_inliers
    assert (score.accepted, score.reason) == (False, "few_inliers")
    assert np.isnan(score.parallax_deg) and score.weight == 0.0  # not measured


@pytest.mark.parametrize("conf, reason", [(ScoreConfig(min_inliers=41), "few_inliers"),
                                          (ScoreConfig(min_overlap=0.5), "low_overlap")])
def test_a_pair_that_fails_before_the_parallax_test_is_not_triangulated(monkeypatch, conf, reason):
    """The parallax test is the scorer's dearest step, and no later stage reads the parallax of a
    pair rejected for its inliers or overlap: such a pair skips it, and everything else is kept."""
    pair = synthetic_pair(look_at(np.array([3.0, -8.0, 1.0]), np.zeros(3)))
    measured = score_pair(pair.view0, pair.view1, ScoreConfig())

    def fail(*args, **kwargs):
        raise AssertionError("the parallax of a rejected pair was measured")

    monkeypatch.setattr(scorer_module, "inlier_parallax_deg", fail)
    score = score_pair(pair.view0, pair.view1, conf)
    assert (score.accepted, score.reason) == (False, reason)
    assert (score.num_matches, score.num_inliers, score.overlap) == (
        measured.num_matches, measured.num_inliers, measured.overlap)
    assert np.isnan(score.parallax_deg) and score.weight == 0.0


def test_too_few_matches_give_no_model():
    pair = synthetic_pair(look_at(np.array([3.0, -8.0, 1.0]), np.zeros(3)), num_true=4,
                          num_wrong=0, num_other=0)
    score = score_pair(pair.view0, pair.view1, ScoreConfig())
    assert (score.num_matches, score.num_inliers, score.overlap) == (4, 0, 0.0)
    assert (score.accepted, score.reason, score.weight) == (False, "no_model", 0.0)


def test_inliers_among_all_matches_rank_pairs_whose_best_matches_all_fit():
    """Two pairs with 80 and 200 true correspondences among 300 keypoints per image: the b = 50
    best matches are inliers in both, so their overlap and weight tie; the inliers among all
    mutual matches do not, and the spanning tree's weight counts those."""
    conf = ScoreConfig(tree_overlap="all")
    pose1 = look_at(np.array([3.0, -8.0, 1.0]), np.zeros(3))
    few, many = (synthetic_pair(pose1, num_true=n, num_wrong=0, num_other=300 - n, seed=3) for n in (80, 200))
    scores = [score_pair(p.view0, p.view1, conf) for p in (few, many)]
    assert [s.num_inliers for s in scores] == [conf.num_matches] * 2
    # every true correspondence, and a few of the random keypoints' matches that fit by chance
    assert 80 <= scores[0].num_inliers_all <= 85 and 200 <= scores[1].num_inliers_all <= 205
    table = PairScores.from_scores([("a", "b"), ("a", "c")], scores)
    assert table.weight[0] == table.weight[1]  # tied
    tree = tree_weights(table, conf)
    assert tree[1] > 2 * tree[0]
    assert tree[0] == pytest.approx(pair_weight(scores[0].num_inliers_all / 300, scores[0].parallax_deg, conf))
    np.testing.assert_array_equal(tree_weights(table, ScoreConfig(tree_overlap="best")), table.weight)
    with pytest.raises(ValueError, match="auto"):  # the pair source resolves "auto" first
        tree_weights(table, ScoreConfig())


def test_a_scores_file_of_an_earlier_version_reads_without_num_inliers_all(tmp_path):
    scores = PairScores(
        name0=["a.jpg"], name1=["b.jpg"], num_matches=np.array([50]), num_inliers=np.array([50]),
        overlap=np.array([0.05]), parallax_deg=np.array([12.0]), weight=np.array([0.05]),
        accepted=np.array([True]), reason=[""],
    )
    path = write_scores_csv(tmp_path / "s.csv", scores)
    rows = [line.split(",") for line in path.read_text().splitlines()]
    column = rows[0].index("num_inliers_all")
    path.write_text("\n".join(",".join(r[:column] + r[column + 1:]) for r in rows) + "\n")
    loaded, _ = read_scores_csv(path)
    np.testing.assert_array_equal(loaded.num_inliers_all, [50])
    np.testing.assert_array_equal(tree_weights(loaded, ScoreConfig(tree_overlap="all")), loaded.weight)


def test_thresholds_and_weight_follow_the_config():
    pair = synthetic_pair(look_at(np.array([3.0, -8.0, 1.0]), np.zeros(3)))
    assert score_pair(pair.view0, pair.view1, ScoreConfig(min_overlap=0.5)).reason == "low_overlap"
    assert score_pair(pair.view0, pair.view1, ScoreConfig(min_inliers=41)).reason == "few_inliers"
    assert score_pair(pair.view0, pair.view1, ScoreConfig(min_parallax_deg=60)).reason == "low_parallax"
    conf = ScoreConfig(alpha=2.0, beta=0.5, parallax_saturation_deg=10.0)
    assert pair_weight(0.1, 2.5, conf) == pytest.approx(0.01 * 0.5)
    assert pair_weight(0.1, 25.0, conf) == pytest.approx(0.01)
    assert pair_weight(0.1, 0.0, conf) == 0.0


# ----------------------------------------------------------------------------------------
# Many pairs from files
# ----------------------------------------------------------------------------------------


def write_synthetic_inputs(folder: Path) -> tuple[Path, Path]:
    """features.h5 (hloc convention) and a COLMAP database for four images of two scenes.

    a, b: a scene seen with a 20-degree baseline; c: camera a turned in place; d: another scene.
    """
    rng = np.random.default_rng(7)
    scene = rng.uniform(-2.0, 2.0, (300, 3))
    scene_desc = rng.normal(size=(300, 128))
    other_scene, other_desc = rng.uniform(-2.0, 2.0, (300, 3)), rng.normal(size=(300, 128))
    pose_a = look_at(CENTER0, np.zeros(3))
    turned = rotation_about_axis([0.0, 1.0, 0.2], 10.0) @ pose_a[0]
    poses = {
        "a.png": (pose_a, scene, scene_desc),
        "b.png": (look_at(np.array([3.0, -8.0, 1.0]), np.zeros(3)), scene, scene_desc),
        "c.png": ((turned, -turned @ CENTER0), scene, scene_desc),
        "d.png": (pose_a, other_scene, other_desc),
    }
    features_path, db_path = folder / "features.h5", folder / "database.db"
    db = pycolmap.Database.open(str(db_path))
    camera_id = db.write_camera(pycolmap.Camera(
        model="PINHOLE", width=CAMERA.width, height=CAMERA.height,
        params=[CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy]))
    with h5py.File(features_path, "w") as h5:
        for name, ((R, t), points, desc) in poses.items():
            uv = CAMERA.project(points @ R.T + t) + rng.normal(0, 0.3, (len(points), 2))
            visible = (uv[:, 0] > 0) & (uv[:, 0] < CAMERA.width) & (uv[:, 1] > 0) & (uv[:, 1] < CAMERA.height)
            noisy = desc[visible] + rng.normal(0, 0.01, desc[visible].shape)
            root_sift = np.clip(512 * np.abs(noisy) / np.linalg.norm(noisy, axis=1, keepdims=True), 0, 255)
            write_features(h5, name, Features(
                keypoints=uv[visible] - 0.5, descriptors=root_sift.astype(np.uint8),
                scores=rng.uniform(1, 5, visible.sum()).astype(np.float32),
                image_size=(CAMERA.width, CAMERA.height)))
            db.write_image(pycolmap.Image(name=name, camera_id=camera_id))
    db.close()
    return features_path, db_path


def test_score_pairs_on_files_and_round_trip_through_csv(tmp_path):
    features_path, db_path = write_synthetic_inputs(tmp_path)
    pairs = [("a.png", "b.png"), ("a.png", "c.png"), ("a.png", "d.png"), ("b.png", "c.png")]
    scores = score_pairs(pairs, features_path, db_path, ScoreConfig(), progress=False)
    assert (scores.name0, scores.name1) == ([p[0] for p in pairs], [p[1] for p in pairs])
    assert scores.accepted.tolist() == [True, False, False, True]
    assert scores.reason == ["", "low_parallax", "few_inliers", ""]
    assert scores.parallax_deg[0] > 10.0 and scores.parallax_deg[1] == 0.0
    assert scores.num_inliers[1] >= 40
    assert scores.weight.dtype == np.float64 and scores.accepted.dtype == bool

    again = score_pairs(pairs, features_path, db_path, ScoreConfig(), progress=False)
    np.testing.assert_array_equal(again.weight, scores.weight)

    roles = ["tree", "rejected", "rejected", "loop"]
    path = write_scores_csv(tmp_path / "scores.csv", scores, roles)
    header = path.read_text().splitlines()[0]
    assert header == ("name0,name1,num_matches,num_inliers,num_inliers_all,overlap,parallax_deg,weight,accepted,"
                      "reason,role,rotvec_x,rotvec_y,rotvec_z,direction_x,direction_y,direction_z")
    assert np.all(scores.num_inliers_all >= scores.num_inliers)
    assert np.all(np.isfinite(scores.rotvec[scores.accepted]))
    centre_b = np.array([3.0, -8.0, 1.0])
    R_b = look_at(centre_b, np.zeros(3))[0]
    R_c = rotation_about_axis([0.0, 1.0, 0.2], 10.0) @ look_at(CENTER0, np.zeros(3))[0]
    for k, seen in ((0, R_b @ (CENTER0 - centre_b)), (3, R_c @ (centre_b - CENTER0))):  # camera 0's centre, from 1
        assert np.degrees(np.arccos(scores.direction[k] @ seen / np.linalg.norm(seen))) < 2.0
    loaded, loaded_roles = read_scores_csv(path)
    assert loaded_roles == roles
    for field in dataclasses.fields(PairScores):
        np.testing.assert_array_equal(getattr(loaded, field.name), getattr(scores, field.name))
    assert not list(tmp_path.glob(".scores.csv.*"))  # no temporary file left behind


def test_a_view_store_scores_as_the_features_do(tmp_path, monkeypatch):
    """The store's cached unit descriptors give the scores of the features as read, bit for bit,
    also when views leave the cache and come back."""
    from sara.scoring.scorer import ViewStore, load_views, score_pair

    features_path, db_path = write_synthetic_inputs(tmp_path)
    names = ["a.png", "b.png", "c.png", "d.png"]
    views = load_views(names, features_path, db_path, 1024, progress=False)
    monkeypatch.setattr(ViewStore, "UNIT_CACHE_VIEWS", 2)
    store = ViewStore.write(tmp_path / "store", names, features_path, db_path, 1024, progress=False)
    order = [(0, 1), (0, 2), (1, 3), (2, 3), (0, 3), (0, 1)]
    for a, b in order:
        cached = score_pair(store.view(a), store.view(b), ScoreConfig())
        assert cached == score_pair(views[names[a]], views[names[b]], ScoreConfig())
    assert len(store._unit) == 2 and not views["a.png"].unit and store.view(0).unit


def test_a_scores_file_without_rotations_reads_with_nan_rotations(tmp_path):
    path = tmp_path / "old.csv"
    path.write_text("name0,name1,num_matches,num_inliers,overlap,parallax_deg,weight,accepted,reason,role\n"
                    "a,b,50,40,0.1,3.0,0.2,true,,tree\n")
    scores, roles = read_scores_csv(path)
    assert roles == ["tree"] and scores.num_inliers_all.tolist() == [40]
    assert scores.rotvec.shape == (1, 3) and np.all(np.isnan(scores.rotvec))


def test_scores_csv_without_roles_and_with_odd_names(tmp_path):
    scores = PairScores(
        name0=["dir/a, b.jpg"], name1=['say "c".jpg'], num_matches=np.array([50]),
        num_inliers=np.array([20]), overlap=np.array([1 / 3]), parallax_deg=np.array([0.1]),
        weight=np.array([0.0]), accepted=np.array([False]), reason=["low_parallax"],
    )
    loaded, roles = read_scores_csv(write_scores_csv(tmp_path / "s.csv", scores))
    assert roles is None
    assert (loaded.name0, loaded.name1, loaded.reason) == (scores.name0, scores.name1, scores.reason)
    assert loaded.overlap[0] == 1 / 3  # full precision
    with pytest.raises(ValueError, match="roles"):
        write_scores_csv(tmp_path / "t.csv", scores, ["tree", "loop"])


def test_read_scores_csv_reports_bad_files(tmp_path):
    (tmp_path / "bad.csv").write_text("name0,name1\na,b\n")
    with pytest.raises(ValueError, match="columns"):
        read_scores_csv(tmp_path / "bad.csv")
    (tmp_path / "bad2.csv").write_text(
        "name0,name1,num_matches,num_inliers,overlap,parallax_deg,weight,accepted,reason,role\n"
        "a,b,50,x,0.1,1.0,0.1,true,,\n")
    with pytest.raises(ValueError, match="line 2: bad num_inliers"):
        read_scores_csv(tmp_path / "bad2.csv")


def test_score_pairs_reports_bad_input(tmp_path):
    features_path, db_path = write_synthetic_inputs(tmp_path)
    with pytest.raises(ValueError, match="itself"):
        score_pairs([("a.png", "a.png")], features_path, db_path, ScoreConfig(), progress=False)
    with pytest.raises(ValueError, match="not in the database"):
        score_pairs([("a.png", "zz.png")], features_path, db_path, ScoreConfig(), progress=False)


def test_shards_give_each_worker_several_but_not_tiny_ones():
    from sara.scoring.scorer import MIN_SHARD_PAIRS, SHARD_PAIRS, shard_pairs

    assert shard_pairs(1356, 2) == 170  # 8 shards on 2 workers, not 512 + 512 + 332
    assert shard_pairs(100_000, 2) == SHARD_PAIRS
    assert shard_pairs(120, 2) == MIN_SHARD_PAIRS  # fewer than two shards: scored in-process
    assert shard_pairs(10, 2, most=4) == 4  # a smaller maximum is kept (the tests' small shards)


def test_scores_kept_in_a_journal_are_not_made_again_and_equal_new_ones(tmp_path, monkeypatch):
    """Stopped after two shards of one pair, scoring again with the journal scores only the other
    two pairs and gives the scores of an uninterrupted run; other settings or inputs score anew."""
    from sara.execute import SerialExecutor
    from sara.scoring import ScoreJournal

    features_path, db_path = write_synthetic_inputs(tmp_path)
    pairs = [("a.png", "b.png"), ("a.png", "c.png"), ("a.png", "d.png"), ("b.png", "c.png")]
    whole = score_pairs(pairs, features_path, db_path, ScoreConfig(), progress=False)
    real, calls, stop_at = scorer_module._score_shard, [], [3]

    def stopping(shard):
        calls.append(len(shard.index0))
        if len(calls) in stop_at:
            stop_at.clear()
            raise KeyboardInterrupt
        return real(shard)

    monkeypatch.setattr(scorer_module, "_score_shard", stopping)

    def score(conf=None, key="inputs-1"):
        journal = ScoreJournal(tmp_path / "journal", key).open()
        return score_pairs(pairs, features_path, db_path, conf or ScoreConfig(), executor=SerialExecutor(),
                           shard_size=1, journal=journal, progress=False)

    with pytest.raises(KeyboardInterrupt):
        score()
    calls.clear()
    again = score()
    assert calls == [1, 1]
    for field in dataclasses.fields(PairScores):
        np.testing.assert_array_equal(getattr(again, field.name), getattr(whole, field.name))
    calls.clear()
    score(ScoreConfig(num_matches=40))
    assert len(calls) == 4
    calls.clear()
    score(key="inputs-2")  # the journal of other features is cleared
    assert len(calls) == 4 and len(list((tmp_path / "journal").glob("*.json"))) == 4


def test_a_journal_row_written_before_the_direction_is_scored_again(tmp_path):
    """A run stopped by an earlier version resumes: its journal's rows without a direction (which the
    spanning tree's rule for views moving straight ahead reads) are not taken, so those pairs are
    scored again; rows of this release beside them read as written."""
    import json

    from sara.scoring import ScoreJournal
    from sara.scoring.journal import _settings

    journal = ScoreJournal(tmp_path / "journal", "inputs").open()
    old = ["a.png", "b.png", 50, 40, 0.2, 12.5, 0.2, True, "", 44, [0.1, 0.0, 0.0]]
    new = ["a.png", "c.png", 50, 40, 0.2, 12.5, 0.2, True, "", 44, [0.1, 0.0, 0.0], [0.0, 0.0, 1.0]]
    (journal.folder / f"{_settings(ScoreConfig(), 0)}-old.json").write_text(json.dumps([old, new]))
    scored = journal.scored(ScoreConfig(), 0)
    assert list(scored) == [("a.png", "c.png")]
    score = scored[("a.png", "c.png")]
    assert (score.num_inliers, score.num_inliers_all, score.rotvec, score.direction) == \
        (40, 44, (0.1, 0.0, 0.0), (0.0, 0.0, 1.0))


def test_the_journal_of_features_made_elsewhere_is_keyed_by_the_features_file(tmp_path):
    """With no extract stage recorded (features brought from elsewhere) the scores belong to the
    features file as it is: the same file keeps them, a rewritten one does not."""
    import os

    from sara.pipeline.pairs_stage import _scores_key

    features = tmp_path / "features-sift.h5"
    features.write_bytes(b"x" * 10)
    key = _scores_key("", features)
    assert _scores_key("", features) == key
    features.write_bytes(b"y" * 11)
    assert _scores_key("", features) != key
    stat = features.stat()
    changed_in_place = _scores_key("", features)
    os.utime(features, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    assert _scores_key("", features) != changed_in_place
