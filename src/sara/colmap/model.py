"""COLMAP models as plain numpy data, and the model and database writes that exports need.

The pycolmap calls of `sara.export`, `sara.report` and `sara.hloc` that `sara.colmap` itself does
not offer are here, so a pycolmap rename is mended inside this package. Conventions (COLMAP's):

- poses are ``cam_from_world``: ``x_cam = R @ X_world + t``; camera centres ``C = -R.T @ t``;
- camera axes x right, y down, z forward (OpenCV);
- pixels: the centre of the top-left pixel is (0.5, 0.5).
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from .reconstruction import has_model


@dataclass(frozen=True)
class Intrinsics:
    """One camera: COLMAP model name, image size in pixels and parameters in COLMAP's order."""

    camera_id: int
    model: str  # "PINHOLE", "SIMPLE_RADIAL", ...
    width: int
    height: int
    params: np.ndarray  # (P,) float64, e.g. PINHOLE fx, fy, cx, cy; SIMPLE_RADIAL f, cx, cy, k


@dataclass(frozen=True)
class ModelData:
    """A reconstruction read into arrays. Rows of the per-image arrays follow `names` (sorted)."""

    cameras: dict[int, Intrinsics]
    names: list[str]  # registered images, sorted
    image_ids: np.ndarray  # (N,) int64
    camera_ids: np.ndarray  # (N,) int64
    rotations: np.ndarray  # (N, 3, 3) float64, cam_from_world
    translations: np.ndarray  # (N, 3) float64, cam_from_world
    num_observations: np.ndarray  # (N,) int64, keypoints of the image with a 3D point
    points_xyz: np.ndarray  # (P, 3) float64, world frame
    points_rgb: np.ndarray  # (P, 3) uint8
    track_lengths: np.ndarray  # (P,) int64, images that see the point
    points_error_px: np.ndarray  # (P,) float64, mean reprojection error of each point

    @property
    def centers(self) -> np.ndarray:
        """(N, 3) camera centres in the world frame: C = -R^T t."""
        return -np.einsum("nji,nj->ni", self.rotations, self.translations)

    @property
    def viewing_directions(self) -> np.ndarray:
        """(N, 3) unit optical axes (camera +z) in the world frame: the third row of R."""
        return self.rotations[:, 2, :].copy()

    def camera_of(self, index: int) -> Intrinsics:
        return self.cameras[int(self.camera_ids[index])]


def find_models(sparse_dir: Path) -> list[Path]:
    """The numbered model folders `sparse_dir/0`, `sparse_dir/1`, ... that hold a model, in order."""
    sparse_dir = Path(sparse_dir)
    if not sparse_dir.is_dir():
        return []
    found = [p for p in sparse_dir.iterdir() if p.is_dir() and p.name.isdigit() and has_model(p)]
    return sorted(found, key=lambda p: int(p.name))


def _read(path: Path) -> pycolmap.Reconstruction:
    path = Path(path)
    if not has_model(path):
        raise FileNotFoundError(f"no COLMAP model (cameras, images, points3D .bin or .txt) in {path}")
    return pycolmap.Reconstruction(str(path))


def read_model(path: Path) -> ModelData:
    """Read a COLMAP model folder (binary or text) into `ModelData`."""
    rec = _read(path)
    cameras = {int(cid): Intrinsics(int(cid), cam.model_name, int(cam.width), int(cam.height),
                                    np.asarray(cam.params, dtype=np.float64).copy())
               for cid, cam in rec.cameras.items()}
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    poses = [im.cam_from_world() for im in images]
    points = list(rec.points3D.values())
    return ModelData(
        cameras=cameras,
        names=[im.name for im in images],
        image_ids=np.array([im.image_id for im in images], dtype=np.int64),
        camera_ids=np.array([im.camera_id for im in images], dtype=np.int64),
        rotations=np.array([p.rotation.matrix() for p in poses], dtype=np.float64).reshape(-1, 3, 3),
        translations=np.array([p.translation for p in poses], dtype=np.float64).reshape(-1, 3),
        num_observations=np.array([im.num_points3D for im in images], dtype=np.int64),
        points_xyz=np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3),
        points_rgb=np.array([p.color for p in points], dtype=np.uint8).reshape(-1, 3),
        track_lengths=np.array([p.track.length() for p in points], dtype=np.int64),
        points_error_px=np.array([p.error for p in points], dtype=np.float64),
    )


