"""`sara.export`: each format is loaded the way its consumer loads it.

- COLMAP: pycolmap itself (COLMAP's own reader) opens the exported database and models.
- 3DGS (graphdeco-inria/gaussian-splatting, not on PyPI): `read_3dgs` below mirrors what
  `scene/__init__.py` and `scene/dataset_readers.py` do for `train.py -s DEST`:
  `Scene.__init__` takes the COLMAP branch when `DEST/sparse` exists; `readColmapSceneInfo` reads
  `sparse/0/images.bin` and `cameras.bin` with `scene/colmap_loader.py`'s `read_extrinsics_binary`
  (struct "idddddddi", a NUL-terminated name, "Q" points, "ddq" per point) and
  `read_intrinsics_binary` ("iiQQ", then the model's parameters as doubles), and
  `read_points3D_binary` ("QdddBBBd", "Q" track length, "ii" per element) for `points3D.ply`;
  `readColmapCameras` asserts the model is SIMPLE_PINHOLE or PINHOLE, takes FovX / FovY from the
  focal lengths and the camera size (`focal2fov`) and opens `images/<basename of the name>`.
  Its renderer (`utils/graphics_utils.py` `getProjectionMatrix`) has a symmetric frustum: the
  principal point must be the image centre, which the geometric test checks by projecting.
- nerfstudio (not on PyPI in a light form): `read_nerfstudio` mirrors
  `nerfstudio/data/dataparsers/nerfstudio_dataparser.py` `Nerfstudio._generate_dataparser_outputs`:
  `transforms.json` in the data folder (L96), shared intrinsics when `fl_x`... are top-level keys
  and per-frame otherwise (L104-154 assert each key), distortion `k1 k2 k3 k4 p1 p2` (L155-166,
  L279-291), `transform_matrix` 4x4 per frame (L170, L236), `camera_model` a key of
  `CAMERA_MODEL_TO_TYPE` (L268), `applied_transform` 3x4 (L323), `ply_file_path` relative to the
  data folder (L353), images opened with PIL by `_get_fname` (L461-491). Rays are then generated as
  `nerfstudio/cameras/cameras.py` `_generate_rays_from_coords` does (L622-656: (x - cx) / fx,
  undistortion, y flipped, z = -1, rotated by camera_to_worlds), which the geometric test replays.
"""

from __future__ import annotations

import json
import math
import os
import struct
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image

from sara.colmap.model import Intrinsics, ModelData
from sara.export import FORMATS, ExportJob, export
from sara.export.colmap_project import project_ini
from sara.export.common import flat_names
from sara.export.nerfstudio import nerfstudio_camera, nerfstudio_transforms

