"""How the images of a run share cameras: the rule of `camera_mode=auto`, and one camera for the
frames of each video of a folder of clips."""

from __future__ import annotations

from pathlib import Path

from . import colmap
from .config import ExtractConfig
from .io import images as image_files
from .io.images import ImageSet


def resolve_camera_mode(images: ImageSet, conf: ExtractConfig, groups: dict[str, str] | None = None) -> str:
    """`auto`: one shared camera when every image has the same size and the same EXIF camera (make,
    model and focal length, or no EXIF at all, as frames of one video); one camera per video
    (`per_video`) for frames of several videos (`groups`: frame -> its video), which may come from
    other phones or the same phone turned; else one camera per image: photos of the same size from
    different phones must not share intrinsics."""
    if conf.camera_mode != "auto":
        if conf.camera_mode not in ("single", "per_image", "per_folder"):
            raise ValueError(f"unknown camera_mode {conf.camera_mode!r}; choose auto, single, per_image or "
                             "per_folder")
        return conf.camera_mode
    if groups and len({groups.get(n) for n in images.names}) > 1:
        return "per_video"
    sizes = {images.sizes[n] for n in images.names}
    if len(sizes) > 1:
        return "per_image"
    cameras = {image_files.exif_camera(images.root / n) for n in images.names}
    return "single" if len(cameras) == 1 else "per_image"


def share_per_video(db_path: Path, images: ImageSet, groups: dict[str, str]) -> dict[str, list[str]]:
    """One camera for the frames of each video (of each size, should a video change size); returns
    video -> its frames in the database."""
    by_video: dict[tuple, list[str]] = {}
    kept = colmap.images_with_keypoints(db_path)
    for name in images.names:
        if name in kept:
            by_video.setdefault((groups.get(name, name), images.sizes[name]), []).append(name)
    colmap.share_cameras(db_path, list(by_video.values()))
    out: dict[str, list[str]] = {}
    for (video, _), names in by_video.items():
        out.setdefault(video, []).extend(names)
    return out
