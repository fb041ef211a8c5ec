"""A synthetic city with true poses at the feature level, for measuring pair selection at scale.

No photographs: a grid of streets lined with building facades, 3D points on the facades, and a
camera walking the streets. Each image's keypoints are the projections of the points it truly
sees, with pixel noise, plus outliers; each point has a descriptor of its own, observed with noise.
The result is a normal sara output folder (``features-sift.h5`` and ``database.db``), so the pair
selection stage runs on it unchanged, plus the truth (``truth.h5``) to judge the pairs it selects.

The world
    Blocks of ``block_size_m`` squared, separated by streets ``street_width_m`` wide, form a grid
    of ``G x G`` blocks walked along their ``(G + 1)^2`` street crossings, with one more ring of
    blocks around so every street has facades on both sides. ``G`` is chosen from the number of
    images so that each street is walked ``visits_per_street`` times on average. Facades carry
    3D points (``point_density`` per m^2, heights 0 to the block's height), each with a physical
    size (log-normal). A share ``repeat_fraction`` of a facade's points repeat one of a few
    descriptors of the facade's style (windows), each deviating from it by ``repeat_jitter``,
    and styles repeat across the city: repeated structure within an image and look-alike
    streets across the city, as in real streets (``repeat_jitter = 0``: identical copies, a
    harder world on which the scorer's top-b-by-similarity matches break down).

The walk
    From a corner, the camera goes from crossing to crossing, always to the least-walked street
    (no U-turns; ties at random), so it closes loops and revisits streets, in either direction.
    It takes an image every ``step_m`` metres, keeping to the right of the street centre
    (``lateral_offset_m``), its heading smoothed round corners; the viewing direction turns
    from the heading by the cycle ``yaw_pattern_deg`` (left, ahead, right, ahead by default),
    with jitter in yaw, pitch, roll, height and lateral position.

What an image sees
    The points within ``max_depth_m``, in front of the camera and inside the image, on a facade
    that faces it at most ``max_view_angle_deg`` from the facade's normal, not hidden behind a
    block (2D ray test: blocks are taller than any facade point is high), and large enough on
    the image (``f * size / distance >= min_scale_px``). Their projections get Gaussian noise of
    ``pixel_noise_px``. Outliers (``outlier_fraction`` of the keypoints) have random positions
    and descriptors. The ``max_keypoints`` with the largest scale are kept; the keypoint score is
    that scale in pixels (as sara's SIFT stores it), so "top M by score" keeps the nearest and
    largest points, consistently across neighbouring views.

Descriptors
    RootSIFT-like: for point ``p``, a 128-d histogram ``g_k = (-log u_k)^1.5`` (``u`` uniform
    from a hash of ``p``, so no table is kept), L1-normalised and square-rooted (a unit vector
    with non-negative entries). An observation adds a drift along a per-point direction,
    proportional to the viewing angle on the facade (``view_drift`` per radian) and to the log
    of the distance (``scale_drift``), and isotropic noise of norm ~``descriptor_noise``; then
    clips, normalises and stores as uint8 scaled by 512 (as COLMAP stores RootSIFT). With the
    defaults, the correct neighbour is the nearest for most points seen from nearby views and for
    fewer across wide changes of viewpoint.

Truth
    ``truth.h5`` holds the names, the true ``cam_from_world`` poses and centres, the 3D points,
    and each image's observed point ids (sorted). Two images truly overlap when they observe at
    least ``min_common`` common 3D points (:class:`Truth`), computed for given pairs only.

Everything is deterministic for a seed; each image draws from its own generator, and memory is
the points (about 20 bytes each) plus one image's features at a time.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import shutil
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from tqdm import tqdm

from ..io import fingerprint, read_json, write_json_atomic
from ..io.h5 import Features, write_features
from ..io.images import ImageSet

logger = logging.getLogger(__name__)

DB_NAME = "database.db"
TRUTH_NAME = "truth.h5"
WORLD_JSON = "world.json"
IMAGES_DIR = "images"  # the ImageSet's root; no image files are written
DESCRIPTOR_DIM = 128
WORLD_VERSION = 2  # bump when the generator changes what it writes

_OUTLIER_KEY_BIT = np.uint64(1 << 62)  # keys of outlier descriptors
_STYLE_KEY_BIT = np.uint64(1 << 61)  # keys of the repeated (style) descriptors


@dataclass(frozen=True, kw_only=True)
class WorldConfig:
    """Everything that shapes a synthetic world; the same config gives the same files."""

    num_images: int = 1000
    seed: int = 0
    # camera: one PINHOLE camera, true focal
    width: int = 1024
    height: int = 768
    focal_px: float = 900.0
    # city
    block_size_m: float = 50.0
    street_width_m: float = 14.0
    facade_height_m: tuple[float, float] = (10.0, 16.0)
    point_density: float = 10.0  # 3D points per m^2 of facade
    point_size_m: float = 0.06  # median physical size of a point's feature
    point_size_sigma: float = 0.5  # log-normal spread of the size
    repeat_fraction: float = 0.2  # points with a repeated (style) descriptor
    num_styles: int = 24  # facade styles in the city
    style_words: int = 12  # repeated descriptors per style
    repeat_jitter: float = 0.5  # a repeated point's own deviation from its style word (0: identical copies)
    grid_blocks: int = 0  # G; 0: chosen from num_images and visits_per_street
    visits_per_street: float = 1.6
    # walk
    step_m: float = 1.2
    yaw_pattern_deg: tuple[float, ...] = (60.0, 0.0, -60.0, 0.0)  # from the heading, + is left
    yaw_jitter_deg: float = 6.0
    pitch_deg: float = 8.0
    pitch_jitter_deg: float = 3.0
    roll_jitter_deg: float = 2.0
    camera_height_m: float = 1.6
    height_jitter_m: float = 0.1
    lateral_offset_m: float = 2.0  # keep right of the street centre
    lateral_jitter_m: float = 0.5
    heading_smoothing_m: float = 6.0
    # visibility and keypoints
    min_depth_m: float = 0.5
    max_depth_m: float = 35.0
    max_view_angle_deg: float = 75.0
    min_scale_px: float = 1.6
    max_keypoints: int = 4096
    outlier_fraction: float = 0.15
    pixel_noise_px: float = 0.7
    # descriptors
    descriptor_noise: float = 0.7
    view_drift: float = 0.35  # per radian of viewing angle
    scale_drift: float = 0.25  # per unit of log distance

    def __post_init__(self) -> None:
        if self.num_images < 2:
            raise ValueError(f"a world needs at least 2 images, got {self.num_images}")
        if not 0 <= self.outlier_fraction < 1 or not 0 <= self.repeat_fraction <= 1:
            raise ValueError("outlier_fraction must be in [0, 1) and repeat_fraction in [0, 1]")
        if self.street_width_m / 2 <= self.lateral_offset_m + 3 * self.lateral_jitter_m:
            raise ValueError("the camera must stay in the street: lateral_offset_m too large for street_width_m")
        if not self.yaw_pattern_deg:
            raise ValueError("yaw_pattern_deg needs at least one angle")

    @property
    def pitch_m(self) -> float:
        """Distance between neighbouring street centrelines (m)."""
        return self.block_size_m + self.street_width_m

    def camera_params(self) -> list[float]:
        """PINHOLE fx, fy, cx, cy in COLMAP's pixel convention."""
        return [self.focal_px, self.focal_px, self.width / 2, self.height / 2]

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def key(self) -> str:
        return fingerprint({"config": self.to_dict(), "version": WORLD_VERSION})


