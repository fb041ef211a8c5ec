"""Keypoints that stay put: an overlay burned into every frame (a dashcam's clock and speed, a
drone's on-screen display, a logo or a watermark) gives keypoints at the same pixels in every image,
and their matches say that the camera never moved. kitti-seq1 with a dashcam's overlay drawn on
its frames built no model (exit 5: "no pair of views to start from", the best pair 2,073 inliers,
most of them the overlay's).

After extraction, among the images of one size (at least MIN_IMAGES of them), the cells of the
image (CELL_PX a side) that hold a keypoint, or have one next to them, in nearly every image are the
overlay's: in at least MIN_SHARE of the images, more than the images' own density of keypoints would
give by chance (fewer than CHANCE_CELLS such cells), and in patches of at least MIN_PATCH cells.
The keypoints in and next to those cells are taken out of the features file and the database
before any pair is scored or matched. Where
the camera moves, no part of the scene stays on the same pixels in nearly every image (none on
kitti-seq1 and the shared scenes, measured), but for the distant scene ahead of a camera driving
straight in a short clip: that drifts by a pixel or two where an overlay's keypoints come back to a
fraction of one, so patches whose keypoints drift are the scene's (`_still`); where the camera
stands still (a turntable's background), what stays put is not the object, and taking it out is
what such captures want too.
The cells found are kept in `.sara/static-cells.npz`, so that a run killed while taking the
keypoints out takes out the same ones when it resumes.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from . import colmap
from .io import atomic_path
from .io.h5 import has_features, read_open, write_features
from .io.images import ImageSet

logger = logging.getLogger(__name__)

CELL_PX = 2
MIN_IMAGES = 10
MIN_SHARE = 0.9
CHANCE_CELLS = 0.01
#: fewest cells of a patch of static cells: a keypoint that stays put makes a patch of 6 to 9 (it
#: counts for the cells around it); a cell that chance fills in nearly every image stands alone
MIN_PATCH = 6
#: static patches this many cells apart or closer belong to one overlay (one line of text), and the
#: box around them reaches MARGIN_CELLS further: the parts of a line that change (a clock's seconds)
#: stay put in fewer images than the rest, but lie between them
JOIN_CELLS = 12
MARGIN_CELLS = 3
#: a patch is an overlay's when STILL_SHARE of its keypoints come back within STILL_PX of their
#: position in at least half of the other images (`_still`), judged on at most STILL_IMAGES images
STILL_PX = 0.5
STILL_SHARE = 0.1
STILL_IMAGES = 40
CELLS_NAME = "static-cells.npz"


def _cells(xy: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N,) flat cell index of each keypoint (hloc's pixel convention), clipped into the image."""
    cx = np.clip((np.asarray(xy)[:, 0] / CELL_PX).astype(np.int64), 0, _grid_w(width) - 1)
    cy = np.clip((np.asarray(xy)[:, 1] / CELL_PX).astype(np.int64), 0, _grid_h(height) - 1)
    return cy * _grid_w(width) + cx


def _grid_w(width: int) -> int:
    return max(1, math.ceil(width / CELL_PX))


def _grid_h(height: int) -> int:
    return max(1, math.ceil(height / CELL_PX))


def needed_count(num_images: int, density: float, num_cells: int) -> int:
    """The fewest images a cell must hold keypoints in to be an overlay's: MIN_SHARE of them, and so
    many that chance (each cell holding a keypoint with probability `density` in each image) gives
    fewer than CHANCE_CELLS cells that many."""
    k = max(1, math.ceil(MIN_SHARE * num_images))
    if not 0.0 < density < 1.0:
        return k
    log_p, log_q = math.log(density), math.log1p(-density)
    log_n = math.lgamma(num_images + 1)
    terms = [log_n - math.lgamma(j + 1) - math.lgamma(num_images - j + 1) + j * log_p + (num_images - j) * log_q
             for j in range(num_images + 1)]
    tail = 0.0
    tails = [0.0] * (num_images + 2)
    for j in range(num_images, -1, -1):  # P(X >= j), from the top down
        tail += math.exp(terms[j])
        tails[j] = tail
    while k <= num_images and num_cells * tails[k] >= CHANCE_CELLS:
        k += 1
    return k


