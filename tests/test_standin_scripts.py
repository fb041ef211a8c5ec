"""The stand-in scripts that docs/results.md shows (`python lab/scripts/X.py SCENE DEST`), run as
written on the five-view synthetic scene: their true models must describe the images they write."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from PIL import Image

from sara.cameras import exif_camera

SCRIPTS = Path(__file__).resolve().parents[1] / "lab" / "scripts"


def _run(script: str, *args) -> None:
    subprocess.run([sys.executable, str(SCRIPTS / script), *map(str, args)], check=True, capture_output=True)


def _model(gt: Path) -> pycolmap.Reconstruction:
    rec = pycolmap.Reconstruction()
    rec.read_text(str(gt))
    return rec


def _pixel(rec: pycolmap.Reconstruction, name: str, xyz: np.ndarray) -> np.ndarray:
    image = next(im for im in rec.images.values() if im.name == name)
    return np.asarray(rec.cameras[image.camera_id].img_from_cam(image.cam_from_world() * xyz))


def test_phones_standin_turns_the_true_camera_with_the_pixels_and_writes_a_phones_exif(five_view_scene, tmp_path):
    import shutil

    scene = tmp_path / "scene"  # the five views, their principal point moved off the centre (as real ones are)
    shutil.copytree(five_view_scene[0].parent, scene)
    cameras = _model(scene / "gt")
    for camera in cameras.cameras.values():
        camera.params = np.asarray(camera.params) + np.array([0.0, 0.0, 23.0, -17.0])[-len(camera.params):]
    cameras.write_text(str(scene / "gt"))
    dest = tmp_path / "phones"
    _run("phones_standin.py", scene, dest, "--phones", "2", "--portrait", "0.5", "--seed", "3")
    source, made = _model(scene / "gt"), _model(dest / "gt")
    turned = 0
    for image in source.images.values():
        name = Path(image.name).with_suffix(".jpg").name
        xyz = image.cam_from_world().inverse() * np.array([0.8, 0.5, 5.0])  # ahead of it, off the axis
        u, v = _pixel(source, image.name, xyz)
        with Image.open(dest / "images" / name) as photo:
            width, height = photo.size
        camera = exif_camera(dest / "images" / name)
        assert camera.complete() and camera.focal_35mm
        scale = max(width, height) / max(source.cameras[image.camera_id].width, source.cameras[image.camera_id].height)
        portrait = height > width
        turned += portrait
        expected = (width - v * scale, u * scale) if portrait else (u * scale, v * scale)  # a quarter clockwise
        assert np.allclose(_pixel(made, name, xyz), expected, atol=1.0), name
    assert 0 < turned < len(source.images)


def test_dashcam_standin_draws_the_overlay_and_keeps_the_poses(five_view_scene, tmp_path):
    scene = five_view_scene[0].parent
    dest = tmp_path / "dashcam"
    _run("dashcam_standin.py", scene, dest)
    names = sorted(p.name for p in (scene / "images").iterdir())
    assert sorted(p.name for p in (dest / "images").iterdir()) == names
    for name in names:
        with Image.open(dest / "images" / name) as drawn, Image.open(scene / "images" / name) as plain:
            box = np.asarray(drawn.convert("L"))[12:48, 12:228]
            assert (box == 0).mean() > 0.5 and not np.array_equal(np.asarray(drawn), np.asarray(plain))
    assert (dest / "gt" / "images.txt").read_text() == (scene / "gt" / "images.txt").read_text()


def test_clips_standin_as_frames_names_them_by_clip_and_turns_the_poses(five_view_scene, tmp_path):
    """`video_clips_standin.py --images` (docs/results.md): each clip's frames as PNG images named by
    clip, the turned clip's frames turned, and the true model under those names, its poses turned too."""
    scene = five_view_scene[0].parent
    dest = tmp_path / "frames"
    _run("video_clips_standin.py", scene, dest, "--turns", "0,1", "--images")
    names = sorted(p.name for p in (dest / "images").iterdir())
    assert [n.split("_")[0] for n in names] == ["clip0"] * 3 + ["clip1"] * 2 and not (dest / "clips").exists()
    with Image.open(scene / "images" / sorted(p.name for p in (scene / "images").iterdir())[0]) as plain:
        width, height = plain.size
    sizes = {n: Image.open(dest / "images" / n).size for n in names}
    assert {sizes[n] for n in names[:3]} == {(width, height)} and {sizes[n] for n in names[3:]} == {(height, width)}
    rec, plain_rec = _model(dest / "gt"), _model(scene / "gt")
    assert sorted(im.name for im in rec.images.values()) == names
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # the camera turned with the picture
    by_name = {im.name: im.cam_from_world() for im in rec.images.values()}
    originals = [im.cam_from_world() for im in sorted(plain_rec.images.values(), key=lambda im: im.name)]
    for k, name in enumerate(names):
        turn = quarter if name.startswith("clip1") else np.eye(3)
        assert np.allclose(by_name[name].rotation.matrix(), turn @ originals[k].rotation.matrix(), atol=1e-6)
        assert np.allclose(by_name[name].translation, turn @ originals[k].translation, atol=1e-6)