def features_name() -> str:
    """The features file sara's extract stage would write for its default (SIFT) backend."""
    try:
        from ..config import ExtractConfig
        from ..features import features_file_name
    except ImportError:  # sara before per-backend feature files
        return "features.h5"
    return features_file_name(ExtractConfig())


def grid_blocks(conf: WorldConfig) -> int:
    """G: blocks per side of the walked grid, so that each street is walked about `visits_per_street` times."""
    if conf.grid_blocks > 0:
        return conf.grid_blocks
    walked = conf.num_images * conf.step_m / (conf.pitch_m * conf.visits_per_street)  # streets to cover
    # 2 G (G + 1) streets between the (G + 1)^2 crossings
    return max(1, round((-1 + math.sqrt(1 + 2 * walked)) / 2))


def image_name(index: int) -> str:
    return f"{index:06d}.jpg"


# ---------------------------------------------------------------------------------------------
# Hash-based descriptors: no table, the same vector for a key every time
# ---------------------------------------------------------------------------------------------

_SM_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_SM_M1 = np.uint64(0xBF58476D1CE4E5B9)
_SM_M2 = np.uint64(0x94D049BB133111EB)


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser, element-wise on a uint64 array (wraps modulo 2^64)."""
    x = x + _SM_GAMMA
    x = (x ^ (x >> np.uint64(30))) * _SM_M1
    x = (x ^ (x >> np.uint64(27))) * _SM_M2
    return x ^ (x >> np.uint64(31))


def _hash_uniform(keys: np.ndarray, seed: int, dim: int = DESCRIPTOR_DIM) -> np.ndarray:
    """(K,) uint64 keys -> (K, dim) float32 uniforms in (0, 1), four 16-bit draws per 64-bit hash."""
    keys = np.asarray(keys, dtype=np.uint64)
    mixed = _splitmix64(keys ^ _splitmix64(np.full(1, seed, dtype=np.uint64)))
    words = -(-dim // 4)
    bits = _splitmix64(mixed[:, None] + np.arange(1, words + 1, dtype=np.uint64)[None, :])
    parts = bits.view(np.uint16).reshape(len(keys), words * 4)[:, :dim]
    return (parts.astype(np.float32) + 0.5) / 65536.0


def base_descriptors(keys: np.ndarray, seed: int) -> np.ndarray:
    """(K,) keys -> (K, 128) float32 unit RootSIFT-like vectors (non-negative entries)."""
    hist = (-np.log(_hash_uniform(keys, seed))) ** 1.5
    hist /= hist.sum(axis=1, keepdims=True)
    return np.sqrt(hist)


# A fixed permutation per drift direction: the drift of a point is its own vector, shuffled and
# centred, so it costs no more hashing and is the same in every image.
_PERM_VIEW = np.random.default_rng(101).permutation(DESCRIPTOR_DIM)
_PERM_SCALE = np.random.default_rng(202).permutation(DESCRIPTOR_DIM)


def point_descriptors(keys: np.ndarray, point_ids: np.ndarray, conf: WorldConfig) -> np.ndarray:
    """(K,) descriptor keys and point ids (-1: none) -> (K, 128) float32 unit descriptors of the points.

    A repeated point (its key a style word) is its word's vector plus ``repeat_jitter`` times a
    centred vector of its own: look-alike, as windows of one facade are, but not identical.
    """
    base = base_descriptors(keys, conf.seed)
    repeated = np.flatnonzero((np.asarray(keys, np.uint64) & _STYLE_KEY_BIT) != 0)
    if conf.repeat_jitter > 0 and len(repeated):
        own = base_descriptors(np.asarray(point_ids)[repeated].astype(np.uint64), conf.seed + 1)
        own -= own.mean(axis=1, keepdims=True)
        mixed = np.maximum(base[repeated] + conf.repeat_jitter * own, 0.0)
        base[repeated] = mixed / np.maximum(np.linalg.norm(mixed, axis=1, keepdims=True), 1e-9)
    return base


def observe_descriptors(keys: np.ndarray, view_angle_rad: np.ndarray, log_distance: np.ndarray,
                        rng: np.random.Generator, conf: WorldConfig, point_ids: np.ndarray | None = None) -> np.ndarray:
    """(K,) keys and viewing conditions -> (K, 128) uint8 noisy observations (RootSIFT x 512, clipped)."""
    base = point_descriptors(keys, np.full(len(keys), -1) if point_ids is None else point_ids, conf)
    if len(base) == 0:
        return np.zeros((0, DESCRIPTOR_DIM), np.uint8)
    centred = base - base.mean(axis=1, keepdims=True)
    drift_v = centred[:, _PERM_VIEW]
    drift_v /= np.maximum(np.linalg.norm(drift_v, axis=1, keepdims=True), 1e-9)
    drift_s = centred[:, _PERM_SCALE]
    drift_s /= np.maximum(np.linalg.norm(drift_s, axis=1, keepdims=True), 1e-9)
    sigma = conf.descriptor_noise * np.exp(0.2 * rng.standard_normal(len(base), dtype=np.float32))
    noise = rng.standard_normal(base.shape, dtype=np.float32) * (sigma / math.sqrt(DESCRIPTOR_DIM))[:, None]
    obs = base + noise
    obs += (conf.view_drift * view_angle_rad.astype(np.float32))[:, None] * drift_v
    obs += (conf.scale_drift * log_distance.astype(np.float32))[:, None] * drift_s
    np.maximum(obs, 0.0, out=obs)
    obs /= np.maximum(np.linalg.norm(obs, axis=1, keepdims=True), 1e-9)
    return np.minimum(np.rint(obs * 512.0), 255.0).astype(np.uint8)


# ---------------------------------------------------------------------------------------------
# The city: blocks, facades, points and a grid of cells to find the points near a camera
# ---------------------------------------------------------------------------------------------


@dataclass
class City:
    """Blocks, facades and the facade points, sorted by cell of a 2D grid.

    blocks: (B, 4) float64 x0, y0, x1, y1. Facades: origin (F, 2), along (F, 2) unit direction,
    normal (F, 2) unit outward (into the street), length (F,), height (F,), style (F,).
    Points: xyz (P, 3) float32, facade (P,) int32, size (P,) float32 metres, key (P,) uint64
    (the descriptor's hash key: the point's id, or its style word for repeated points).
    cell_start: (num_cells + 1,) int64 offsets of each cell's points.
    """

    conf: WorldConfig
    grid: int
    blocks: np.ndarray
    facade_origin: np.ndarray
    facade_along: np.ndarray
    facade_normal: np.ndarray
    facade_length: np.ndarray
    facade_height: np.ndarray
    facade_style: np.ndarray
    xyz: np.ndarray
    facade: np.ndarray
    size: np.ndarray
    key: np.ndarray
    cell_size: float
    cell_origin: np.ndarray
    cell_shape: tuple[int, int]  # (nx, ny); cell id = iy * nx + ix
    cell_start: np.ndarray
    block_range: tuple[int, int]  # block indices per axis run from block_range[0] to block_range[1]

    @property
    def num_points(self) -> int:
        return len(self.xyz)

    def points_near(self, center_xy: np.ndarray, radius: float) -> np.ndarray:
        """Indices of the points in the cells that meet the square of half-side `radius`."""
        nx, ny = self.cell_shape
        lo = np.floor((center_xy - radius - self.cell_origin) / self.cell_size).astype(int)
        hi = np.floor((center_xy + radius - self.cell_origin) / self.cell_size).astype(int)
        x0, x1 = max(lo[0], 0), min(hi[0], nx - 1)
        y0, y1 = max(lo[1], 0), min(hi[1], ny - 1)
        if x0 > x1 or y0 > y1:
            return np.zeros(0, np.int64)
        parts = [np.arange(self.cell_start[iy * nx + x0], self.cell_start[iy * nx + x1 + 1])
                 for iy in range(y0, y1 + 1)]
        return np.concatenate(parts)

    def blocks_near(self, center_xy: np.ndarray, radius: float) -> np.ndarray:
        b = self.blocks
        near = ((b[:, 0] <= center_xy[0] + radius) & (b[:, 2] >= center_xy[0] - radius)
                & (b[:, 1] <= center_xy[1] + radius) & (b[:, 3] >= center_xy[1] - radius))
        return b[near]


def build_city(conf: WorldConfig) -> City:
    """Blocks around the G x G walked grid (one more ring outside), facades and their points."""
    grid = grid_blocks(conf)
    pitch, half = conf.pitch_m, conf.street_width_m / 2
    rng = np.random.default_rng([conf.seed, 7])
    block_ids = range(-1, grid + 1)
    blocks, heights = [], []
    for by in block_ids:
        for bx in block_ids:
            blocks.append((bx * pitch + half, by * pitch + half, (bx + 1) * pitch - half, (by + 1) * pitch - half))
            heights.append(rng.uniform(*conf.facade_height_m))
    blocks_arr = np.array(blocks, dtype=np.float64)
    origin, along, normal, length, height, style = [], [], [], [], [], []
    for (x0, y0, x1, y1), h in zip(blocks_arr, heights):
        # south, north, west, east faces: (origin, along, outward normal, length)
        for o, a, n, ln in (((x0, y0), (1, 0), (0, -1), x1 - x0), ((x0, y1), (1, 0), (0, 1), x1 - x0),
                            ((x0, y0), (0, 1), (-1, 0), y1 - y0), ((x1, y0), (0, 1), (1, 0), y1 - y0)):
            origin.append(o)
            along.append(a)
            normal.append(n)
            length.append(ln)
            height.append(h)
            style.append(int(rng.integers(conf.num_styles)))
    origin_arr = np.array(origin, np.float64)
    along_arr = np.array(along, np.float64)
    normal_arr = np.array(normal, np.float64)
    length_arr = np.array(length, np.float64)
    height_arr = np.array(height, np.float64)
    style_arr = np.array(style, np.int64)

    xyz_parts, facade_parts, size_parts, repeat_parts = [], [], [], []
    for f in range(len(origin_arr)):
        frng = np.random.default_rng([conf.seed, 11, f])
        count = int(frng.poisson(conf.point_density * length_arr[f] * height_arr[f]))
        u = frng.uniform(0, length_arr[f], count)
        z = frng.uniform(0, height_arr[f], count)
        xy = origin_arr[f] + u[:, None] * along_arr[f]
        xyz_parts.append(np.column_stack([xy, z]).astype(np.float32))
        facade_parts.append(np.full(count, f, np.int32))
        size_parts.append((conf.point_size_m * np.exp(conf.point_size_sigma * frng.standard_normal(count)))
                          .astype(np.float32))
        word = frng.integers(conf.style_words, size=count)
        repeat = frng.random(count) < conf.repeat_fraction
        repeat_parts.append(np.where(repeat, style_arr[f] * conf.style_words + word, -1))
    xyz = np.concatenate(xyz_parts)
    facade = np.concatenate(facade_parts)
    size = np.concatenate(size_parts)
    repeat_word = np.concatenate(repeat_parts)

    cell_size = 8.0
    lo = blocks_arr[:, :2].min(axis=0) - 1.0
    hi = blocks_arr[:, 2:].max(axis=0) + 1.0
    nx, ny = (int(v) for v in np.ceil((hi - lo) / cell_size))
    cx = np.clip(((xyz[:, 0] - lo[0]) / cell_size).astype(np.int64), 0, nx - 1)
    cy = np.clip(((xyz[:, 1] - lo[1]) / cell_size).astype(np.int64), 0, ny - 1)
    cell = cy * nx + cx
    order = np.argsort(cell, kind="stable")
    xyz, facade, size, repeat_word, cell = xyz[order], facade[order], size[order], repeat_word[order], cell[order]
    cell_start = np.zeros(nx * ny + 1, np.int64)
    np.cumsum(np.bincount(cell, minlength=nx * ny), out=cell_start[1:])
    point_ids = np.arange(len(xyz), dtype=np.uint64)
    key = np.where(repeat_word >= 0, _STYLE_KEY_BIT | repeat_word.astype(np.uint64), point_ids)
    return City(conf=conf, grid=grid, blocks=blocks_arr, facade_origin=origin_arr, facade_along=along_arr,
                facade_normal=normal_arr, facade_length=length_arr, facade_height=height_arr,
                facade_style=style_arr, xyz=xyz, facade=facade, size=size, key=key, cell_size=cell_size,
                cell_origin=lo, cell_shape=(nx, ny), cell_start=cell_start, block_range=(-1, grid))


# ---------------------------------------------------------------------------------------------
# The walk and the camera poses
# ---------------------------------------------------------------------------------------------


def walk_crossings(grid: int, length_m: float, pitch_m: float, rng: np.random.Generator) -> list[tuple[int, int]]:
    """Crossings (i, j) in 0..grid visited in order: always the least-walked street, no U-turn."""
    node, prev = (0, 0), None
    path = [node]
    visits: dict[tuple[tuple[int, int], tuple[int, int]], int] = {}
    walked = 0.0
    while walked < length_m:
        nbrs = [(node[0] + dx, node[1] + dy) for dx, dy in ((1, 0), (0, 1), (-1, 0), (0, -1))
                if 0 <= node[0] + dx <= grid and 0 <= node[1] + dy <= grid]
        options = [n for n in nbrs if n != prev] or nbrs
        counts = [visits.get((min(node, n), max(node, n)), 0) for n in options]
        best = [n for n, c in zip(options, counts) if c == min(counts)]
        nxt = best[int(rng.integers(len(best)))]
        seg = (min(node, nxt), max(node, nxt))
        visits[seg] = visits.get(seg, 0) + 1
        prev, node = node, nxt
        path.append(node)
        walked += pitch_m
    return path


def _rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """(N,) angles (rad) -> (N, 3, 3) cam_from_world rotations (x right, y down, z forward; world z up).

    yaw is measured from world +x towards +y, pitch up, roll about the viewing direction.
    """
    cp, sp, cy, sy = np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    forward = np.stack([cp * cy, cp * sy, sp], axis=1)
    right = np.stack([sy, -cy, np.zeros_like(yaw)], axis=1)
    down = np.cross(forward, right)
    cr, sr = np.cos(roll)[:, None], np.sin(roll)[:, None]
    right, down = cr * right + sr * down, -sr * right + cr * down
    return np.stack([right, down, forward], axis=1)


def camera_poses(conf: WorldConfig, grid: int) -> dict[str, np.ndarray]:
    """True poses of the walk: centers (N, 3), R (N, 3, 3) cam_from_world, t (N, 3), heading (N,),
    crossing path (M, 2) int and the arc length (N,) of each image along it."""
    rng = np.random.default_rng([conf.seed, 3])
    n = conf.num_images
    length = n * conf.step_m
    path = np.array(walk_crossings(grid, length + conf.pitch_m, conf.pitch_m, rng), dtype=np.float64)
    pts = path * conf.pitch_m
    seg = np.diff(pts, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    dirs = seg / seg_len[:, None]

    def at(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = np.clip(s, 0, cum[-1] - 1e-9)
        k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
        return pts[k] + (s - cum[k])[:, None] * dirs[k], dirs[k]

    s = conf.step_m * (np.arange(n) + 0.5)
    centre, _ = at(s)
    offsets = np.linspace(-conf.heading_smoothing_m, conf.heading_smoothing_m, 9)
    heading_vec = sum(at(s + o)[1] for o in offsets)
    heading_vec /= np.maximum(np.linalg.norm(heading_vec, axis=1, keepdims=True), 1e-9)
    heading = np.arctan2(heading_vec[:, 1], heading_vec[:, 0])
    right = np.stack([np.sin(heading), -np.cos(heading)], axis=1)
    lateral = conf.lateral_offset_m + conf.lateral_jitter_m * rng.standard_normal(n)
    xy = centre + lateral[:, None] * right
    z = conf.camera_height_m + conf.height_jitter_m * rng.standard_normal(n)
    centers = np.column_stack([xy, z])
    pattern = np.radians(np.asarray(conf.yaw_pattern_deg, np.float64))
    yaw = heading + pattern[np.arange(n) % len(pattern)] + np.radians(conf.yaw_jitter_deg) * rng.standard_normal(n)
    pitch = np.radians(conf.pitch_deg + conf.pitch_jitter_deg * rng.standard_normal(n))
    roll = np.radians(conf.roll_jitter_deg) * rng.standard_normal(n)
    R = _rotation(yaw, pitch, roll)
    t = -np.einsum("nij,nj->ni", R, centers)
    return {"centers": centers, "R": R, "t": t, "heading": heading, "path": path.astype(np.int64), "arc_m": s}


# ---------------------------------------------------------------------------------------------
# One image
# ---------------------------------------------------------------------------------------------


@dataclass
class ImageObservation:
    """One synthetic image's features: keypoints (K, 2) hloc pixels, descriptors (K, 128) uint8,
    scores (K,) pixels; point_ids (K,) int64, -1 for outliers."""

    keypoints: np.ndarray
    descriptors: np.ndarray
    scores: np.ndarray
    point_ids: np.ndarray


def _occluded(city: City, center_xy: np.ndarray, targets_xy: np.ndarray, radius: float) -> np.ndarray:
    """(K,) bool: the 2D segment from the camera to the target crosses a block's interior."""
    blocked = np.zeros(len(targets_xy), bool)
    if len(targets_xy) == 0:
        return blocked
    d = targets_xy - center_xy
    eps = 0.02
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        for x0, y0, x1, y1 in city.blocks_near(center_xy, radius):
            tmin = np.zeros(len(d))
            tmax = np.ones(len(d))
            for axis, lo, hi in ((0, x0 + eps, x1 - eps), (1, y0 + eps, y1 - eps)):
                t1 = (lo - center_xy[axis]) * inv[:, axis]
                t2 = (hi - center_xy[axis]) * inv[:, axis]
                flat = d[:, axis] == 0
                inside = lo < center_xy[axis] < hi
                near = np.where(flat, -np.inf if inside else np.inf, np.minimum(t1, t2))
                far = np.where(flat, np.inf if inside else -np.inf, np.maximum(t1, t2))
                np.maximum(tmin, near, out=tmin)
                np.minimum(tmax, far, out=tmax)
            blocked |= tmin < tmax
    return blocked


