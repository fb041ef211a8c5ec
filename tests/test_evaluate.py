"""Tests of sara.evaluate on hand-built models with exactly known errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from model_utils import (
    PinholeCamera,
    Point3D,
    camera_center,
    random_rotation,
    ring_poses,
    rotation_about_axis,
    transform_poses,
    write_text_model,
)
from sara.colmap import load_poses
from sara.colmap.reconstruction import reprojection_errors_px
from sara.evaluation import evaluate as run
from sara.evaluation import evaluate_models, find_model_dirs, format_table
from sara.evaluation.metrics import (
    direction_angle_deg,
    pose_auc,
    relative_pose_errors,
    rotation_angle_deg,
    umeyama_similarity,
)

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
THRESHOLDS_DEG = (1, 3, 5, 10)
AUC_KEYS = ("1", "3", "5", "10")
NUM_IMAGES = 8
NUM_PAIRS = NUM_IMAGES * (NUM_IMAGES - 1) // 2


def _step_recall_auc(errors_deg: list[float], num_total: int, threshold_deg: float) -> float:
    """AUC by integrating the step recall curve numerically on a fine grid (independent check)."""
    xs = np.linspace(0.0, threshold_deg, 200_001)
    errors = np.sort(np.asarray(errors_deg, dtype=np.float64))
    recall = np.searchsorted(errors, xs, side="right") / num_total
    return float(np.trapezoid(recall, xs) / threshold_deg)


@pytest.fixture()
def gt_poses() -> dict:
    return ring_poses(NUM_IMAGES, seed=1)


@pytest.fixture()
def gt_dir(tmp_path: Path, gt_poses: dict) -> Path:
    return write_text_model(tmp_path / "gt", gt_poses)


# ------------------------------------------------------------------------------------------------
# Pure cores


def test_angle_helpers_exact_and_zero_norm() -> None:
    R = random_rotation(np.random.default_rng(3))
    assert rotation_angle_deg(R, R) == pytest.approx(0.0, abs=1e-12)
    R_turned = rotation_about_axis([1, 2, 3], 7.5) @ R
    assert rotation_angle_deg(R, R_turned) == pytest.approx(7.5, abs=1e-9)
    assert direction_angle_deg([1.0, 0, 0], [0, 2.0, 0]) == pytest.approx(90.0)
    assert direction_angle_deg([1.0, 0, 0], [-3.0, 0, 0]) == pytest.approx(180.0)
    # no gt direction: nothing to miss; no estimated direction: 90 degrees, never NaN
    assert direction_angle_deg([1.0, 0, 0], [0.0, 0, 0]) == 0.0
    assert direction_angle_deg([0.0, 0, 0], [1.0, 0, 0]) == 90.0


def test_pose_auc_matches_definition() -> None:
    errors = [0.0, 2.0, 4.0]
    # recall 1/4 on [0, 2), 2/4 on [2, 4): integral 0.5 + 1.0 over threshold 4
    assert pose_auc(np.array(errors), [4], num_total=4) == [pytest.approx(0.375)]
    aucs = pose_auc(np.array(errors), THRESHOLDS_DEG, num_total=5)
    for auc, threshold in zip(aucs, THRESHOLDS_DEG):
        assert auc == pytest.approx(_step_recall_auc(errors, 5, threshold), abs=1e-4)
    assert pose_auc(np.zeros(0), THRESHOLDS_DEG, num_total=0) == [0.0] * 4
    assert pose_auc(np.array([np.nan, 0.0]), [1], num_total=2) == [0.5]
    with pytest.raises(ValueError):
        pose_auc(np.zeros(3), [1], num_total=2)


def test_umeyama_recovers_random_similarity() -> None:
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    scale_true, R_true, t_true = 2.7, random_rotation(rng), rng.normal(size=3)
    dst = scale_true * src @ R_true.T + t_true
    scale, R, t = umeyama_similarity(src, dst)
    assert scale == pytest.approx(scale_true, rel=1e-12)
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(t, t_true, atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # a mirror image must still give a proper rotation
    _, R_mirror, _ = umeyama_similarity(src, src * [1, 1, -1])
    assert np.linalg.det(R_mirror) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="collinear"):
        umeyama_similarity(np.outer(np.arange(5.0), [1, 2, 3]), rng.normal(size=(5, 3)))
    with pytest.raises(ValueError, match="at least 3"):
        umeyama_similarity(src[:2], dst[:2])


def test_relative_errors_of_one_rotated_camera(gt_poses: dict) -> None:
    names = list(gt_poses)
    k, angle_deg = 3, 3.0
    est = dict(gt_poses)
    R_k, t_k = gt_poses[names[k]]
    R_z = rotation_about_axis([0, 0, 1], angle_deg)  # about the camera's optical axis
    est[names[k]] = (R_z @ R_k, R_z @ t_k)  # same centre, rolled by 3 degrees
    rot_err, trans_err = relative_pose_errors(est, gt_poses, names)
    pairs = list(zip(*np.triu_indices(NUM_IMAGES, 1)))
    for (i, j), rot, trans in zip(pairs, rot_err, trans_err):
        assert rot == pytest.approx(angle_deg if k in (i, j) else 0.0, abs=1e-9)
        if j == k:  # cam_k_from_cam_i: baseline seen from camera k, rolled with it
            baseline = camera_center(gt_poses[names[i]]) - camera_center(gt_poses[names[k]])
            baseline_in_k = R_k @ baseline
            expected = direction_angle_deg(R_z @ baseline_in_k, baseline_in_k)
        else:
            expected = 0.0
        assert trans == pytest.approx(expected, abs=1e-9)
        assert trans <= angle_deg + 1e-9


def test_rotated_camera_gives_hand_computed_auc(
    tmp_path: Path, gt_poses: dict, gt_dir: Path
) -> None:
    names = list(gt_poses)
    R_k, t_k = gt_poses[names[2]]
    R_z = rotation_about_axis([0, 0, 1], 3.0)
    est = dict(gt_poses)
    est[names[2]] = (R_z @ R_k, R_z @ t_k)
    metrics = evaluate_models([write_text_model(tmp_path / "est", est)], gt_dir)
    # NUM_IMAGES - 1 pairs have max error 3 deg, the rest 0: recall (N - m) / N below 3 deg, 1 after
    num_bad = NUM_IMAGES - 1
    good = (NUM_PAIRS - num_bad) / NUM_PAIRS
    expected = {"1": good, "3": good, "5": (3 * good + 2) / 5, "10": (3 * good + 7) / 10}
    assert metrics["auc"] == pytest.approx(expected, abs=1e-9)
    assert metrics["rel_rotation_error_median_deg"] == pytest.approx(0.0, abs=1e-6)
    assert metrics["abs_rotation_error_median_deg"] == pytest.approx(0.0, abs=1e-6)
    assert metrics["position_error_median_pct"] == pytest.approx(0.0, abs=1e-6)


# ------------------------------------------------------------------------------------------------
# Whole models


def test_similarity_transformed_model_is_perfect(
    tmp_path: Path, gt_poses: dict, gt_dir: Path
) -> None:
    rng = np.random.default_rng(7)
    est = transform_poses(gt_poses, 0.37, random_rotation(rng), rng.normal(scale=10.0, size=3))
    # binary model inside a sparse/ folder, found by run() like a mapper output
    est_rec = pycolmap.Reconstruction(write_text_model(tmp_path / "est_text", est))
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    est_rec.write(tmp_path / "sparse" / "0")
    out_path = tmp_path / "eval" / "metrics.json"
    metrics = run(tmp_path / "sparse", gt_dir, out_path)
    assert json.loads(out_path.read_text()) == metrics
    assert metrics["auc"] == {key: pytest.approx(1.0, abs=1e-9) for key in AUC_KEYS}
    assert metrics["num_registered"] == metrics["num_images_gt"] == NUM_IMAGES
    assert metrics["registered_pct"] == 100.0
    assert metrics["num_components"] == 1
    assert metrics["num_pairs_coregistered"] == NUM_PAIRS
    for key in ("rel_rotation_error_median_deg", "rel_translation_error_median_deg",
                "abs_rotation_error_median_deg", "position_error_median_pct"):
        assert metrics[key] == pytest.approx(0.0, abs=1e-6), key
    assert "auc@10" in format_table(metrics)


def test_missing_image_lowers_auc_by_its_pairs(
    tmp_path: Path, gt_poses: dict, gt_dir: Path
) -> None:
    est = {name: pose for name, pose in gt_poses.items() if name != "0005.jpg"}
    metrics = evaluate_models(write_text_model(tmp_path / "est", est), gt_dir)
    expected = (NUM_IMAGES - 1) * (NUM_IMAGES - 2) / 2 / NUM_PAIRS
    assert metrics["auc"] == {key: pytest.approx(expected, abs=1e-9) for key in AUC_KEYS}
    assert metrics["num_registered"] == NUM_IMAGES - 1
    assert metrics["registered_pct"] == pytest.approx(100.0 * (NUM_IMAGES - 1) / NUM_IMAGES)
    assert metrics["num_pairs_coregistered"] == (NUM_IMAGES - 1) * (NUM_IMAGES - 2) // 2


def test_largest_component_is_scored(tmp_path: Path, gt_poses: dict, gt_dir: Path) -> None:
    names = list(gt_poses)
    small = {name: gt_poses[name] for name in names[:3]}
    large = {name: gt_poses[name] for name in names[2:]}
    write_text_model(tmp_path / "sparse" / "0", small)
    write_text_model(tmp_path / "sparse" / "1", large)
    assert [p.name for p in find_model_dirs(tmp_path / "sparse")] == ["0", "1"]
    metrics = run(tmp_path / "sparse", gt_dir)
    assert metrics["num_components"] == 2
    assert metrics["num_registered"] == metrics["num_images_est"] == NUM_IMAGES - 2
    assert metrics["num_registered_any"] == NUM_IMAGES
    expected_auc = (NUM_IMAGES - 2) * (NUM_IMAGES - 3) / 2 / NUM_PAIRS
    assert metrics["auc"]["5"] == pytest.approx(expected_auc, abs=1e-9)


def test_reprojection_errors_of_known_offsets(tmp_path: Path, gt_dir: Path) -> None:
    camera = PinholeCamera()
    poses = ring_poses(3, seed=2)
    points_xyz = [np.array([0.1, -0.2, 0.3]), np.array([-0.3, 0.2, -0.1])]
    offsets_px = [{"0000.jpg": (3.0, 4.0), "0001.jpg": (0.0, 0.0)},
                  {"0000.jpg": (1.0, 0.0), "0002.jpg": (0.0, -2.0)}]  # errors 5, 0, 1, 2
    points = []
    for xyz, offsets in zip(points_xyz, offsets_px):
        observations = {}
        for name, offset in offsets.items():
            R, t = poses[name]
            observations[name] = camera.project(R @ xyz + t)[0] + offset
        points.append(Point3D(xyz, observations))
    model_dir = write_text_model(tmp_path / "est", poses, camera, points)
    errors = np.sort(reprojection_errors_px(pycolmap.Reconstruction(model_dir)))
    np.testing.assert_allclose(errors, [0.0, 1.0, 2.0, 5.0], atol=1e-9)
    metrics = evaluate_models([model_dir], gt_dir)
    assert metrics["num_points3d"] == 2
    assert metrics["mean_track_length"] == pytest.approx(2.0)
    assert metrics["reproj_error_mean_px"] == pytest.approx(2.0, abs=1e-9)
    assert metrics["reproj_error_median_px"] == pytest.approx(1.5, abs=1e-9)


def test_reprojection_errors_agree_with_pycolmap_on_rig_scene() -> None:
    pycolmap.set_random_seed(0)
    options = pycolmap.SyntheticDatasetOptions()
    options.num_points3D = 50
    rec = pycolmap.synthesize_dataset(options)  # rigs, distortion, full tracks
    rng = np.random.default_rng(0)
    for point in rec.points3D.values():
        point.xyz = point.xyz + rng.normal(scale=0.01, size=3)
    rec.update_point_3d_errors()
    errors = reprojection_errors_px(rec)
    assert errors.size == rec.compute_num_observations()
    assert errors.mean() > 0.1
    # every track spans all images, so the mean of per-point means is the mean per observation
    assert errors.mean() == pytest.approx(rec.compute_mean_reprojection_error(), rel=1e-6)


def test_missing_model_scores_as_failure(tmp_path: Path, gt_dir: Path) -> None:
    for metrics in (evaluate_models([], gt_dir),
                    evaluate_models([tmp_path / "sparse" / "0"], gt_dir),
                    run(tmp_path / "nothing", gt_dir, tmp_path / "metrics.json")):
        assert metrics["num_registered"] == 0
        assert metrics["num_images_gt"] == NUM_IMAGES
        assert metrics["auc"] == {"1": 0.0, "3": 0.0, "5": 0.0, "10": 0.0}
        assert metrics["rel_rotation_error_median_deg"] is None
        assert metrics["position_error_median_pct"] is None
        json.dumps(metrics, allow_nan=False)
    assert json.loads((tmp_path / "metrics.json").read_text())["num_registered"] == 0
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_poses(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="No COLMAP model"):
        load_poses(tmp_path / "empty")


def test_fountain_gt_against_itself() -> None:
    gt_dir = SHARED_DATA / "strecha-fountain-P11" / "gt"
    if not gt_dir.is_dir():
        pytest.skip(f"shared scene not found at {gt_dir}")
    metrics = run(gt_dir, gt_dir)
    assert metrics["num_registered"] == metrics["num_images_gt"] == 11
    assert metrics["auc"] == {"1": 1.0, "3": 1.0, "5": 1.0, "10": 1.0}
    assert metrics["position_error_median_pct"] == pytest.approx(0.0, abs=1e-9)
