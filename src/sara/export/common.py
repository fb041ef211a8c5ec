"""What every export format shares: the job it is given, finding the model and the images of a
run, refusing a destination that would overwrite them, and image names without folders."""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from ..colmap import model
from ..io import read_json
from ..io.images import read_from_copy


@dataclass(frozen=True, kw_only=True)
class ExportJob:
    """What a format's `write(job)` gets: checked inputs and a destination folder that exists."""

    out_dir: Path  # the sara output folder (run.json, database.db, sparse/)
    model_dir: Path  # the model to export, `out_dir/sparse/<index>`
    images_root: Path  # the images the model was made from
    dest: Path  # where to write (created; the format replaces only its own files there)
    undistort: bool = False  # formats that can keep distortion: write undistorted images instead
    max_image_size: int = -1  # with undistortion, the longer image side at most this (px; -1: keep)
    progress: bool = True  # progress bars over the images


def find_model(out_dir: Path, model_index: int = 0) -> Path:
    """`out_dir/sparse/<model_index>`, or a clear FileNotFoundError when the run made no model."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise FileNotFoundError(f"output folder not found: {out_dir}")
    models = model.find_models(out_dir / "sparse")
    if not models:
        raise FileNotFoundError(f"{out_dir} holds no model (no sparse/0): run `sara run IMAGES {out_dir}` first, "
                                "or see its report for why mapping failed")
    wanted = out_dir / "sparse" / str(model_index)
    if wanted not in models:
        raise FileNotFoundError(f"{out_dir} has no model {model_index}; it has {', '.join(p.name for p in models)}")
    return wanted


def recorded_images_root(out_dir: Path) -> Path:
    """The image folder a run's model was made from: the copies when the run made them (of EXIF-rotated
    images under `exif_orientation=apply`, or of images COLMAP cannot read: HEIC, WebP, AVIF)."""
    run_json = Path(out_dir) / "run.json"
    if not run_json.exists():
        raise FileNotFoundError(f"{out_dir} has no run.json to name the image folder; pass the images folder")
    run = read_json(run_json)
    upright = Path(out_dir) / "images_upright"
    if upright.is_dir() and (run.get("config", {}).get("images", {}).get("exif_orientation") == "apply"
                             or any(read_from_copy(p.name) for p in upright.rglob("*") if not p.is_symlink())):
        return upright
    if not run.get("images_root"):
        raise FileNotFoundError(f"{run_json} names no image folder; pass the images folder")
    return Path(run["images_root"])


def check_destination(out_dir: Path, dest: Path, images_root: Path) -> None:
    """Refuse a destination that is, or holds, the run or its images: a format replaces folders there."""
    dest_r, out_r, images_r = dest.resolve(), out_dir.resolve(), images_root.resolve()
    if dest_r == out_r or out_r.is_relative_to(dest_r) or dest_r == images_r or images_r.is_relative_to(dest_r):
        raise ValueError(f"export destination {dest} would overwrite the run or its images; choose a new folder")


def flat_names(names: list[str]) -> dict[str, str]:
    """name -> a file name without folders, unique: `a/b.jpg` -> `a_b.jpg` (3DGS opens images/<basename>)."""
    mapping = {name: name.replace("/", "_") for name in names}
    if len(set(mapping.values())) < len(mapping):
        seen: dict[str, str] = {}
        for name, flat in mapping.items():
            if flat in seen:
                raise ValueError(f"images {seen[flat]!r} and {name!r} both become {flat!r} without folders; "
                                 "rename one of them")
            seen[flat] = name
    return mapping


def undistort_flat(model_dir: Path, images_root: Path, dest: Path, max_image_size: int, progress: bool) -> Path:
    """Undistorted images as `dest/images/<flat name>` and their PINHOLE model in `dest/sparse/0`.
    COLMAP writes each image in the format its name ends with: an image of a format it cannot
    write (HEIC, WebP, AVIF: the run read a JPEG copy of it) is written as `<name>.jpg`."""
    names = model.read_model(model_dir).names
    with tempfile.TemporaryDirectory(prefix=".sara-export-", dir=dest) as tmp:
        model_dir, images_root, names = _jpeg_names(model_dir, images_root, Path(tmp), names)
        rename = flat_names(names)
        images_dir, sparse_dir = model.undistort_images(model_dir, images_root, Path(tmp),
                                                        max_image_size=max_image_size)
        for folder in (dest / "images", dest / "sparse"):
            if folder.exists():
                shutil.rmtree(folder)
        (dest / "images").mkdir()
        for name, flat in tqdm(rename.items(), desc="undistorted images", unit="img", disable=not progress):
            shutil.move(str(images_dir / name), str(dest / "images" / flat))
        model.write_model(sparse_dir, dest / "sparse" / "0", rename=rename)
    return dest / "sparse" / "0"


def jpeg_name(name: str) -> str:
    """`name.jpg` for an image the run read from a JPEG copy (HEIC, WebP, AVIF), else `name`: exported
    files are named for what they hold."""
    return f"{name}.jpg" if read_from_copy(name) else name


def _jpeg_names(model_dir: Path, images_root: Path, tmp: Path, names: list[str]) -> tuple[Path, Path, list[str]]:
    """(model, image folder, names) in which each image COLMAP cannot write is named `<name>.jpg`:
    the model renamed into `tmp/renamed`, the images linked into `tmp/linked` under the new names.
    Unchanged where no image needs it."""
    jpeg = {name: jpeg_name(name) for name in names}
    if all(new == name for name, new in jpeg.items()):
        return model_dir, images_root, names
    model.write_model(model_dir, tmp / "renamed", rename=jpeg)
    for name, new in jpeg.items():
        (tmp / "linked" / new).parent.mkdir(parents=True, exist_ok=True)
        (tmp / "linked" / new).symlink_to((Path(images_root) / name).resolve())
    return tmp / "renamed", tmp / "linked", list(jpeg.values())


def copy_images(src_root: Path, dst_root: Path, rename: dict[str, str], progress: bool) -> None:
    """Copy each image `src_root/<name>` to `dst_root/<rename[name]>`, replacing `dst_root`."""
    if dst_root.exists():
        shutil.rmtree(dst_root)
    dst_root.mkdir(parents=True)
    for name, flat in tqdm(rename.items(), desc="copy images", unit="img", disable=not progress):
        shutil.copy2(src_root / name, dst_root / flat)
