"""An occluder stand-in made from a shared scene: something textured that travels with the camera.

A hand or a selfie stick in the corner of a phone video, a car's bonnet with its reflections under a
dashcam, a drone's landing gear: textured, in nearly every frame, moving a few pixels from frame to
frame, so neither a static overlay (sara's `overlay`, which needs keypoints within half a pixel)
nor the scene explains its matches. This pastes a textured ellipse (a crop of another scene's image)
near the bottom of each frame of SCENE, shifted by up to --jitter pixels at random per frame,
writes the matching masks (black on the ellipse, a few pixels wider), and copies the true poses.

    python lab/scripts/occluder_standin.py ../shared/data/kitti-seq1 DEST \\
        --texture ../shared/data/strecha-castle-P30/images/0010.jpg [--jitter 6] [--size 0.45]

DEST gets images/ (the source names and formats), masks/ (DEST/masks/<name>.png), gt/ (a copy) and
SCENE.md.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import cv2
import numpy as np


def occluder(texture: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(patch, ellipse mask) of `width` x `height` pixels from the middle of `texture`."""
    th, tw = texture.shape[:2]
    scale = max(width / tw, height / th) * 1.2
    resized = cv2.resize(texture, (int(tw * scale) + 1, int(th * scale) + 1), interpolation=cv2.INTER_AREA)
    y0, x0 = (resized.shape[0] - height) // 2, (resized.shape[1] - width) // 2
    patch = resized[y0:y0 + height, x0:x0 + width]
    ellipse = np.zeros((height, width), np.uint8)
    cv2.ellipse(ellipse, (width // 2, height // 2), (width // 2 - 1, height // 2 - 1), 0, 0, 360, 255, -1)
    return patch, ellipse > 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("dest", type=Path)
    parser.add_argument("--texture", type=Path, required=True, help="an image whose middle becomes the occluder")
    parser.add_argument("--size", type=float, default=0.45, help="the occluder's height over the frame's (0.45)")
    parser.add_argument("--jitter", type=float, default=6.0, help="largest shift between frames, pixels (6)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    images, masks = args.dest / "images", args.dest / "masks"
    images.mkdir(parents=True)
    masks.mkdir()
    sources = sorted((args.scene / "images").iterdir())
    first = cv2.imread(str(sources[0]), cv2.IMREAD_UNCHANGED)
    h, w = first.shape[:2]
    oh = int(args.size * h)
    ow = int(1.6 * oh)
    texture = cv2.imread(str(args.texture), cv2.IMREAD_GRAYSCALE if first.ndim == 2 else cv2.IMREAD_COLOR)
    patch, inside = occluder(texture, ow, oh)
    margin = int(np.ceil(args.jitter)) + 4
    for source in sources:
        frame = cv2.imread(str(source), cv2.IMREAD_UNCHANGED)
        dx, dy = rng.uniform(-args.jitter, args.jitter, 2)
        x0, y0 = int(round(w * 0.62 + dx)), int(round(h - oh - margin + dy))
        region = frame[y0:y0 + oh, x0:x0 + ow]
        region[inside[:region.shape[0], :region.shape[1]]] = patch[:region.shape[0], :region.shape[1]][
            inside[:region.shape[0], :region.shape[1]]]
        name = source.name  # the true model's name (JPEG kept as JPEG, at quality 95)
        cv2.imwrite(str(images / name), frame, [cv2.IMWRITE_JPEG_QUALITY, 95])
        mask = np.full((h, w), 255, np.uint8)
        cv2.ellipse(mask, (x0 + ow // 2, y0 + oh // 2), (ow // 2 + 4, oh // 2 + 4), 0, 0, 360, 0, -1)
        cv2.imwrite(str(masks / f"{name}.png"), mask)
    shutil.copytree(args.scene / "gt", args.dest / "gt")
    (args.dest / "SCENE.md").write_text(
        f"Occluder stand-in of {args.scene.name} (lab/scripts/occluder_standin.py, texture {args.texture.name}, "
        f"size {args.size}, jitter {args.jitter} px, seed {args.seed}): a textured ellipse near the bottom of "
        "every frame, moving by up to the jitter between frames; masks/ black on it.\n", encoding="utf-8")


if __name__ == "__main__":
    main()
