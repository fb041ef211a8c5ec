"""Camera models other than the default (`extract.camera_model`): the fisheye models a dashcam's,
an action camera's or a drone's wide lens needs."""

from __future__ import annotations

import json
from pathlib import Path

import pycolmap

from sara import colmap
from sara.colmap.database import fisheye_focal_priors, open_pycolmap_database


def test_only_fisheye_cameras_without_a_prior_are_marked(tmp_path: Path):
    db_path = tmp_path / "database.db"
    colmap.create_database(db_path)
    with open_pycolmap_database(db_path) as db:
        for model in ("OPENCV_FISHEYE", "SIMPLE_RADIAL", "FISHEYE"):
            db.write_camera(pycolmap.Camera.create_from_model_name(0, model, 600.0, 640, 480))
        known = pycolmap.Camera.create_from_model_name(0, "SIMPLE_RADIAL_FISHEYE", 300.0, 640, 480)
        known.has_prior_focal_length = True
        db.write_camera(known)
    assert fisheye_focal_priors(db_path) == [1, 3]
    assert colmap.camera_priors(db_path) == {1: True, 2: False, 3: True, 4: True}
    assert fisheye_focal_priors(db_path) == []  # marked once


def test_a_fisheye_camera_model_gets_its_pairs_verified_and_mapped(five_view_scene, tmp_path: Path, run_cli):
    """COLMAP 4 marks every pair of a fisheye camera whose focal length is not a prior degenerate
    (its fallback, the fundamental matrix, assumes a pinhole): with `extract.camera_model=
    OPENCV_FISHEYE` no pair was verified and `sara run` ended in exit 5. The guess is now given to
    COLMAP as a prior before it verifies; the extract record still counts the camera as guessed. The
    first mapping holds the model's distortion (fountain-P11 through a fisheye: its four terms,
    fitted to a first model of few views, left 7 of 11 views registered; held, 11)."""
    images, _ = five_view_scene
    out = tmp_path / "out"
    result = run_cli("run", images, out, "-q", "-s", "extract.camera_model=OPENCV_FISHEYE")
    assert result.code == 0, result.err
    stages = json.loads((out / "run.json").read_text())["stages"]
    assert stages["extract"]["cameras_guessed"] == [1, 1]
    assert stages["match"]["num_verified_pairs"] == stages["match"]["num_pairs"] >= 4
    assert stages["map"]["distortion_held"] is True  # a fisheye model's four terms, held in the first mapping
    model = pycolmap.Reconstruction(out / "sparse" / "0")
    assert model.num_reg_images() == 5
    assert {camera.model.name for camera in model.cameras.values()} == {"OPENCV_FISHEYE"}


def test_no_start_through_a_fisheye_model_names_the_default_camera(tmp_path: Path, monkeypatch):
    """A straight drive through a fisheye model gave COLMAP's mapper no pair to start from (its angles
    are measured with the lens's focal length), where the default camera mapped it whole: the exit
    message says so when the cameras are fisheye, and only then."""
    from sara import mapping
    from sara.config import MapConfig

    monkeypatch.setattr(colmap, "verified_graph", lambda db, min_inliers: (97, 51, [51], 711))
    for model, said in (("OPENCV_FISHEYE", True), ("SIMPLE_RADIAL", False)):
        db_path = tmp_path / f"{model}.db"
        colmap.create_database(db_path)
        with open_pycolmap_database(db_path) as db:
            db.write_camera(pycolmap.Camera.create_from_model_name(0, model, 600.0, 640, 480))
        reason = mapping.no_model_reason(db_path, MapConfig(), 15)
        assert "no pair of views to start from among the 51 images" in reason
        assert ("default camera model (SIMPLE_RADIAL)" in reason) == said
