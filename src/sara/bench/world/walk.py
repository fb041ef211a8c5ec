"""The walk through the streets and the true camera poses along it."""

from __future__ import annotations

import numpy as np

from .config import WorldConfig


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

