"""`sara export OUT DEST --format 3dgs|nerfstudio|colmap`: a sara model in the layout other tools read.

- ``3dgs``: what 3D Gaussian Splatting's ``train.py -s DEST`` loads (its
  ``scene/dataset_readers.py``): ``DEST/images/<name>`` undistorted, ``DEST/sparse/0`` with
  ``cameras.bin``, ``images.bin`` and ``points3D.bin`` whose cameras are all PINHOLE. 3DGS opens
  ``images/<basename of the name>``, so images in sub-folders are renamed ``sub_name.jpg``.
- ``nerfstudio``: what its ``nerfstudio-data`` parser loads: ``DEST/transforms.json`` with
  ``DEST/images/<name>`` and ``DEST/sparse_pc.ply``, written the way ``ns-process-data``'s
  ``colmap_to_json`` writes them (camera-to-world in OpenGL axes, world z up, ``applied_transform``).
  The images are copied as they are, with COLMAP's distortion as OpenCV ``k1 k2 p1 p2``;
  ``undistort=True`` (or a camera model nerfstudio has no parameters for) writes undistorted ones.
- ``colmap``: ``DEST/database.db``, ``DEST/sparse/N`` and ``DEST/project.ini`` naming the
  database and the image folder, for ``colmap gui --project_path DEST/project.ini`` (COLMAP 4.x:
  the database has COLMAP 4's rig and frame tables) or
  ``colmap gui --import_path DEST/sparse/0 --database_path DEST/database.db --image_path IMAGES``.

`export` reads the model `OUT/sparse/<model_index>` of a `sara run` and the image folder recorded in
`OUT/run.json`. It replaces what the format writes in DEST (the folders `images` and `sparse`, the
files `transforms.json`, `sparse_pc.ply`, `database.db`, `project.ini`) and leaves anything else there.
"""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import colmap
from .colmap import model
from .io import read_json, write_text_atomic

logger = logging.getLogger(__name__)

FORMATS = ("3dgs", "nerfstudio", "colmap")
NERFSTUDIO_PLY = "sparse_pc.ply"

# COLMAP's camera models that nerfstudio's `parse_colmap_camera_params` turns into OpenCV parameters:
# model -> (nerfstudio camera_model, names of the COLMAP parameters after the focal lengths and centre)
_NERFSTUDIO_MODELS: dict[str, tuple[str, tuple[str, ...]]] = {
    "SIMPLE_PINHOLE": ("OPENCV", ()),
    "PINHOLE": ("OPENCV", ()),
    "SIMPLE_RADIAL": ("OPENCV", ("k1",)),
    "RADIAL": ("OPENCV", ("k1", "k2")),
    "OPENCV": ("OPENCV", ("k1", "k2", "p1", "p2")),
    "OPENCV_FISHEYE": ("OPENCV_FISHEYE", ("k1", "k2", "k3", "k4")),
}

# COLMAP's axes (x right, y down, z forward) to OpenGL's (x right, y up, z back): flip y and z
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0])
# nerfstudio's world: z up instead of COLMAP's usual -y: (x, y, z) -> (x, z, -y), as colmap_to_json
APPLIED_TRANSFORM = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]])


