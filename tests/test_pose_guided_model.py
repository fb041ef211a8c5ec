"""The pose-guided round on a real (synthesized) COLMAP model: reading its geometry, choosing pairs,
re-triangulating with fixed poses and bundle-adjusting (`sara.colmap.refine`, `sara.pairs.sara.pose_guided`)."""

from __future__ import annotations

import logging
from itertools import combinations
from pathlib import Path

import h5py
import numpy as np
import pycolmap
import pytest

from model_utils import synthetic_database
from sara.colmap import tracks as tracks_module
from sara.colmap.refine import read_geometry, triangulate_and_adjust
from sara.colmap.tracks import TrackExtension, extend_tracks, track_distance_threshold, track_sizes
from sara.config import make_config
from sara.pairs import PairContext
from sara.pairs.sara import pose_guided as round_
from sara.selection.pose_guided import covisibility

ON = {"rounds.pose_guided_pairs_per_image": 0.5, "budget.max_pairs_per_image": 4.0,
      "budget.max_pairs_fraction": 0.25, "rounds.repair_rounds": 3}


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    """8 posed views of 200 points, every point seen by every view; matches in `database.db`."""
    root = tmp_path_factory.mktemp("pose_guided")
    rec = synthetic_database(root / "database.db", 8, 200)
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "images").mkdir()
    rec.write(str(root / "sparse" / "0"))
    return root


def test_read_geometry_gives_poses_intrinsics_and_tracks(model: Path):
    geom = read_geometry(model / "sparse" / "0")
    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    assert geom.names == sorted(im.name for im in rec.images.values())
    assert geom.points_xyz.shape == (200, 3) and len(geom.obs_point) == len(geom.obs_view) == 1600
    assert np.allclose(geom.focal_px, 300.0) and np.allclose(geom.principal_px, [160.0, 120.0])
    image = next(im for im in rec.images.values() if im.name == geom.names[0])
    assert np.allclose(geom.centers[0], image.projection_center())
    cov = covisibility(geom, np.array(list(combinations(range(8), 2))), max_view_angle_deg=180.0)
    assert np.all(cov.covisible == 200) and np.all(cov.linked == 200) and np.all(cov.observed == 200)


def test_triangulate_and_adjust_keeps_poses_and_points(model: Path, tmp_path: Path):
    counts = triangulate_and_adjust(model / "sparse" / "0", model / "database.db", model / "images", tmp_path / "out")
    assert counts == {"num_points3d": 200.0, "num_registered": 8.0, "observations_added": 0.0}
    before, after = read_geometry(model / "sparse" / "0"), read_geometry(tmp_path / "out")
    assert after.names == before.names
    assert np.allclose(after.centers, before.centers, atol=1e-3 * np.ptp(before.centers))


def test_bundle_adjustment_keeps_colmap_off_the_console(model: Path, tmp_path: Path, capfd):
    """pycolmap's bundle adjustment turns COLMAP's console log on for the whole process; with the log
    sent to a folder (as `sara run` does), nothing of it may reach the terminal, then or later."""
    from sara import colmap

    log = pycolmap.logging
    saved = (log.logtostderr, log.alsologtostderr, log.stderrthreshold, log.minloglevel)
    try:
        colmap.send_log_to(tmp_path / "logs")
        triangulate_and_adjust(model / "sparse" / "0", model / "database.db", model / "images", tmp_path / "out")
        assert (log.logtostderr, log.alsologtostderr, log.stderrthreshold) == (False, False, 3)
        log.info("a later COLMAP message")
        err = capfd.readouterr().err
        assert "bundle" not in err.lower() and "later COLMAP message" not in err
        assert any("Global bundle adjustment" in f.read_text() for f in (tmp_path / "logs").iterdir())
    finally:
        log.logtostderr, log.alsologtostderr, log.stderrthreshold, log.minloglevel = saved