def observe_image(city: City, R: np.ndarray, center: np.ndarray, rng: np.random.Generator) -> ImageObservation:
    """The features of one image (cam_from_world R, centre in world coordinates)."""
    conf = city.conf
    f, cx, cy = conf.focal_px, conf.width / 2, conf.height / 2
    ids = city.points_near(center[:2], conf.max_depth_m)
    rel = city.xyz[ids].astype(np.float64) - center
    dist = np.linalg.norm(rel, axis=1)
    cam = rel @ R.T
    ok = (cam[:, 2] > conf.min_depth_m) & (dist < conf.max_depth_m)
    ids, rel, dist, cam = ids[ok], rel[ok], dist[ok], cam[ok]
    u = f * cam[:, 0] / cam[:, 2] + cx
    v = f * cam[:, 1] / cam[:, 2] + cy
    scale = f * city.size[ids] / dist
    normal = city.facade_normal[city.facade[ids]]
    to_cam = -rel[:, :2]
    horiz = np.maximum(np.linalg.norm(to_cam, axis=1), 1e-9)
    cos_view = np.sum(normal * to_cam, axis=1) / horiz
    ok = ((u >= 0) & (u < conf.width) & (v >= 0) & (v < conf.height) & (scale >= conf.min_scale_px)
          & (cos_view > math.cos(math.radians(conf.max_view_angle_deg))))
    ids, u, v, scale, dist, normal, to_cam, horiz = ids[ok], u[ok], v[ok], scale[ok], dist[ok], normal[ok], \
        to_cam[ok], horiz[ok]
    visible = ~_occluded(city, center[:2], city.xyz[ids, :2].astype(np.float64), conf.max_depth_m)
    ids, u, v, scale, dist, normal, to_cam, horiz = ids[visible], u[visible], v[visible], scale[visible], \
        dist[visible], normal[visible], to_cam[visible], horiz[visible]
    # signed horizontal viewing angle on the facade: the descriptor drifts with it
    along = np.stack([-normal[:, 1], normal[:, 0]], axis=1)
    view_angle = np.arctan2(np.sum(along * to_cam, axis=1), np.sum(normal * to_cam, axis=1))
    xy = np.column_stack([u, v]) + conf.pixel_noise_px * rng.standard_normal((len(u), 2))
    num_out = round(conf.outlier_fraction / (1 - conf.outlier_fraction) * len(ids))
    out_xy = rng.uniform((0, 0), (conf.width, conf.height), size=(num_out, 2))
    if len(scale):
        out_scale = rng.choice(scale, num_out) * np.exp(0.3 * rng.standard_normal(num_out))
    else:
        out_scale = np.full(num_out, 2.0 * conf.min_scale_px)
    out_keys = _OUTLIER_KEY_BIT | rng.integers(0, 1 << 60, size=num_out, dtype=np.uint64)
    xy = np.concatenate([xy, out_xy])
    scores = np.concatenate([scale, out_scale]).astype(np.float32)
    keys = np.concatenate([city.key[ids], out_keys])
    view = np.concatenate([view_angle, rng.uniform(-1, 1, num_out)])
    log_dist = np.concatenate([np.log(dist / 10.0), rng.uniform(-1, 1, num_out)])
    point_ids = np.concatenate([ids.astype(np.int64), np.full(num_out, -1, np.int64)])
    keep = np.argsort(-scores, kind="stable")[: conf.max_keypoints]
    keep = keep[rng.permutation(len(keep))]  # stored in no particular order, as extractors do
    xy = np.clip(xy[keep], 0.0, [conf.width - 1e-3, conf.height - 1e-3])
    desc = observe_descriptors(keys[keep], view[keep], log_dist[keep], rng, conf, point_ids[keep])
    return ImageObservation(keypoints=(xy - 0.5).astype(np.float32),  # COLMAP -> hloc convention
                            descriptors=desc, scores=scores[keep], point_ids=point_ids[keep])