WIDTH, HEIGHT = 320, 240
SUBFOLDER = "left"  # half the images live in a sub-folder, as with `sara run --recursive`


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A sara output folder made by hand: a SIMPLE_RADIAL (k = 0.05) model of 6 rendered images."""
    root = tmp_path_factory.mktemp("export")
    out, images = root / "out", root / "images"
    pycolmap.set_random_seed(0)
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_cameras_per_rig, opts.num_frames_per_rig = 1, 1, 6
    opts.num_points3D = 150
    opts.camera_width, opts.camera_height = WIDTH, HEIGHT
    opts.camera_model_id = pycolmap.CameraModelId.SIMPLE_RADIAL
    opts.camera_params = [300.0, WIDTH / 2, HEIGHT / 2, 0.05]
    out.mkdir()
    images.mkdir()
    db = pycolmap.Database.open(str(out / "database.db"))
    rec = pycolmap.synthesize_dataset(opts, db)
    pycolmap.synthesize_images(pycolmap.SyntheticImageOptions(), rec, str(images))
    (images / SUBFOLDER).mkdir()
    for i, image in enumerate(sorted(rec.images.values(), key=lambda im: im.name)):
        if i % 2:
            new = f"{SUBFOLDER}/{image.name}"
            os.replace(images / image.name, images / new)
            db_image = db.read_image(image.image_id)
            db_image.name = new
            db.update_image(db_image)
            image.name = new
    db.close()
    for i, point in enumerate(rec.points3D.values()):
        point.color = np.array([i % 256, 100, 200], dtype=np.uint8)
    (out / "sparse" / "0").mkdir(parents=True)
    rec.write(str(out / "sparse" / "0"))
    config = {"images": {"exif_orientation": "ignore"}, "extract": {"camera_model": "SIMPLE_RADIAL"},
              "map": {"min_model_size": 3, "abs_pose_min_num_inliers": 15, "abs_pose_min_inlier_ratio": 0.1}}
    (out / "run.json").write_text(json.dumps({"images_root": str(images), "config": config}))
    return out


def source_model(run_dir: Path) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(str(run_dir / "sparse" / "0"))


# ---------------------------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------------------------


def test_missing_model_is_one_clear_error(tmp_path: Path):
    (tmp_path / "out").mkdir()
    with pytest.raises(FileNotFoundError, match="holds no model"):
        export(tmp_path / "out", tmp_path / "dest", "3dgs")
    with pytest.raises(FileNotFoundError, match="output folder not found"):
        export(tmp_path / "nothing", tmp_path / "dest", "nerfstudio")


def test_unknown_format_and_unsafe_destination(run_dir: Path, tmp_path: Path):
    with pytest.raises(ValueError, match="3dgs, nerfstudio, colmap"):
        export(run_dir, tmp_path / "dest", "ply")
    with pytest.raises(ValueError, match="overwrite the run"):
        export(run_dir, run_dir, "3dgs")
    with pytest.raises(FileNotFoundError, match="no model 3"):
        export(run_dir, tmp_path / "dest", "3dgs", model_index=3)


def test_a_new_format_is_one_function_and_one_registry_line(run_dir: Path, tmp_path: Path, capsys):
    """A toy format, registered here and nowhere else, runs end to end through the command line."""
    from sara.cli import build_parser, main
    from sara.cli.parser import subcommands
    from sara.colmap.model import read_model

    def write_image_list(job: ExportJob) -> None:
        """A list of the model's images in DEST/cameras.json."""
        names = read_model(job.model_dir).names
        (job.dest / "cameras.json").write_text(json.dumps({"images": names, "from": str(job.images_root)}))

    FORMATS.register("toy", write_image_list)
    try:
        assert main(["export", str(run_dir), str(tmp_path / "toy"), "--format", "toy", "-q"]) == 0
        export_help = " ".join(subcommands(build_parser())["export"].format_help().split())
        assert "toy: a list of the model's images in DEST/cameras.json" in export_help
        assert build_parser().parse_args(["run", "imgs", "out", "--export", "toy"]).export == "toy"
    finally:
        FORMATS.unregister("toy")
    written = json.loads((tmp_path / "toy" / "cameras.json").read_text())
    assert written["images"] == sorted(im.name for im in source_model(run_dir).images.values())
    assert "toy export of" in capsys.readouterr().out
    with pytest.raises(SystemExit):  # gone from the choices once unregistered
        build_parser().parse_args(["export", str(run_dir), str(tmp_path / "again"), "--format", "toy"])


def test_flat_names_refuses_collisions():
    assert flat_names(["a/b.jpg", "c.jpg"]) == {"a/b.jpg": "a_b.jpg", "c.jpg": "c.jpg"}
    with pytest.raises(ValueError, match="both become"):
        flat_names(["a/b.jpg", "a_b.jpg"])


# ---------------------------------------------------------------------------------------------
# 3D Gaussian Splatting
# ---------------------------------------------------------------------------------------------

# scene/colmap_loader.py CAMERA_MODELS: model_id -> (name, number of parameters)
COLMAP_MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
                 4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
                 8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12)}


