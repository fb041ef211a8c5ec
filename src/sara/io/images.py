"""Finding the images of a collection and setting aside the ones that cannot be used."""

from __future__ import annotations

import hashlib
import logging
import os
import unicodedata
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import read_json, write_json_atomic
from .pairs import name_problem

logger = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".pgm", ".ppm")
MIN_IMAGE_SIDE_PX = 32


@dataclass
class ImageSet:
    """The usable images of a folder.

    names: paths relative to `root`, POSIX separators, sorted; the identity of an image everywhere
    (pairs files, HDF5 groups, the COLMAP database). sizes: name -> (width, height) in pixels.
    skipped: name -> the reason the image cannot be used.
    """

    root: Path
    names: list[str]
    sizes: dict[str, tuple[int, int]]
    skipped: dict[str, str] = field(default_factory=dict)
    orientation: dict[str, int] = field(default_factory=dict)  # EXIF orientation, only where not 1
    needs_copy: set[str] = field(default_factory=set)  # formats COLMAP cannot read (HEIC, WebP): used from a copy

    def fingerprint_data(self) -> list[tuple[str, int, int]]:
        """Names, file sizes in bytes and modification times: what identified the set for the
        caches of sara before `content_digests` (kept to recognise outputs made then)."""
        out = []
        for name in self.names:
            st = (self.root / name).stat()
            out.append((name, st.st_size, int(st.st_mtime)))
        return out


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(2**20), b""):
            h.update(block)
    return h.hexdigest()[:24]


def content_digests(images: ImageSet, cache_path: Path, *,
                    progress: bool = True) -> tuple[dict[str, str], dict[str, list] | None]:
    """(name -> a digest of the image file's bytes for every image of the set, the cache entries
    to save with `save_digests`, or None when the cache is up to date).

    What identifies an image for the caches is its content, not its modification time: a folder
    copied or restored elsewhere (new times, same bytes) keeps its features. Hashing reads every
    file once; `cache_path` (JSON, name -> [size, mtime_ns, digest]) remembers the digests, and a
    file whose size and modification time are those of its entry is not read again. Nothing is
    written here, so that a run refused for its inputs leaves the output folder as it was.
    """
    cache_path = Path(cache_path)
    try:
        cached = read_json(cache_path) if cache_path.exists() else {}
    except (OSError, ValueError, UnicodeDecodeError):  # a cache cut short or damaged: hash again
        cached = {}
    if not isinstance(cached, dict):
        cached = {}
    digests: dict[str, str] = {}
    entries: dict[str, list] = {}
    todo: list[tuple[str, int, int]] = []
    for name in images.names:
        try:
            st = (images.root / name).stat()
        except OSError as exc:  # gone since the scan: set aside later, by the extractor
            digests[name] = f"unreadable: {exc.strerror}"
            continue
        entry = cached.get(name)
        if isinstance(entry, list) and len(entry) == 3 and entry[:2] == [st.st_size, st.st_mtime_ns]:
            digests[name], entries[name] = entry[2], entry
        else:
            todo.append((name, st.st_size, st.st_mtime_ns))
    for name, size, mtime_ns in tqdm(todo, desc="hash images", unit="img", disable=not progress or len(todo) < 100):
        try:
            digests[name] = _sha256(images.root / name)
        except OSError as exc:
            digests[name] = f"unreadable: {exc.strerror}"
            continue
        entries[name] = [size, mtime_ns, digests[name]]
    return digests, (entries if todo or len(entries) != len(cached) else None)


def save_digests(cache_path: Path, entries: dict[str, list] | None) -> None:
    """Write the cache entries `content_digests` returned (nothing when it returned None)."""
    if entries is not None:
        Path(cache_path).parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(Path(cache_path), entries)