# ---------------------------------------------------------------------------------------------
# The world on disk
# ---------------------------------------------------------------------------------------------


def _complete(out_dir: Path, conf: WorldConfig) -> dict[str, Any] | None:
    path = out_dir / WORLD_JSON
    if not path.exists():
        return None
    try:
        info = read_json(path)
    except ValueError:
        return None
    if info.get("key") != conf.key() or not info.get("complete"):
        return None
    if not all((out_dir / n).exists() for n in (info.get("features_file", ""), DB_NAME, TRUTH_NAME)):
        return None
    return info


def make_world(out_dir: Path, conf: WorldConfig, *, db_features: bool = False, progress: bool = True,
               overwrite: bool = False) -> dict[str, Any]:
    """Write a world into `out_dir` (features-sift.h5, database.db, truth.h5, world.json); returns world.json.

    Skipped when `out_dir` already holds this world (same config and generator version).
    db_features: also write keypoints and descriptors into the database (COLMAP matching could run
    on it; the selection stage reads only the cameras), which doubles the disk used.
    """
    from ..colmap.build import DatabaseBuilder  # pycolmap stays in sara.colmap

    out_dir = Path(out_dir)
    if not overwrite and (info := _complete(out_dir, conf)) is not None:
        logger.info("world: %s is up to date, skipping", out_dir)
        return info
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / WORLD_JSON).unlink(missing_ok=True)
    tic = time.perf_counter()
    city = build_city(conf)
    poses = camera_poses(conf, city.grid)
    n = conf.num_images
    names = [image_name(i) for i in range(n)]
    features_file = features_name()
    tmp = {name: out_dir / f".{name}.tmp" for name in (features_file, DB_NAME, TRUTH_NAME)}
    for path in tmp.values():
        path.unlink(missing_ok=True)
    num_kp = np.zeros(n, np.int64)
    num_in = np.zeros(n, np.int64)
    with h5py.File(tmp[features_file], "w") as feats_h5, h5py.File(tmp[TRUTH_NAME], "w") as truth_h5, \
            DatabaseBuilder(tmp[DB_NAME], model="PINHOLE", width=conf.width, height=conf.height,
                            params=conf.camera_params()) as db:
        ids_ds = truth_h5.create_dataset("point_ids", shape=(0,), maxshape=(None,), dtype=np.int32,
                                         chunks=(1 << 16,))
        offsets = np.zeros(n + 1, np.int64)
        for i in tqdm(range(n), desc="synthesise images", unit="img", disable=not progress):
            rng = np.random.default_rng([conf.seed, 5, i])
            obs = observe_image(city, poses["R"][i], poses["centers"][i], rng)
            write_features(feats_h5, names[i], Features(obs.keypoints, obs.descriptors, obs.scores,
                                                        (conf.width, conf.height)))
            if db_features:
                db.add_image(names[i], obs.keypoints + 0.5, obs.scores, obs.descriptors)
            else:
                db.add_image(names[i])
            seen = np.sort(obs.point_ids[obs.point_ids >= 0]).astype(np.int32)
            offsets[i + 1] = offsets[i] + len(seen)
            ids_ds.resize((offsets[i + 1],))
            ids_ds[offsets[i]:offsets[i + 1]] = seen
            num_kp[i], num_in[i] = len(obs.point_ids), len(seen)
        truth_h5.create_dataset("offsets", data=offsets)
        truth_h5.create_dataset("names", data=np.array(names, dtype=object), dtype=h5py.string_dtype())
        truth_h5.create_dataset("cam_from_world_R", data=poses["R"])
        truth_h5.create_dataset("cam_from_world_t", data=poses["t"])
        truth_h5.create_dataset("centers", data=poses["centers"])
        truth_h5.create_dataset("heading", data=poses["heading"])
        truth_h5.create_dataset("arc_m", data=poses["arc_m"])
        truth_h5.create_dataset("crossings", data=poses["path"])
        truth_h5.create_dataset("points_xyz", data=city.xyz)
        truth_h5.create_dataset("points_facade", data=city.facade)
        truth_h5.create_dataset("blocks", data=city.blocks)
        truth_h5.attrs["camera_model"] = "PINHOLE"
        truth_h5.attrs["camera_params"] = conf.camera_params()
        truth_h5.attrs["config"] = json.dumps(conf.to_dict())
    for name, path in tmp.items():
        os.replace(path, out_dir / name)
    visits = _street_visits(poses["path"])
    info = {
        "key": conf.key(),
        "complete": True,
        "config": conf.to_dict(),
        "grid_blocks": city.grid,
        "num_images": n,
        "num_points3D": city.num_points,
        "walk_length_m": float(n * conf.step_m),
        "streets": 2 * city.grid * (city.grid + 1),
        "streets_walked": len(visits),
        "streets_walked_twice_or_more": int(sum(v >= 2 for v in visits.values())),
        "street_walks_opposite_direction": int(sum(1 for v in _street_directions(poses["path"]).values()
                                                   if len(v) > 1)),
        "keypoints_mean": float(num_kp.mean()),
        "keypoints_min": int(num_kp.min()),
        "inlier_keypoints_mean": float(num_in.mean()),
        "features_file": features_file,
        "db_features": db_features,
        "synthesis_s": time.perf_counter() - tic,
        "disk_bytes": {name: (out_dir / name).stat().st_size for name in tmp},
    }
    write_json_atomic(out_dir / WORLD_JSON, info)
    return info


