"""Known poses from a transforms.json (nerfstudio, instant-ngp, the NeRF synthetic scenes) as the
ground truth of `sara evaluate` and `sara run --gt`, and ground-truth names matched to image names."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from harness import assert_error, assert_ok
from model_utils import random_rotation, rotation_about_axis
from sara.evaluation.ground_truth import match_names, read_transforms


@pytest.fixture
def exported(finished_run, run_cli) -> Path:
    """The finished run's model as nerfstudio's transforms.json (`sara export --format nerfstudio`)."""
    assert_ok(run_cli("export", finished_run, finished_run.parent / "ns", "--format", "nerfstudio", "-q"))
    return finished_run.parent / "ns"


def _metrics(out: Path) -> dict:
    return json.loads(out.read_text())


def test_a_model_scores_perfectly_against_its_own_nerfstudio_export(finished_run, exported, run_cli):
    """The export's camera-to-world matrices (OpenGL axes, nerfstudio's world) read back as the
    model's own poses: every image registered, every relative pose exact. The file or its folder."""
    registered = json.loads((finished_run / "metrics.json").read_text())["num_registered"]
    for gt in (exported / "transforms.json", exported):
        assert_ok(run_cli("evaluate", finished_run, gt, "--json", finished_run / "ns.json"))
        metrics = _metrics(finished_run / "ns.json")
        assert metrics["num_registered"] == metrics["num_images_gt"] == registered > 3
        assert all(v == pytest.approx(1.0, abs=1e-6) for v in metrics["auc"].values()), metrics["auc"]
        assert metrics["rel_rotation_error_median_deg"] < 1e-5


def test_nerf_synthetic_paths_without_extension_and_a_scaled_world(finished_run, exported, run_cli):
    """`./train/<stem>` paths (no extension, another folder) find their images; a world moved, turned
    and scaled (a dataset's own frame and scene scale) changes no metric; a pose perturbed does."""
    meta = json.loads((exported / "transforms.json").read_text())
    world = np.eye(4)
    world[:3, :3], world[:3, 3] = 2.5 * random_rotation(np.random.default_rng(3)), [4.0, -1.0, 7.0]
    for frame in meta["frames"]:
        frame["file_path"] = "./train/" + Path(frame["file_path"]).stem
        frame["transform_matrix"] = (world @ np.asarray(frame["transform_matrix"])).tolist()
    synthetic = finished_run.parent / "transforms_train.json"
    synthetic.write_text(json.dumps(meta))
    assert_ok(run_cli("evaluate", finished_run, synthetic, "--json", finished_run / "syn.json"))
    metrics = _metrics(finished_run / "syn.json")
    assert metrics["num_registered"] == metrics["num_images_gt"] == len(meta["frames"])
    assert metrics["auc"]["1"] == pytest.approx(1.0, abs=1e-6)
    turned = np.asarray(meta["frames"][0]["transform_matrix"])
    turned[:3, :3] = turned[:3, :3] @ rotation_about_axis([0.3, 1.0, 0.2], 5.0)
    meta["frames"][0]["transform_matrix"] = turned.tolist()
    synthetic.write_text(json.dumps(meta))
    assert_ok(run_cli("evaluate", finished_run, synthetic, "--json", finished_run / "syn.json"))
    assert _metrics(finished_run / "syn.json")["auc"]["1"] < 0.95


def test_run_scores_against_a_transforms_file(synthetic_scene, finished_run, exported, run_cli):
    """`sara run --gt transforms.json` on the finished run: the metrics of the new ground truth."""
    images, _ = synthetic_scene
    assert_ok(run_cli("run", images, finished_run, "-q", "--gt", exported / "transforms.json"))
    assert _metrics(finished_run / "metrics.json")["auc"]["1"] == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("content, message", [
    ("{not json", "does not read as a transforms.json"),
    ('{"camera_model": "OPENCV"}', "holds no frames"),
    ('{"frames": [{"file_path": "images/a.png"}]}', "frame 0 has no readable file_path and transform_matrix"),
    ('{"frames": [{"file_path": "a.png", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], '
     '[0, 0, 0, 1]]}]}', "holds no rotation"),
    ('{"frames": [{"file_path": "a.png", "transform_matrix": [[1, 0], [0, 1]]}]}', "not a finite 4 x 4"),
])
def test_a_transforms_file_that_does_not_read_is_one_line(content, message, finished_run, run_cli):
    bad = finished_run.parent / "transforms.json"
    bad.write_text(content)
    assert_error(run_cli("evaluate", finished_run, bad), 2, str(bad), message)


def test_ground_truth_names_match_image_names_by_the_end_of_their_paths():
    pose = (np.eye(3), np.zeros(3))
    gt = dict.fromkeys(("images/0001.jpg", "train/r_0", "x.png", "c.png", "other/z.png", "0001"), pose)
    names = ["0001.jpg", "r_0.png", "a/x.png", "b/x.png", "c.png", "d/z.png"]
    matched = match_names(gt, names)
    # 0001.jpg fits two entries ("images/0001.jpg" and "0001"), x.png two images, z.png another folder
    assert sorted(matched) == sorted(["images/0001.jpg", "r_0.png", "x.png", "c.png", "other/z.png", "0001"])
    assert len(matched) == len(gt)
    assert match_names({"images/0001.jpg": pose}, names).keys() == {"0001.jpg"}


def test_frames_read_as_colmap_poses(tmp_path):
    """A camera at (1, 2, 3) looking down the world's -z with OpenGL axes: COLMAP's rotation
    flips y and z, its translation is -R c."""
    c2w = np.eye(4)
    c2w[:3, 3] = [1.0, 2.0, 3.0]
    frames = [{"file_path": "./a.png", "transform_matrix": c2w.tolist()}]
    (tmp_path / "t.json").write_text(json.dumps({"frames": frames}))
    R, t = read_transforms(tmp_path / "t.json")["a.png"]
    np.testing.assert_allclose(R, np.diag([1.0, -1.0, -1.0]))
    np.testing.assert_allclose(t, [-1.0, 2.0, 3.0])
