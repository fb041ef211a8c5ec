"""A stand-in for photos of one place from a few phones: each photo from one of `--phones` phones,
some held upright (portrait), every photo with the EXIF a phone writes.

Each phone has its own resolution (a scale of the scene's images), its own make, model and focal
length in EXIF (FocalLength in mm and FocalLengthIn35mmFilm, which gives COLMAP the focal length in
pixels to within the rounding of a whole millimetre), and its own colour rendering; every photo is
given to a phone at random, and `--portrait` of them are turned a quarter clockwise as a phone held
upright saves them (pixels turned, no orientation tag). The true model follows: a portrait photo's
camera turned about its optical axis, its principal point moved with the pixels. Photos of one phone
and one orientation share their true intrinsics, as they would (a fixed-lens phone, no zoom).
Seeded: the same seed gives the same files.

    python lab/scripts/phones_standin.py ../shared/data/strecha-Herz-Jesus-P25 DEST [--phones 3]
        [--portrait 0.3] [--seed 1]

DEST gets images/, gt/ (COLMAP text) and SCENE.md (which photo came from which phone).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image, ImageEnhance

#: make, model, focal length in mm, scale of the scene's images: phones of different resolutions
PHONES = [("Apple", "iPhone 13", 5.1, 0.6), ("Google", "Pixel 7", 6.81, 0.8), ("samsung", "SM-G991B", 5.4, 0.45),
          ("Xiaomi", "2201123G", 5.6, 0.7)]
#: a quarter turn clockwise of the camera's image axes: x' = -y, y' = x
QUARTER = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def rendering(rng: np.random.Generator) -> tuple[float, float, float, float, int]:
    """A phone's colour rendering: brightness, contrast, saturation, gamma; and its JPEG quality."""
    return (float(rng.uniform(0.7, 1.3)), float(rng.uniform(0.8, 1.2)), float(rng.uniform(0.6, 1.4)),
            float(rng.uniform(0.8, 1.25)), int(rng.integers(75, 96)))


def photo_of(original: Image.Image, scale: float, look: tuple, portrait: bool) -> Image.Image:
    out = original.convert("RGB").resize((round(original.width * scale), round(original.height * scale)),
                                         Image.LANCZOS)
    out = ImageEnhance.Brightness(out).enhance(look[0])
    out = ImageEnhance.Contrast(out).enhance(look[1])
    out = ImageEnhance.Color(out).enhance(look[2])
    out = out.point([min(255, round(255 * (i / 255) ** look[3])) for i in range(256)] * 3)
    return out.transpose(Image.Transpose.ROTATE_270) if portrait else out  # ROTATE_270: a quarter clockwise


def exif_of(make: str, model: str, focal_mm: float, focal_px: float, width: int, height: int) -> bytes:
    exif = Image.Exif()
    exif[0x010F], exif[0x0110] = make, model
    sub = exif.get_ifd(0x8769)
    sub[0x920A] = focal_mm  # FocalLength
    sub[0xA405] = round(focal_px / max(width, height) * 35.0)  # FocalLengthIn35mmFilm, as COLMAP reads it
    return exif.tobytes()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("dest", type=Path)
    parser.add_argument("--phones", type=int, default=3, choices=range(1, len(PHONES) + 1))
    parser.add_argument("--portrait", type=float, default=0.3, help="share of the photos held upright")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    looks = [rendering(rng) for _ in range(args.phones)]
    gt = pycolmap.Reconstruction()
    gt.read_text(str(args.scene / "gt"))
    (args.dest / "images").mkdir(parents=True, exist_ok=True)
    (args.dest / "gt").mkdir(parents=True, exist_ok=True)
    cameras, images, lines = [], [], []
    for image_id in sorted(gt.images):
        image = gt.images[image_id]
        phone, portrait = int(rng.integers(args.phones)), bool(rng.random() < args.portrait)
        make, model, focal_mm, scale = PHONES[phone]
        photo = photo_of(Image.open(args.scene / "images" / image.name), scale, looks[phone], portrait)
        fx, fy, cx, cy = (p * scale for p in gt.cameras[image.camera_id].params[:4])
        pose = image.cam_from_world()
        rotation, translation = pose.rotation.matrix(), np.asarray(pose.translation)
        if portrait:  # pixel (u, v) goes to (h - v, u): x' = -y, y' = x in the camera's frame
            fx, fy, cx, cy = fy, fx, photo.width - cy, cx
            rotation, translation = QUARTER @ rotation, QUARTER @ translation
        name = Path(image.name).with_suffix(".jpg").name
        photo.save(args.dest / "images" / name, quality=looks[phone][4],
                   exif=exif_of(make, model, focal_mm, (fx + fy) / 2, photo.width, photo.height))
        cameras.append(f"{image_id} PINHOLE {photo.width} {photo.height} {fx:.6f} {fy:.6f} {cx:.6f} {cy:.6f}")
        qx, qy, qz, qw = pycolmap.Rotation3d(rotation).quat
        tx, ty, tz = translation
        images.append(f"{image_id} {qw} {qx} {qy} {qz} {tx} {ty} {tz} {image_id} {name}\n\n")
        lines.append(f"{name} {make} {model} {'portrait' if portrait else 'landscape'} {photo.width}x{photo.height}")
    (args.dest / "gt" / "cameras.txt").write_text("\n".join(cameras) + "\n")
    (args.dest / "gt" / "images.txt").write_text("".join(images))
    (args.dest / "gt" / "points3D.txt").write_text("")
    (args.dest / "SCENE.md").write_text(
        f"Phones stand-in of {args.scene.name} (lab/scripts/phones_standin.py, {args.phones} phones, "
        f"{args.portrait} portrait, seed {args.seed}); each photo: name, make, model, orientation, size:\n"
        + "\n".join(lines) + "\n")
    print(f"{len(lines)} photos -> {args.dest / 'images'}")


if __name__ == "__main__":
    main()
