"""How the images of a run share cameras: the rule of `camera_mode=auto`, one camera for the frames
of each video of a folder of clips (or of each numbered sequence of frames a user extracted), and one
for the photos of each phone of a collection."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

from . import colmap
from .config import ExtractConfig
from .io.images import ImageSet
from .io.numbered import numbered

#: the camera modes that import a camera per image, then give each group of images one camera
GROUPED_MODES = ("per_video", "per_exif", "per_sequence")
#: fewest frames of a numbered sequence of one size and EXIF that share a camera (`per_sequence`)
MIN_SEQUENCE_FRAMES = 3


class ExifCamera(NamedTuple):
    """What EXIF says of the camera of a photo; each None where absent or unreadable."""

    make: str | None
    model: str | None
    focal_mm: float | None
    focal_35mm: float | None  # FocalLengthIn35mmFilm: changes with a phone's digital zoom, the mm do not

    def complete(self) -> bool:
        """Whether it names one camera and lens setting: make, model and focal length."""
        return bool(self.make and self.model and self.focal_mm)


def exif_camera(path: Path) -> ExifCamera:
    """The EXIF camera of the image at `path` (all None without EXIF, or for a file it cannot read)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            exif = im.getexif()
            sub = exif.get_ifd(0x8769)
            make, model = exif.get(0x010F), exif.get(0x0110)
            focal, focal_35 = sub.get(0x920A) or exif.get(0x920A), sub.get(0xA405) or exif.get(0xA405)
    except Exception:  # noqa: BLE001 - EXIF is optional; any failure means "no EXIF"
        return ExifCamera(None, None, None, None)

    def number(value: object) -> float | None:
        try:
            return float(value) if value else None
        except (TypeError, ValueError, ZeroDivisionError):
            return None

    def text(value: object) -> str | None:
        return str(value).strip("\x00 ").strip() or None if value else None

    return ExifCamera(text(make), text(model), number(focal), number(focal_35))


def camera_sharing(images: ImageSet, conf: ExtractConfig,
                   videos: dict[str, str] | None = None) -> tuple[str, dict[str, str] | None]:
    """(camera mode, image -> its group for the grouped modes). `auto`: one shared camera when every
    image has the same size and the same EXIF camera (make, model and focal lengths, or no EXIF at
    all, as frames of one video) and they are not frames of several clips; one camera per video
    (`per_video`) for frames of several videos (`videos`: frame -> its video), which may come from
    other phones or the same phone turned; one camera per clip (`per_sequence`) for frames a user
    extracted from several clips (names that differ only by a frame number, without a camera in EXIF:
    `clip0_0001.png`, ...; `_sequence_groups`), clips of one size too, which a phone's other lens or a
    zoom may have filmed, the phones grouped as well; one camera per phone (`per_exif`) for photos
    whose EXIF names their camera (make, model, focal length) when some of them share one and a size
    (a few phones, a phone held both ways); else one camera per image: photos of the same size from
    different phones must not share intrinsics."""
    if conf.camera_mode != "auto":
        if conf.camera_mode not in ("single", "per_image", "per_folder"):
            raise ValueError(f"unknown camera_mode {conf.camera_mode!r}; choose auto, single, per_image or "
                             "per_folder")
        return conf.camera_mode, None
    if videos and len({videos.get(n) for n in images.names}) > 1:
        return "per_video", videos
    exif = {n: exif_camera(images.root / n) for n in images.names}
    one_camera = len({images.sizes[n] for n in images.names}) == 1 and len(set(exif.values())) == 1
    phones = {n: _phone_key(cam, images.sizes[n]) for n, cam in exif.items() if cam.complete()}
    frames = {} if videos else _sequence_groups(images, {n: cam for n, cam in exif.items() if not cam.complete()})
    if len(set(frames.values())) > 1 or (frames and not one_camera):  # clips of one size may be zoomed apart
        return "per_sequence", {**frames, **phones}
    if one_camera:
        return "single", None
    if len(phones) - len(set(phones.values())) > 0:  # two photos or more from one phone held one way
        return "per_exif", phones
    return "per_image", None


def may_leave_single(images: ImageSet, added: list[str]) -> bool:
    """Whether images `added` to a run of one shared camera may need cameras of their own (then
    `camera_sharing` decides, reading every image's EXIF): another size among the images, a numbered
    sequence that none of the earlier images is in (another clip), or another EXIF camera than the
    earlier images' (another phone). Only the added images' EXIF is read, and one earlier image's, so
    an update of a large run of one camera stays cheap."""
    added_set = set(added)
    earlier = [n for n in images.names if n not in added_set]

    def sequences(names: list[str]) -> set[tuple[str, str]]:
        return {found[0] for found in map(numbered, names) if found is not None}

    if len({images.sizes[n] for n in images.names}) > 1 or sequences(added) - sequences(earlier):
        return True
    reference = exif_camera(images.root / earlier[0]) if earlier else None
    return reference is not None and any(exif_camera(images.root / n) != reference for n in added)


def _sequence_groups(images: ImageSet, exif: dict[str, ExifCamera]) -> dict[str, str]:
    """image -> its clip, for the images in `exif` (those without a camera in EXIF) in numbered
    sequences: a sequence, in frame-number order, splits where the size or the EXIF changes, and is
    a set of clips when every piece holds `MIN_SEQUENCE_FRAMES` frames or more (frames of two clips
    numbered on from one to the other too); one piece is `single`'s rule held within the sequence.
    A numbered collection from many cameras (`00000.jpg`, ...) changes size between neighbours: no clip."""
    sequences: dict[tuple[str, str], list[tuple[int, str]]] = {}
    for name in exif:
        found = numbered(name)
        if found is not None:
            sequences.setdefault(found[0], []).append((found[1], name))
    out: dict[str, str] = {}
    for (before, after), frames in sequences.items():
        names = [name for _, name in sorted(frames)]
        camera = [(images.sizes[n], exif[n]) for n in names]
        starts = [k for k in range(len(names)) if k == 0 or camera[k] != camera[k - 1]]
        pieces = [names[a:b] for a, b in zip(starts, [*starts[1:], len(names)])]
        if all(len(piece) >= MIN_SEQUENCE_FRAMES for piece in pieces):
            out.update({n: f"frames {before}#{after}" + (f" from {piece[0]}" if len(pieces) > 1 else "")
                        for piece in pieces for n in piece})
    return out


def _phone_key(camera: ExifCamera, size: tuple[int, int]) -> str:
    zoom = f", {camera.focal_35mm:g} mm in 35 mm" if camera.focal_35mm else ""
    return f"{camera.make} {camera.model}, {camera.focal_mm:g} mm{zoom}, {size[0]}x{size[1]}"


def share_per_group(db_path: Path, images: ImageSet, groups: dict[str, str]) -> dict[str, list[str]]:
    """One camera for the images of each group (`groups`: image -> its video, or its phone; of each
    size, should a video change size); an image without a group keeps its own. Returns group -> its
    images in the database."""
    by_group: dict[tuple, list[str]] = {}
    kept = colmap.images_with_keypoints(db_path)
    for name in images.names:
        if name in kept:
            by_group.setdefault((groups.get(name, name), images.sizes[name]), []).append(name)
    colmap.share_cameras(db_path, list(by_group.values()))
    out: dict[str, list[str]] = {}
    for (group, _), names in by_group.items():
        out.setdefault(group, []).extend(names)
    return out