def folder_mismatch(root: Path, cache_path: Path, *, rotated: frozenset[str] = frozenset()) -> str | None:
    """Why the images in `root` are not those whose digests `cache_path` holds (None when they are).

    `cache_path` is the digest cache `content_digests` keeps for a run's images. None of its
    names in `root`, or an image whose bytes differ, is a mismatch; images missing from `root`
    are not (a file removed since). `rotated`: names whose digest is that of an upright copy made
    by sara, which cannot be compared with the original. A missing or unreadable cache: None.
    """
    try:
        cached = read_json(Path(cache_path))
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    if not isinstance(cached, dict) or not cached:
        return None
    present = [name for name in sorted(cached) if (Path(root) / name).is_file()]
    if not present:
        return f"none of its images is in {root} (e.g. {next(iter(sorted(cached)))!r})"
    for name in present:
        entry, st = cached[name], (Path(root) / name).stat()
        if name in rotated or not isinstance(entry, list) or len(entry) != 3:
            continue
        if entry[:2] != [st.st_size, st.st_mtime_ns] and _sha256(Path(root) / name) != entry[2]:
            return f"{root / name} is not the image of that name the features were made from"
    return None


#: the extensions of the videos `sara run` picks frames from (`sara.video`)
VIDEO_EXTENSIONS = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".mpg", ".mpeg", ".mts", ".m2ts", ".wmv",
                    ".flv", ".3gp", ".ogv")
#: HEIC photos (phones) are read through pillow-heif, an optional extra
HEIC_EXTENSIONS = (".heic", ".heif")
HEIC_MISSING = "HEIC photo: install pillow-heif (pip install 'sara[heic]') to use it"
#: web formats (downloaded photo collections) read through Pillow where it was built with them:
#: extension -> Pillow's name of the feature. Like HEIC, COLMAP cannot read them, so the stages
#: read JPEG copies (`upright_copy`)
WEB_FORMATS = {".webp": "webp", ".avif": "avif"}
#: image formats sara does not read, named so that the warning says what they are
OTHER_IMAGE_FORMATS = (".gif", ".webp", ".avif", ".jxl", ".jp2", ".psd", ".svg", ".exr", ".hdr", ".dng", ".raw",
                       ".cr2", ".cr3", ".nef", ".arw", ".orf", ".rw2")
#: what marks a folder as a sara output folder (never scanned for images: it holds sara's own copies)
OUTPUT_MARKERS = (".sara", ".sara.lock")


def heic_supported() -> bool:
    """Whether HEIC photos can be decoded (pillow-heif importable; its Pillow plug-in is registered)."""
    try:
        import pillow_heif
    except ImportError:
        return False
    pillow_heif.register_heif_opener()
    return True


def copied_extensions(files: list[str]) -> tuple[str, ...]:
    """The extensions among `files` that sara decodes although COLMAP cannot (read from JPEG
    copies): HEIC where pillow-heif is installed, WebP and AVIF where Pillow decodes them."""
    from PIL import features

    suffixes = {Path(name.lower()).suffix for name in files}
    found = [ext for ext, feature in WEB_FORMATS.items() if ext in suffixes and features.check(feature)]
    if suffixes & set(HEIC_EXTENSIONS) and heic_supported():
        found += HEIC_EXTENSIONS
    return tuple(found)


def read_from_copy(name: str) -> bool:
    """Whether COLMAP cannot read this image file, so that the stages read a JPEG copy of it."""
    return name.lower().endswith(HEIC_EXTENSIONS + tuple(WEB_FORMATS))


def _is_output_folder(folder: Path, out_dir: Path | None) -> bool:
    if any((folder / marker).exists() for marker in OUTPUT_MARKERS):
        return True
    return out_dir is not None and folder.resolve() == Path(out_dir).resolve()


def _all_files(root: Path, recursive: bool, out_dir: Path | None) -> list[str]:
    """Names (relative, POSIX) of every file under `root`, broken links included; hidden folders
    and sara output folders (`out_dir`, or one with sara's marker) are not entered, the latter
    with one warning each."""
    if not recursive:
        return [entry.name for entry in root.iterdir() if not entry.is_dir()]
    names = []
    for dirpath, dirnames, filenames in os.walk(root):
        kept = []
        for dirname in sorted(d for d in dirnames if not d.startswith(".")):
            if _is_output_folder(Path(dirpath) / dirname, out_dir):
                logger.warning("not looking for images in %s: a sara output folder (sara's own copies of the "
                               "images are there)", Path(dirpath) / dirname)
            else:
                kept.append(dirname)
        dirnames[:] = kept
        names += [(Path(dirpath) / fname).relative_to(root).as_posix() for fname in filenames]
    return names


