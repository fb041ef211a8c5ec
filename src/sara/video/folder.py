"""The frames folder of a video run, `OUT/images`: made once, reused, updated where the folder of
videos changed, never mixed with other frames; its record `OUT/.sara/video.json`."""

from __future__ import annotations

import logging
import re
import shutil
from pathlib import Path
from typing import Any

from ..colmap import model as colmap_model
from ..io import OutputLock, OutputStateError, prepare_output_dir, read_json, write_json_atomic
from .picking import DEFAULT_FRAMES, SPARSE_SPACING_S, FrameSettings, decode_video, identity_of

logger = logging.getLogger(__name__)

#: where the record of the picked frames lives, relative to the output folder
RECORD = Path(".sara") / "video.json"
#: the ground truth of the picked frames (`--gt` of a video run), relative to the output folder
FRAMES_GT = Path(".sara") / "video-gt"
RECORD_VERSION = 1


def frames_for_run(videos: list[Path], out_dir: Path, settings: FrameSettings, *, gt_dir: Path | None = None,
                   overwrite: bool = False, progress: bool = True) -> tuple[Path, Path | None]:
    """(`OUT/images` holding the frames picked from `videos`, the ground truth of those frames or
    None): what `sara run VIDEO OUT` reconstructs from and is scored against.

    The frames are reused when `OUT/.sara/video.json` says the folder holds the frames of these
    very videos and settings, those of each unchanged video when some changed; the others are picked
    (every frame written atomically, the record marked complete only at the end). Raises
    OutputStateError (exit 3) when the folder holds frames of other settings or of none of these
    videos, or files sara did not write; `overwrite` picks them all again instead.
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
    """The frames of `videos` in OUT/images. A folder of videos that changed (a clip added, removed
    or replaced) keeps the frames of the videos that did not: only the others are decoded, and the
    pipeline then updates the run for the frames added and removed (`sara.incremental`). Refused:
    other settings, or no video in common (another capture), or files sara did not write."""
    folder = out_dir / "images"
    identity = [{"name": v.name, **identity_of(v)} for v in videos]
    record = None if overwrite else read_record(out_dir)
    kept = _reusable(record, identity, settings, folder)
    unreadable = _still_unreadable(record, identity, settings)
    if not overwrite:
        before = [v for v in (record or {}).get("videos_identity") or [] if v in identity]
        if record is not None and (record.get("settings") != settings.to_dict() or not before):
            raise OutputStateError(f"{_difference(record, identity, settings, folder)}: use another output folder, "
                                   "or --overwrite to pick the frames again")
        foreign = _foreign_files(folder, record)
        if foreign:
            raise OutputStateError(f"{folder} holds files sara did not pick from {videos[0].name} (e.g. "
                                   f"{foreign[0]}): use another output folder, or --overwrite to pick the frames "
                                   "again (it removes them)")
        if record is not None and record.get("complete") and record.get("videos_identity") == identity \
                and len(kept) + len(unreadable) == len(identity):
            logger.info("reusing the %d frames picked (%s) in %s", _count(record), settings.flag(), folder)
            _say_unreadable(unreadable)
            return folder
    _clear(folder, record, keep={frame["name"] for entry in kept.values() for frame in entry["frames"]})
    folder.mkdir(parents=True, exist_ok=True)
    pending = {"version": RECORD_VERSION, "complete": False, "settings": settings.to_dict(),
               "videos_identity": identity, "videos": [kept[v.name] for v in videos if v.name in kept],
               "unreadable": unreadable}
    write_json_atomic(out_dir / RECORD, pending)
    if kept and record is not None and record.get("complete"):
        logger.warning("videos: the frames of %d kept (%s), %d to pick; the run is updated for the frames added "
                       "and removed", len(kept), ", ".join(sorted(kept)), len(videos) - len(kept))
    elif kept:
        logger.info("the frames of %d video(s) picked before the run stopped are kept", len(kept))
    entries = []
    for k, video in enumerate(videos):
        if video.name in kept or video.name in unreadable:
            entries += [kept[video.name]] if video.name in kept else []
            continue
        try:
            entries.append(decode_video(video, folder, settings, progress=progress))
        except ValueError as exc:  # a clip of a folder that cannot be read: set aside, as an unreadable image is
            if len(videos) == 1:
                raise
            unreadable[video.name] = {"why": str(exc), **identity[k]}
            _say_unreadable({video.name: unreadable[video.name]})
        pending["videos"] = entries + [kept[v.name] for v in videos[k + 1:] if v.name in kept]
        write_json_atomic(out_dir / RECORD, pending)  # a kill loses the video being decoded, not those before
    if not entries:
        raise ValueError(f"none of the {len(videos)} videos could be read ({next(iter(unreadable.values()))['why']})")
    write_json_atomic(out_dir / RECORD, {**pending, "complete": True, "videos": entries})
    logger.info("%d frames picked from %d video(s) (%s) -> %s", sum(len(e["frames"]) for e in entries),
                len(entries), settings.flag(), folder)
    if settings.frames is None and settings.fps is None:
        _say_spacing(entries)
    return folder


def _reusable(record: dict[str, Any] | None, identity: list[dict[str, Any]], settings: FrameSettings,
              folder: Path) -> dict[str, dict[str, Any]]:
    """Video name -> its entry in `record`, for the videos of `identity` whose frames the folder holds
    as picked under the same settings (the same bytes, every frame present): those need no decoding."""
    if record is None or record.get("settings") != settings.to_dict():
        return {}
    before = {v.get("name"): v for v in record.get("videos_identity") or []}
    entries = {e.get("name"): e for e in record.get("videos", [])}
    return {v["name"]: entries[v["name"]] for v in identity
            if before.get(v["name"]) == v and v["name"] in entries and _frames_present([entries[v["name"]]], folder)}


def _still_unreadable(record: dict[str, Any] | None, identity: list[dict[str, Any]],
                     settings: FrameSettings) -> dict[str, dict[str, Any]]:
    """The videos of `identity` that `record` found unreadable, unchanged since: not tried again."""
    if record is None or record.get("settings") != settings.to_dict():
        return {}
    before = record.get("unreadable") or {}
    return {v["name"]: before[v["name"]] for v in identity
            if v["name"] in before and {k: before[v["name"]].get(k) for k in v} == v}


def _say_unreadable(unreadable: dict[str, dict[str, Any]]) -> None:
    for name, info in unreadable.items():
        logger.warning("skipping the video %s: %s", name, info["why"])


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


def summary(out_dir: Path) -> dict[str, Any] | None:
    """Where the frames of a video run came from (`stages.video` of run.json): the settings, and for
    each video its frames, those picked and those passed over as flat; the videos set aside."""
    record = read_record(out_dir)
    if not record or not record.get("complete"):
        return None
    try:
        flag = FrameSettings(**record["settings"]).flag()
    except (KeyError, TypeError, ValueError):
        flag = ""
    videos = [{"name": e.get("name"), "num_frames": e.get("num_frames"), "num_picked": len(e.get("frames", [])),
               "num_flat": e.get("num_flat", 0)} for e in record.get("videos", [])]
    return {"settings": flag, "videos": videos, "unreadable": sorted(record.get("unreadable") or {})}


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


def _clear(folder: Path, record: dict[str, Any] | None, *, keep: set[str] = frozenset()) -> None:
    """Remove the frames (and temporary files) of `record` from `folder`, but the frames `keep`
    (names); with no record, every file (`--overwrite`: the folder is sara's own)."""
    if not folder.is_dir():
        return
    ours = _ours(record)
    for path in folder.iterdir():
        if path.name not in keep and (record is None or ours.match(path.name)):
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink()


def _frames_present(entries: list[dict[str, Any]], folder: Path) -> bool:
    """Whether every frame of the videos `entries` (of a record) is in `folder` with the size it was
    written with."""
    for video in entries:
        for frame in video.get("frames", []):
            path = folder / frame["name"]
            if not path.is_file() or path.stat().st_size != frame.get("bytes"):
                logger.warning("frame %s is missing or changed: picking the frames of %s again", frame["name"],
                               video.get("name"))
                return False
    return sum(len(video.get("frames", [])) for video in entries) > 0


def _count(record: dict[str, Any]) -> int:
    return sum(len(video.get("frames", [])) for video in record.get("videos", []))


def frames_ground_truth(gt_dir: Path, out_dir: Path) -> Path:
    """The ground truth of the picked frames only, `OUT/.sara/video-gt` (COLMAP text): a run on a
    video is scored on the frames it was given, not on every frame that a ground truth poses.

    Raises FileNotFoundError for a missing ground truth, ValueError when it poses none of the frames.
    """
    from ..evaluation.ground_truth import transforms_file

    gt_dir = Path(gt_dir)
    if not gt_dir.exists():
        raise FileNotFoundError(f"ground-truth folder not found: {gt_dir}")
    if transforms_file(gt_dir) is not None:
        raise ValueError(f"the ground truth of a video's frames is a COLMAP model of them ({gt_dir} is a "
                         "transforms.json): its frames are named <video stem>_f<frame index>.png")
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
