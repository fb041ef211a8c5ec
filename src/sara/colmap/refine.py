"""Reading a finished model's geometry as arrays, and refining a model with known poses.

The pycolmap calls of SARA's rounds after mapping (pose-guided pairs, repair) live here:

- `read_geometry`: poses, pinhole intrinsics, 3D points and their tracks of a model folder, as
  plain arrays (what the covisibility prediction of `sara.selection.pose_guided` needs);
- `triangulate_new_matches`: the same triangulator keeping the model's points, so that a mapper
  continuing from the model finds 3D points on the features that newly matched views share with it;
- `triangulate_and_adjust`: COLMAP's point triangulator with the poses of a model held fixed
  (`pycolmap.triangulate_points`), then a global bundle adjustment that frees the poses again
  (optionally followed by `extend_tracks` and one more adjustment);
- `extend_and_adjust`: `extend_tracks` (`sara.colmap.tracks`: longer tracks without matching more
  pairs) on a model, then a global bundle adjustment.

Conventions (COLMAP's): poses are ``cam_from_world`` (``x_cam = R @ X + t``), pixels have the
centre of the top-left pixel at (0.5, 0.5).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from .sfm import bundle_adjust
from .tracks import TrackExtension, extend_tracks

#: the most iterations of a refinement's adjustments, after re-triangulation and after a track
#: extension (pycolmap's default: 100). The model's poses come from a mapper that adjusted them:
#: every shared scene converges within 18, and what the cap cuts is the slow tail of large models.
REFINE_BA_MAX_ITERATIONS = 30


@dataclass(frozen=True)
class ModelGeometry:
    """A model's registered views and points; rows of the per-view arrays follow `names` (sorted).

    Attributes:
        names: registered image names, sorted (V).
        rotations: (V, 3, 3) float64 cam_from_world.
        translations: (V, 3) float64 cam_from_world.
        focal_px: (V,) float64 mean focal length in pixels.
        principal_px: (V, 2) float64 principal point in pixels.
        sizes_px: (V, 2) float64 image width and height in pixels.
        points_xyz: (P, 3) float64 world frame.
        obs_point: (M,) int64 row of `points_xyz` of each observation.
        obs_view: (M,) int64 row of `names` of each observation.
    """

    names: list[str]
    rotations: np.ndarray
    translations: np.ndarray
    focal_px: np.ndarray
    principal_px: np.ndarray
    sizes_px: np.ndarray
    points_xyz: np.ndarray
    obs_point: np.ndarray
    obs_view: np.ndarray

    @property
    def centers(self) -> np.ndarray:
        """(V, 3) camera centres in the world frame: C = -R^T t."""
        return -np.einsum("nji,nj->ni", self.rotations, self.translations)


def read_geometry(model_dir: Path) -> ModelGeometry:
    """The registered views, their pinhole intrinsics (distortion left out) and the tracks of a model."""
    rec = pycolmap.Reconstruction(str(model_dir))
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    row = {im.image_id: k for k, im in enumerate(images)}
    poses = [im.cam_from_world() for im in images]
    cams = [rec.cameras[im.camera_id] for im in images]
    xyz = np.array([p.xyz for p in rec.points3D.values()], dtype=np.float64).reshape(-1, 3)
    obs_point, obs_view = [], []
    for k, point in enumerate(rec.points3D.values()):
        for element in point.track.elements:
            if element.image_id in row:
                obs_point.append(k)
                obs_view.append(row[element.image_id])
    return ModelGeometry(
        names=[im.name for im in images],
        rotations=np.array([p.rotation.matrix() for p in poses], dtype=np.float64).reshape(-1, 3, 3),
        translations=np.array([p.translation for p in poses], dtype=np.float64).reshape(-1, 3),
        focal_px=np.array([np.mean([c.focal_length_x, c.focal_length_y]) for c in cams], dtype=np.float64),
        principal_px=np.array([[c.principal_point_x, c.principal_point_y] for c in cams],
                              dtype=np.float64).reshape(-1, 2),
        sizes_px=np.array([[c.width, c.height] for c in cams], dtype=np.float64).reshape(-1, 2),
        points_xyz=xyz,
        obs_point=np.asarray(obs_point, dtype=np.int64),
        obs_view=np.asarray(obs_view, dtype=np.int64),
    )


def _triangulate(model_dir: Path, db_path: Path, image_dir: Path, work_dir: Path, *, clear_points: bool,
                 num_threads: int, seed: int) -> pycolmap.Reconstruction:
    """COLMAP's point triangulator over every match of the database, the model's poses fixed."""
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = num_threads
    options.random_seed = seed
    options.triangulation.random_seed = seed
    return pycolmap.triangulate_points(pycolmap.Reconstruction(str(model_dir)), str(db_path), str(image_dir),
                                       str(work_dir), clear_points=clear_points, options=options,
                                       refine_intrinsics=False)


def triangulate_new_matches(model_dir: Path, db_path: Path, image_dir: Path, out_dir: Path, *,
                            num_threads: int = -1, seed: int = 0) -> int:
    """Write `model_dir` with its points completed from every match of `db_path` (poses fixed, the
    existing points kept) to `out_dir`; returns the number of 3D points.

    Continuing COLMAP's mapper straight from a model written before new pairs were matched left
    views out that those pairs join to it (templeSparseRing: 13 of 16 registered, 16 after this).
    """
    out_dir = Path(out_dir)
    shutil.rmtree(out_dir, ignore_errors=True)
    out_dir.mkdir(parents=True)
    rec = _triangulate(model_dir, db_path, image_dir, out_dir, clear_points=False, num_threads=num_threads, seed=seed)
    rec.write(str(out_dir))
    return int(rec.num_points3D())


def triangulate_and_adjust(model_dir: Path, db_path: Path, image_dir: Path, out_dir: Path, *,
                           num_threads: int = -1, seed: int = 0, features_path: Path | None = None,
                           extension: TrackExtension | None = None, refine_distortion: bool = True) -> dict[str, float]:
    """Re-triangulate every match of the database with the model's poses fixed, then bundle-adjust all.

    COLMAP's point triangulator (`pycolmap.triangulate_points`: triangulation, track merging and
    completion, re-triangulation, with the poses held constant), then a global bundle adjustment of
    poses and points (focal length and radial distortion refined, principal point fixed, as in
    COLMAP's mapper; the distortion held with `refine_distortion` False); with `extension`, the
    tracks are then extended (`extend_tracks`, keypoints and descriptors of `features_path`) and
    adjusted once more. Writes the result to `out_dir` (replaced); returns counts.
    """
    out_dir = Path(out_dir)
    tmp = out_dir.with_name(out_dir.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    rec = _triangulate(model_dir, db_path, image_dir, tmp, clear_points=True, num_threads=num_threads, seed=seed)
    adjust_refined(rec, refine_distortion=refine_distortion)
    added = 0
    if extension is not None and features_path is not None:
        # on the adjusted poses, whose projections are closer to the keypoints; then adjust again
        added = extend_tracks(rec, features_path, extension)
        if added:
            adjust_refined(rec, refine_distortion=refine_distortion)
    return _write_model(rec, out_dir, added)


def extend_and_adjust(model_dir: Path, out_dir: Path, features_path: Path, extension: TrackExtension = TrackExtension(),
                      *, refine_distortion: bool = True) -> dict[str, float]:
    """`extend_tracks` on the model of `model_dir`, then a global bundle adjustment when anything
    was added; writes the result to `out_dir` (replaced) and returns counts."""
    out_dir = Path(out_dir)
    rec = pycolmap.Reconstruction(str(model_dir))
    added = extend_tracks(rec, Path(features_path), extension)
    if added:
        adjust_refined(rec, refine_distortion=refine_distortion)
    return _write_model(rec, out_dir, added)


def adjust_refined(rec: pycolmap.Reconstruction, *, refine_distortion: bool = True) -> None:
    """A refinement's global adjustment (after re-triangulation, after `extend_tracks`), within
    `REFINE_BA_MAX_ITERATIONS`; the cameras' distortion held when `refine_distortion` is False (as
    the mapper held it: `map.refine_distortion`, `stages.map.distortion_held`).

    The model was adjusted by the mapper before its points were re-triangulated or its tracks grew;
    what was added moves it a little. On the 1,000-image synthetic world (979 views, 295,698
    observations added) the adjustment after the extension ran its 100 iterations in 70.4 s without
    converging; 30 gave the same AUC@1 to 0.0001 in 23.5 s, and so did 10 in 11.0 s, against 0.8689
    without the extension. The adjustment after re-triangulation there (996 views) took 70
    iterations, 62 s, for a cost of 0.4076 -> 0.4046 px (lab/notes/SCALE.md)."""
    options = pycolmap.BundleAdjustmentOptions()
    options.ceres.solver_options.max_num_iterations = REFINE_BA_MAX_ITERATIONS
    options.refine_extra_params = refine_distortion
    bundle_adjust(rec, options)


def _write_model(rec: pycolmap.Reconstruction, out_dir: Path, added: int) -> dict[str, float]:
    """Write `rec` to `out_dir` (replaced, through `<out_dir>.partial`); its counts."""
    tmp = out_dir.with_name(out_dir.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    rec.write(str(tmp))
    if out_dir.exists():
        shutil.rmtree(out_dir)
    tmp.rename(out_dir)
    return {"num_points3d": float(rec.num_points3D()), "num_registered": float(rec.num_reg_images()),
            "observations_added": float(added)}
