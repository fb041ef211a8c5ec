"""Picking the frames of a video: windows of consecutive frames, the sharpest of each near its
middle (the pure core), finding the videos of an input, and decoding them (OpenCV's FFmpeg)."""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ..io import atomic_path, file_digest
from ..io.images import HEIC_EXTENSIONS, IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, WEB_FORMATS, list_image_files

logger = logging.getLogger(__name__)

#: frames picked per video when neither --frames nor --fps is given
DEFAULT_FRAMES = 150
#: above this many seconds between the frames picked by default, the run says how to pick closer
#: ones: a camera carried at walking pace moves about a metre a second, and turns faster than that
SPARSE_SPACING_S = 1.0
#: frames are scored for sharpness at most this many pixels a side, which bounds the cost for 4K video
SHARPNESS_SIDE_PX = 1024
#: a frame at least this fraction of its window's highest sharpness counts as sharp: the frames of a
#: steady sequence differ from their neighbours by a few percent, a blurred one scores far lower
SHARP_ENOUGH = 0.9
#: a frame whose grey levels spread less than this (standard deviation, of 255) holds nothing to
#: match: black, one colour, a lens cap, the first frames of a fade. Such frames are passed over,
#: and the picks spread over the others (textured frames spread by tens: 47-64 on the test scenes)
FLAT_CONTRAST = 4.0


# ---------------------------------------------------------------------------------------------
# The pure core: windows and picks
# ---------------------------------------------------------------------------------------------


def window_bounds(num_frames: int, num_picks: int) -> np.ndarray:
    """(num_picks + 1,) int64 frame indices: window k holds the frames [b[k], b[k + 1]); with
    1 <= num_picks <= num_frames every window holds at least one frame."""
    if not 1 <= num_picks <= num_frames:
        raise ValueError(f"cannot pick {num_picks} frames out of {num_frames}")
    return (np.arange(num_picks + 1, dtype=np.int64) * num_frames) // num_picks


def pick_sharp(sharpness: np.ndarray, num_picks: int) -> list[int]:
    """One frame index for each of `num_picks` even windows: the sharp frame nearest the window's
    middle, where sharp means at least SHARP_ENOUGH times the window's highest sharpness (the first
    of two equally near).

    sharpness: (num_frames,) float, higher is sharper. Taking the sharpest frame outright would pick
    at random among the equally sharp frames of a steady video, and two picks could then be
    neighbours; a blurred frame scores far below SHARP_ENOUGH and is still passed over.
    """
    sharpness = np.asarray(sharpness, dtype=np.float64)
    bounds = window_bounds(len(sharpness), num_picks)
    picks = []
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        window = sharpness[lo:hi]
        sharp = np.flatnonzero(window >= SHARP_ENOUGH * window.max())
        picks.append(int(lo + sharp[np.argmin(np.abs(sharp - (hi - lo - 1) / 2))]))
    return picks


def frame_scores(frame: np.ndarray) -> tuple[float, float]:
    """(sharpness: the variance of the Laplacian of the frame's grey image, higher is sharper;
    contrast: the standard deviation of its grey levels), from one grey image (BGR or grey uint8)
    downscaled to at most SHARPNESS_SIDE_PX a side."""
    import cv2

    grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame
    scale = SHARPNESS_SIDE_PX / max(grey.shape[:2])
    if scale < 1:
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var()), float(grey.std())


def pick_textured(sharpness: np.ndarray, contrast: np.ndarray, num_picks: Callable[[int], int]) -> list[int]:
    """`pick_sharp` over the frames that are not flat (contrast at least FLAT_CONTRAST; all of them
    when every frame is flat), `num_picks(number of such frames)` of them: frame indices."""
    textured = np.flatnonzero(np.asarray(contrast) >= FLAT_CONTRAST)
    if len(textured) == 0:
        textured = np.arange(len(sharpness))
    return [int(textured[k]) for k in pick_sharp(np.asarray(sharpness)[textured], num_picks(len(textured)))]


@dataclass(frozen=True)
class FrameSettings:
    """How many frames to pick per video: `frames`, or `fps` frames per second of video."""

    frames: int | None = None
    fps: float | None = None

    def __post_init__(self) -> None:
        if self.frames is not None and self.fps is not None:
            raise ValueError("give --frames or --fps, not both")
        if self.frames is not None and self.frames < 1:
            raise ValueError(f"--frames must be at least 1, got {self.frames}")
        if self.fps is not None and not self.fps > 0:
            raise ValueError(f"--fps must be above 0, got {self.fps}")

    def to_dict(self) -> dict[str, Any]:
        """The settings as recorded (with neither given: the default number of frames)."""
        if self.fps is not None:
            return {"frames": None, "fps": self.fps}
        return {"frames": self.frames or DEFAULT_FRAMES, "fps": None}

    def flag(self) -> str:
        """The settings as the command line gives them, e.g. `--frames 150`."""
        return f"--fps {self.fps:g}" if self.fps is not None else f"--frames {self.to_dict()['frames']}"

    def num_picks(self, num_frames: int, video_fps: float, name: str) -> int:
        """Frames to pick from a video of `num_frames` frames at `video_fps` (at most all of them)."""
        if self.fps is None:
            return min(self.to_dict()["frames"], num_frames)
        if not video_fps > 0:
            raise ValueError(f"the video {name} does not state its frame rate: use --frames instead of --fps")
        return min(num_frames, max(1, round(num_frames * self.fps / video_fps)))