def static_grid(keypoints: list[np.ndarray], width: int, height: int) -> np.ndarray:
    """(H / CELL_PX, W / CELL_PX) bool: the cells in and next to those an overlay holds, from the
    keypoints (hloc's convention) of images of one size. A keypoint counts for its cell and the
    eight around it, so that one that wavers across a cell's edge from image to image still counts
    in one cell in every image."""
    gw, gh = _grid_w(width), _grid_h(height)
    counts = np.zeros(gw * gh, np.int64)
    for xy in keypoints:
        counts[_around(np.unique(_cells(xy, width, height)), gw, gh)] += 1
    density = float(counts.sum()) / (len(keypoints) * gw * gh) if keypoints else 0.0
    full = (counts >= needed_count(len(keypoints), density, gw * gh)).reshape(gh, gw)
    return _boxes(_still(_patches(full, MIN_PATCH), keypoints, width, height))


def _still(patches: np.ndarray, keypoints: list[np.ndarray], width: int, height: int) -> np.ndarray:
    """`patches` without those whose keypoints drift: an overlay's pixels are the same in every frame,
    so some of its keypoints come back at the same position to a fraction of a pixel (STILL_SHARE of
    them within STILL_PX of one in at least half of the other images); the distant scene ahead of a
    camera driving straight drifts slowly out from the point it heads for, and in a short clip stays
    in its cells too (kitti-seq1's first 26 frames: three patches there, their stillest tenth of
    keypoints 1.4-1.7 px away in half the frames; a dashcam's overlay on the same frames: 0.00-0.09)."""
    from scipy import ndimage
    from scipy.spatial import cKDTree

    labels, num = ndimage.label(patches, structure=np.ones((3, 3), bool))
    if num == 0:
        return patches
    gw, gh = _grid_w(width), _grid_h(height)
    sample = keypoints[::max(1, len(keypoints) // STILL_IMAGES)]  # a long video costs what STILL_IMAGES do
    cells = [_cells(xy, width, height) if len(xy) else np.zeros(0, np.int64) for xy in sample]
    keep = np.zeros(num + 1, bool)
    for label in range(1, num + 1):
        near = np.zeros(gw * gh, bool)
        near[_around(np.flatnonzero(labels.ravel() == label), gw, gh)] = True
        inside = [np.asarray(xy, np.float64)[near[c]] for xy, c in zip(sample, cells)]
        points, image = np.concatenate(inside), np.repeat(np.arange(len(inside)), [len(i) for i in inside])
        others = sum(len(i) > 0 for i in inside) - 1
        if others < 1:
            continue
        close = cKDTree(points).query_pairs(STILL_PX, output_type="ndarray")
        a, b = np.concatenate([close[:, 0], close[:, 1]]), np.concatenate([close[:, 1], close[:, 0]])
        apart = image[a] != image[b]
        seen = np.unique(a[apart] * len(inside) + image[b[apart]])  # (point, another image it comes back in)
        comes_back = np.bincount(seen // len(inside), minlength=len(points))
        keep[label] = np.mean(2 * comes_back >= others) >= STILL_SHARE
    return keep[labels]


def _boxes(static: np.ndarray) -> np.ndarray:
    """The boxes around the patches of `static` cells and those within JOIN_CELLS of each other (the
    parts of one line of text that changes, a clock's seconds between a date and a speed that do not),
    MARGIN_CELLS wider on each side: what an overlay covers."""
    from scipy import ndimage

    grid = np.zeros_like(static)
    if not static.any():
        return grid
    joined = ndimage.binary_dilation(static, np.ones((2 * JOIN_CELLS + 1,) * 2, bool))
    labels, _ = ndimage.label(joined, structure=np.ones((3, 3), bool))
    for rows, cols in ndimage.find_objects(labels):
        inner = static[rows, cols]  # the static cells of this box: its extent without the joining
        ys, xs = np.nonzero(inner)
        y0, y1 = rows.start + ys.min() - MARGIN_CELLS, rows.start + ys.max() + MARGIN_CELLS + 1
        x0, x1 = cols.start + xs.min() - MARGIN_CELLS, cols.start + xs.max() + MARGIN_CELLS + 1
        grid[max(y0, 0):y1, max(x0, 0):x1] = True
    return grid


def _patches(grid: np.ndarray, min_cells: int) -> np.ndarray:
    """`grid` without its patches (8-connected) of fewer than `min_cells` cells."""
    from scipy import ndimage

    labels, num = ndimage.label(grid, structure=np.ones((3, 3), bool))
    if num == 0:
        return grid
    sizes = np.bincount(labels.ravel())
    keep = sizes >= min_cells
    keep[0] = False
    return keep[labels]


def _around(cells: np.ndarray, gw: int, gh: int) -> np.ndarray:
    """The flat indices of `cells` and of the cells next to them (inside the grid), each once."""
    cy, cx = np.divmod(np.asarray(cells, np.int64), gw)
    out = [(y * gw + x)[(x >= 0) & (x < gw) & (y >= 0) & (y < gh)]
           for y, x in ((cy + dy, cx + dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1))]
    return np.unique(np.concatenate(out)) if out else np.zeros(0, np.int64)


def _find(h5: h5py.File, images: ImageSet) -> dict[str, np.ndarray]:
    """`WxH` -> the static grid of the images of that size (only sizes where one was found)."""
    by_size: dict[tuple[int, int], list[str]] = {}
    for name in images.names:
        if has_features(h5, name):
            by_size.setdefault(images.sizes[name], []).append(name)
    grids = {}
    for (width, height), names in by_size.items():
        if len(names) >= MIN_IMAGES:
            grid = static_grid([h5[n]["keypoints"][()] for n in names], width, height)
            if grid.any():
                grids[f"{width}x{height}"] = grid
    return grids


def remove_static(db_path: Path, h5_path: Path, images: ImageSet, state_dir: Path) -> dict[str, Any]:
    """Take the overlay's keypoints out of the features file and the database (before matching);
    returns what was found and taken out (for the extract stage's record)."""
    saved = Path(state_dir) / CELLS_NAME
    with h5py.File(h5_path, "r+") as h5:
        if saved.exists():  # found before a kill: take out the same cells
            with np.load(saved) as kept:
                grids = {k: kept[k] for k in kept.files}
        else:
            grids = _find(h5, images)
            with atomic_path(saved) as tmp, open(tmp, "wb") as f:
                np.savez(f, **grids)
        if not grids:
            return {"num_cells": 0, "num_keypoints": 0, "num_images": 0}

        def static(name: str, xy: np.ndarray) -> np.ndarray | None:
            size = images.sizes.get(name)
            grid = grids.get("{}x{}".format(*size)) if size else None
            return grid.reshape(-1)[_cells(xy, *size)] if grid is not None and len(xy) else None

        touched = 0
        for name in images.names:
            drop = static(name, h5[name]["keypoints"][()]) if has_features(h5, name) else None
            if drop is not None and drop.any():  # only then the descriptors are read and written again
                feats = read_open(h5, name)
                keep = ~drop
                feats.keypoints, feats.descriptors, feats.scores = (
                    feats.keypoints[keep], feats.descriptors[keep], feats.scores[keep])
                write_features(h5, name, feats)
                touched += 1
    removed = colmap.keep_keypoints(db_path, lambda name, xy: static(name, np.asarray(xy) - 0.5))
    cells = int(sum(int(g.sum()) for g in grids.values()))
    logger.warning("features that stay put on the same pixels of %d images (an overlay: a clock, a speed, a logo "
                   "burned into the frames): %d keypoints taken out before matching", touched, removed)
    return {"num_cells": cells, "num_keypoints": removed, "num_images": touched}
