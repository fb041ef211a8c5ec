"""A dashcam stand-in made from a shared sequence: an overlay burned into every frame.

Dashcams (and many drones and action cameras) burn a logo, a running clock and the speed into
their frames. Those pixels never move, so their keypoints match between every two frames at zero
motion and tell the mapper the camera stood still. This draws such an overlay on each frame of
SCENE (a black logo box in the top-left corner with white text, and a clock whose seconds change
from frame to frame with a speed, white, bottom right), as `tests/test_overlay.py` does, and copies
the true poses unchanged.

    python lab/scripts/dashcam_standin.py ../shared/data/kitti-seq1 DEST

DEST gets images/ (PNG, the source names), gt/ (a copy) and SCENE.md.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import cv2


def draw_overlay(image, k: int):
    """`image` with the overlay of frame `k` drawn on it (in place; returned)."""
    cv2.rectangle(image, (10, 10), (230, 50), (0, 0, 0), -1)
    cv2.putText(image, "DASHCAM 4K", (18, 40), cv2.FONT_HERSHEY_SIMPLEX, 0.9, (255, 255, 255), 2)
    cv2.putText(image, f"2026/12/07 08:13:{k % 60:02d}  52 km/h", (image.shape[1] - 520, image.shape[0] - 15),
                cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2)
    return image


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("dest", type=Path)
    args = parser.parse_args()
    images = args.dest / "images"
    images.mkdir(parents=True)
    sources = sorted((args.scene / "images").iterdir())
    for k, path in enumerate(sources):
        cv2.imwrite(str(images / path.name), draw_overlay(cv2.imread(str(path)), k))
    shutil.copytree(args.scene / "gt", args.dest / "gt")
    (args.dest / "SCENE.md").write_text(
        f"# {args.scene.name} with a dashcam's overlay\n\n{len(sources)} frames of {args.scene.name} with a logo "
        "box, a running clock and a speed drawn on each (lab/scripts/dashcam_standin.py); poses unchanged.\n")
    print(f"{len(sources)} frames -> {images}")


if __name__ == "__main__":
    main()