# ---------------------------------------------------------------------------------------------
# Finding the videos of an input
# ---------------------------------------------------------------------------------------------


ARCHIVE_SUFFIXES = (".zip", ".tar", ".tgz", ".tar.gz", ".tar.bz2", ".tar.xz", ".7z", ".rar")


def _what_to_give(source: Path) -> str:
    """What to give instead of the file `source`: its folder for an image, the unpacked folder for an
    archive ("" for another file: the video extensions are listed instead)."""
    name = source.name.lower()
    if name.endswith(ARCHIVE_SUFFIXES):
        return ": an archive; unpack it and give the folder of images it holds"
    if name.endswith(IMAGE_EXTENSIONS + HEIC_EXTENSIONS + tuple(WEB_FORMATS)):
        return f": one image; give the folder that holds the images, {source.parent}"
    return ""


def find_videos(source: Path, *, recursive: bool = False) -> list[Path]:
    """The videos that `sara run SOURCE` reconstructs from: [SOURCE] for a video file, the videos
    of a folder that holds no image (and of its sub-folders, `recursive`), or [] for a folder of
    images (or a missing path, which the image scan reports). A file that is neither a video nor a
    folder is an error (ValueError)."""
    source = Path(source)
    if source.is_file():
        if source.suffix.lower() in VIDEO_EXTENSIONS:
            return [source]
        hint = _what_to_give(source) or f" (video extensions: {', '.join(VIDEO_EXTENSIONS)})"
        raise ValueError(f"{source} is neither a folder of images nor a video{hint}")
    if not source.is_dir():
        return []
    found = source.rglob("*") if recursive else source.iterdir()
    videos = sorted(p for p in found if p.suffix.lower() in VIDEO_EXTENSIONS and p.is_file()
                    and not any(part.startswith(".") for part in p.relative_to(source).parts))
    if videos and list_image_files(source, recursive=recursive):
        logger.warning("%s holds images and %d video(s): using the images; give a video, or a folder of videos "
                       "only, to use the videos", source, len(videos))
        return []
    stems = [p.stem for p in videos]
    twins = sorted({s for s in stems if stems.count(s) > 1})
    if twins:
        raise ValueError(f"{source} holds several videos named {twins[0]} (other extensions or folders): their "
                         "frames would get the same names; rename one")
    return videos


def frame_name(stem: str, index: int, num_frames: int) -> str:
    """`<stem>_f000123.png`: six digits at least, more for longer videos, so names sort in time order."""
    return f"{stem}_f{index:0{max(6, len(str(max(num_frames - 1, 0))))}d}.png"


# ---------------------------------------------------------------------------------------------
# Decoding
# ---------------------------------------------------------------------------------------------


@contextlib.contextmanager
def open_video(path: Path) -> Iterator[Any]:
    """An OpenCV capture of a video (its FFmpeg back end, quiet); ValueError when it cannot be read."""
    import cv2

    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # FFmpeg's own complaints, before the one line
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    finally:
        cv2.utils.logging.setLogLevel(level)
    if not capture.isOpened():
        if path.stat().st_size == 0:
            raise ValueError(f"cannot read the video {path}: empty file (0 bytes)")
        raise ValueError(f"cannot read the video {path}: corrupt, truncated, without a video stream (sound only), "
                         "or in a format OpenCV's FFmpeg cannot decode")
    try:
        yield capture
    finally:
        capture.release()


def _write_png(frame: np.ndarray, path: Path) -> int:
    """Write a frame losslessly and atomically (a killed run leaves no half-written frame); its bytes."""
    import cv2

    ok, data = cv2.imencode(".png", frame)
    if not ok:
        raise OSError(f"could not encode frame {path.name} as PNG")
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.tobytes())
    return len(data)