def test_round_chooses_unmatched_pairs_within_its_budget_once(model: Path, tmp_path: Path):
    names = read_geometry(model / "sparse" / "0").names
    conf = make_config("sift-offline", ON)
    features = _features_of(pycolmap.Reconstruction(str(model / "sparse" / "0")), tmp_path / "features.h5")
    ctx = PairContext(names=names, images_root=model / "images", features_path=features,
                      db_path=model / "database.db", out_dir=tmp_path, conf=conf, progress=False)
    chain = [(names[k], names[k + 1]) for k in range(4)]
    extra, info = round_.select_extra(ctx, chain, model / "sparse" / "0")
    # its own budget is ceil(0.5 * 8) = 4, but all rounds together may match min(4 * 8, 25% of 28) = 7
    assert len(extra) == info["budget"] == 7 - 4
    assert not set(extra) & {tuple(sorted(p)) for p in chain}
    key = round_.selection_key(chain, conf)
    assert round_.recorded_pairs(tmp_path, key) is None
    round_.mark_chosen(tmp_path, key, extra, info)
    assert round_.recorded_pairs(tmp_path, key) == extra
    # refinement only for the round's own pairs (a repair round maps again)
    assert round_.refine(ctx, chain[:2], model / "database.db", model / "sparse" / "0", tmp_path / "r") is None
    refined = round_.refine(ctx, extra, model / "database.db", model / "sparse" / "0", tmp_path / "r")
    assert refined is not None and refined["num_registered"] == 8 and refined["time_s"] >= 0


def test_mapping_continues_from_an_input_model(model: Path, tmp_path: Path):
    """A repair round's mapping: the views missing from the model are registered into it."""
    from sara import mapping
    from sara.colmap import registered_images
    from sara.config import MapConfig

    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    left_out = sorted(rec.images)[-2:]
    names = {rec.images[i].name for i in left_out}
    for image_id in left_out:
        rec.deregister_frame(rec.images[image_id].frame_id)
    partial = tmp_path / "partial"
    partial.mkdir()
    rec.write(str(partial))
    assert not names & registered_images(partial)
    sparse = mapping.run(MapConfig(num_threads=1), model / "database.db", model / "images", tmp_path / "out",
                         input_model=partial, progress=False)
    assert len(registered_images(sparse / "0")) == 8
    # continued, not started again: the mapper registers only the two missing views
    from sara import colmap

    def images_registered(input_path, out: str):
        calls = []
        (tmp_path / out).mkdir()
        colmap.incremental_mapping(model / "database.db", model / "images", tmp_path / out,
                                   seed=0, min_model_size=3, abs_pose_min_num_inliers=15,
                                   abs_pose_min_inlier_ratio=0.1, num_threads=1,
                                   on_next_image=lambda: calls.append(1), input_path=input_path)
        return len(calls)

    assert images_registered(partial, "continued") == 2
    assert images_registered(None, "scratch") >= 6  # the control: from scratch, every view after the first pair


def test_continuing_from_a_model_without_points_on_the_new_matches(model: Path, tmp_path: Path, caplog):
    """The repair round's case: the left-out views match features the model never triangulated.

    Continued as written, such a model cannot register them; sara first triangulates the new
    matches with the poses fixed, so the mapper registers them without mapping anew."""
    from sara import mapping
    from sara.colmap import registered_images
    from sara.colmap.refine import triangulate_new_matches
    from sara.config import MapConfig

    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    for image_id in sorted(rec.images)[-2:]:
        rec.deregister_frame(rec.images[image_id].frame_id)
    for point_id in list(rec.points3D):
        rec.delete_point3D(point_id)
    bare = tmp_path / "bare"
    bare.mkdir()
    rec.write(str(bare))
    assert pycolmap.Reconstruction(str(bare)).num_points3D() == 0
    assert triangulate_new_matches(bare, model / "database.db", model / "images", tmp_path / "tri") == 200
    before, after = read_geometry(bare), read_geometry(tmp_path / "tri")
    assert after.names == before.names and np.allclose(after.centers, before.centers)
    caplog.set_level("INFO", logger="sara.mapping")
    sparse = mapping.run(MapConfig(num_threads=1), model / "database.db", model / "images", tmp_path / "out",
                         input_model=bare, progress=False)
    assert len(registered_images(sparse / "0")) == 8
    assert "views joined by verified pairs" not in caplog.text  # continuing reached every joined view


