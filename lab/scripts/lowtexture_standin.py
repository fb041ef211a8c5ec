"""A low-texture stand-in made from a shared scene: every view small and blurred, so that SIFT starves.

On plain objects, blank walls and turntables SIFT finds a few hundred keypoints per image where the
shared scenes give thousands (a held-out 48-image turntable: about 250), its pairs are few and
weak, and the model splits. This makes such a capture from a scene with true poses: each image is
resized to a long side of `--long-side` pixels and blurred with a Gaussian of `--blur` pixels, which
takes away the fine texture SIFT's detector responds to while keeping the object's outline and
coarse shading. The true model is written with the intrinsics scaled. It stands in for the
keypoint starvation, not for the look of a textureless surface (the learned detectors see the
same blurred images).

    python lab/scripts/lowtexture_standin.py ../shared/data/middlebury-templeRing DEST [--long-side 320] [--blur 2]

DEST gets images/, gt/ (COLMAP text) and SCENE.md (how it was made).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import pycolmap
from sweep_standin import image_line, write_truth  # this folder's: run as a script


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("dest", type=Path)
    parser.add_argument("--long-side", type=int, default=320)
    parser.add_argument("--blur", type=float, default=2.0, help="Gaussian sigma in pixels of the resized image")
    args = parser.parse_args()
    gt = pycolmap.Reconstruction()
    gt.read_text(str(args.scene / "gt"))
    (args.dest / "images").mkdir(parents=True, exist_ok=True)
    (args.dest / "gt").mkdir(parents=True, exist_ok=True)
    cameras, images = [], []
    for k, image_id in enumerate(sorted(gt.images, key=lambda i: gt.images[i].name), start=1):
        image = gt.images[image_id]
        photo = cv2.imread(str(args.scene / "images" / image.name), cv2.IMREAD_COLOR)
        if photo is None:
            continue
        height, width = photo.shape[:2]
        scale = args.long_side / max(width, height)
        photo = cv2.resize(photo, (round(width * scale), round(height * scale)), interpolation=cv2.INTER_AREA)
        if args.blur > 0:
            photo = cv2.GaussianBlur(photo, (0, 0), args.blur)
        name = Path(image.name).with_suffix(".png").name
        cv2.imwrite(str(args.dest / "images" / name), photo)
        camera = gt.cameras[image.camera_id]
        sx, sy = photo.shape[1] / camera.width, photo.shape[0] / camera.height
        fx, fy, cx, cy = camera.params[:4] if camera.model.name == "PINHOLE" else \
            (camera.params[0], camera.params[0], camera.params[1], camera.params[2])
        cameras.append(f"{k} PINHOLE {photo.shape[1]} {photo.shape[0]} {fx * sx:.6f} {fy * sy:.6f} {cx * sx:.6f} "
                       f"{cy * sy:.6f}")
        images.append(image_line(k, image, name))
    write_truth(args.dest / "gt", cameras, images)
    (args.dest / "SCENE.md").write_text(
        f"Low-texture stand-in of {args.scene.name} (lab/scripts/lowtexture_standin.py): every view resized to a "
        f"long side of {args.long_side} px and blurred with a Gaussian of sigma {args.blur} px, saved as PNG; one "
        "PINHOLE camera per image in gt/, intrinsics scaled.\n")


if __name__ == "__main__":
    main()
