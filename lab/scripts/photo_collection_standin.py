"""A photo-collection stand-in made from a shared scene: every photo as if from another camera.

Each image is rescaled by its own random factor (so each has its own size and focal length in
pixels), its brightness, contrast, saturation and gamma changed, and saved as JPEG at a random
quality; the true model gets one PINHOLE camera per image with the intrinsics scaled to match. It
stands in for photos of one place from many people's cameras, with none of their other differences
(viewpoint, season). Seeded: the same seed gives the same files.

With `--crop F` each photo is first cut to a random window of F to 1 of its width and height at a
random place (a zoomed or cropped photo: its own field of view, its principal point off the
centre; the true intrinsics follow), and with `--occluders K` up to K random opaque ellipses of
2-15% of its area are drawn on it (people and cars in front of the building). With `--frames K`, K
neighbouring images (in name order, from a random place) are a video's frames instead, as a user
extracts them: one size (half the scene's), no other change, PNG named `video_f000000.png`, ... and
no EXIF, like the photos.

    python lab/scripts/photo_collection_standin.py ../shared/data/strecha-castle-P30 DEST [--seed 1]
        [--crop 0.5] [--occluders 3] [--frames 10]

DEST gets images/, gt/ (COLMAP text) and SCENE.md (how it was made).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image, ImageEnhance


def crop(img: Image.Image, rng: np.random.Generator, smallest: float) -> tuple[Image.Image, int, int]:
    """A random window of `smallest` to 1 of the photo's width and height; returns it and its corner."""
    if smallest >= 1.0:
        return img, 0, 0
    w, h = (max(32, round(side * float(rng.uniform(smallest, 1.0)))) for side in img.size)
    x0, y0 = int(rng.integers(0, img.width - w + 1)), int(rng.integers(0, img.height - h + 1))
    return img.crop((x0, y0, x0 + w, y0 + h)), x0, y0


def occlude(img: Image.Image, rng: np.random.Generator, most: int) -> Image.Image:
    """Up to `most` opaque ellipses of random colour, 2-15% of the photo's area each."""
    from PIL import ImageDraw

    draw = ImageDraw.Draw(img)
    for _ in range(int(rng.integers(0, most + 1))):
        area = float(rng.uniform(0.02, 0.15)) * img.width * img.height
        aspect = float(rng.uniform(0.3, 1.0))  # taller than wide, like people
        rx, ry = (area * aspect / np.pi) ** 0.5, (area / aspect / np.pi) ** 0.5
        cx, cy = float(rng.uniform(0, img.width)), float(rng.uniform(0, img.height))
        draw.ellipse((cx - rx, cy - ry, cx + rx, cy + ry), fill=tuple(int(v) for v in rng.integers(0, 256, 3)))
    return img


def perturb(img: Image.Image, rng: np.random.Generator) -> tuple[Image.Image, float, int]:
    """The photo as another camera would take it; returns it, its scale and its JPEG quality."""
    scale = float(rng.uniform(0.35, 1.0))
    size = (max(1, round(img.width * scale)), max(1, round(img.height * scale)))
    out = img.convert("RGB").resize(size, Image.LANCZOS)
    out = ImageEnhance.Brightness(out).enhance(float(rng.uniform(0.5, 1.5)))
    out = ImageEnhance.Contrast(out).enhance(float(rng.uniform(0.6, 1.4)))
    out = ImageEnhance.Color(out).enhance(float(rng.uniform(0.3, 1.7)))
    gamma = float(rng.uniform(0.6, 1.6))
    lut = [min(255, round(255 * (i / 255) ** gamma)) for i in range(256)] * 3
    return out.point(lut), size[0] / img.width, int(rng.integers(50, 91))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("dest", type=Path)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--crop", type=float, default=1.0, help="smallest share of width and height kept (1: none)")
    parser.add_argument("--occluders", type=int, default=0, help="most occluding ellipses per photo")
    parser.add_argument("--frames", type=int, default=0, help="neighbouring images written as a video's frames")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    gt = pycolmap.Reconstruction()
    gt.read_text(str(args.scene / "gt"))
    by_name = sorted(gt.images, key=lambda i: gt.images[i].name)
    first = int(rng.integers(0, len(by_name) - args.frames + 1)) if args.frames else 0
    frames = {image_id: f"video_f{k:06d}.png" for k, image_id in enumerate(by_name[first:first + args.frames])}
    names = {}
    (args.dest / "images").mkdir(parents=True, exist_ok=True)
    (args.dest / "gt").mkdir(parents=True, exist_ok=True)
    out = pycolmap.Reconstruction()
    lines = []
    for image_id in sorted(gt.images):
        image = gt.images[image_id]
        original = Image.open(args.scene / "images" / image.name).convert("RGB")
        if image_id in frames:  # a video's frame: half size, nothing else changed
            x0 = y0 = 0
            cut, quality = original, 100
            photo = original.resize((round(original.width / 2), round(original.height / 2)), Image.LANCZOS)
            scale = photo.width / original.width
            names[image_id] = frames[image_id]
            photo.save(args.dest / "images" / names[image_id])
        else:
            cut, x0, y0 = crop(original, rng, args.crop)
            photo, scale, quality = perturb(cut, rng)
            photo = occlude(photo, rng, args.occluders) if args.occluders else photo
            names[image_id] = Path(image.name).with_suffix(".jpg").name
            photo.save(args.dest / "images" / names[image_id], quality=quality)
        fx, fy, cx, cy = gt.cameras[image.camera_id].params[:4]
        camera = pycolmap.Camera(model="PINHOLE", width=photo.width, height=photo.height,
                                 params=[fx * scale, fy * scale, (cx - x0) * scale, (cy - y0) * scale],
                                 camera_id=image_id)
        out.add_camera(camera)
        lines.append(f"{image_id} {camera.width} {camera.height} {scale:.4f} {quality} {x0} {y0} {cut.width} "
                     f"{cut.height}")
    # the true poses, written as text with the new names and cameras
    with open(args.dest / "gt" / "cameras.txt", "w") as f:
        for image_id in sorted(gt.images):
            cam = out.cameras[image_id]
            f.write(f"{image_id} PINHOLE {cam.width} {cam.height} " + " ".join(f"{p:.6f}" for p in cam.params) + "\n")
    with open(args.dest / "gt" / "images.txt", "w") as f:
        for image_id in sorted(gt.images):
            image = gt.images[image_id]
            pose = image.cam_from_world()
            qx, qy, qz, qw = pose.rotation.quat
            tx, ty, tz = pose.translation
            f.write(f"{image_id} {qw} {qx} {qy} {qz} {tx} {ty} {tz} {image_id} {names[image_id]}\n\n")
    (args.dest / "gt" / "points3D.txt").write_text("")
    (args.dest / "SCENE.md").write_text(
        f"Photo-collection stand-in of {args.scene.name} (lab/scripts/photo_collection_standin.py, seed "
        f"{args.seed}): each image rescaled by 0.35-1, brightness x0.5-1.5, contrast x0.6-1.4, saturation "
        "x0.3-1.7, gamma 0.6-1.6, JPEG quality 50-90; one PINHOLE camera per image, intrinsics scaled; "
        f"cropped first to {args.crop}-1 of each side; up to {args.occluders} occluding ellipses; "
        f"{args.frames} neighbouring images as a video's frames at half size (video_f*.png).\n"
        "image_id width height scale quality crop_x crop_y crop_width crop_height:\n" + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