def export(out_dir: Path, dest: Path, fmt: str = "3dgs", *, model_index: int = 0, images: Path | None = None,
           undistort: bool = False, max_image_size: int = -1, progress: bool = True,
           verbose_colmap: bool = False) -> Path:
    """Export model `OUT/sparse/<model_index>` of a sara run to `dest` in format `fmt`; returns `dest`.

    images: the image folder (default: the one recorded in `OUT/run.json`).
    undistort: nerfstudio only (3dgs always undistorts, colmap never does).
    max_image_size: with undistortion, also downscale the longer image side to this (px; -1: keep).
    progress: progress bars over the images.
    verbose_colmap: COLMAP's own log (the undistorter's) on the console instead of `OUT/logs`.
    Raises FileNotFoundError when OUT has no model or the images are missing, ValueError for a bad format.
    """
    writers: dict[str, Callable[..., None]] = {"3dgs": _export_3dgs, "nerfstudio": _export_nerfstudio,
                                               "colmap": _export_colmap}
    if fmt not in writers:
        raise ValueError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    out_dir, dest = Path(out_dir), Path(dest)
    model_dir = find_model(out_dir, model_index)
    images_root = Path(images) if images is not None else recorded_images_root(out_dir)
    if not images_root.is_dir():
        raise FileNotFoundError(f"image folder {images_root} not found; pass the images the model was made from")
    _check_destination(out_dir, dest, images_root)
    dest.mkdir(parents=True, exist_ok=True)
    colmap.send_log_to(out_dir / "logs", verbose=verbose_colmap)
    writers[fmt](model_dir, images_root, dest, out_dir=out_dir, undistort=undistort, max_image_size=max_image_size,
                 progress=progress)
    logger.info("exported %s (%s) to %s", model_dir, fmt, dest)
    return dest


def find_model(out_dir: Path, model_index: int = 0) -> Path:
    """`out_dir/sparse/<model_index>`, or a clear FileNotFoundError when the run made no model."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise FileNotFoundError(f"output folder not found: {out_dir}")
    models = model.find_models(out_dir / "sparse")
    if not models:
        raise FileNotFoundError(f"{out_dir} holds no model (no sparse/0): run `sara run IMAGES {out_dir}` first, "
                                "or see its report for why mapping failed")
    wanted = out_dir / "sparse" / str(model_index)
    if wanted not in models:
        raise FileNotFoundError(f"{out_dir} has no model {model_index}; it has {', '.join(p.name for p in models)}")
    return wanted


def recorded_images_root(out_dir: Path) -> Path:
    """The image folder a run's model was made from (the upright copies when the run made them)."""
    run_json = Path(out_dir) / "run.json"
    if not run_json.exists():
        raise FileNotFoundError(f"{out_dir} has no run.json to name the image folder; pass the images folder")
    run = read_json(run_json)
    upright = Path(out_dir) / "images_upright"
    if run.get("config", {}).get("images", {}).get("exif_orientation") == "apply" and upright.is_dir():
        return upright
    if not run.get("images_root"):
        raise FileNotFoundError(f"{run_json} names no image folder; pass the images folder")
    return Path(run["images_root"])


def _check_destination(out_dir: Path, dest: Path, images_root: Path) -> None:
    dest_r, out_r, images_r = dest.resolve(), out_dir.resolve(), images_root.resolve()
    if dest_r == out_r or out_r.is_relative_to(dest_r) or dest_r == images_r or images_r.is_relative_to(dest_r):
        raise ValueError(f"export destination {dest} would overwrite the run or its images; choose a new folder")


# ---------------------------------------------------------------------------------------------
# 3D Gaussian Splatting
# ---------------------------------------------------------------------------------------------


def flat_names(names: list[str]) -> dict[str, str]:
    """name -> a file name without folders, unique: `a/b.jpg` -> `a_b.jpg` (3DGS opens images/<basename>)."""
    mapping = {name: name.replace("/", "_") for name in names}
    if len(set(mapping.values())) < len(mapping):
        seen: dict[str, str] = {}
        for name, flat in mapping.items():
            if flat in seen:
                raise ValueError(f"images {seen[flat]!r} and {name!r} both become {flat!r} without folders; "
                                 "rename one of them")
            seen[flat] = name
    return mapping


def _export_3dgs(model_dir: Path, images_root: Path, dest: Path, *, max_image_size: int, progress: bool,
                 **_: object) -> None:
    _undistort_flat(model_dir, images_root, dest, max_image_size, progress)


