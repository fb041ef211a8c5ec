"""The city: blocks, facades, their points, and a grid of cells to find the points near a camera."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import STYLE_KEY_BIT, WorldConfig, grid_blocks


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

    xyz, facade, size, repeat_word = _facade_points(conf, origin_arr, along_arr, length_arr, height_arr,
                                                    style_arr)

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
    key = np.where(repeat_word >= 0, STYLE_KEY_BIT | repeat_word.astype(np.uint64), point_ids)
    return City(conf=conf, grid=grid, blocks=blocks_arr, facade_origin=origin_arr, facade_along=along_arr,
                facade_normal=normal_arr, facade_length=length_arr, facade_height=height_arr,
                facade_style=style_arr, xyz=xyz, facade=facade, size=size, key=key, cell_size=cell_size,
                cell_origin=lo, cell_shape=(nx, ny), cell_start=cell_start, block_range=(-1, grid))


def _facade_points(conf: WorldConfig, origin: np.ndarray, along: np.ndarray, length: np.ndarray,
                   height: np.ndarray, style: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The points of every facade, each facade drawing from its own generator: xyz (P, 3) float32,
    facade (P,) int32, size (P,) float32 metres, repeated style word (P,) int64 (-1: a point of its own)."""
    xyz_parts, facade_parts, size_parts, repeat_parts = [], [], [], []
    for f in range(len(origin)):
        frng = np.random.default_rng([conf.seed, 11, f])
        count = int(frng.poisson(conf.point_density * length[f] * height[f]))
        u = frng.uniform(0, length[f], count)
        z = frng.uniform(0, height[f], count)
        xy = origin[f] + u[:, None] * along[f]
        xyz_parts.append(np.column_stack([xy, z]).astype(np.float32))
        facade_parts.append(np.full(count, f, np.int32))
        size_parts.append((conf.point_size_m * np.exp(conf.point_size_sigma * frng.standard_normal(count)))
                          .astype(np.float32))
        word = frng.integers(conf.style_words, size=count)
        repeat = frng.random(count) < conf.repeat_fraction
        repeat_parts.append(np.where(repeat, style[f] * conf.style_words + word, -1))
    xyz = np.concatenate(xyz_parts)
    facade = np.concatenate(facade_parts)
    size = np.concatenate(size_parts)
    repeat_word = np.concatenate(repeat_parts)
    return xyz, facade, size, repeat_word