def not_used_reason(root: Path, name: str, *, copied: tuple[str, ...] = ()) -> str | None:
    """Why a file of the folder is not an image sara reads (None for an image file to check);
    `copied`: the extensions read from copies (`copied_extensions`)."""
    path, lower = Path(root) / name, name.lower()
    if path.is_symlink() and not path.exists():
        return "broken symbolic link (its target is missing)"
    if lower.endswith(IMAGE_EXTENSIONS + copied):
        return None
    stripped = lower.rstrip()
    if stripped != lower and stripped.endswith(IMAGE_EXTENSIONS + HEIC_EXTENSIONS):
        return f"blank characters after its extension ({Path(name).name!r}); rename it to use it"
    if lower.endswith(HEIC_EXTENSIONS):
        return HEIC_MISSING
    suffix = Path(lower).suffix
    if suffix in OTHER_IMAGE_FORMATS:
        return f"a {suffix} file, a format sara does not read; convert it to JPEG or PNG to use it"
    if suffix in VIDEO_EXTENSIONS:  # beside photos: a phone's Live Photo clip, or a video to use on its own
        return ("a video among images: sara uses the images; `sara run` on the video (or on a folder of videos) "
                "uses its frames")
    return "not an image file"


def _summary_label(reason: str) -> str:
    for start, label in (("broken", "broken link"), ("blank", "blank after the extension"),
                         ("HEIC", "HEIC photo (pip install 'sara[heic]')"), ("a .", "unsupported image format"),
                         ("a video", "video (`sara run VIDEO` for its frames)"),
                         ("not an image", "not an image")):
        if reason.startswith(start):
            return label
    return reason


def summarise_not_used(reasons: dict[str, str]) -> str:
    """`3 broken link, 1 not an image`: counts by kind of the files not used."""
    counts: dict[str, int] = {}
    for reason in reasons.values():
        counts[_summary_label(reason)] = counts.get(_summary_label(reason), 0) + 1
    return ", ".join(f"{n} {label}" for label, n in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def list_image_files(root: Path, *, recursive: bool = False, out_dir: Path | None = None,
                     not_used: dict[str, str] | None = None) -> list[str]:
    """Names (relative, POSIX) of files with an image extension under `root`, sorted.

    Hidden files (a name starting with '.') are listed too, so that the scan can say it skips
    them; hidden folders and sara output folders are not entered. `not_used`, when given,
    receives every other file of the folder with the reason it is not used (`not_used_reason`).
    """
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"image folder not found: {root}")
    if not root.is_dir():
        raise NotADirectoryError(f"not a folder: {root} (give the folder that holds the images; of the commands, "
                                 "`sara run` also takes a video)")
    files = _all_files(root, recursive, out_dir)
    copied = copied_extensions(files)
    names = []
    for name in files:
        reason = not_used_reason(root, name, copied=copied)
        if reason is None:
            names.append(name)
        elif not_used is not None:
            not_used[name] = reason
    return sorted(names)


HIDDEN_REASON = "hidden file (its name starts with '.'); rename it to use it"