def _street_visits(path: np.ndarray) -> dict[tuple, int]:
    visits: dict[tuple, int] = {}
    for a, b in zip(map(tuple, path[:-1]), map(tuple, path[1:])):
        key = (min(a, b), max(a, b))
        visits[key] = visits.get(key, 0) + 1
    return visits


def _street_directions(path: np.ndarray) -> dict[tuple, set]:
    dirs: dict[tuple, set] = {}
    for a, b in zip(map(tuple, path[:-1]), map(tuple, path[1:])):
        dirs.setdefault((min(a, b), max(a, b)), set()).add(a < b)
    return dirs


def remove_world(out_dir: Path) -> None:
    """Delete a world's files (and whatever a selection run left in the folder)."""
    shutil.rmtree(out_dir, ignore_errors=True)


def world_info(out_dir: Path) -> dict[str, Any]:
    """The world.json of a world folder."""
    return read_json(Path(out_dir) / WORLD_JSON)


def features_path(out_dir: Path) -> Path:
    """The features file of a world folder."""
    return Path(out_dir) / world_info(out_dir)["features_file"]


def image_set(out_dir: Path) -> ImageSet:
    """The world's images as sara's ImageSet (the folder `images/` does not exist: no pixels)."""
    out_dir = Path(out_dir)
    info = read_json(out_dir / WORLD_JSON)
    conf = info["config"]
    names = [image_name(i) for i in range(info["num_images"])]
    size = (int(conf["width"]), int(conf["height"]))
    return ImageSet(root=out_dir / IMAGES_DIR, names=names, sizes={n: size for n in names})


