"""A wide-lens stand-in made from a shared scene: every view as a fisheye lens would have shown it.

Dashcams, action cameras and many drones film through fisheye lenses: the image height grows with
the angle from the optical axis (r = f theta, the equidistant projection) instead of with its
tangent (a pinhole), so straight lines bend and the frame's edges are squeezed. This makes such a
capture from a scene with true poses: each view is resampled so that the pixel at angle theta from
the axis shows what the pinhole image showed at that angle, with the focal length chosen so that
the frame's corners keep the pinhole image's corners (every pixel of the new frame has a source
pixel, the centre is enlarged). `--strength S` (0 to 1) blends the two projections (r = f ((1 - S)
tan theta + S theta), S = 1 the full fisheye), for lenses in between. The poses do not change; gt/
holds the true camera as OPENCV_FISHEYE (k1-k4 zero) for S = 1, as the pinhole's focal length
otherwise (the evaluator reads the poses only). `--every K` keeps every K-th view.

    python lab/scripts/wide_lens_standin.py ../shared/data/kitti-seq1 DEST [--strength 1] [--every 1]

DEST gets images/, gt/ (COLMAP text) and SCENE.md (how it was made).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from sweep_standin import image_line, write_truth  # this folder's: run as a script


def lens_height(theta: np.ndarray, strength: float) -> np.ndarray:
    """Image height (focal length 1) of a ray at angle `theta` from the axis: pinhole blended with fisheye."""
    return (1.0 - strength) * np.tan(theta) + strength * theta


def lens_angle(height: np.ndarray, strength: float) -> np.ndarray:
    """The inverse of `lens_height` (a few Newton steps; the blend is increasing on [0, pi / 2))."""
    theta = np.arctan(height)
    for _ in range(30):
        slope = (1.0 - strength) / np.cos(theta) ** 2 + strength
        theta = np.clip(theta - (lens_height(theta, strength) - height) / slope, 0.0, 1.55)
    return theta


def widened(photo: np.ndarray, f: float, cx: float, cy: float, strength: float) -> tuple[np.ndarray, float]:
    """`photo` (a pinhole view of focal length `f`, principal point `cx, cy`) through the blended lens,
    same size; returns the image and the new lens's focal length."""
    height, width = photo.shape[:2]
    corner = max(np.hypot(x - cx, y - cy) for x in (0.0, width) for y in (0.0, height))
    f_new = corner / lens_height(np.arctan(corner / f), strength)
    xs, ys = np.meshgrid(np.arange(width) + 0.5 - cx, np.arange(height) + 0.5 - cy)
    radius = np.hypot(xs, ys)
    theta = lens_angle(radius / f_new, strength)
    gain = np.where(radius > 0, f * np.tan(theta) / np.maximum(radius, 1e-9), f / f_new)
    map_x = (xs * gain + cx - 0.5).astype(np.float32)
    map_y = (ys * gain + cy - 0.5).astype(np.float32)
    return cv2.remap(photo, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT), f_new


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("dest", type=Path)
    parser.add_argument("--strength", type=float, default=1.0, help="0: pinhole, 1: equidistant fisheye")
    parser.add_argument("--every", type=int, default=1)
    args = parser.parse_args()
    if not 0.0 <= args.strength <= 1.0:
        parser.error("--strength must be in [0, 1]")
    gt = pycolmap.Reconstruction()
    gt.read_text(str(args.scene / "gt"))
    (args.dest / "images").mkdir(parents=True, exist_ok=True)
    (args.dest / "gt").mkdir(parents=True, exist_ok=True)
    cameras, images = [], []
    ids = sorted(gt.images, key=lambda i: gt.images[i].name)[:: args.every]
    for k, image_id in enumerate(ids, start=1):
        image = gt.images[image_id]
        photo = cv2.imread(str(args.scene / "images" / image.name), cv2.IMREAD_COLOR)
        camera = gt.cameras[image.camera_id]
        fx, fy, cx, cy = camera.params[:4] if camera.model.name == "PINHOLE" else \
            (camera.params[0], camera.params[0], camera.params[1], camera.params[2])
        warped, f_new = widened(photo, float(np.sqrt(fx * fy)), cx, cy, args.strength)
        name = Path(image.name).with_suffix(".png").name
        cv2.imwrite(str(args.dest / "images" / name), warped)
        size = f"{warped.shape[1]} {warped.shape[0]}"
        cameras.append(f"{k} OPENCV_FISHEYE {size} {f_new:.6f} {f_new:.6f} {cx:.6f} {cy:.6f} 0 0 0 0"
                       if args.strength == 1.0 else f"{k} PINHOLE {size} {fx:.6f} {fy:.6f} {cx:.6f} {cy:.6f}")
        images.append(image_line(k, image, name))
    write_truth(args.dest / "gt", cameras, images)
    (args.dest / "SCENE.md").write_text(
        f"Wide-lens stand-in of {args.scene.name} (lab/scripts/wide_lens_standin.py): every view resampled "
        f"through a lens of strength {args.strength} (1: equidistant fisheye), corners kept, every "
        f"{args.every}th view; true poses unchanged.\n")


if __name__ == "__main__":
    main()