def test_a_model_inside_a_larger_one_is_not_written(model: Path, tmp_path: Path):
    """[8, 5] where the 5 views are also in the 8-view model: one model, not two."""
    from sara.colmap.sfm import write_models_by_size

    full = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    part = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    for image_id in sorted(part.images)[5:]:
        part.deregister_frame(part.images[image_id].frame_id)
    other = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    for image_id in sorted(other.images)[:-2]:
        other.deregister_frame(other.images[image_id].frame_id)
    assert write_models_by_size(tmp_path, {0: part, 1: full}) == [8]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["0"]
    # a model with a view of its own is kept
    assert write_models_by_size(tmp_path, {0: part, 1: other}) == [5, 2]


def _features_of(rec: pycolmap.Reconstruction, path: Path, *, seed: int = 0, noise: float = 0.1) -> Path:
    """A features file for the model's keypoints (hloc's pixel convention): every 3D point gets a
    random unit descriptor that its observations carry with `noise` (a little by default); other
    keypoints get descriptors of their own."""
    from sara.io.h5 import Features, write_features

    rng = np.random.default_rng(seed)
    point_desc = {pid: rng.normal(size=64) for pid in rec.point3D_ids()}
    with h5py.File(path, "w") as h5:
        for image in rec.images.values():
            xy = np.array([p.xy for p in image.points2D], dtype=np.float32).reshape(-1, 2) - 0.5
            desc = rng.normal(size=(len(xy), 64))
            for k, p in enumerate(image.points2D):
                if p.has_point3D():
                    desc[k] = point_desc[p.point3D_id] + noise * rng.normal(size=64)
            desc /= np.linalg.norm(desc, axis=1, keepdims=True)
            write_features(h5, image.name, Features(xy, desc.astype(np.float32), np.ones(len(xy), np.float32),
                                                    (320, 240)))
    return path


def test_extend_tracks_finds_the_observations_a_model_lost(model: Path, tmp_path: Path):
    """Observations taken out of a model come back, each on its own keypoint; a keypoint whose
    descriptor is another's does not join a track."""
    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    features = _features_of(rec, tmp_path / "features.h5")
    rng = np.random.default_rng(1)
    removed = set()
    for pid in sorted(rec.point3D_ids()):
        elements = list(rec.points3D[pid].track.elements)
        for element in rng.choice(elements, size=2, replace=False):
            removed.add((element.image_id, element.point2D_idx, pid))
            rec.delete_observation(element.image_id, element.point2D_idx)
    assert rec.compute_num_observations() == 1600 - len(removed)
    added = extend_tracks(rec, features, TrackExtension(max_view_angle_deg=180.0))
    found = {(e.image_id, e.point2D_idx, pid) for pid in rec.point3D_ids() for e in rec.points3D[pid].track.elements}
    assert added == len(removed) == 400 and removed <= found

    # the same with the removed keypoints' descriptors scrambled: nothing joins
    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    for image_id, idx, _ in removed:
        rec.delete_observation(image_id, idx)
    with h5py.File(features, "r+") as h5:
        for image_id, idx, _ in removed:
            grp = h5[rec.images[image_id].name]["descriptors"]
            column = rng.normal(size=grp.shape[0])
            grp[:, idx] = column / np.linalg.norm(column)
    assert extend_tracks(rec, features, TrackExtension(max_view_angle_deg=180.0)) == 0


def test_a_model_too_large_for_float32_descriptors_is_extended_with_float16_ones(model: Path, tmp_path: Path,
                                                                                caplog):
    """Above `max_values` descriptor values the tracks' descriptors are held as float16 (half the
    memory) and the same observations come back; above twice as many the model is left as it is."""
    features = _features_of(pycolmap.Reconstruction(str(model / "sparse" / "0")), tmp_path / "f.h5", noise=0.9)

    def extended(max_values: int) -> set:
        rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
        _remove_two_per_track(rec, seed=2)
        assert rec.compute_num_observations() * 64 == 76_800
        extend_tracks(rec, features, TrackExtension(max_view_angle_deg=180.0, max_values=max_values))
        return {(e.image_id, e.point2D_idx, pid) for pid in rec.point3D_ids() for e in rec.points3D[pid].track.elements}

    before = extended(0)  # above twice the limit: nothing added
    assert len(before) == 1200
    with caplog.at_level(logging.INFO, logger="sara.colmap.tracks"):
        whole = extended(76_800)
        assert "float16" not in caplog.text
        half = extended(40_000)
        assert "held as float16" in caplog.text
    assert len(whole) >= 1200 + 0.95 * 400 and half == whole