def selection_context(conf: Any, out_dir: Path, run_dir: Path, *, progress: bool = True,
                      executor: Any = None) -> Any:
    """The `sara.pairs.PairContext` the pipeline would build to select pairs on this world.

    The selection writes into `run_dir` (global descriptors, scores.csv), which gets a copy of the
    world's database (a link when it holds features), so runs never share cached results.
    `executor`: where the work runs, for a sara that has executors (None: its default).
    """
    from ..pairs import PairContext

    out_dir, run_dir = Path(out_dir), Path(run_dir)
    (run_dir / ".sara").mkdir(parents=True, exist_ok=True)  # the pipeline's records folder exists by then
    images = image_set(out_dir)
    feats = features_path(out_dir)
    db = run_dir / DB_NAME
    if not db.exists():
        if world_info(out_dir).get("db_features"):
            db.symlink_to((out_dir / DB_NAME).resolve())
        else:
            shutil.copyfile(out_dir / DB_NAME, db)
    try:
        from ..pipeline import pair_context
    except ImportError:
        pair_context = None
    if pair_context is not None:
        for kwargs in ({"executor": executor, "progress": progress}, {"progress": progress}):
            if executor is None:
                kwargs.pop("executor", None)
            try:
                return pair_context(conf, images, feats, run_dir, **kwargs)
            except TypeError:  # another signature: try without the executor, then from the fields
                continue
    values = {"names": images.names, "images_root": images.root, "features_path": feats, "db_path": db,
              "out_dir": run_dir, "conf": conf, "progress": progress, "executor": executor}
    fields = {f.name for f in dataclasses.fields(PairContext)}
    return PairContext(**{k: v for k, v in values.items() if k in fields})


