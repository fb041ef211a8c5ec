"""Masks: the parts of each image whose keypoints the reconstruction must not use (`--masks DIR`,
`extract.mask_path`): the operator's hand or shadow, a car's bonnet, people walking through, the sky,
the turntable under an object. `--masks FILE` gives every image one mask (a bonnet, a mount).

A mask is an image of the same size (or the same shape at another scale) whose black (zero) pixels
mark what to leave out, found as COLMAP names it, `DIR/<image name>.png`, or as nerfstudio does,
`DIR/<image name without its extension>.png`, or under the image's own name (sub-folders as the
images'). After extraction the keypoints on black pixels are taken out of the features file and the
database, before any pair is scored or matched; an image without a mask is used whole. Taking them
out again takes out nothing more, so a run killed part-way resumes with the same features.
"""

from __future__ import annotations

import functools
import logging
import shutil
from pathlib import Path, PurePosixPath
from typing import Any

import h5py
import numpy as np
from PIL import Image

from . import colmap
from .io import fingerprint, read_json
from .io.h5 import has_features, read_open, write_features
from .io.images import ImageSet

logger = logging.getLogger(__name__)

#: a mask of another size than its image must have the image's shape within this share
ASPECT_TOLERANCE = 0.01


def mask_file(folder: Path, name: str) -> Path | None:
    """The mask of image `name` in `folder` (COLMAP's name, nerfstudio's, the image's own), or None;
    `folder` may be one mask image instead, every image's (a camera's bonnet, a mount)."""
    if Path(folder).is_file():
        return Path(folder)
    path = PurePosixPath(name)
    for candidate in (f"{name}.png", str(path.with_suffix(".png")), name):
        if (Path(folder) / candidate).is_file():
            return Path(folder) / candidate
    return None


def masks_key(mask_path: str) -> str:
    """What keys the features besides the setting: every file of the folder, its size and time
    (a mask changed, added or removed makes the features again); a ValueError where it is no folder."""
    folder = check_folder(mask_path)  # before any work
    files = sorted(p for p in folder.rglob("*") if p.is_file()) if folder.is_dir() else [folder]
    return fingerprint([[str(p.relative_to(folder)) if p != folder else p.name, p.stat().st_size,
                         p.stat().st_mtime_ns] for p in files])


def check_folder(mask_path: str) -> Path:
    """The mask folder (or the one mask image), or a ValueError naming the setting when it is none."""
    folder = Path(mask_path).expanduser()
    if not folder.exists():
        raise ValueError(f"mask folder not found: {folder} (--masks, extract.mask_path: a folder of masks, or one "
                         "mask image for every image)")
    return folder


def _found(folder: Path, names: list[str]) -> dict[str, Path]:
    """Image name -> its mask in `folder`, for the images that have one."""
    return {name: path for name in names if (path := mask_file(folder, name)) is not None}


def check(mask_path: str, images: ImageSet, *, upright: bool = False) -> None:
    """Before any work: the mask folder exists, holds a mask for at least one image, and each mask
    found reads as an image of its image's shape (its header only; `upright`: the shape the image's
    EXIF orientation turns it to, as `images.exif_orientation=apply` reads it)."""
    if not mask_path:
        return
    folder = check_folder(mask_path)
    found = _found(folder, images.names)
    if not found:
        example = images.names[0] if images.names else "IMAGE"
        raise ValueError(f"no mask in {folder} for any of the {len(images.names)} images (looked for e.g. "
                         f"{example}.png and {PurePosixPath(example).with_suffix('.png')})")
    for name, path in found.items():
        try:
            with Image.open(path) as im:
                size = im.size
        except OSError as error:
            raise ValueError(f"mask {path} does not read as an image ({error})") from error
        w, h = images.sizes[name]
        turned = upright and images.orientation.get(name, 1) >= 5  # EXIF 5-8 turn by a quarter
        _check_shape(path, size, (h, w) if turned else (w, h))


def _check_shape(mask_path: Path, mask_size: tuple[int, int], size: tuple[int, int]) -> None:
    (mw, mh), (w, h) = mask_size, size
    if abs(mw / mh - w / h) > ASPECT_TOLERANCE * (w / h):
        raise ValueError(f"mask {mask_path} is {mw}x{mh}, its image {w}x{h}: a mask has its image's shape "
                         "(an image turned by its EXIF orientation needs its mask turned too)")


