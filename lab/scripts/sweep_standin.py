"""A forward-facing sweep stand-in made from a shared scene: the views that face one way, at phone size.

A forward-facing capture (a phone swept in front of a scene, LLFF-style) has views that all look
the same way, so that every pair overlaps. This picks the `--count` views of SCENE whose optical
axes are closest to the mean axis of all views, resizes each to a long side of `--long-side`
pixels and saves it as JPEG at `--quality` (one camera, as from one phone), and writes the true
model with the intrinsics scaled. It stands in for the geometry of a sweep (one direction, all pairs
overlapping), not for a phone's optics (wide angle, rolling shutter, motion blur): on dtu-scan24 the
views are about 12 degrees apart on a sphere, where a phone's video frames are a few degrees apart.

    python lab/scripts/sweep_standin.py ../shared/data/dtu-scan24 DEST [--count 20] [--long-side 1008] [--radial K1]

`--radial K1` adds a phone lens's radial distortion to every image: the pixel at normalised
coordinates x (focal length 1, from the true intrinsics) shows what the undistorted image showed
at u with x = u (1 + K1 |u|^2), COLMAP's SIMPLE_RADIAL model; the poses do not change, gt/ keeps the
pinhole intrinsics, and the mapper has to find K1 itself.

DEST gets images/, gt/ (COLMAP text) and SCENE.md (how it was made and which views).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from PIL import Image


def image_line(k: int, image: pycolmap.Image, name: str) -> str:
    """images.txt's lines of a true view as image `k` (camera `k`) named `name`, with no 2D points."""
    pose = image.cam_from_world()
    qx, qy, qz, qw = pose.rotation.quat
    tx, ty, tz = pose.translation
    return f"{k} {qw} {qx} {qy} {qz} {tx} {ty} {tz} {k} {name}\n\n"  # no 2D points: an empty line


def write_truth(gt_dir: Path, cameras: list[str], images: list[str]) -> None:
    """A true model in COLMAP text: `cameras` (cameras.txt lines), `images` (`image_line`s), no points."""
    (gt_dir / "cameras.txt").write_text("\n".join(cameras) + "\n")
    (gt_dir / "images.txt").write_text("".join(images))
    (gt_dir / "points3D.txt").write_text("")


def facing_views(gt: pycolmap.Reconstruction, count: int) -> list[int]:
    """The `count` image ids whose optical axes are closest to the mean axis, in name order."""
    ids = sorted(gt.images, key=lambda i: gt.images[i].name)
    axes = np.array([gt.images[i].cam_from_world().rotation.matrix()[2] for i in ids])
    mean = axes.mean(axis=0)
    mean /= np.linalg.norm(mean)
    order = np.argsort(-(axes @ mean), kind="stable")[:count]
    return sorted((ids[k] for k in order), key=lambda i: gt.images[i].name)


def distorted(photo: Image.Image, fx: float, fy: float, cx: float, cy: float, k1: float) -> Image.Image:
    """`photo` as a lens with radial distortion `k1` (SIMPLE_RADIAL) would have shown it."""
    xs, ys = np.meshgrid(np.arange(photo.width) + 0.5, np.arange(photo.height) + 0.5)
    xd, yd = (xs - cx) / fx, (ys - cy) / fy
    xu, yu = xd.copy(), yd.copy()
    for _ in range(20):  # x_u = x_d / (1 + k1 |x_u|^2), a contraction for the small k1 of a lens
        factor = 1.0 + k1 * (xu * xu + yu * yu)
        xu, yu = xd / factor, yd / factor
    map_x = (xu * fx + cx - 0.5).astype(np.float32)
    map_y = (yu * fy + cy - 0.5).astype(np.float32)
    warped = cv2.remap(np.asarray(photo), map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return Image.fromarray(warped)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("dest", type=Path)
    parser.add_argument("--count", type=int, default=20)
    parser.add_argument("--long-side", type=int, default=1008)
    parser.add_argument("--quality", type=int, default=90)
    parser.add_argument("--radial", type=float, default=0.0, help="radial distortion K1 to add (default none)")
    args = parser.parse_args()
    gt = pycolmap.Reconstruction()
    gt.read_text(str(args.scene / "gt"))
    chosen = facing_views(gt, args.count)
    (args.dest / "images").mkdir(parents=True, exist_ok=True)
    (args.dest / "gt").mkdir(parents=True, exist_ok=True)
    cameras, images = [], []
    for k, image_id in enumerate(chosen, start=1):
        image = gt.images[image_id]
        photo = Image.open(args.scene / "images" / image.name).convert("RGB")
        scale = args.long_side / max(photo.size)
        photo = photo.resize((round(photo.width * scale), round(photo.height * scale)), Image.LANCZOS)
        name = Path(image.name).with_suffix(".jpg").name
        sx, sy = photo.width / gt.cameras[image.camera_id].width, photo.height / gt.cameras[image.camera_id].height
        fx, fy, cx, cy = gt.cameras[image.camera_id].params[:4]
        if args.radial:
            photo = distorted(photo, fx * sx, fy * sy, cx * sx, cy * sy, args.radial)
        photo.save(args.dest / "images" / name, quality=args.quality)
        params = f"{fx * sx:.6f} {fy * sy:.6f} {cx * sx:.6f} {cy * sy:.6f}"
        cameras.append(f"{k} PINHOLE {photo.width} {photo.height} {params}")
        images.append(image_line(k, image, name))
    write_truth(args.dest / "gt", cameras, images)
    (args.dest / "SCENE.md").write_text(
        f"Forward-facing sweep stand-in of {args.scene.name} (lab/scripts/sweep_standin.py): the {args.count} "
        f"views whose optical axes are closest to the mean axis, resized to a long side of {args.long_side} px, "
        f"JPEG quality {args.quality}; one PINHOLE camera per image in gt/, intrinsics scaled"
        + (f"; radial distortion K1 = {args.radial} added (SIMPLE_RADIAL), not in gt/" if args.radial else "") + ".\n"
        "views: " + " ".join(gt.images[i].name for i in chosen) + "\n")


if __name__ == "__main__":
    main()