def check_image(path: Path) -> tuple[tuple[int, int] | None, str | None, int]:
    """Decode an image fully (JPEGs at reduced scale, which still reads every byte).

    Returns ((width, height) of the stored pixels, None, EXIF orientation) or (None, reason, 1).
    """
    from PIL import Image, UnidentifiedImageError

    orientation = 1
    try:
        if path.stat().st_size == 0:
            return None, "empty file (0 bytes)", 1
        with Image.open(path) as im:
            size = im.size
            if im.format == "JPEG":
                im.draft("RGB", (max(1, size[0] // 8), max(1, size[1] // 8)))
            orientation = int(im.getexif().get(0x0112, 1) or 1)
            im.load()
    except UnidentifiedImageError:
        return None, "not a readable image (unknown or corrupt format)", 1
    except Image.DecompressionBombError as exc:
        return None, f"image too large to decode safely ({exc})", 1
    except (OSError, ValueError, SyntaxError) as exc:
        return None, f"corrupt or truncated image ({exc})", 1
    if min(size) < MIN_IMAGE_SIDE_PX:
        return None, f"too small ({size[0]}x{size[1]} px, need at least {MIN_IMAGE_SIDE_PX} px per side)", 1
    return size, None, orientation if 1 <= orientation <= 8 else 1


def display_name(name: str) -> str:
    """A name as it can be printed on one line and stored in UTF-8 files: bytes that are not UTF-8
    as `\\xNN`, control characters (newlines, tabs) escaped as Python writes them."""
    text = name.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    return "".join(repr(c)[1:-1] if unicodedata.category(c) in ("Cc", "Zl", "Zp") else c for c in text)


def set_aside(images: ImageSet, reasons: dict[str, str], *, warn: bool = True) -> ImageSet:
    """The set without the images of `reasons` (name -> why), each skipped with one warning."""
    if not reasons:
        return images
    for name, reason in reasons.items():
        if warn:
            logger.warning("skipping %s: %s", display_name(name), reason)
    skipped = {**images.skipped, **{display_name(n): r for n, r in reasons.items()}}
    return ImageSet(root=images.root, names=[n for n in images.names if n not in reasons],
                    sizes={n: s for n, s in images.sizes.items() if n not in reasons}, skipped=skipped,
                    orientation={n: o for n, o in images.orientation.items() if n not in reasons},
                    needs_copy=images.needs_copy - set(reasons))


def other_sizes(images: ImageSet, given: str) -> dict[str, str]:
    """Under one camera (`given` by that setting), the images of another size than most (name -> why)."""
    (w, h), _ = Counter(images.sizes[n] for n in images.names).most_common(1)[0]
    return {n: f"its size {images.sizes[n][0]}x{images.sizes[n][1]} is not the one camera's {w}x{h} ({given}: one "
            "camera for images of one size)" for n in images.names if images.sizes[n] != (w, h)}


def scan_images(root: Path, *, recursive: bool = False, progress: bool = True,
                out_dir: Path | None = None) -> ImageSet:
    """List and check the images of a folder; unusable ones are skipped with one warning each.

    An image is skipped when its name cannot go through sara's files (see `sara.io.pairs.name_problem`:
    control characters, bytes that are not UTF-8) or when Pillow cannot decode it. Every other file
    of the folder (not an image, a format sara does not read, a broken link) is skipped too, with
    one warning line for all, counted by reason. `out_dir` (the run's output folder) and any other
    sara output folder are never scanned. Raises ValueError when no usable image is left.
    """
    root = Path(root)
    not_used: dict[str, str] = {}
    candidates = list_image_files(root, recursive=recursive, out_dir=out_dir, not_used=not_used)
    if not_used:
        logger.warning("%d file(s) in %s not used: %s (each listed with its reason in run.json, skipped_images)",
                       len(not_used), root, summarise_not_used(not_used))
    if not candidates:
        hint = "" if recursive else " (use --recursive to look into sub-folders)"
        found = f"; found only: {summarise_not_used(not_used)}" if not_used else ""
        raise ValueError(f"no images found in {root}; looked for {', '.join(IMAGE_EXTENSIONS)}{hint}{found}")
    names, sizes, orientation, copies = [], {}, {}, set()
    skipped = {display_name(n): r for n, r in sorted(not_used.items())}
    for name in tqdm(candidates, desc="check images", unit="img", disable=not progress):
        reason = HIDDEN_REASON if Path(name).name.startswith(".") else name_problem(name)
        size, orient = None, 1
        if reason is None:
            size, reason, orient = check_image(root / name)
        if reason is not None:
            logger.warning("skipping %s: %s", display_name(name), reason)
            skipped[display_name(name)] = reason
            continue
        names.append(name)
        sizes[name] = size
        if orient != 1:
            orientation[name] = orient
        if read_from_copy(name):
            copies.add(name)
    if not names:
        raise ValueError(f"none of the {len(candidates)} image files in {root} could be used (see the warnings)")
    return ImageSet(root=root, names=names, sizes=sizes, skipped=skipped, orientation=orientation,
                    needs_copy=copies)


def upright_copy(images: ImageSet, folder: Path, *, rotate: bool = True, progress: bool = True) -> ImageSet:
    """An ImageSet in `folder`: with `rotate`, EXIF-rotated images stored upright; images COLMAP
    cannot read (`needs_copy`: HEIC, WebP, AVIF) stored as JPEG under their own names; the others linked.

    COLMAP uses the stored pixels and ignores the EXIF orientation tag; tools that honour the tag
    would then see other pixels than the model was made from. This makes both agree.
    """
    from PIL import Image

    folder = Path(folder)
    sizes = dict(images.sizes)
    recode = set(images.needs_copy) | (set(images.orientation) if rotate else set())
    for name in tqdm(images.names, desc="upright images", unit="img", disable=not progress):
        src, dst = images.root / name, folder / name
        if name not in recode and dst.is_symlink():
            continue
        if name in recode and dst.is_file() and not dst.is_symlink() and dst.stat().st_mtime >= src.stat().st_mtime:
            with Image.open(dst) as im:
                sizes[name] = im.size
            continue
        dst.unlink(missing_ok=True)
        dst.parent.mkdir(parents=True, exist_ok=True)
        if name not in recode:
            dst.symlink_to(src.resolve())
            continue
        sizes[name] = _recode(src, dst, rotate=rotate and name in images.orientation,
                              as_jpeg=name in images.needs_copy)
    return ImageSet(root=folder, names=list(images.names), sizes=sizes, skipped=dict(images.skipped))


def _recode(src: Path, dst: Path, *, rotate: bool, as_jpeg: bool) -> tuple[int, int]:
    """Write the pixels of `src` to `dst` (upright with `rotate`; JPEG whatever the name with
    `as_jpeg`: COLMAP's reader goes by the content) with its EXIF (the camera and focal length that
    COLMAP's prior and the cameras' sharing read; the orientation tag gone where turned upright);
    returns their (width, height)."""
    from PIL import Image, ImageOps

    with Image.open(src) as im:
        exif = im.getexif()
        pixels = ImageOps.exif_transpose(im) if rotate else im
        if as_jpeg and pixels.mode not in ("RGB", "L"):
            pixels = pixels.convert("RGB")
        if rotate:
            exif.pop(0x0112, None)
        tmp = dst.with_name(f".{dst.name}.tmp{dst.suffix}")
        pixels.save(tmp, format="JPEG" if as_jpeg else None, quality=95, **({"exif": exif.tobytes()} if exif else {}))
        tmp.replace(dst)
        return pixels.size


def load_image(path: Path, max_size: int) -> tuple[np.ndarray, tuple[float, float]]:
    """(H, W, 3) uint8 RGB pixels as stored (no EXIF rotation, like COLMAP), the longer side at most
    `max_size`; and the (x, y) factors that take its pixel coordinates back to the full image."""
    from PIL import Image

    with Image.open(path) as im:
        im = im.convert("RGB")
        width, height = im.size
        scale = min(1.0, max_size / max(width, height))
        if scale < 1.0:
            im = im.resize((max(1, round(width * scale)), max(1, round(height * scale))), Image.Resampling.BICUBIC)
        pixels = np.asarray(im, dtype=np.uint8)
    return pixels, (width / pixels.shape[1], height / pixels.shape[0])


def to_full_resolution(xy: np.ndarray, factors: tuple[float, float]) -> np.ndarray:
    """hloc-convention pixel coordinates of a resized image -> those of the full image."""
    return ((np.asarray(xy, np.float64) + 0.5) * np.asarray(factors) - 0.5).astype(np.float32)