def _remove_two_per_track(rec: pycolmap.Reconstruction, seed: int) -> set:
    rng = np.random.default_rng(seed)
    removed = set()
    for pid in sorted(rec.point3D_ids()):
        for element in rng.choice(list(rec.points3D[pid].track.elements), size=2, replace=False):
            removed.add((element.image_id, element.point2D_idx, pid))
            rec.delete_observation(element.image_id, element.point2D_idx)
    return removed


def test_extension_takes_its_descriptor_threshold_from_tracks_that_spread_more_than_sift(model: Path,
                                                                                      tmp_path: Path):
    """Learned descriptors of one 3D point differ more than SIFT's (nearest in the track at ~1, not
    ~0.3): COLMAP's SIFT threshold 0.7 turns their observations away, the tracks' own threshold
    takes them back, and a keypoint with another descriptor still does not join."""
    features = _features_of(pycolmap.Reconstruction(str(model / "sparse" / "0")), tmp_path / "f.h5", noise=0.9)
    wide = TrackExtension(max_view_angle_deg=180.0)
    fixed = TrackExtension(max_view_angle_deg=180.0, track_distance_quantile=0.0)  # 0.7 alone
    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    removed = _remove_two_per_track(rec, seed=2)
    assert extend_tracks(rec, features, fixed) < 0.5 * len(removed)
    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    _remove_two_per_track(rec, seed=2)
    added = extend_tracks(rec, features, wide)
    found = {(e.image_id, e.point2D_idx, pid) for pid in rec.point3D_ids() for e in rec.points3D[pid].track.elements}
    assert added >= 0.95 * len(removed) and len(removed & found) == added

    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    removed = _remove_two_per_track(rec, seed=2)
    rng = np.random.default_rng(3)
    with h5py.File(features, "r+") as h5:
        for image_id, idx, _ in removed:
            grp = h5[rec.images[image_id].name]["descriptors"]
            column = rng.normal(size=grp.shape[0])
            grp[:, idx] = column / np.linalg.norm(column)
    assert extend_tracks(rec, features, wide) == 0


def _set_scales(rec: pycolmap.Reconstruction, path: Path, *, seed: int, spread: float = 0.05) -> None:
    """Scores of `path` become SIFT-like scales: each 3D point has a size in the scene, and its
    keypoints the scale that size has at their depth (focal / depth), within `spread` (log)."""
    rng = np.random.default_rng(seed)
    size = {pid: rng.uniform(0.005, 0.05) for pid in rec.point3D_ids()}
    with h5py.File(path, "r+") as h5:
        for image in rec.images.values():
            focal = rec.cameras[image.camera_id].mean_focal_length()
            scale = rng.uniform(1.0, 8.0, size=image.num_points2D())
            for k, p in enumerate(image.points2D):
                if p.has_point3D():
                    depth = (image.cam_from_world() * rec.points3D[p.point3D_id].xyz)[2]
                    scale[k] = size[p.point3D_id] * focal / depth * np.exp(spread * rng.normal())
            h5[image.name]["scores"][...] = scale.astype(np.float32)


def test_extension_turns_away_keypoints_whose_scale_does_not_fit_the_track(model: Path, tmp_path: Path):
    """With the scale test, a removed observation comes back on a keypoint of the track's size in
    the scene, and not when its scale is three times that; without it, it comes back either way."""
    full = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    features = _features_of(full, tmp_path / "f.h5")
    _set_scales(full, features, seed=4)
    scaled = TrackExtension(max_view_angle_deg=180.0, scale_quantile=0.99)
    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    removed = _remove_two_per_track(rec, seed=5)
    added = extend_tracks(rec, features, scaled)
    found = {(e.image_id, e.point2D_idx, pid) for pid in rec.point3D_ids() for e in rec.points3D[pid].track.elements}
    assert added >= 0.95 * len(removed) and len(removed & found) == added

    with h5py.File(features, "r+") as h5:  # the removed keypoints three times their size
        for image_id, idx, _ in removed:
            h5[rec.images[image_id].name]["scores"][idx] *= 3.0
    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    _remove_two_per_track(rec, seed=5)
    assert extend_tracks(rec, features, scaled) == 0
    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    _remove_two_per_track(rec, seed=5)
    assert extend_tracks(rec, features, TrackExtension(max_view_angle_deg=180.0)) == len(removed)