class Reader:
    """colmap_loader.read_next_bytes: little-endian struct unpacking; `done` checks nothing is left."""

    def __init__(self, path: Path):
        self.data, self.pos = path.read_bytes(), 0

    def read(self, fmt: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return values

    def done(self) -> bool:
        return self.pos == len(self.data)


def read_cameras_3dgs(path: Path) -> dict[int, tuple[str, int, int, np.ndarray]]:
    r = Reader(path)
    cameras = {}
    for _ in range(r.read("Q")[0]):
        camera_id, model_id, width, height = r.read("iiQQ")
        name, num_params = COLMAP_MODELS[model_id]
        cameras[camera_id] = (name, width, height, np.array(r.read("d" * num_params)))
    assert r.done(), "cameras.bin has bytes that 3DGS's reader does not expect"
    return cameras


def read_images_3dgs(path: Path) -> dict[int, dict]:
    r = Reader(path)
    images = {}
    for _ in range(r.read("Q")[0]):
        props = r.read("idddddddi")
        name = b""
        while (char := r.read("c")[0]) != b"\x00":
            name += char
        num_points = r.read("Q")[0]
        xyid = r.read("ddq" * num_points)
        images[props[0]] = {"qvec": np.array(props[1:5]), "tvec": np.array(props[5:8]), "camera_id": props[8],
                            "name": name.decode("utf-8"), "xys": np.array(xyid).reshape(-1, 3)[:, :2],
                            "point3D_ids": np.array(xyid[2::3], dtype=np.int64)}
    assert r.done(), "images.bin has bytes that 3DGS's reader does not expect"
    return images


def read_points_3dgs(path: Path) -> dict[int, np.ndarray]:
    r = Reader(path)
    points = {}
    for _ in range(r.read("Q")[0]):
        props = r.read("QdddBBBd")
        track_length = r.read("Q")[0]
        r.read("ii" * track_length)
        points[props[0]] = np.array(props[1:4])
    assert r.done(), "points3D.bin has bytes that 3DGS's reader does not expect"
    return points


def qvec2rotmat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array([[1 - 2 * y * y - 2 * z * z, 2 * x * y - 2 * w * z, 2 * z * x + 2 * w * y],
                     [2 * x * y + 2 * w * z, 1 - 2 * x * x - 2 * z * z, 2 * y * z - 2 * w * x],
                     [2 * z * x - 2 * w * y, 2 * y * z + 2 * w * x, 1 - 2 * x * x - 2 * y * y]])


def read_3dgs(dest: Path) -> list[dict]:
    """What readColmapSceneInfo + readColmapCameras produce, with their checks."""
    assert (dest / "sparse").exists()  # scene/__init__.py: the Colmap branch
    images = read_images_3dgs(dest / "sparse" / "0" / "images.bin")
    cameras = read_cameras_3dgs(dest / "sparse" / "0" / "cameras.bin")
    cams = []
    for image in images.values():
        model, width, height, params = cameras[image["camera_id"]]
        assert model in ("SIMPLE_PINHOLE", "PINHOLE"), "Colmap camera model not handled"  # readColmapCameras
        fx, fy = (params[0], params[0]) if model == "SIMPLE_PINHOLE" else (params[0], params[1])
        image_path = dest / "images" / os.path.basename(image["name"])
        with Image.open(image_path) as im:  # utils/camera_utils.py loadCam opens it
            assert im.size == (width, height)
        cams.append({**image, "width": width, "height": height, "params": params, "model": model,
                     "FovX": 2 * math.atan(width / (2 * fx)), "FovY": 2 * math.atan(height / (2 * fy))})
    return cams


def project_3dgs(cam: dict, xyz: np.ndarray) -> np.ndarray:
    """Pixel of a world point through 3DGS's camera: w2c from qvec/tvec, symmetric frustum of FovX/FovY."""
    x_cam = qvec2rotmat(cam["qvec"]) @ xyz + cam["tvec"]
    ndc = x_cam[:2] / x_cam[2] / np.tan([cam["FovX"] / 2, cam["FovY"] / 2])
    return (ndc + 1) / 2 * [cam["width"], cam["height"]]


def test_3dgs_export_loads_like_gaussian_splatting(run_dir: Path, tmp_path: Path):
    dest = export(run_dir, tmp_path / "gs", "3dgs")
    cams = read_3dgs(dest)
    src = source_model(run_dir)
    assert sorted(c["name"] for c in cams) == sorted(flat_names([im.name for im in src.images.values()]).values())
    assert any(im.name.startswith(f"{SUBFOLDER}/") for im in src.images.values())
    points = read_points_3dgs(dest / "sparse" / "0" / "points3D.bin")
    assert len(points) == src.num_points3D()
    errors = []
    for cam in cams:
        for xy, point_id in zip(cam["xys"], cam["point3D_ids"]):
            if point_id != -1:
                errors.append(np.linalg.norm(project_3dgs(cam, points[point_id]) - xy))
    assert len(errors) > 100
    assert np.median(errors) < 0.5, "3DGS's centred frustum does not reproduce the undistorted keypoints"


def test_3dgs_keeps_the_poses(run_dir: Path, tmp_path: Path):
    dest = export(run_dir, tmp_path / "gs", "3dgs", max_image_size=200)
    src = {im.name.replace("/", "_"): im for im in source_model(run_dir).images.values()}
    for cam in read_3dgs(dest):
        pose = src[cam["name"]].cam_from_world()
        np.testing.assert_allclose(qvec2rotmat(cam["qvec"]), pose.rotation.matrix(), atol=1e-9)
        np.testing.assert_allclose(cam["tvec"], pose.translation, atol=1e-9)
        assert max(cam["width"], cam["height"]) <= 200


# ---------------------------------------------------------------------------------------------
# nerfstudio
# ---------------------------------------------------------------------------------------------

CAMERA_MODEL_TO_TYPE = {"SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE",
                        "EQUIRECTANGULAR", "OMNIDIRECTIONALSTEREO_L", "OMNIDIRECTIONALSTEREO_R", "VR180_L",
                        "VR180_R", "ORTHOPHOTO", "FISHEYE624"}  # nerfstudio/cameras/cameras.py


def read_ascii_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    lines = path.read_text().splitlines()
    end = lines.index("end_header")
    header = lines[:end]
    assert header[:2] == ["ply", "format ascii 1.0"]
    count = int(next(line for line in header if line.startswith("element vertex")).split()[-1])
    props = [line.split()[-1] for line in header if line.startswith("property")]
    assert props == ["x", "y", "z", "red", "green", "blue"]
    rows = np.array([line.split() for line in lines[end + 1:end + 1 + count]], dtype=np.float64).reshape(-1, 6)
    return rows[:, :3], rows[:, 3:].astype(np.uint8)


def read_nerfstudio(data: Path) -> tuple[dict, list[dict]]:
    """_generate_dataparser_outputs: per-frame cameras with every key it asserts."""
    meta = json.loads((data / "transforms.json").read_text())
    fixed = {key: key in meta for key in ("fl_x", "fl_y", "cx", "cy", "h", "w")}
    distortion_keys = ("k1", "k2", "k3", "k4", "p1", "p2")
    distort_fixed = any(k in meta for k in distortion_keys)
    frames = []
    for frame in sorted(meta["frames"], key=lambda f: str(data / f["file_path"])):
        cam = {}
        for key, is_fixed in fixed.items():
            source = meta if is_fixed else frame
            assert key in source, f"{key} not specified in frame"
            cam[key] = float(source[key])
        source = meta if distort_fixed else frame
        cam["distortion"] = [float(source.get(k, 0.0)) for k in distortion_keys]
        pose = np.array(frame["transform_matrix"], dtype=np.float64)
        assert pose.shape == (4, 4)
        with Image.open(data / frame["file_path"]) as im:
            assert im.size == (int(cam["w"]), int(cam["h"]))
        frames.append({**cam, "c2w": pose, "file_path": frame["file_path"]})
    assert meta.get("camera_model", "OPENCV") in CAMERA_MODEL_TO_TYPE
    assert np.array(meta["applied_transform"]).shape == (3, 4)
    assert (data / meta["ply_file_path"]).is_file()
    return meta, frames


def nerfstudio_ray(frame: dict, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cameras.py: pixel -> (origin, unit direction) in the exported world frame."""
    coord = np.array([(xy[0] - frame["cx"]) / frame["fl_x"], (xy[1] - frame["cy"]) / frame["fl_y"]])
    k1, k2, _, _, p1, p2 = frame["distortion"]
    undist = coord.copy()
    for _ in range(50):  # radial_and_tangential_undistort: invert the OpenCV distortion
        r2 = undist @ undist
        radial = 1 + k1 * r2 + k2 * r2 * r2
        tangential = np.array([2 * p1 * undist[0] * undist[1] + p2 * (r2 + 2 * undist[0] ** 2),
                               2 * p2 * undist[0] * undist[1] + p1 * (r2 + 2 * undist[1] ** 2)])
        undist = (coord - tangential) / radial
    direction = frame["c2w"][:3, :3] @ np.array([undist[0], -undist[1], -1.0])
    return frame["c2w"][:3, 3], direction / np.linalg.norm(direction)


@pytest.mark.parametrize("undistort", [False, True])
def test_nerfstudio_export_loads_like_nerfstudio(run_dir: Path, tmp_path: Path, undistort: bool):
    dest = export(run_dir, tmp_path / "ns", "nerfstudio", undistort=undistort)
    meta, frames = read_nerfstudio(dest)
    src = source_model(run_dir)
    assert len(frames) == src.num_reg_images()
    assert meta["camera_model"] == "OPENCV" and "fl_x" in meta  # one shared camera
    assert math.isclose(meta["k1"], 0.0 if undistort else 0.05, abs_tol=1e-9)
    xyz, _ = read_ascii_ply(dest / meta["ply_file_path"])
    assert len(xyz) == src.num_points3D()
    applied = np.array(meta["applied_transform"])
    by_id = {int(f["colmap_im_id"]): f for f in meta["frames"]}
    angles = []
    for frame in frames:  # a rigid camera-to-world, as auto_orient_and_center_poses expects
        R = frame["c2w"][:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) > 0
    # every observation's ray passes through its 3D point (the exported world = applied_transform @ COLMAP's)
    model = pycolmap.Reconstruction(str(dest / "sparse" / "0")) if undistort else src
    frames_by_path = {f["file_path"]: f for f in frames}
    for image_id, image in model.images.items():
        frame = frames_by_path[by_id[image_id]["file_path"]]
        for p2d in image.points2D:
            if p2d.has_point3D():
                world = applied[:, :3] @ model.points3D[p2d.point3D_id].xyz + applied[:, 3]
                origin, direction = nerfstudio_ray(frame, p2d.xy)
                to_point = (world - origin) / np.linalg.norm(world - origin)
                angles.append(np.degrees(np.arccos(np.clip(to_point @ direction, -1, 1))))
    assert len(angles) > 100
    assert np.median(angles) < 0.05, "nerfstudio's rays miss the 3D points: a convention is wrong"


def test_nerfstudio_ply_holds_the_transformed_points(run_dir: Path, tmp_path: Path):
    dest = export(run_dir, tmp_path / "ns", "nerfstudio")
    meta = json.loads((dest / "transforms.json").read_text())
    xyz, rgb = read_ascii_ply(dest / "sparse_pc.ply")
    src = source_model(run_dir)
    applied = np.array(meta["applied_transform"])
    expected = np.array([p.xyz for p in src.points3D.values()]) @ applied[:, :3].T + applied[:, 3]
    np.testing.assert_allclose(xyz, expected, atol=1e-6)
    np.testing.assert_array_equal(rgb, np.array([p.color for p in src.points3D.values()]))


# ---------------------------------------------------------------------------------------------
# COLMAP
# ---------------------------------------------------------------------------------------------

# option names COLMAP 4 registers (src/colmap/controllers/option_manager.cc); it rejects any other
# that `colmap mapper --project_path` registers too (the GUI registers every option)
COLMAP_OPTIONS = {"database_path", "image_path", "Mapper.min_model_size", "Mapper.abs_pose_min_num_inliers",
                  "Mapper.abs_pose_min_inlier_ratio"}


def parse_ini(text: str) -> dict[str, str]:
    section, values = "", {}
    for line in text.splitlines():
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1] + "."
        elif line.strip():
            key, value = line.split("=", 1)
            values[section + key] = value
    return values


def test_colmap_export_opens_in_pycolmap(run_dir: Path, tmp_path: Path):
    dest = export(run_dir, tmp_path / "colmap", "colmap")
    ini = parse_ini((dest / "project.ini").read_text())
    assert set(ini) <= COLMAP_OPTIONS
    assert Path(ini["database_path"]) == (dest / "database.db").resolve()
    images_root = Path(ini["image_path"])
    db = pycolmap.Database.open(ini["database_path"])
    try:
        db_names = sorted(im.name for im in db.read_all_images())
        assert db.num_keypoints() > 0 and db.num_matched_image_pairs() > 0
    finally:
        db.close()
    rec = pycolmap.Reconstruction(str(dest / "sparse" / "0"))
    assert sorted(im.name for im in rec.images.values()) == db_names
    assert all((images_root / name).is_file() for name in db_names)
    assert rec.num_points3D() == source_model(run_dir).num_points3D()


def test_project_ini_uses_the_run_settings(tmp_path: Path):
    text = project_ini(tmp_path / "db.db", tmp_path, {"map": {"abs_pose_min_num_inliers": 12}})
    ini = parse_ini(text)
    assert ini["Mapper.abs_pose_min_num_inliers"] == "12"
    assert ini["database_path"] == str((tmp_path / "db.db").resolve())


def test_nerfstudio_cameras_per_frame_and_models():
    """Two cameras: intrinsics go into each frame (nerfstudio asserts them there when not top-level)."""
    cams = {1: Intrinsics(1, "PINHOLE", 640, 480, np.array([500.0, 510.0, 320.0, 240.0])),
            2: Intrinsics(2, "OPENCV", 800, 600, np.array([600.0, 610.0, 400.0, 300.0, 0.1, -0.01, 0.001, 0.002]))}
    data = ModelData(cameras=cams, names=["a.jpg", "b.jpg"], image_ids=np.array([1, 2]), camera_ids=np.array([1, 2]),
                     rotations=np.stack([np.eye(3)] * 2), translations=np.zeros((2, 3)),
                     num_observations=np.zeros(2, np.int64), points_xyz=np.zeros((0, 3)),
                     points_rgb=np.zeros((0, 3), np.uint8), track_lengths=np.zeros(0, np.int64),
                     points_error_px=np.zeros(0))
    meta = nerfstudio_transforms(data, {"a.jpg": "a.jpg", "b.jpg": "b.jpg"})
    assert "fl_x" not in meta and meta["camera_model"] == "OPENCV"
    b = meta["frames"][1]
    assert (b["fl_x"], b["fl_y"], b["cx"], b["cy"], b["w"], b["h"]) == (600.0, 610.0, 400.0, 300.0, 800, 600)
    assert (b["k1"], b["k2"], b["p1"], b["p2"]) == (0.1, -0.01, 0.001, 0.002)
    assert meta["frames"][0]["k1"] == 0.0
    fisheye_params = np.array([50, 50, 50, 50, 0.1, 0.2, 0.3, 0.4])
    fisheye = nerfstudio_camera(Intrinsics(3, "OPENCV_FISHEYE", 100, 100, fisheye_params))
    assert fisheye["camera_model"] == "OPENCV_FISHEYE" and fisheye["k4"] == 0.4 and "p1" not in fisheye
    with pytest.raises(ValueError, match="undistort first"):
        nerfstudio_camera(Intrinsics(4, "FOV", 100, 100, np.array([50, 50, 50, 50, 0.1])))