# ---------------------------------------------------------------------------------------------
# Truth: poses and which pairs truly overlap
# ---------------------------------------------------------------------------------------------


class Truth:
    """The true poses and observations of a world, for judging selected pairs.

    Two images truly overlap when they observe at least `min_common` common 3D points (their
    keypoints with a 3D point, outliers aside, within the `max_keypoints` kept). Counts are
    computed for the pairs asked, never for all N^2.
    """

    def __init__(self, out_dir: Path, *, min_common: int = 20):
        self.min_common = int(min_common)
        with h5py.File(Path(out_dir) / TRUTH_NAME, "r") as h5:
            self.names = [n.decode() if isinstance(n, bytes) else str(n) for n in h5["names"][()]]
            self.offsets = h5["offsets"][()]
            self.point_ids = h5["point_ids"][()]
            self.R = h5["cam_from_world_R"][()]
            self.t = h5["cam_from_world_t"][()]
            self.centers = h5["centers"][()]
        self.index = {n: i for i, n in enumerate(self.names)}

    def observed(self, image: int | str) -> np.ndarray:
        """Sorted int32 ids of the 3D points an image observes."""
        i = self.index[image] if isinstance(image, str) else int(image)
        return self.point_ids[self.offsets[i]:self.offsets[i + 1]]

    def common_points(self, a: int | str, b: int | str) -> int:
        return int(np.intersect1d(self.observed(a), self.observed(b), assume_unique=True).size)

    def common_counts(self, pairs: Iterable[Sequence[int | str]]) -> np.ndarray:
        """(P,) int64 common 3D points of each pair (names or indices)."""
        return np.array([self.common_points(a, b) for a, b in pairs], dtype=np.int64)

    def overlaps(self, pairs: Iterable[Sequence[int | str]]) -> np.ndarray:
        """(P,) bool: the pair truly overlaps (at least `min_common` common points)."""
        return self.common_counts(pairs) >= self.min_common

    def relative_angle_deg(self, a: int | str, b: int | str) -> float:
        """Angle of the relative rotation between two cameras, degrees."""
        i = self.index[a] if isinstance(a, str) else int(a)
        j = self.index[b] if isinstance(b, str) else int(b)
        rel = self.R[j] @ self.R[i].T
        return float(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1))))