def write_model(src: Path, dst: Path, *, rename: Mapping[str, str] | None = None, text: bool = False,
                keep: Collection[str] | None = None) -> Path:
    """Copy the model in `src` to `dst` (binary, or text), renaming images on the way.

    rename: old image name -> new image name (images not listed keep their name).
    keep: the (new) names of the images to keep posed; the others lose their pose and are left out
    of the written model (None: every image).
    """
    rec = _read(src)
    for image in rec.images.values():
        if rename and image.name in rename:
            image.name = rename[image.name]
        if keep is not None and image.name not in keep and image.has_pose:
            rec.deregister_frame(image.frame_id)
    dst = Path(dst)
    dst.mkdir(parents=True, exist_ok=True)
    if text:
        rec.write_text(str(dst))
    else:
        rec.write_binary(str(dst))
    return dst


def undistort_images(model_dir: Path, image_dir: Path, out_dir: Path, *, max_image_size: int = -1,
                     num_threads: int = -1) -> tuple[Path, Path]:
    """COLMAP's image undistorter: PINHOLE cameras and resampled images.

    Writes `out_dir/images/<name>` (the model's image names) and the undistorted model; returns
    (images folder, model folder). `max_image_size` > 0 also downscales the longer side to it.
    COLMAP's stereo scripts and folders, which exports do not need, are removed.
    """
    out_dir = Path(out_dir)
    options = pycolmap.UndistortCameraOptions()
    options.max_image_size = int(max_image_size)
    with tempfile.TemporaryDirectory(prefix=".undistort-", dir=_existing_parent(out_dir)) as tmp:
        pycolmap.undistort_images(str(tmp), str(model_dir), str(image_dir), output_type="COLMAP",
                                  undistort_options=options, num_threads=num_threads)
        out_dir.mkdir(parents=True, exist_ok=True)
        for name in ("images", "sparse"):
            if (out_dir / name).exists():
                shutil.rmtree(out_dir / name)
            shutil.move(str(Path(tmp) / name), str(out_dir / name))
    return out_dir / "images", out_dir / "sparse"


def _existing_parent(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    return path


# ---------------------------------------------------------------------------------------------
# Databases built from arrays (features that COLMAP did not extract, e.g. hloc's)
# ---------------------------------------------------------------------------------------------


def _prior_camera(width: int, height: int, camera_model: str, focal_length_factor: float) -> pycolmap.Camera:
    focal = float(focal_length_factor) * max(int(width), int(height))
    return pycolmap.Camera.create_from_model_name(0, camera_model, focal, int(width), int(height))


def database_from_sizes(db_path: Path, image_sizes: Mapping[str, tuple[int, int]], *,
                        camera_model: str = "SIMPLE_RADIAL", focal_length_factor: float = 1.2) -> dict[str, int]:
    """A new database with one camera per image (COLMAP's focal prior), a trivial rig and frame each.

    image_sizes: name -> (width, height) in pixels. Replaces an existing file; returns name -> image_id.
    """
    db_path = Path(db_path)
    db_path.unlink(missing_ok=True)
    ids: dict[str, int] = {}
    db = pycolmap.Database.open(str(db_path))
    try:
        for name, (width, height) in image_sizes.items():
            camera = _prior_camera(width, height, camera_model, focal_length_factor)
            camera.camera_id = db.write_camera(camera)
            rig = pycolmap.Rig()
            rig.add_ref_sensor(camera.sensor_id)
            rig_id = db.write_rig(rig)
            image = pycolmap.Image(name=name, camera_id=camera.camera_id)
            image.image_id = db.write_image(image)
            frame = pycolmap.Frame()
            frame.rig_id = rig_id
            frame.add_data_id(image.data_id)
            db.write_frame(frame)
            ids[name] = int(image.image_id)
    finally:
        db.close()
    return ids


def database_pairs(db_path: Path) -> tuple[list[str], dict[tuple[str, str], int]]:
    """Image names of a database (sorted) and its verified pairs: (name0, name1) with name0 < name1 -> inliers."""
    db = pycolmap.Database.open(str(db_path))
    try:
        names = {im.image_id: im.name for im in db.read_all_images()}
        pair_ids, num_inliers = db.read_two_view_geometry_num_inliers()
    finally:
        db.close()
    verified = {}
    for pair_id, count in zip(pair_ids, num_inliers):
        if int(count) <= 0:
            continue
        a, b = sorted(names[int(i)] for i in pycolmap.pair_id_to_image_pair(int(pair_id)))
        verified[(a, b)] = int(count)
    return sorted(names.values()), verified