def test_track_sizes_are_medians_and_a_quantile_of_the_distance_to_them():
    # track 0: 0, 1, 3 (median 1; distances 1, 0, 2); track 1: 2, 4 (median 3; 1, 1); track 2: one, left out
    o_size = np.array([3.0, 0.0, 1.0, 4.0, 2.0, 7.0])
    start, count = np.array([0, 3, 5]), np.array([3, 2, 1])
    median, tol = track_sizes(o_size, start, count, 1.0)
    assert median == pytest.approx([1.0, 3.0, 7.0]) and tol == pytest.approx(2.0)
    assert track_sizes(o_size, start, count, 0.5)[1] == pytest.approx(1.0)
    assert track_sizes(np.array([5.0]), np.array([0]), np.array([1]), 0.99)[1] == np.inf  # no track of two


def test_track_distance_threshold_is_a_quantile_of_each_observations_nearest_in_its_track():
    # track 0: three unit vectors, nearest distances 0 (two equal) and sqrt(2); track 1: two at distance 2
    desc = np.array([[1, 0], [1, 0], [0, 1], [1, 0], [-1, 0]], dtype=np.float32)
    start, count = np.array([0, 3, 5]), np.array([3, 2, 0])
    assert track_distance_threshold(desc, start, count, 1.0) == pytest.approx(2.0)
    assert track_distance_threshold(desc, start, count, 0.0) == 0.0  # off
    # distances 0, 0, sqrt(2), 2, 2: the median is sqrt(2)
    assert track_distance_threshold(desc, start, count, 0.5) == pytest.approx(np.sqrt(2.0))
    assert track_distance_threshold(desc, np.array([0]), np.array([1]), 0.99) == 0.0  # no track of two


def test_extension_of_a_model_too_large_to_project_whole_compares_views_with_covisible_points(model: Path,
                                                                                              tmp_path: Path):
    """Above `max_projections` views x points, each view is compared with the points of the views
    it shares points with (here: all of them, so everything comes back), and the extension stops
    when those comparisons reach the budget."""
    features = _features_of(pycolmap.Reconstruction(str(model / "sparse" / "0")), tmp_path / "f.h5")
    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    removed = _remove_two_per_track(rec, seed=4)
    whole = 8 * 200  # views x points of the model
    added = extend_tracks(rec, features, TrackExtension(max_view_angle_deg=180.0, max_projections=whole - 1))
    found = {(e.image_id, e.point2D_idx, pid) for pid in rec.point3D_ids() for e in rec.points3D[pid].track.elements}
    assert added == len(removed) == 400 and removed <= found

    # a budget of 120 comparisons: views are extended in order while their comparisons (each view's
    # unobserved points: here its removed observations) fit in it
    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    removed = _remove_two_per_track(rec, seed=4)
    per_view = [sum(1 for image_id, _, _ in removed if image_id == v) for v in sorted(rec.reg_image_ids())]
    fits = np.cumsum(per_view) <= 120
    added = extend_tracks(rec, features, TrackExtension(max_view_angle_deg=180.0, max_projections=120))
    assert 0 < added == sum(np.array(per_view)[fits]) < len(removed)