def _keep(mask_path: Path, size: tuple[int, int]) -> np.ndarray:
    """(H, W) bool, True where keypoints stay, at the mask's own resolution; a ValueError names a mask
    that is no image or whose shape is not its image's."""
    try:
        with Image.open(mask_path) as im:
            keep = np.asarray(im.convert("L")) > 0
    except (OSError, ValueError) as error:
        raise ValueError(f"mask {mask_path} does not read as an image ({error})") from error
    _check_shape(mask_path, keep.shape[::-1], size)
    return keep


def _dropped(keep: np.ndarray, size: tuple[int, int], xy: np.ndarray) -> np.ndarray:
    """Which keypoints (hloc's pixel convention: the first pixel's centre at 0) lie on black pixels."""
    (w, h), (mh, mw) = size, keep.shape
    cols = np.clip(np.floor((xy[:, 0] + 0.5) * mw / w), 0, mw - 1).astype(np.int64)
    rows = np.clip(np.floor((xy[:, 1] + 0.5) * mh / h), 0, mh - 1).astype(np.int64)
    return ~keep[rows, cols]


def apply(mask_path: str, db_path: Path, h5_path: Path, images: ImageSet) -> dict[str, Any]:
    """Take the keypoints on the masks' black pixels out of the features file and the database;
    returns what was done (for the extract stage's record). Nothing without a mask folder."""
    if not mask_path:
        return {}
    folder = check_folder(mask_path)
    found = _found(folder, images.names)  # the run checked them (`check`); an update's new images may have none
    if not found:
        return {"num_images": 0, "num_keypoints": 0, "num_images_without_mask": len(images.names)}

    @functools.lru_cache(maxsize=2)  # one mask at a time in memory (the features file, then the database)
    def keep(name: str) -> np.ndarray:
        return _keep(found[name], images.sizes[name])

    def dropped(name: str, xy: np.ndarray) -> np.ndarray | None:
        return _dropped(keep(name), images.sizes[name], xy) if name in found and len(xy) else None

    with h5py.File(h5_path, "r+") as h5:
        for name in found:
            drop = dropped(name, h5[name]["keypoints"][()]) if has_features(h5, name) else None
            if drop is not None and drop.any():
                feats = read_open(h5, name)
                feats.keypoints, feats.descriptors, feats.scores = (
                    feats.keypoints[~drop], feats.descriptors[~drop], feats.scores[~drop])
                write_features(h5, name, feats)
    removed = colmap.keep_keypoints(db_path, lambda name, xy: dropped(name, np.asarray(xy) - 0.5))
    without = [n for n in images.names if n not in found]
    if without:
        logger.warning("%d of %d images have no mask in %s and are used whole (e.g. %s)", len(without),
                       len(images.names), folder, without[0])
    logger.info("masks: %d keypoints on the masks' black pixels taken out of %d images", removed, len(found))
    return {"num_images": len(found), "num_keypoints": removed, "images_without_mask": without[:20],
            "num_images_without_mask": len(without)}


def run_mask_folder(out_dir: Path) -> Path | None:
    """The mask folder a finished run used (`extract.mask_path` in its run.json), None without one."""
    run_json = Path(out_dir) / "run.json"
    mask_path = read_json(run_json).get("config", {}).get("extract", {}).get("mask_path") if run_json.exists() else ""
    return Path(mask_path).expanduser() if mask_path else None


def write_masks(folder: Path, names: dict[str, str], sizes: dict[str, tuple[int, int]], dest: Path) -> dict[str, str]:
    """Each image's mask as `dest/<names[name]>.png` at its image's size (black and white, as
    nerfstudio reads a frame's `mask_path`; the whole name, so that `a.jpg` and `a.png` keep a mask
    each); returns name -> the file written (relative to dest's parent). Images without a mask get none."""
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    written = {}
    for name, flat in names.items():
        found = mask_file(folder, name)
        if found is None:
            continue
        keep = _keep(found, sizes[name])
        mask = Image.fromarray((keep * 255).astype(np.uint8)).resize(sizes[name], Image.NEAREST)
        target = dest / f"{flat}.png"
        mask.save(target)
        written[name] = f"{dest.name}/{target.name}"
    return written