def decode_video(video: Path, folder: Path, settings: FrameSettings, *, progress: bool = True) -> dict[str, Any]:
    """Pick the frames of one video and write them into `folder`; returns the video's record entry.

    One reading scores every frame and counts them, and writes the picks of even windows over the
    frame count the container states as it goes (`OnePass`). The picks are then those of
    `pick_textured` on every frame's scores; where they differ from the frames written (the count
    was an estimate, some frames were flat, a window held too many candidates), the frames written
    that are not picks are deleted and a second reading writes the picks missing.
    """
    import cv2

    sharpness, contrast, times = [], [], []  # of every frame; times in seconds
    with open_video(video) as capture:
        stated = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
        size = (int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        one_pass = OnePass(window_bounds(stated, settings.num_picks(stated, fps, video.name)),
                           lambda index, frame: _write_png(frame, folder / frame_name(video.stem, index, stated))) \
            if stated > 0 else None
        for index, frame in enumerate(tqdm(_frames(capture), total=stated if stated > 0 else None,
                                           desc=f"read frames of {video.name}", unit="frame", disable=not progress)):
            scores = frame_scores(frame)
            sharpness.append(scores[0])
            contrast.append(scores[1])
            times.append(capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0)
            if one_pass is not None:
                one_pass.offer(index, scores[0], frame)
    if not sharpness:
        raise ValueError(f"cannot read the video {video}: no frame could be decoded")
    num_frames = len(sharpness)
    picks = pick_textured(np.array(sharpness), np.array(contrast), lambda n: settings.num_picks(n, fps, video.name))
    flat = int(np.sum(np.array(contrast) < FLAT_CONTRAST))
    if flat:
        logger.info("%s: %d of its %d frames have no texture (black or one colour: a fade, a lens cap): the frames "
                    "are picked among the others", video.name, flat, num_frames)
    written = {} if one_pass is None else one_pass.written
    for index in list(written):  # not a pick after all, or named for another count of frames
        if index not in picks or frame_name(video.stem, index, stated) != frame_name(video.stem, index, num_frames):
            (folder / frame_name(video.stem, index, stated)).unlink(missing_ok=True)
            del written[index]
    missing = [index for index in picks if index not in written]
    if missing:
        written.update(_write_frames(video, folder, missing, num_frames, progress=progress))
    entry = {"name": video.name, "path": str(video.resolve()), **identity_of(video), "num_frames": num_frames,
             "num_flat": flat, "fps": fps, "width": size[0], "height": size[1], "readings": 2 if missing else 1,
             "frames": []}
    for index in picks:
        entry["frames"].append({"name": frame_name(video.stem, index, num_frames), "index": index,
                                "time_s": round(times[index], 6), "sharpness": round(sharpness[index], 3),
                                "bytes": written[index]})
    return entry


class OnePass:
    """The picks of `pick_sharp` over the windows `bounds`, written while the frames go by in order.

    Of the frames of the current window only those that could still be its pick are held: a frame
    is passed over once another of the window is at least as sharp and nearer its middle (or as near
    and earlier), as that one is then picked before it whatever comes later, or once it is under
    SHARP_ENOUGH of the window's sharpest so far, as it cannot be sharp again. When the window ends
    its pick is written (`write(index, frame)` -> bytes). A window whose frames would hold more than
    MAX_HELD in memory at once writes nothing (a second reading does)."""

    #: the most frames of one window held at once: in a steady video a few are (sharpness varies by a
    #: few percent from frame to frame); a 4K frame takes 25 MB
    MAX_HELD = 8

    def __init__(self, bounds: np.ndarray, write: Callable[[int, np.ndarray], int]) -> None:
        self.bounds, self.write = [int(b) for b in bounds], write
        self.window, self.held, self.best, self.overflow = 0, [], 0.0, False
        self.written: dict[int, int] = {}  # frame index -> bytes written

    def offer(self, index: int, sharpness: float, frame: np.ndarray) -> None:
        while self.window + 1 < len(self.bounds) and index >= self.bounds[self.window + 1]:
            self.window, self.held, self.best, self.overflow = self.window + 1, [], 0.0, False
        if self.window + 1 >= len(self.bounds):
            return  # beyond the frames the container stated
        lo, hi = self.bounds[self.window], self.bounds[self.window + 1]
        distance = abs(index - lo - (hi - lo - 1) / 2)
        self.best = max(self.best, sharpness)
        if not self.overflow and not any(d <= distance and s >= sharpness for d, s, _, _ in self.held):
            self.held = [h for h in self.held if not (distance < h[0] and sharpness >= h[1])  # passed over
                         and h[1] >= SHARP_ENOUGH * self.best] + [(distance, sharpness, index, frame)]  # sharp
            if len(self.held) > self.MAX_HELD:
                self.held, self.overflow = [], True
        if index == hi - 1 and self.held:
            _, _, pick, chosen = min((h for h in self.held if h[1] >= SHARP_ENOUGH * self.best),
                                     key=lambda h: (h[0], h[2]))
            self.written[pick] = self.write(pick, chosen)
            self.held = []


def _frames(capture: Any) -> Iterator[np.ndarray]:
    while True:
        ok, frame = capture.read()
        if not ok:
            return
        yield frame


def _write_frames(video: Path, folder: Path, picks: list[int], num_frames: int, *,
                  progress: bool = True) -> dict[int, int]:
    """Decode the video again and write the frames `picks` (indices, ascending); index -> bytes."""
    wanted, written = set(picks), {}
    with open_video(video) as capture:
        for index in tqdm(range(picks[-1] + 1), desc=f"write frames of {video.name}", unit="frame",
                          disable=not progress):
            if not capture.grab():
                break
            if index in wanted:
                ok, frame = capture.retrieve()
                if ok:
                    written[index] = _write_png(frame, folder / frame_name(video.stem, index, num_frames))
    missing = wanted - set(written)
    if missing:
        raise ValueError(f"cannot read the video {video}: frame {min(missing)} could not be decoded a second time")
    return written


def identity_of(video: Path) -> dict[str, Any]:
    digest = file_digest(video)
    return {"size": digest["size"], "sha256": digest["sha256"]}