def test_a_view_whose_features_do_not_fit_the_model_is_left_out_of_the_extension(model: Path, tmp_path: Path):
    """A view whose features file holds another number of keypoints than the model's view is neither
    extended nor used as a track's descriptor; the other views are extended as before."""
    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    features = _features_of(rec, tmp_path / "f.h5")
    odd = sorted(rec.reg_image_ids())[0]
    with h5py.File(features, "r+") as h5:  # one keypoint more than the model's view has
        grp = h5[rec.images[odd].name]
        for key in ("keypoints", "descriptors", "scores"):
            data = grp[key][()]
            axis = 1 if key == "descriptors" else 0
            del grp[key]
            grp[key] = np.concatenate([data, np.take(data, [0], axis=axis)], axis=axis)
    removed = _remove_two_per_track(rec, seed=5)
    added = extend_tracks(rec, features, TrackExtension(max_view_angle_deg=180.0))
    found = {(e.image_id, e.point2D_idx, pid) for pid in rec.point3D_ids() for e in rec.points3D[pid].track.elements}
    assert added == sum(1 for image_id, _, _ in removed if image_id != odd) > 0
    assert {r for r in removed if r[0] != odd} <= found
    assert not {r for r in removed if r[0] == odd} & found  # the odd view gets nothing back


def test_the_tracks_without_a_view_keep_their_descriptors_in_place():
    """Dropping a view's observations moves the other descriptors down inside the same array, a chunk
    at a time, instead of copying gigabytes."""
    rng = np.random.default_rng(3)
    desc = rng.normal(size=(1000, 8)).astype(np.float16)
    rows = np.flatnonzero(rng.random(1000) < 0.7)
    expected = desc[rows].copy()
    kept = tracks_module._keep_rows(desc, rows, chunk=37)
    assert np.array_equal(kept, expected)
    assert np.shares_memory(kept, desc)


def test_the_scale_test_is_on_only_for_features_whose_scores_are_scales():
    rounds = make_config().rounds
    assert round_._extension(rounds, "sift").scale_quantile == rounds.extend_tracks_scale_quantile > 0
    for backend in ("aliked-n16", "disk", "xfeat"):  # their scores are detection scores
        assert round_._extension(rounds, backend).scale_quantile == 0.0


def test_the_adjustment_after_a_track_extension_is_capped(model: Path, tmp_path: Path, monkeypatch):
    """The model was adjusted before its tracks grew: the adjustment after the extension stops after
    `REFINE_BA_MAX_ITERATIONS` (pycolmap's own default is 100)."""
    from sara.colmap import refine

    seen = []
    monkeypatch.setattr(refine, "extend_tracks", lambda rec, features, ext: 5)
    monkeypatch.setattr(refine, "bundle_adjust", lambda rec, options=None: seen.append(
        None if options is None else options.ceres.solver_options.max_num_iterations))
    counts = refine.extend_and_adjust(model / "sparse" / "0", tmp_path / "out", tmp_path / "features.h5")
    assert counts["observations_added"] == 5.0
    assert seen == [refine.REFINE_BA_MAX_ITERATIONS] and refine.REFINE_BA_MAX_ITERATIONS < 100
    assert pycolmap.BundleAdjustmentOptions().ceres.solver_options.max_num_iterations == 100


def test_the_adjustment_after_re_triangulation_is_capped_too(model: Path, tmp_path: Path, monkeypatch):
    """Both adjustments of a refinement (after re-triangulating, after extending the tracks) stop after
    `REFINE_BA_MAX_ITERATIONS`; the model written is the triangulated one."""
    from sara.colmap import refine
    from sara.colmap.tracks import TrackExtension

    seen = []
    monkeypatch.setattr(refine, "extend_tracks", lambda rec, features, ext: 7)
    monkeypatch.setattr(refine, "bundle_adjust", lambda rec, options=None: seen.append(
        None if options is None else options.ceres.solver_options.max_num_iterations))
    counts = refine.triangulate_and_adjust(model / "sparse" / "0", model / "database.db", model / "images",
                                           tmp_path / "out", features_path=tmp_path / "features.h5",
                                           extension=TrackExtension())
    assert seen == [refine.REFINE_BA_MAX_ITERATIONS] * 2
    assert counts["observations_added"] == 7.0 and counts["num_points3d"] > 0
    assert (tmp_path / "out" / "images.bin").exists()


