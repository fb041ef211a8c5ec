"""Finding the images of a collection and setting aside the ones that cannot be used."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

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

    def fingerprint_data(self) -> list[tuple[str, int, int]]:
        """What identifies the set for caches: names and file sizes in bytes and mtimes."""
        out = []
        for name in self.names:
            st = (self.root / name).stat()
            out.append((name, st.st_size, int(st.st_mtime)))
        return out


def list_image_files(root: Path, *, recursive: bool = False) -> list[str]:
    """Names (relative, POSIX) of files with an image extension under `root`, sorted."""
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"image folder not found: {root}")
    if not root.is_dir():
        raise NotADirectoryError(f"not a folder: {root} (give the folder that holds the images)")
    names = []
    if recursive:
        for dirpath, dirnames, filenames in os.walk(root):
            dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
            for fname in filenames:
                if fname.lower().endswith(IMAGE_EXTENSIONS) and not fname.startswith("."):
                    names.append((Path(dirpath) / fname).relative_to(root).as_posix())
    else:
        for entry in root.iterdir():
            if entry.is_file() and entry.suffix.lower() in IMAGE_EXTENSIONS and not entry.name.startswith("."):
                names.append(entry.name)
    return sorted(names)


def check_image(path: Path) -> tuple[tuple[int, int] | None, str | None]:
    """Decode an image fully. Returns ((width, height), None) or (None, reason)."""
    from PIL import Image, UnidentifiedImageError

    try:
        if path.stat().st_size == 0:
            return None, "empty file (0 bytes)"
        with Image.open(path) as im:
            im.load()
            size = im.size
    except UnidentifiedImageError:
        return None, "not a readable image (unknown or corrupt format)"
    except (OSError, ValueError, SyntaxError) as exc:
        return None, f"corrupt or truncated image ({exc})"
    except Image.DecompressionBombError as exc:
        return None, f"image too large to decode safely ({exc})"
    if min(size) < MIN_IMAGE_SIDE_PX:
        return None, f"too small ({size[0]}x{size[1]} px, need at least {MIN_IMAGE_SIDE_PX} px per side)"
    return size, None


def scan_images(root: Path, *, recursive: bool = False, progress: bool = True) -> ImageSet:
    """List and check the images of a folder; unusable ones are skipped with one warning each.

    Raises ValueError when no usable image is left.
    """
    root = Path(root)
    candidates = list_image_files(root, recursive=recursive)
    if not candidates:
        hint = "" if recursive else " (use --recursive to look into sub-folders)"
        raise ValueError(f"no images found in {root}; looked for {', '.join(IMAGE_EXTENSIONS)}{hint}")
    names, sizes, skipped = [], {}, {}
    for name in tqdm(candidates, desc="check images", unit="img", disable=not progress):
        size, reason = check_image(root / name)
        if reason is not None:
            logger.warning("skipping %s: %s", name, reason)
            skipped[name] = reason
            continue
        names.append(name)
        sizes[name] = size
    if not names:
        raise ValueError(f"none of the {len(candidates)} image files in {root} could be used (see the warnings)")
    return ImageSet(root=root, names=names, sizes=sizes, skipped=skipped)
