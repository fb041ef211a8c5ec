"""Video input: the frames of a video, or of a folder of videos, picked and written as PNG images so
that the pipeline runs on them as on any folder of images (`sara run capture.mp4 OUT`).

Frames are picked evenly in time: each video is cut into as many windows of consecutive frames as
frames are wanted, and one sharp frame of each window is kept (by the variance of the Laplacian of
its grey image: the frame nearest the window's middle among those nearly as sharp as the sharpest),
since motion blur is what spoils the frames of a hand-held capture. A frame's name says where it
comes from and sorts in time order: `<video stem>_f<frame index>.png`, the index counted from 0 in
the video. `OUT/.sara/video.json` records the videos (size and digest), the
settings and every picked frame (index, time, sharpness): a re-run with the same videos and
settings reuses the frames without decoding, other videos or settings are refused.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from .colmap import model as colmap_model
from .io import OutputLock, OutputStateError, atomic_path, file_digest, prepare_output_dir, read_json, write_json_atomic
from .io.images import list_image_files

logger = logging.getLogger(__name__)

VIDEO_EXTENSIONS = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".mpg", ".mpeg", ".mts", ".m2ts", ".wmv",
                    ".flv", ".3gp", ".ogv")
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
#: where the record of the picked frames lives, relative to the output folder
RECORD = Path(".sara") / "video.json"
#: the ground truth of the picked frames (`--gt` of a video run), relative to the output folder
FRAMES_GT = Path(".sara") / "video-gt"
RECORD_VERSION = 1


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


def laplacian_sharpness(frame: np.ndarray) -> float:
    """Variance of the Laplacian of a frame's grey image (BGR or grey uint8, downscaled to at most
    SHARPNESS_SIDE_PX a side): higher is sharper."""
    import cv2

    grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame
    scale = SHARPNESS_SIDE_PX / max(grey.shape[:2])
    if scale < 1:
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


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


def find_videos(source: Path, *, recursive: bool = False) -> list[Path]:
    """The videos that `sara run SOURCE` reconstructs from: [SOURCE] for a video file, the videos
    of a folder that holds no image, or [] for a folder of images (or a missing path, which the
    image scan reports). A file that is neither a video nor a folder is an error (ValueError)."""
    source = Path(source)
    if source.is_file():
        if source.suffix.lower() in VIDEO_EXTENSIONS:
            return [source]
        raise ValueError(f"{source} is neither a folder of images nor a video (video extensions: "
                         f"{', '.join(VIDEO_EXTENSIONS)})")
    if not source.is_dir():
        return []
    videos = sorted(p for p in source.iterdir() if p.suffix.lower() in VIDEO_EXTENSIONS and p.is_file()
                    and not p.name.startswith("."))
    if videos and list_image_files(source, recursive=recursive):
        logger.warning("%s holds images and %d video(s): using the images; give a video, or a folder of videos "
                       "only, to use the videos", source, len(videos))
        return []
    stems = [p.stem for p in videos]
    twins = sorted({s for s in stems if stems.count(s) > 1})
    if twins:
        raise ValueError(f"{source} holds several videos named {twins[0]} (other extensions): their frames would "
                         "get the same names; rename one")
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
        raise ValueError(f"cannot read the video {path}: corrupt, truncated, or in a format OpenCV's FFmpeg cannot "
                         "decode")
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

    Two passes: the first scores every frame (and counts them: the count a container states is an
    estimate in some formats), the second writes the frames picked. Keeping the candidates of a
    window in memory instead would cost a window of full-size frames.
    """
    import cv2

    sharpness, times = [], []  # of every frame; times in seconds
    with open_video(video) as capture:
        stated = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
        size = (int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        for frame in tqdm(_frames(capture), total=stated if stated > 0 else None, desc=f"score frames of {video.name}",
                          unit="frame", disable=not progress):
            sharpness.append(laplacian_sharpness(frame))
            times.append(capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0)
    if not sharpness:
        raise ValueError(f"cannot read the video {video}: no frame could be decoded")
    num_frames = len(sharpness)
    picks = pick_sharp(np.array(sharpness), settings.num_picks(num_frames, fps, video.name))
    written = _write_frames(video, folder, picks, num_frames, progress=progress)
    entry = {"name": video.name, "path": str(video.resolve()), **_identity(video), "num_frames": num_frames,
             "fps": fps, "width": size[0], "height": size[1], "frames": []}
    for index in picks:
        entry["frames"].append({"name": frame_name(video.stem, index, num_frames), "index": index,
                                "time_s": round(times[index], 6), "sharpness": round(sharpness[index], 3),
                                "bytes": written[index]})
    return entry


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


def _identity(video: Path) -> dict[str, Any]:
    digest = file_digest(video)
    return {"size": digest["size"], "sha256": digest["sha256"]}


# ---------------------------------------------------------------------------------------------
# The frames folder of a run: made once, reused, never mixed with other frames
# ---------------------------------------------------------------------------------------------


def frames_for_run(videos: list[Path], out_dir: Path, settings: FrameSettings, *, gt_dir: Path | None = None,
                   overwrite: bool = False, progress: bool = True) -> tuple[Path, Path | None]:
    """(`OUT/images` holding the frames picked from `videos`, the ground truth of those frames or
    None): what `sara run VIDEO OUT` reconstructs from and is scored against.

    The frames are reused when `OUT/.sara/video.json` says the folder holds the frames of these
    very videos and settings; otherwise they are picked (every frame written atomically, the record
    marked complete only at the end). Raises OutputStateError (exit 3) when the folder holds frames
    of other videos or settings, or files sara did not write; `overwrite` picks them again instead.
    """
    if gt_dir is not None and not Path(gt_dir).exists():  # before any decoding
        raise FileNotFoundError(f"ground-truth folder not found: {gt_dir}")
    out_dir = prepare_output_dir(Path(out_dir))
    with OutputLock(out_dir):
        folder = _picked_frames(videos, out_dir, settings, overwrite=overwrite, progress=progress)
        gt = frames_ground_truth(Path(gt_dir), out_dir) if gt_dir is not None else None
    return folder, gt


def _picked_frames(videos: list[Path], out_dir: Path, settings: FrameSettings, *, overwrite: bool,
                   progress: bool) -> Path:
    folder = out_dir / "images"
    identity = [{"name": v.name, **_identity(v)} for v in videos]
    record = read_record(out_dir)
    same = record is not None and record.get("videos_identity") == identity and record.get("settings") == \
        settings.to_dict()
    if not overwrite:
        if record is not None and not same:
            raise OutputStateError(f"{_difference(record, identity, settings, folder)}: use another output folder, "
                                   "or --overwrite to pick the frames again")
        foreign = _foreign_files(folder, record)
        if foreign:
            raise OutputStateError(f"{folder} holds files sara did not pick from {videos[0].name} (e.g. "
                                   f"{foreign[0]}): use another output folder, or --overwrite to pick the frames "
                                   "again (it removes them)")
        if same and record.get("complete") and _frames_present(record, folder):
            logger.info("reusing the %d frames picked (%s) in %s", _count(record), settings.flag(), folder)
            return folder
    _clear(folder, record if not overwrite else None)
    folder.mkdir(parents=True, exist_ok=True)
    pending = {"version": RECORD_VERSION, "complete": False, "settings": settings.to_dict(),
               "videos_identity": identity, "videos": []}
    write_json_atomic(out_dir / RECORD, pending)
    entries = [decode_video(video, folder, settings, progress=progress) for video in videos]
    write_json_atomic(out_dir / RECORD, {**pending, "complete": True, "videos": entries})
    logger.info("%d frames picked from %d video(s) (%s) -> %s", sum(len(e["frames"]) for e in entries),
                len(entries), settings.flag(), folder)
    if settings.frames is None and settings.fps is None:
        _say_spacing(entries)
    return folder


def _say_spacing(entries: list[dict[str, Any]]) -> None:
    """Warn where the default number of frames leaves more than `SPARSE_SPACING_S` between them."""
    for entry in entries:
        picked, fps = len(entry["frames"]), entry.get("fps") or 0.0
        spacing = entry["num_frames"] / fps / max(picked, 1) if fps > 0 else 0.0
        if spacing > SPARSE_SPACING_S and picked < entry["num_frames"]:
            logger.warning("%s: %d frames of a %.0f s video, one every %.1f s (the default, --frames %d): a "
                           "camera that walks or turns needs closer frames, e.g. --fps 2 (%d frames)", entry["name"],
                           picked, entry["num_frames"] / fps, spacing, DEFAULT_FRAMES,
                           min(entry["num_frames"], round(2 * entry["num_frames"] / fps)))


def read_record(out_dir: Path) -> dict[str, Any] | None:
    """The record of the picked frames of an output folder (None when absent or unreadable)."""
    try:
        record = read_json(Path(out_dir) / RECORD)
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    return record if isinstance(record, dict) and record.get("version") == RECORD_VERSION else None


def camera_groups(out_dir: Path, images_root: Path) -> dict[str, str]:
    """Frame name -> the video it was picked from, where `images_root` is the frames folder of a
    video run (`sara run VIDEO OUT`); empty for any other folder of images."""
    record = read_record(out_dir)
    if not record or not record.get("complete") or Path(images_root).resolve() != (Path(out_dir) / "images").resolve():
        return {}
    return {frame["name"]: entry["name"] for entry in record.get("videos", []) for frame in entry.get("frames", [])}


def _difference(record: dict[str, Any], identity: list[dict[str, Any]], settings: FrameSettings,
                folder: Path) -> str:
    """What differs between the frames of `folder` and what this run asks for, in one clause."""
    before = record.get("videos_identity") or []
    old_names, new_names = [v.get("name") for v in before], [v["name"] for v in identity]
    if old_names != new_names:
        return f"{folder} holds the frames of {', '.join(map(str, old_names))}, not of {', '.join(new_names)}"
    changed = [new["name"] for old, new in zip(before, identity) if old != new]
    if changed:
        return f"{changed[0]} changed (size or content) since its frames in {folder} were picked"
    try:
        old_flag = FrameSettings(**record["settings"]).flag()
    except (KeyError, TypeError, ValueError):
        old_flag = "other settings"
    return f"{folder} holds frames picked with {old_flag}, not {settings.flag()}"


def _ours(record: dict[str, Any] | None) -> re.Pattern[str]:
    """The names sara writes in the frames folder for the videos of `record`: frames and the
    temporary files of atomic writes."""
    stems = [re.escape(Path(v.get("name", "")).stem) for v in (record or {}).get("videos_identity", [])]
    frames = rf"(?:{'|'.join(stems)})_f\d{{6,}}\.png" if stems else r"(?!)"
    return re.compile(rf"^(?:{frames}|\..+\.tmp)$")


def _foreign_files(folder: Path, record: dict[str, Any] | None) -> list[str]:
    if not folder.is_dir():
        return []
    ours = _ours(record)
    return sorted(p.name for p in folder.iterdir() if not ours.match(p.name))


def _clear(folder: Path, record: dict[str, Any] | None) -> None:
    """Remove the frames (and temporary files) of `record` from `folder`; with no record, every file
    (`--overwrite`: the folder is sara's own)."""
    if not folder.is_dir():
        return
    ours = _ours(record)
    for path in folder.iterdir():
        if record is None or ours.match(path.name):
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink()


def _frames_present(record: dict[str, Any], folder: Path) -> bool:
    """Whether every frame of a complete record is in `folder` with the size it was written with."""
    for video in record.get("videos", []):
        for frame in video.get("frames", []):
            path = folder / frame["name"]
            if not path.is_file() or path.stat().st_size != frame.get("bytes"):
                logger.warning("frame %s is missing or changed: picking the frames again", frame["name"])
                return False
    return _count(record) > 0


def _count(record: dict[str, Any]) -> int:
    return sum(len(video.get("frames", [])) for video in record.get("videos", []))


def frames_ground_truth(gt_dir: Path, out_dir: Path) -> Path:
    """The ground truth of the picked frames only, `OUT/.sara/video-gt` (COLMAP text): a run on a
    video is scored on the frames it was given, not on every frame that a ground truth poses.

    Raises FileNotFoundError for a missing ground truth, ValueError when it poses none of the frames.
    """
    gt_dir = Path(gt_dir)
    if not gt_dir.exists():
        raise FileNotFoundError(f"ground-truth folder not found: {gt_dir}")
    record = read_record(out_dir) or {}
    names = {frame["name"] for video in record.get("videos", []) for frame in video["frames"]}
    posed = set(colmap_model.read_model(gt_dir).names)
    common = names & posed
    if not common:
        raise ValueError(f"the ground truth {gt_dir} poses none of the frames picked from the video (e.g. "
                         f"{min(names, default='-')}; it poses e.g. {min(posed, default='-')}): frames are named "
                         "<video stem>_f<frame index>.png, the index counted from 0")
    dest = out_dir / FRAMES_GT
    tmp = dest.with_name(f"{dest.name}.tmp")  # removed with the temporaries of a killed run
    shutil.rmtree(tmp, ignore_errors=True)
    colmap_model.write_model(gt_dir, tmp, keep=common, text=True)
    shutil.rmtree(dest, ignore_errors=True)
    tmp.rename(dest)
    return dest
