"""Stage `extract`: SIFT features into the COLMAP database and an hloc-style `features.h5`."""

from __future__ import annotations

import logging
from pathlib import Path

import h5py
import numpy as np
from tqdm import tqdm

from . import colmap
from .io import records
from .config import ExtractConfig
from .io.h5 import Features, write_features
from .io.images import ImageSet
from .io import atomic_path, fingerprint

logger = logging.getLogger(__name__)

STAGE = "extract"
DB_NAME = "database.db"
FEATURES_NAME = "features.h5"


class OutputMismatchError(ValueError):
    """An output folder holds results made from other inputs or settings."""


def exif_focal_mm(path: Path) -> float | None:
    """The EXIF focal length in mm, or None."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            exif = im.getexif()
            focal = exif.get_ifd(0x8769).get(0x920A) or exif.get(0x920A)
    except Exception:  # noqa: BLE001 - EXIF is optional; any failure means "no EXIF focal"
        return None
    try:
        return float(focal) if focal else None
    except (TypeError, ValueError, ZeroDivisionError):
        return None


def resolve_camera_mode(images: ImageSet, conf: ExtractConfig) -> str:
    """`auto`: one shared camera when every image has the same size and EXIF focal, else per image."""
    if conf.camera_mode != "auto":
        if conf.camera_mode not in ("single", "per_image", "per_folder"):
            raise ValueError(
                f"unknown camera_mode {conf.camera_mode!r}; choose auto, single, per_image or per_folder"
            )
        return conf.camera_mode
    sizes = {images.sizes[n] for n in images.names}
    if len(sizes) > 1:
        return "per_image"
    focals = {exif_focal_mm(images.root / n) for n in images.names}
    return "single" if len(focals) == 1 else "per_image"


def _key(images: ImageSet, conf: ExtractConfig) -> str:
    return fingerprint({"images": images.fingerprint_data(), "conf": conf.__dict__})


def _check_existing_database(db_path: Path, images: ImageSet) -> bool:
    """True when the database can be resumed; False when it must be made anew."""
    in_db = colmap.database_images(db_path)
    unknown = sorted(set(in_db) - set(images.names))
    if unknown:
        raise OutputMismatchError(
            f"{db_path.parent} holds a database made from another image set ({len(unknown)} images not in "
            f"this folder, e.g. {unknown[0]!r}); use another output folder or --overwrite"
        )
    return len(in_db) == len(images.names)


def run(conf: ExtractConfig, images: ImageSet, out_dir: Path, *, overwrite: bool = False,
        progress: bool = True) -> Path:
    """Extract SIFT for every image; returns the path of `features.h5`. Resumes an interrupted run."""
    out_dir = Path(out_dir)
    db_path, h5_path = out_dir / DB_NAME, out_dir / FEATURES_NAME
    key = _key(images, conf)
    if not overwrite and records.is_done(out_dir, STAGE, key) and db_path.exists() and h5_path.exists():
        logger.info("extract: features up to date, skipping")
        return h5_path
    record = records.read_record(out_dir, STAGE)
    if overwrite or (record is not None and record.get("key") != key):
        if record is not None and record.get("key") != key and not overwrite and db_path.exists():
            raise OutputMismatchError(
                f"{out_dir} holds features made from other images or other extraction settings; "
                "use another output folder or --overwrite to redo them"
            )
        db_path.unlink(missing_ok=True)
        h5_path.unlink(missing_ok=True)
    if db_path.exists() and not _check_existing_database(db_path, images):
        db_path.unlink()  # images were being imported when the run stopped: importing is cheap
    records.mark_started(out_dir, STAGE, key)

    camera_mode = resolve_camera_mode(images, conf)
    if not db_path.exists():
        with atomic_path(db_path) as tmp:
            tmp.unlink()
            colmap.create_database(tmp)
            colmap.import_images(tmp, images.root, images.names, camera_mode=camera_mode, camera_model=conf.camera_model,
                                 camera_params=conf.camera_params,
                                 default_focal_length_factor=conf.default_focal_length_factor)
    _extract_missing(db_path, images, conf, progress)
    info = _export_h5(db_path, h5_path, images, progress)
    info["camera_mode"] = camera_mode
    records.mark_done(out_dir, STAGE, key, info)
    return h5_path


def _extract_missing(db_path: Path, images: ImageSet, conf: ExtractConfig, progress: bool) -> None:
    with colmap.open_database(db_path) as db:
        todo = [im.name for im in db.read_all_images() if not db.exists_keypoints(im.image_id)]
    todo = sorted(todo)
    if not todo:
        return
    chunk = max(2, min(16, len(todo) // 20 or 2))
    with tqdm(total=len(todo), desc="extract SIFT", unit="img", disable=not progress) as bar:
        for start in range(0, len(todo), chunk):
            names = todo[start:start + chunk]
            colmap.extract_sift(db_path, images.root, names, max_image_size=conf.max_image_size,
                                max_num_features=conf.max_num_features, camera_model=conf.camera_model,
                                camera_params=conf.camera_params, num_threads=conf.num_threads)
            bar.update(len(names))


def _export_h5(db_path: Path, h5_path: Path, images: ImageSet, progress: bool) -> dict:
    """Copy the database's features into `features.h5`; returns per-collection counts."""
    num_kp: dict[str, int] = {}
    with colmap.open_database(db_path) as db, atomic_path(h5_path) as tmp:
        with h5py.File(tmp, "w") as h5:
            for im in tqdm(sorted(db.read_all_images(), key=lambda im: im.name), desc="write features.h5",
                           unit="img", disable=not progress):
                kp, scale, desc = colmap.read_sift(db, im.image_id)
                write_features(h5, im.name, Features(
                    keypoints=colmap.colmap_to_hloc_keypoints(kp), descriptors=desc,
                    scores=scale, image_size=images.sizes[im.name]))
                num_kp[im.name] = len(kp)
    no_features = sorted(n for n, k in num_kp.items() if k == 0)
    for name in no_features:
        logger.warning("no features found in %s (flat or featureless image): it cannot be registered", name)
    counts = np.array(list(num_kp.values()))
    return {
        "num_images": len(num_kp),
        "keypoints_mean": float(counts.mean()) if len(counts) else 0.0,
        "keypoints_min": int(counts.min()) if len(counts) else 0,
        "images_without_features": no_features,
    }
