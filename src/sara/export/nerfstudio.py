"""The ``nerfstudio`` export: what its ``nerfstudio-data`` parser loads.

``DEST/transforms.json`` with ``DEST/images/<name>`` and ``DEST/sparse_pc.ply``, written the way
``ns-process-data``'s ``colmap_to_json`` writes them (camera-to-world in OpenGL axes, world z up,
``applied_transform``). The images are copied as they are, with COLMAP's distortion as OpenCV
``k1 k2 p1 p2``; ``undistort=True`` (or a camera model nerfstudio has no parameters for) writes
undistorted ones.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from .. import masks
from ..colmap import model
from ..io import write_text_atomic
from .common import ExportJob, copy_images, flat_names, jpeg_name, undistort_flat

logger = logging.getLogger(__name__)

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


def write(job: ExportJob) -> None:
    """For nerfstudio, DEST/transforms.json, DEST/images (undistorted with --undistort), DEST/sparse_pc.ply."""
    data = model.read_model(job.model_dir)
    undistorted = job.undistort or any(c.model not in _NERFSTUDIO_MODELS for c in data.cameras.values())
    if undistorted:
        model_dir = undistort_flat(job.model_dir, job.images_root, job.dest, job.max_image_size, job.progress)
        data = model.read_model(model_dir)
        rename = {name: name for name in data.names}
    else:
        rename = {name: jpeg_name(flat) for name, flat in flat_names(data.names).items()}
        copy_images(job.images_root, job.dest / "images", rename, job.progress)
    meta = nerfstudio_transforms(data, rename)
    _add_masks(job, data, rename, meta, undistorted)
    write_ply(job.dest / NERFSTUDIO_PLY, data.points_xyz @ APPLIED_TRANSFORM[:, :3].T, data.points_rgb)
    write_text_atomic(job.dest / "transforms.json", json.dumps(meta, indent=2) + "\n")


def _add_masks(job: ExportJob, data: model.ModelData, rename: dict[str, str], meta: dict, undistorted: bool) -> None:
    """The run's masks (`--masks`) as `DEST/masks/<image>.png`, each frame's `mask_path`, so that
    nerfstudio leaves out what the reconstruction did; not beside undistorted images, whose pixels
    moved."""
    folder = masks.run_mask_folder(job.out_dir)
    if folder is None:
        return
    if not folder.exists():
        logger.warning("the run's masks (%s) are gone: exported without them", folder)
        return
    if undistorted:
        logger.warning("the run's masks are not exported beside undistorted images; export without --undistort "
                       "to keep them")
        return
    sizes = {name: (data.cameras[int(c)].width, data.cameras[int(c)].height) for name, c in zip(data.names,
                                                                                               data.camera_ids)}
    written = masks.write_masks(folder, rename, sizes, job.dest / "masks")
    for frame, name in zip(meta["frames"], data.names):
        if name in written:
            frame["mask_path"] = written[name]


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