def _undistort_flat(model_dir: Path, images_root: Path, dest: Path, max_image_size: int, progress: bool) -> Path:
    """Undistorted images as `dest/images/<flat name>` and their PINHOLE model in `dest/sparse/0`."""
    names = model.read_model(model_dir).names
    rename = flat_names(names)
    with tempfile.TemporaryDirectory(prefix=".sara-export-", dir=dest) as tmp:
        images_dir, sparse_dir = model.undistort_images(model_dir, images_root, Path(tmp),
                                                        max_image_size=max_image_size)
        for folder in (dest / "images", dest / "sparse"):
            if folder.exists():
                shutil.rmtree(folder)
        (dest / "images").mkdir()
        for name, flat in tqdm(rename.items(), desc="undistorted images", unit="img", disable=not progress):
            shutil.move(str(images_dir / name), str(dest / "images" / flat))
        model.write_model(sparse_dir, dest / "sparse" / "0", rename=rename)
    return dest / "sparse" / "0"


# ---------------------------------------------------------------------------------------------
# nerfstudio
# ---------------------------------------------------------------------------------------------


def nerfstudio_camera(camera: model.Intrinsics) -> dict[str, float | int | str]:
    """transforms.json intrinsics of a COLMAP camera, as nerfstudio's parse_colmap_camera_params names them."""
    if camera.model not in _NERFSTUDIO_MODELS:
        raise ValueError(f"nerfstudio has no parameters for COLMAP camera model {camera.model}: undistort first")
    ns_model, extra_names = _NERFSTUDIO_MODELS[camera.model]
    p = camera.params
    if camera.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy, extra = p[1], p[2], p[3:]
    else:
        fx, fy, cx, cy, extra = p[0], p[1], p[2], p[3], p[4:]
    out: dict[str, float | int | str] = {"w": camera.width, "h": camera.height, "fl_x": float(fx),
                                         "fl_y": float(fy), "cx": float(cx), "cy": float(cy)}
    if ns_model == "OPENCV":
        out.update(k1=0.0, k2=0.0, p1=0.0, p2=0.0)
    out.update({key: float(value) for key, value in zip(extra_names, extra)})
    out["camera_model"] = ns_model
    return out


