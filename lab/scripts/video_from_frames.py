"""A video made from a scene's image sequence, with the ground truth of its frames, so that a model
made by `sara run VIDEO OUT` can be scored against the true poses of the frames sara picks.

    python lab/scripts/video_from_frames.py ../shared/data/kitti-seq1 DEST [--stem kitti] [--fps 10]
        [--fourcc MJPG] [--quality 95]

writes DEST/<stem>.avi (the images of SCENE/images in name order, one frame each) and DEST/gt: the
true model of SCENE/gt with image k renamed `<stem>_f<k>.png`, the name sara gives frame k of the
video (`sara.video.frame_name`). Then

    sara run DEST/<stem>.avi OUT --frames N --gt DEST/gt

scores the frames picked (sara keeps of the ground truth only the frames it picked).

MJPG in AVI (lossy, quality 95 by default, like a camera's own compression) is written and read by
OpenCV's FFmpeg everywhere; FFV1 is lossless; `mp4v` in .mp4 also works here, H.264 (`avc1`) did
not (no encoder in the opencv-python-headless wheel).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2

from sara.colmap import model
from sara.io.images import list_image_files
from sara.video import frame_name


def make_video(scene: Path, dest: Path, *, stem: str, fps: float, fourcc: str, quality: int) -> tuple[Path, Path]:
    names = list_image_files(scene / "images")
    if not names:
        raise SystemExit(f"no images in {scene / 'images'}")
    first = cv2.imread(str(scene / "images" / names[0]))
    height, width = first.shape[:2]
    dest.mkdir(parents=True, exist_ok=True)
    suffix = ".mp4" if fourcc == "mp4v" else ".avi"
    path = dest / f"{stem}{suffix}"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (width, height))
    if not writer.isOpened():
        raise SystemExit(f"OpenCV cannot write {fourcc} into {path}")
    if fourcc == "MJPG":
        writer.set(cv2.VIDEOWRITER_PROP_QUALITY, quality)
    for name in names:
        frame = cv2.imread(str(scene / "images" / name))
        if frame.shape[:2] != (height, width):
            raise SystemExit(f"{name} is {frame.shape[1]}x{frame.shape[0]}, not {width}x{height}: a video has "
                             "one size")
        writer.write(frame)
    writer.release()
    rename = {name: frame_name(stem, k, len(names)) for k, name in enumerate(names)}
    gt = model.write_model(scene / "gt", dest / "gt", rename=rename, text=True)
    (dest / "frames.json").write_text(json.dumps({"video": path.name, "fps": fps, "fourcc": fourcc,
                                                  "frames": rename}, indent=2) + "\n")
    return path, gt


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", type=Path, help="a folder holding images/ and gt/")
    parser.add_argument("dest", type=Path)
    parser.add_argument("--stem", default=None, help="the video's name without extension (default: the scene's)")
    parser.add_argument("--fps", type=float, default=10.0)
    parser.add_argument("--fourcc", default="MJPG", choices=["MJPG", "FFV1", "mp4v"])
    parser.add_argument("--quality", type=int, default=95, help="MJPG quality, 0-100")
    args = parser.parse_args()
    path, gt = make_video(args.scene, args.dest, stem=args.stem or args.scene.name, fps=args.fps,
                          fourcc=args.fourcc, quality=args.quality)
    print(f"{path} ({path.stat().st_size / 1e6:.1f} MB), ground truth of its frames: {gt}")


if __name__ == "__main__":
    main()