@pytest.mark.parametrize("refine_distortion", [True, False])
def test_the_refinement_holds_the_distortion_where_the_mapper_held_it(model: Path, tmp_path: Path,
                                                                      refine_distortion: bool):
    """A model mapped with the distortion held (`stages.map.distortion_held`) keeps it through the
    refinement's adjustment; otherwise the adjustment refines it (here towards the images' none)."""
    start = tmp_path / "start"
    start.mkdir()
    rec = pycolmap.Reconstruction(str(model / "sparse" / "0"))
    for camera in rec.cameras.values():
        camera.params = [*camera.params[:3], 0.05]  # SIMPLE_RADIAL: f, cx, cy, k
    rec.write(str(start))
    triangulate_and_adjust(start, model / "database.db", model / "images", tmp_path / "out",
                           refine_distortion=refine_distortion)
    after = [camera.params[3] for camera in pycolmap.Reconstruction(str(tmp_path / "out")).cameras.values()]
    if refine_distortion:
        assert all(abs(k) < 0.05 for k in after)
    else:
        assert after == pytest.approx([0.05] * len(after), abs=1e-12)


def test_the_pose_guided_round_holds_the_distortion_where_the_settings_hold_it(tmp_path: Path):
    """`map.refine_distortion` false holds it in the refinement too; the map stage's retry does not
    (the model is whole by then, and refining it there scored higher: lab/notes/CAPTURES.md 24)."""
    from sara import mapping
    from sara.io import records

    def ctx(settings: dict) -> PairContext:
        return PairContext(names=[], features_path=tmp_path / "f.h5", out_dir=tmp_path, db_path=tmp_path / "db",
                           images_root=tmp_path, conf=make_config("sift-offline", settings))

    for held in (False, True):
        records.mark_done(tmp_path, mapping.STAGE, "k", {"distortion_held": held})
        assert round_.distortion_refined(ctx({}))
        assert not round_.distortion_refined(ctx({"map.refine_distortion": "false"}))


def test_the_round_holds_its_prediction_to_what_the_scorer_counted(model: Path, tmp_path: Path):
    """Where the scorer counts a pair's matches among every keypoint of both views, a count under the
    round's minimum points keeps the pair out however many points the model predicts (a low-texture
    stand-in: 18 of the round's 41 pairs did not verify); a chosen pair it had not scored is scored,
    and the choice made again; a count above the prediction changes nothing."""
    names = read_geometry(model / "sparse" / "0").names
    features = _features_of(pycolmap.Reconstruction(str(model / "sparse" / "0")), tmp_path / "features.h5")
    ctx = PairContext(names=names, images_root=model / "images", features_path=features,
                      db_path=model / "database.db", out_dir=tmp_path, conf=make_config("sift-offline", ON),
                      progress=False)
    chain = [(names[k], names[k + 1]) for k in range(4)]
    sparse = model / "sparse" / "0"
    free, info = round_.select_extra(ctx, chain, sparse)
    assert free and "num_counted" in info
    floor = ctx.conf.rounds.pose_guided_min_points
    held, info = round_.select_extra(ctx, chain, sparse, round_.Counts(dict.fromkeys(free, floor - 1), set(names)))
    assert len(held) == len(free) and not set(held) & set(free)
    assert info["num_counted_too_few"] == len(free) and info["num_counted"] == 0
    plenty, _ = round_.select_extra(ctx, chain, sparse, round_.Counts(dict.fromkeys(free, 10000), set(names)))
    assert plenty == free
    # nothing known: the chosen pairs are scored (each one once), those counted too few give way
    asked: list = []

    def count(pairs):
        asked.extend(pairs)
        return {p: (floor - 1 if p in free else 10_000) for p in pairs}

    again, info = round_.select_extra(ctx, chain, sparse, round_.Counts({}, set(names), count))
    assert again == held and set(free) <= set(asked) and len(asked) == len(set(asked))
    assert info["num_counted"] == len(asked)
    # only pairs of views scored whole are counted
    part, _ = round_.select_extra(ctx, chain, sparse, round_.Counts({}, {names[0]}, count))
    assert part == free


