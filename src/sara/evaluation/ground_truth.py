"""Known poses to score a model against (`sara evaluate OUT GT`, `sara run --gt GT`).

GT is a COLMAP model (text or binary), or a `transforms.json` as nerfstudio, instant-ngp and the
NeRF synthetic scenes write it (the file, or a folder that holds it and no COLMAP model): one frame
per image, its `file_path` and its camera-to-world `transform_matrix` in OpenGL's camera axes (x
right, y up, z back). The metrics are relative poses and a similarity alignment, so the world frame
and scale a dataset chose (nerfstudio's `applied_transform`, its scene scaling) change nothing.

A ground-truth name that is not an image name is matched to the image whose path ends like it,
folder by folder (`images/0001.jpg` and `0001.jpg`), and, for a `file_path` without an extension
(the NeRF synthetic scenes' `./train/r_0`), to the image of that path and any extension.
"""

from __future__ import annotations

import json
import logging
from collections import defaultdict
from collections.abc import Iterable
from pathlib import Path, PurePosixPath

import numpy as np

from .. import colmap

logger = logging.getLogger(__name__)

TRANSFORMS_NAME = "transforms.json"
#: OpenGL's camera axes to COLMAP's (x right, y down, z forward): flip y and z
_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0])

Poses = dict[str, tuple[np.ndarray, np.ndarray]]


def transforms_file(path: Path) -> Path | None:
    """The transforms.json that `path` names (the file, or a folder holding one and no COLMAP
    model); None for anything else (read as a COLMAP model)."""
    path = Path(path)
    if path.is_file() and path.suffix.lower() == ".json":
        return path
    if path.is_dir() and not colmap.has_model(path) and (path / TRANSFORMS_NAME).is_file():
        return path / TRANSFORMS_NAME
    return None


def load_ground_truth(path: Path) -> Poses:
    """name -> (R cam_from_world, t cam_from_world) of every posed image of the ground truth at `path`.

    Raises FileNotFoundError where there is none (no folder, no model), ValueError for a
    transforms.json that does not read as one."""
    found = transforms_file(path)
    return colmap.load_poses(Path(path)) if found is None else read_transforms(found)


def read_transforms(path: Path) -> Poses:
    """The poses of a transforms.json, keyed by each frame's `file_path` (without a leading `./`)."""
    try:
        meta = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{path} does not read as a transforms.json: {error}") from error
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{path} holds no frames: a transforms.json lists each image under \"frames\", with "
                         "its file_path and transform_matrix")
    poses: Poses = {}
    for k, frame in enumerate(frames):
        name, pose = _frame_pose(frame, f"{path}: frame {k}")
        if name in poses:
            raise ValueError(f"{path}: frame {k} names {name!r} again")
        poses[name] = pose
    return poses


def _frame_pose(frame: object, where: str) -> tuple[str, tuple[np.ndarray, np.ndarray]]:
    try:
        name = str(PurePosixPath(str(frame["file_path"]).replace("\\", "/")))  # type: ignore[index]
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)  # type: ignore[index]
    except (KeyError, TypeError, ValueError) as error:
        raise ValueError(f"{where} has no readable file_path and transform_matrix ({error!r})") from error
    if c2w.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(c2w)):
        raise ValueError(f"{where}: transform_matrix is not a finite 4 x 4 (or 3 x 4) matrix")
    u, s, vt = np.linalg.svd(c2w[:3, :3])
    if s[-1] <= 1e-9 * s[0] or np.linalg.det(u @ vt) < 0:
        raise ValueError(f"{where}: transform_matrix holds no rotation (singular or a reflection)")
    world_from_cam = (u @ vt) @ _OPENGL_TO_OPENCV  # a scaled rotation (a scene's scaling) taken as its rotation
    rotation = world_from_cam.T
    return name, (rotation, -rotation @ c2w[:3, 3])


def match_names(ground_truth: Poses, names: Iterable[str]) -> Poses:
    """`ground_truth` with each entry under the image name it poses: its own where it is an image
    name, else the one image whose path ends like it folder by folder (or, without an extension in
    the ground truth, like it with any extension). An entry that fits no image or several, and two
    entries that fit one image, keep their own names (posing no image); none is lost."""
    names = set(names)
    by_file: dict[str, set[str]] = defaultdict(set)
    for name in names:
        path = PurePosixPath(name)
        by_file[path.name].add(name)
        by_file[path.stem].add(name)
    fits: dict[str, list[str]] = defaultdict(list)  # image name -> ground-truth keys that fit it
    for key in ground_truth:
        if key in names:
            fits[key].append(key)
            continue
        path = PurePosixPath(key)
        found = [n for n in by_file.get(path.name, ()) if _ends_like(PurePosixPath(n), path)]
        if len(found) == 1:
            fits[found[0]].append(key)
    rename = {keys[0]: name for name, keys in fits.items() if len(keys) == 1 and keys[0] != name}
    if rename:
        logger.info("ground truth: %d of its names matched to image names by the end of their paths (e.g. %r is "
                    "%r)", len(rename), *next(iter(rename.items())))
    return {rename.get(key, key): pose for key, pose in ground_truth.items()}


def _ends_like(name: PurePosixPath, key: PurePosixPath) -> bool:
    """Whether the shorter of the two paths is the end of the longer, folder by folder; a key
    without an extension compares with the name's path without its extension."""
    if not key.suffix:
        name = name.with_suffix("")
    a, b = [p for p in name.parts if p != "."], [p for p in key.parts if p != "."]
    n = min(len(a), len(b))
    return n > 0 and a[-n:] == b[-n:]
