"""A folder of clips cut from one image sequence, as a user brings the videos of a phone: each clip
its own video, of its own size (`--scale`), turned a quarter as a phone held upright (`--turns`), or
filmed with a longer lens at the same size (`--zoom`: the centre 1 / z of each frame, enlarged back),
with the ground truth of the frames, so that the run on the folder is scored against true poses.

    python lab/scripts/video_clips_standin.py ../shared/data/kitti-seq1 DEST --clips 2 [--scale 1,0.8]
        [--turns 0,1] [--zoom 1,1.25] [--quality 95] [--images]
    sara run DEST/clips OUT --frames N --gt DEST/gt
    sara run DEST/images OUT --gt DEST/gt          # with --images

writes DEST/clips/clip<k>.avi (MJPG, as `video_from_frames.py`; consecutive images of SCENE/images
in name order, split into equal runs) and DEST/gt: the true model of SCENE/gt with each image named
as sara names its frame (`sara.video.frame_name`), the poses of the turned clips' frames turned
with their images (the camera's x and y axes go with the picture), so the evaluation holds for them.
With `--images`, each clip's frames are written instead as numbered PNG images in DEST/images, with
the names sara would give them and no EXIF, as a user's own `ffmpeg -i clip0.mp4 clip0_f%06d.png`
leaves them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from sara.colmap import model
from sara.io.images import list_image_files
from sara.video import frame_name

#: camera axes of an image turned a quarter clockwise (np.rot90(k=-1)): x' = -y, y' = x
QUARTER = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    w = np.sqrt(max(0.0, 1 + np.trace(R))) / 2
    x = np.copysign(np.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
    y = np.copysign(np.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
    z = np.copysign(np.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
    return np.array([w, x, y, z])


def _turned(q: np.ndarray, t: np.ndarray, turns: int) -> list[str]:
    Q = np.linalg.matrix_power(QUARTER, turns)
    return [f"{v:.12g}" for v in (*matrix_to_quat(Q @ quat_to_matrix(q)), *(Q @ t))]


def turn_poses(gt: Path, turned: dict[str, int]) -> None:
    """Turn the poses of the images `turned` (name -> quarter turns clockwise) in a text model:
    COLMAP keeps a pose on the image's frame (frames.txt; one camera a rig here, so the frame's pose
    is the camera's) and repeats it in images.txt."""
    lines = (gt / "images.txt").read_text().splitlines()
    header = [line for line in lines if line.startswith("#")]
    body = lines[len(header):]  # two lines an image: its pose, then its points (an empty line if none)
    turns_of_id = {}
    for k in range(0, len(body), 2):
        f = body[k].split()
        name = " ".join(f[9:])
        if turned.get(name):
            turns_of_id[f[0]] = turned[name]
            body[k] = " ".join([f[0], *_turned(np.array(f[1:5], float), np.array(f[5:8], float), turned[name]),
                                f[8], name])
    (gt / "images.txt").write_text("\n".join(header + body) + "\n")
    frames = []
    for line in (gt / "frames.txt").read_text().splitlines():
        f = line.split()
        if not line.startswith("#") and f[9] == "1" and f[12] in turns_of_id:  # one image: its pose
            line = " ".join([f[0], f[1], *_turned(np.array(f[2:6], float), np.array(f[6:9], float),
                                                  turns_of_id[f[12]]), *f[9:]])
        frames.append(line)
    (gt / "frames.txt").write_text("\n".join(frames) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", type=Path, help="a folder holding images/ and gt/ (a sequence)")
    parser.add_argument("dest", type=Path)
    parser.add_argument("--clips", type=int, default=2)
    parser.add_argument("--scale", default="", help="per clip, comma-separated (default 1 each)")
    parser.add_argument("--turns", default="", help="per clip, quarter turns clockwise (default 0 each)")
    parser.add_argument("--zoom", default="", help="per clip, focal length over the scene's (default 1 each)")
    parser.add_argument("--fps", type=float, default=10.0)
    parser.add_argument("--quality", type=int, default=95)
    parser.add_argument("--images", action="store_true", help="write each clip's frames as PNG images, not a video")
    args = parser.parse_args()
    names = list_image_files(args.scene / "images")
    scales = [float(v) for v in args.scale.split(",")] if args.scale else [1.0] * args.clips
    turns = [int(v) for v in args.turns.split(",")] if args.turns else [0] * args.clips
    zooms = [float(v) for v in args.zoom.split(",")] if args.zoom else [1.0] * args.clips
    if len(scales) != args.clips or len(turns) != args.clips or len(zooms) != args.clips:
        raise SystemExit("--scale, --turns and --zoom take one value per clip")
    clips_dir = args.dest / ("images" if args.images else "clips")
    clips_dir.mkdir(parents=True, exist_ok=True)
    rename, turned, listing = {}, {}, []
    for k, part in enumerate(np.array_split(np.array(names), args.clips)):
        stem = f"clip{k}"
        frames = []
        for name in part:
            frame = cv2.imread(str(args.scene / "images" / name))
            if zooms[k] != 1.0:  # the centre enlarged about the image centre: a longer lens
                h, w = frame.shape[:2]
                M = np.array([[zooms[k], 0.0, (1 - zooms[k]) * w / 2], [0.0, zooms[k], (1 - zooms[k]) * h / 2]])
                frame = cv2.warpAffine(frame, M, (w, h), flags=cv2.INTER_LINEAR)
            if scales[k] != 1.0:
                frame = cv2.resize(frame, None, fx=scales[k], fy=scales[k], interpolation=cv2.INTER_AREA)
            frames.append(np.ascontiguousarray(np.rot90(frame, k=-turns[k])))
        height, width = frames[0].shape[:2]
        for index, name in enumerate(part):
            rename[str(name)] = frame_name(stem, index, len(part))
            turned[rename[str(name)]] = turns[k] % 4
        path = clips_dir / f"{stem}.avi"
        if args.images:
            for frame, name in zip(frames, part):
                cv2.imwrite(str(clips_dir / rename[str(name)]), frame)
        else:
            writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), args.fps, (width, height))
            writer.set(cv2.VIDEOWRITER_PROP_QUALITY, args.quality)
            for frame in frames:
                writer.write(frame)
            writer.release()
        listing.append({"video": None if args.images else path.name, "images": [str(n) for n in part],
                        "size": [width, height], "scale": scales[k], "turns": turns[k], "zoom": zooms[k]})
    gt = model.write_model(args.scene / "gt", args.dest / "gt", rename=rename, text=True)
    turn_poses(gt, turned)
    (args.dest / "clips.json").write_text(json.dumps(listing, indent=2) + "\n")
    print(f"{args.clips} clips {'as frames ' if args.images else ''}in {clips_dir}, ground truth of their frames: {gt}")


if __name__ == "__main__":
    main()