def nerfstudio_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) camera-to-world in nerfstudio's convention from a COLMAP cam_from_world (R (3, 3), t (3,)).

    OpenGL camera axes (x right, y up, z back) and the world turned by `APPLIED_TRANSFORM`.
    """
    c2w = np.eye(4)
    c2w[:3, :3] = APPLIED_TRANSFORM[:, :3] @ rotation.T @ OPENCV_TO_OPENGL
    c2w[:3, 3] = APPLIED_TRANSFORM[:, :3] @ (-rotation.T @ translation)
    return c2w


def _export_nerfstudio(model_dir: Path, images_root: Path, dest: Path, *, undistort: bool, max_image_size: int,
                       progress: bool, **_: object) -> None:
    data = model.read_model(model_dir)
    if undistort or any(c.model not in _NERFSTUDIO_MODELS for c in data.cameras.values()):
        model_dir = _undistort_flat(model_dir, images_root, dest, max_image_size, progress)
        data = model.read_model(model_dir)
        rename = {name: name for name in data.names}
    else:
        rename = flat_names(data.names)
        _copy_images(images_root, dest / "images", rename, progress)
    meta = nerfstudio_transforms(data, rename)
    write_ply(dest / NERFSTUDIO_PLY, data.points_xyz @ APPLIED_TRANSFORM[:, :3].T, data.points_rgb)
    write_text_atomic(dest / "transforms.json", json.dumps(meta, indent=2) + "\n")


def nerfstudio_transforms(data: model.ModelData, rename: dict[str, str]) -> dict:
    """The content of transforms.json: shared intrinsics when all images share one camera, else per frame.

    rename: image name in the model -> file name under `images/`.
    """
    cameras = {cid: nerfstudio_camera(cam) for cid, cam in data.cameras.items()}
    kinds = {c["camera_model"] for c in cameras.values()}
    if len(kinds) > 1:
        raise ValueError(f"nerfstudio needs one camera type for all images, the model has {sorted(kinds)}")
    shared = len(set(data.camera_ids.tolist())) == 1
    meta: dict = {"camera_model": kinds.pop()}
    if shared:
        meta.update({k: v for k, v in cameras[int(data.camera_ids[0])].items() if k != "camera_model"})
    frames = []
    for i, name in enumerate(data.names):
        frame = {"file_path": f"images/{rename[name]}",
                 "transform_matrix": nerfstudio_transform(data.rotations[i], data.translations[i]).tolist(),
                 "colmap_im_id": int(data.image_ids[i])}
        if not shared:
            frame.update({k: v for k, v in cameras[int(data.camera_ids[i])].items() if k != "camera_model"})
        frames.append(frame)
    meta["frames"] = frames
    meta["applied_transform"] = APPLIED_TRANSFORM.tolist()
    meta["ply_file_path"] = NERFSTUDIO_PLY
    return meta


def _copy_images(src_root: Path, dst_root: Path, rename: dict[str, str], progress: bool) -> None:
    if dst_root.exists():
        shutil.rmtree(dst_root)
    dst_root.mkdir(parents=True)
    for name, flat in tqdm(rename.items(), desc="copy images", unit="img", disable=not progress):
        shutil.copy2(src_root / name, dst_root / flat)


def write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> Path:
    """A point cloud as ASCII PLY: float x y z, uint8 red green blue (the properties nerfstudio writes).

    xyz: (P, 3) float; rgb: (P, 3) uint8.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    rgb = np.asarray(rgb, dtype=np.uint8).reshape(-1, 3)
    header = ["ply", "format ascii 1.0", f"element vertex {len(xyz)}"]
    header += [f"property float {axis}" for axis in "xyz"]
    header += [f"property uint8 {c}" for c in ("red", "green", "blue")]
    header.append("end_header")
    rows = [f"{x:.8f} {y:.8f} {z:.8f} {r} {g} {b}" for (x, y, z), (r, g, b) in zip(xyz.tolist(), rgb.tolist())]
    write_text_atomic(Path(path), "\n".join(header + rows) + "\n")
    return Path(path)


# ---------------------------------------------------------------------------------------------
# COLMAP
# ---------------------------------------------------------------------------------------------


def _export_colmap(model_dir: Path, images_root: Path, dest: Path, *, out_dir: Path, **_: object) -> None:
    db_src = out_dir / "database.db"
    if not db_src.exists():
        raise FileNotFoundError(f"{db_src} not found: the colmap export needs the run's database")
    colmap.copy_database(db_src, dest / "database.db")
    if (dest / "sparse").exists():
        shutil.rmtree(dest / "sparse")
    for src in model.find_models(out_dir / "sparse"):
        model.write_model(src, dest / "sparse" / src.name)
    config = read_json(out_dir / "run.json").get("config", {}) if (out_dir / "run.json").exists() else {}
    write_text_atomic(dest / "project.ini", project_ini(dest / "database.db", images_root, config))


def project_ini(database: Path, images_root: Path, config: dict) -> str:
    """A COLMAP project file: the database, the image folder and the mapper settings sara ran with.

    COLMAP rejects keys that a command does not register (boost program_options), so only the paths
    and `Mapper.*` options are written, which `colmap gui` and `colmap mapper` both register.
    """
    mapper = config.get("map", {})
    lines = [f"database_path={Path(database).resolve()}", f"image_path={Path(images_root).resolve()}",
             "[Mapper]", f"min_model_size={mapper.get('min_model_size', 10)}",
             f"abs_pose_min_num_inliers={mapper.get('abs_pose_min_num_inliers', 30)}",
             f"abs_pose_min_inlier_ratio={mapper.get('abs_pose_min_inlier_ratio', 0.25)}"]
    return "\n".join(lines) + "\n"