def test_the_round_takes_the_scorers_counts_only_where_it_saw_every_keypoint(tmp_path: Path, monkeypatch):
    """`_counts`: the scorer's counts of the pairs whose two views have no more keypoints than it
    used (`score.num_keypoints`), its scoring for others of them, and none where no view qualifies
    or the matcher is not a nearest-neighbour one."""
    from types import SimpleNamespace

    from sara.io.h5 import Features, write_features
    from sara.pairs.sara import rounds as sara_rounds

    with h5py.File(tmp_path / "features.h5", "w") as h5:
        for name, num in (("a", 100), ("b", 1024), ("c", 1025)):
            write_features(h5, name, Features(np.zeros((num, 2), np.float32), np.zeros((num, 8), np.float32),
                                              np.ones(num, np.float32), (320, 240)))
    header = "name0,name1,num_matches,num_inliers,num_inliers_all,overlap,parallax_deg,weight,accepted,reason,role\n"
    (tmp_path / "scores.csv").write_text(header + "b,a,50,20,21,0.1,5,0.1,true,,tree\n"
                                                  "a,c,50,30,64,0.1,5,0.1,true,,tree\n"
                                                  "b,c,50,9,9,0.1,nan,0,false,few_inliers,rejected\n")
    monkeypatch.setattr(sara_rounds, "score_pairs_of",
                        lambda ctx, pairs: SimpleNamespace(num_inliers_all=[7] * len(pairs)))

    def ctx(preset: str, names=("a", "b", "c")) -> PairContext:
        return PairContext(names=list(names), images_root=tmp_path, features_path=tmp_path / "features.h5",
                           db_path=tmp_path / "database.db", out_dir=tmp_path, conf=make_config(preset),
                           progress=False)

    counts = sara_rounds._counts(ctx("sift-offline"))
    assert counts.known == {("a", "b"): 21} and counts.whole == {"a", "b"}
    assert counts.count([("a", "b")]) == {("a", "b"): 7}
    assert sara_rounds._counts(ctx("aliked-lightglue")) is None
    assert sara_rounds._counts(ctx("sift-offline", names=("c",))) is None


def test_the_round_is_given_the_scorers_counts(model: Path, tmp_path: Path, monkeypatch):
    """`pose_guided_round` hands the scorer's counts to the choice: the first round's counts from
    `scores.csv`, and the scorer for the chosen pairs it had not scored (these views have a few hundred
    keypoints each, so the scorer used them all)."""
    from types import SimpleNamespace

    from sara.pairs.sara import rounds as sara_rounds

    names = read_geometry(model / "sparse" / "0").names
    features = _features_of(pycolmap.Reconstruction(str(model / "sparse" / "0")), tmp_path / "features.h5")
    chain = [(names[k], names[k + 1]) for k in range(4)]
    header = "name0,name1,num_matches,num_inliers,num_inliers_all,overlap,parallax_deg,weight,accepted,reason,role\n"
    rows = "".join(f"{a},{b},50,50,100,0.1,5,0.1,true,,tree\n" for a, b in chain)
    (tmp_path / "scores.csv").write_text(header + rows)
    ctx = PairContext(names=names, images_root=model / "images", features_path=features,
                      db_path=model / "database.db", out_dir=tmp_path, conf=make_config("sift-offline", ON),
                      progress=False)
    floor = ctx.conf.rounds.pose_guided_min_points
    scored: list = []

    def score_pairs_of(ctx, pairs):
        scored.extend(pairs)
        return SimpleNamespace(num_inliers_all=[floor - 1] * len(pairs))

    monkeypatch.setattr(sara_rounds, "score_pairs_of", score_pairs_of)
    extra = sara_rounds.pose_guided_round(ctx, chain, model / "sparse" / "0")
    # every pair the round could take was counted under its minimum: none is matched
    assert scored and extra == []
    info = sara_rounds.records.read_record(tmp_path, round_.STAGE)["info"]
    assert info["num_counted"] == len(scored) and info["num_chosen"] == 0
    # the passes run out: the pairs counted last are still left out, those never counted taken
    monkeypatch.setattr(round_, "COUNT_PASSES", 1)
    scored.clear()
    again, _ = round_.select_extra(ctx, chain, model / "sparse" / "0", sara_rounds._counts(ctx))
    assert scored and again and not set(again) & set(scored)