def test_clips_standin_zooms_a_clip_about_the_image_centre(five_view_scene, tmp_path):
    """`--zoom 1,1.5`: the second clip as through a 1.5x longer lens, at the same size (the centre
    two thirds of each side enlarged), the poses unchanged."""
    scene = five_view_scene[0].parent
    dest = tmp_path / "zoomed"
    _run("video_clips_standin.py", scene, dest, "--zoom", "1,1.5", "--images")
    originals = sorted(p.name for p in (scene / "images").iterdir())
    names = sorted(p.name for p in (dest / "images").iterdir())
    plain = np.asarray(Image.open(scene / "images" / originals[3]).convert("L"), np.float64)
    zoomed = np.asarray(Image.open(dest / "images" / names[3]).convert("L"), np.float64)
    assert zoomed.shape == plain.shape
    h, w = plain.shape
    centre = cv2.resize(plain[round(h / 6):round(5 * h / 6), round(w / 6):round(5 * w / 6)], (w, h))
    assert np.abs(zoomed - centre).mean() < np.abs(zoomed - plain).mean() / 3
    rec, plain_rec = _model(dest / "gt"), _model(scene / "gt")
    for (a, b) in zip(sorted(rec.images.values(), key=lambda im: im.name),
                      sorted(plain_rec.images.values(), key=lambda im: im.name)):
        assert np.allclose(a.cam_from_world().matrix(), b.cam_from_world().matrix())


def test_photo_collection_standin_with_a_videos_frames(five_view_scene, tmp_path):
    """`photo_collection_standin.py --frames 3` (docs/results.md): three neighbouring images as a
    video's frames at half size, named in order, the others photos of their own sizes; the true
    model names them all and scales the frames' intrinsics, the poses unchanged."""
    scene = five_view_scene[0].parent
    dest = tmp_path / "mixed"
    _run("photo_collection_standin.py", scene, dest, "--frames", "3")
    frames = sorted(p.name for p in (dest / "images").glob("video_f*.png"))
    assert frames == [f"video_f{k:06d}.png" for k in range(3)]
    rec, plain = _model(dest / "gt"), _model(scene / "gt")
    assert len(rec.images) == len(plain.images) == len(list((dest / "images").iterdir()))
    for name in frames:
        image = next(im for im in rec.images.values() if im.name == name)
        original = plain.images[image.image_id]
        camera, plain_camera = rec.cameras[image.camera_id], plain.cameras[original.camera_id]
        assert Image.open(dest / "images" / name).size == (camera.width, camera.height)
        assert abs(camera.width - plain_camera.width / 2) <= 1
        assert np.allclose(camera.params[0], plain_camera.params[0] * camera.width / plain_camera.width)
        assert np.allclose(image.cam_from_world().matrix(), original.cam_from_world().matrix())


def test_wide_lens_standin_shows_each_point_where_its_fisheye_camera_projects_it(five_view_scene, tmp_path):
    """Each of the scene's points (a rendered dot) is shown in the resampled view where gt/'s
    OPENCV_FISHEYE camera projects it, as the pinhole view showed it where its camera did (a focal
    length 3% off moves the dots away: the mean difference rises from about 3 to about 43 grey levels,
    the dots' contrast about 87)."""
    scene = five_view_scene[0].parent
    dest = tmp_path / "wide"
    _run("wide_lens_standin.py", scene, dest)
    source, made = _model(scene / "gt"), _model(dest / "gt")
    assert {camera.model.name for camera in made.cameras.values()} == {"OPENCV_FISHEYE"}
    points = [point.xyz for point in source.points3D.values()]

    def greys(path: Path, pixels: list) -> np.ndarray:
        image = cv2.GaussianBlur(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), (0, 0), 1.5).astype(np.float32)
        return np.array([cv2.getRectSubPix(image, (1, 1), (float(x) - 0.5, float(y) - 0.5))[0, 0] for x, y in pixels])

    for image in source.images.values():
        name = Path(image.name).with_suffix(".png").name
        camera = source.cameras[image.camera_id]
        size = (camera.width, camera.height)
        inside = [xyz for xyz in points if (image.cam_from_world() * xyz)[2] > 0
                  and all(20 < c < m - 20 for c, m in zip(_pixel(source, image.name, xyz), size))]
        assert len(inside) > 50
        plain = greys(scene / "images" / image.name, [_pixel(source, image.name, xyz) for xyz in inside[:80]])
        wide = greys(dest / "images" / name, [_pixel(made, name, xyz) for xyz in inside[:80]])
        background = float(np.median(cv2.imread(str(scene / "images" / image.name), cv2.IMREAD_GRAYSCALE)))
        assert np.mean(np.abs(wide - plain)) < 0.1 * np.mean(np.abs(plain - background)), name


def test_video_from_frames_writes_every_frame_and_names_the_truth_as_sara_names_frames(five_view_scene, tmp_path):
    """`video_from_frames.py SCENE DEST --stem kitti` (docs/results.md): one frame per image in name
    order, and gt/ holds each image's pose under the name `sara.video.frame_name` gives its frame."""
    from sara.video import frame_name

    scene = five_view_scene[0].parent
    dest = tmp_path / "video"
    _run("video_from_frames.py", scene, dest, "--stem", "kitti")
    names = sorted(p.name for p in (scene / "images").iterdir())
    capture = cv2.VideoCapture(str(dest / "kitti.avi"))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == len(names)
    capture.release()
    source, made = _model(scene / "gt"), _model(dest / "gt")
    poses = {im.name: im.cam_from_world().matrix() for im in source.images.values()}
    for k, name in enumerate(names):
        image = next(im for im in made.images.values() if im.name == frame_name("kitti", k, len(names)))
        np.testing.assert_allclose(image.cam_from_world().matrix(), poses[name])
