"""The report's inline SVG figures: where the views go, the view graph, the top-down plot, histograms.

Top-down frame: "up" is the mean of the cameras' up axes (COLMAP cameras look along +z with y
down, so up is -y); the plot's x axis is the main direction of the camera centres in the plane
orthogonal to up. Without a model the views are placed by a force-directed layout of the selected graph.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np

from ..colmap.model import ModelData
from ..io.pairs import Pair
from . import ADDED_ROLES, SELECTED_ROLES, RunData
from .markup import esc

# role -> (colour, stroke width, opacity, dash pattern)
ROLE_STYLE: dict[str, tuple[str, float, float, str]] = {
    "tree": ("#1f4e9c", 2.6, 0.95, ""),
    "loop": ("#2a9d3f", 2.0, 0.9, ""),
    "anchor": ("#e08a00", 2.0, 0.9, ""),
    "weak": ("#8e44ad", 2.0, 0.9, ""),
    "rescue": ("#8b5a2b", 2.0, 0.9, "6 3"),
    "chain": ("#4682b4", 2.0, 0.9, ""),
    "support": ("#00897b", 2.0, 0.9, "6 3"),
    "pose-guided": ("#f06292", 2.0, 0.9, "6 3"),
    "repair": ("#c2185b", 2.0, 0.9, "6 3"),
    "fill": ("#5d4037", 2.0, 0.9, "6 3"),
    "selected": ("#1f4e9c", 2.0, 0.9, ""),
    "unselected": ("#8a96a3", 0.8, 0.35, ""),
    "rejected": ("#d62728", 0.8, 0.22, "2 3"),
}
#: drawing order, faint first so the chosen edges lie on top
ROLE_ORDER = ("rejected", "unselected", "fill", "repair", "pose-guided", "support", "rescue", "chain", "weak", "anchor",
              "loop", "tree", "selected")
#: the style of a role this page does not know (a pair source's own round): dashed, like the added roles
OTHER_ROLE_STYLE = ("#6d4c41", 2.0, 0.9, "6 3")


def role_order(present: Iterable[str]) -> list[str]:
    """The roles of `present` in drawing order; roles this page does not know go with the added ones."""
    present = set(present)
    known = [r for r in ROLE_ORDER if r in present]
    others = sorted(present - set(ROLE_ORDER))
    at = next((i for i, r in enumerate(known) if r not in ("rejected", "unselected")), len(known))
    return known[:at] + others + known[at:]


def role_style(role: str) -> tuple[str, float, float, str]:
    """(colour, stroke width, opacity, dash pattern) of the edges of `role`."""
    return ROLE_STYLE.get(role, OTHER_ROLE_STYLE)
MAX_POINTS_DRAWN = 6000
MAX_FAINT_EDGES = 20000
FIG_W, FIG_H = 560, 460  # px of the two plots seen from above


# ---------------------------------------------------------------------------------------------
# Geometry of the figures (pure numpy)
# ---------------------------------------------------------------------------------------------


def top_down_frame(centers: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal rows spanning the ground plane of a model (see the module docstring).

    centers: (N, 3) camera centres; rotations: (N, 3, 3) cam_from_world.
    """
    up = -rotations[:, 1, :].mean(0) if len(rotations) else np.zeros(3)
    if np.linalg.norm(up) < 0.3:  # cameras rolled every way: the flattest direction of the centres
        up = np.linalg.svd(centers - centers.mean(0))[2][-1] if len(centers) >= 3 else np.array([0.0, 0.0, 1.0])
    up = up / np.linalg.norm(up)
    flat = centers - centers.mean(0)
    flat = flat - np.outer(flat @ up, up)
    axis = np.linalg.svd(flat)[2][0] if len(centers) >= 2 and np.linalg.norm(flat) > 1e-12 else None
    if axis is None or abs(axis @ up) > 0.9:
        axis = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = axis - (axis @ up) * up
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(up, e1)])


def graph_layout(num_nodes: int, edges: np.ndarray, weights: np.ndarray | None = None, *,
                 iterations: int = 300, seed: int = 0) -> np.ndarray:
    """(N, 2) positions by a Fruchterman-Reingold force layout; edges (E, 2) int, weights (E,) >= 0.

    Deterministic for a seed; nodes start on a circle in index order.
    """
    if num_nodes == 0:
        return np.zeros((0, 2))
    angle = 2 * np.pi * np.arange(num_nodes) / num_nodes
    pos = np.stack([np.cos(angle), np.sin(angle)], 1) + np.random.default_rng(seed).normal(0, 1e-3, (num_nodes, 2))
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    w = np.ones(len(edges)) if weights is None else np.asarray(weights, float) / max(np.max(weights, initial=0), 1e-12)
    k = 1.0 / math.sqrt(num_nodes)
    temperature = 0.1
    for _ in range(iterations):
        delta = pos[:, None, :] - pos[None, :, :]
        dist = np.maximum(np.linalg.norm(delta, axis=2), 1e-3)
        disp = (delta * (k * k / dist ** 2)[:, :, None]).sum(1)
        if len(edges):
            d = pos[edges[:, 0]] - pos[edges[:, 1]]
            length = np.maximum(np.linalg.norm(d, axis=1), 1e-3)
            pull = d * (length / k * (0.2 + w))[:, None]
            np.add.at(disp, edges[:, 0], -pull)
            np.add.at(disp, edges[:, 1], pull)
        step = np.linalg.norm(disp, axis=1, keepdims=True)
        pos += disp / np.maximum(step, 1e-12) * np.minimum(step, temperature)
        temperature = max(temperature * 0.985, 0.002)
    return pos - pos.mean(0)


class Viewport:
    """Maps 2D world coordinates into an SVG box (aspect kept, y up on screen)."""

    def __init__(self, xy: np.ndarray, width: int, height: int, pad: float = 24.0):
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        lo, hi = (xy.min(0), xy.max(0)) if len(xy) else (np.zeros(2), np.ones(2))
        span = np.maximum(hi - lo, 1e-9)
        self.scale = float(min((width - 2 * pad) / span[0], (height - 2 * pad) / span[1]))
        self.offset = np.array([width, height]) / 2 - (lo + hi) / 2 * [self.scale, -self.scale]
        self.width, self.height = width, height

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        return np.asarray(xy, dtype=np.float64) * [self.scale, -self.scale] + self.offset

    def inside(self, uv: np.ndarray) -> np.ndarray:
        return (uv[:, 0] >= 0) & (uv[:, 0] <= self.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= self.height)


def robust_bounds(xy: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Corner points that hold `keep` and the middle 96% of `xy` (outlying 3D points are cut)."""
    parts = [keep.reshape(-1, 2)]
    if len(xy) >= 10:
        parts.append(np.percentile(xy, [2, 98], axis=0))
    elif len(xy):
        parts.append(xy)
    return np.concatenate(parts)


def subsample(count: int, limit: int) -> np.ndarray:
    """Indices of at most `limit` of `count` items, the same ones every time."""
    return np.arange(count) if count <= limit else np.random.default_rng(0).choice(count, limit, replace=False)


def node_positions(data: RunData) -> tuple[np.ndarray, np.ndarray, str]:
    """(N, 2) positions of `data.names`, (N,) registered mask and a word on how they were placed."""
    index = {n: i for i, n in enumerate(data.names)}
    registered = np.zeros(len(data.names), dtype=bool)
    if data.model is not None and len(data.model.names) >= 2:
        basis = top_down_frame(data.model.centers, data.model.rotations)
        xy = data.model.centers @ basis.T
        pos = np.zeros((len(data.names), 2))
        rows = [index[n] for n in data.model.names]
        pos[rows], registered[rows] = xy, True
        _park_unregistered(pos, registered)
        return pos, registered, "camera positions seen from above"
    roles = data.edge_roles()
    chosen = [(index[a], index[b]) for (a, b), r in roles.items() if r in SELECTED_ROLES + ADDED_ROLES + ("selected",)]
    pos = graph_layout(len(data.names), np.array(chosen, dtype=np.int64).reshape(-1, 2))
    return pos, registered, "a force-directed layout of the selected graph (no model)"


def _park_unregistered(pos: np.ndarray, registered: np.ndarray) -> None:
    """Line the images the model left out up to the right of the registered ones."""
    left_out = np.flatnonzero(~registered)
    if len(left_out) == 0:
        return
    lo, hi = pos[registered].min(0), pos[registered].max(0)
    span = max(float(np.max(hi - lo)), 1e-9)
    ys = np.linspace(hi[1], lo[1], len(left_out)) if len(left_out) > 1 else np.array([(lo[1] + hi[1]) / 2])
    pos[left_out] = np.stack([np.full(len(left_out), hi[0] + 0.25 * span), ys], 1)


def model_points_2d(data: RunData, limit: int = 3000) -> np.ndarray:
    """(P, 2) top-down positions of at most `limit` 3D points of model 0 (none without a model)."""
    if data.model is None or len(data.model.names) < 2 or not len(data.model.points_xyz):
        return np.zeros((0, 2))
    basis = top_down_frame(data.model.centers, data.model.rotations)
    return data.model.points_xyz[subsample(len(data.model.points_xyz), limit)] @ basis.T


# ---------------------------------------------------------------------------------------------
# The view graph
# ---------------------------------------------------------------------------------------------


def view_graph_svg(data: RunData, roles: dict[Pair, str], pos: np.ndarray, registered: np.ndarray,
                   edge_title: Callable[[Pair, str], str]) -> str:
    """The view graph over `pos` (N, 2), one group of edges per role (the legend toggles them)."""
    view = Viewport(robust_bounds(model_points_2d(data), pos), FIG_W, FIG_H, pad=30)
    uv = view(pos)
    index = {n: i for i, n in enumerate(data.names)}
    parts = [_faint_points(data, view)]
    for role in role_order([*ROLE_ORDER, *roles.values()]):  # a group per known role, empty ones too
        pairs = [p for p, r in roles.items() if r == role]
        if role in ("unselected", "rejected"):
            pairs = [pairs[i] for i in np.sort(subsample(len(pairs), MAX_FAINT_EDGES))]
        colour, width, opacity, dash = role_style(role)
        dash_attr = f" stroke-dasharray=\"{dash}\"" if dash else ""
        lines = []
        for pair in pairs:
            (x0, y0), (x1, y1) = uv[index[pair[0]]], uv[index[pair[1]]]
            lines.append(f"<line x1=\"{x0:.1f}\" y1=\"{y0:.1f}\" x2=\"{x1:.1f}\" y2=\"{y1:.1f}\">"
                         f"<title>{esc(edge_title(pair, role))}</title></line>")
        parts.append(f"<g class=\"edges role-{role}\" stroke=\"{colour}\" stroke-width=\"{width}\" "
                     f"stroke-opacity=\"{opacity}\"{dash_attr}>{''.join(lines)}</g>")
    parts.append(_graph_nodes(data, uv, registered, roles))
    return f"<svg id=\"viewgraph\" class=\"fig\" viewBox=\"0 0 {view.width} {view.height}\">{''.join(parts)}</svg>"


def _faint_points(data: RunData, view: Viewport) -> str:
    xy = model_points_2d(data)
    if not len(xy):
        return ""
    uv = view(xy)
    uv = uv[view.inside(uv)]
    dots = "".join(f"<rect x=\"{u:.1f}\" y=\"{v:.1f}\" width=\"1.4\" height=\"1.4\"/>" for u, v in uv)
    return f"<g fill=\"#b8c2cc\" fill-opacity=\"0.5\">{dots}</g>"


def _graph_nodes(data: RunData, uv: np.ndarray, registered: np.ndarray, roles: dict[Pair, str]) -> str:
    degree = Counter(n for p, r in roles.items() if r not in ("unselected", "rejected") for n in p)
    observations = dict(zip(data.model.names, data.model.num_observations)) if data.model is not None else {}
    label_all = len(data.names) <= 40
    nodes, labels = [], []
    for i, name in enumerate(data.names):
        x, y = uv[i]
        left_out = data.model is not None and not registered[i]
        radius = 3.5 + min(degree[name], 12) * 0.35
        style = "fill=\"#fff\" stroke=\"#d62728\" stroke-width=\"2\"" if left_out else "fill=\"#243447\""
        info = f"{name}: {degree[name]} matched pairs" + (
            "; not registered" if left_out else f"; {observations[name]} 3D points" if name in observations else "")
        nodes.append(f"<circle cx=\"{x:.1f}\" cy=\"{y:.1f}\" r=\"{radius:.1f}\" {style}>"
                     f"<title>{esc(info)}</title></circle>")
        if label_all or left_out:
            right = x > 0.7 * FIG_W  # near the right edge: the label goes left of the node
            lx = x - radius - 2 if right else x + radius + 2
            anchor = " text-anchor=\"end\"" if right else ""
            labels.append(f"<text x=\"{lx:.1f}\" y=\"{y - radius:.1f}\"{anchor}>{esc(short_label(name))}</text>")
    return f"<g>{''.join(nodes)}</g><g class=\"labels\">{''.join(labels)}</g>"


def short_label(name: str, max_chars: int = 14) -> str:
    """A node label: the file name without extension, its last `max_chars` characters when longer."""
    stem = Path(name).stem
    return stem if len(stem) <= max_chars else "\u2026" + stem[-(max_chars - 1):]


def role_swatch(role: str) -> str:
    """A short line drawn in the role's style, for the legend."""
    colour, width, opacity, dash = role_style(role)
    dash_attr = f" stroke-dasharray=\"{dash}\"" if dash else ""
    return (f"<svg width=\"28\" height=\"10\"><line x1=\"1\" y1=\"5\" x2=\"27\" y2=\"5\" stroke=\"{colour}\" "
            f"stroke-width=\"{max(width, 1.5)}\" stroke-opacity=\"{max(opacity, 0.5)}\"{dash_attr}/></svg>")


# ---------------------------------------------------------------------------------------------
# Cameras and points from above; histograms
# ---------------------------------------------------------------------------------------------


def top_down_svg(m: ModelData) -> tuple[str, int]:
    """The cameras (centre and viewing direction) and the points of `m` in their colours, seen from
    above, and how many points were drawn; `m` has two images or more."""
    basis = top_down_frame(m.centers, m.rotations)
    cams = m.centers @ basis.T
    keep = subsample(len(m.points_xyz), MAX_POINTS_DRAWN)
    pts = m.points_xyz[keep] @ basis.T
    view = Viewport(robust_bounds(pts, cams), FIG_W, FIG_H)
    uv = view(pts)
    inside = view.inside(uv)
    dots = "".join(f"<rect x=\"{u:.1f}\" y=\"{v:.1f}\" width=\"1.6\" height=\"1.6\" fill=\"rgb({r},{g},{b})\"/>"
                   for (u, v), (r, g, b) in zip(uv[inside], m.points_rgb[keep][inside].tolist()))
    span = float(np.ptp(cams, axis=0).max()) if len(cams) > 1 else 1.0
    tips = view(cams + (m.viewing_directions @ basis.T) * 0.06 * span)
    cam_uv = view(cams)
    glyphs = "".join(
        f"<g><title>{esc(name)}</title><line x1=\"{a[0]:.1f}\" y1=\"{a[1]:.1f}\" x2=\"{b[0]:.1f}\" y2=\"{b[1]:.1f}\"/>"
        f"<circle cx=\"{a[0]:.1f}\" cy=\"{a[1]:.1f}\" r=\"3\"/></g>" for name, a, b in zip(m.names, cam_uv, tips))
    svg = (f"<svg class=\"fig dark\" viewBox=\"0 0 {view.width} {view.height}\"><g>{dots}</g>"
           f"<g class=\"cams\" stroke=\"#ff4d4d\" stroke-width=\"2\" fill=\"#ff4d4d\">{glyphs}</g></svg>")
    return svg, len(keep)


def histogram_svg(values: np.ndarray, groups: Sequence[tuple[str, np.ndarray, str]], *, title: str,
                  threshold: float | None = None, threshold_label: str = "", bins: int = 30,
                  upper: float | None = None) -> str:
    """A stacked histogram as inline SVG: groups are (label, mask over values, colour)."""
    values = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(values)
    hi = upper if upper is not None else (float(np.percentile(values[finite], 99)) if finite.any() else 1.0)
    if threshold is not None:
        hi = max(hi, 1.5 * threshold)
    hi = hi if hi > 0 else 1.0
    edges = np.linspace(0.0, hi, bins + 1)
    clipped = np.clip(values, 0.0, hi)
    counts = [np.histogram(clipped[mask & finite], edges)[0] for _, mask, _ in groups]
    top = max(int(np.sum(counts, axis=0).max(initial=0)), 1)
    w, h, left, bottom, ceiling = 340, 180, 34, 28, 32  # ceiling: the top of the tallest bar
    bw, height = (w - left - 8) / bins, h - bottom - ceiling
    rects, base = [], np.zeros(bins)
    for (label, _, colour), count in zip(groups, counts):
        for i, c in enumerate(count):
            if c:
                y0 = h - bottom - (base[i] + c) / top * height
                rects.append(f"<rect x=\"{left + i * bw:.1f}\" y=\"{y0:.1f}\" width=\"{bw - 1:.1f}\" "
                             f"height=\"{c / top * height:.1f}\" fill=\"{colour}\"><title>{esc(label)}: {c} "
                             f"in [{edges[i]:.3g}, {edges[i + 1]:.3g})</title></rect>")
        base += count
    parts = [f"<text x=\"{left}\" y=\"11\" class=\"t\">{esc(title)}</text>", "".join(rects),
             f"<line x1=\"{left}\" y1=\"{h - bottom}\" x2=\"{w - 8}\" y2=\"{h - bottom}\" stroke=\"#555\"/>",
             f"<text x=\"{left}\" y=\"{h - bottom + 14}\">0</text>",
             f"<text x=\"{w - 8}\" y=\"{h - bottom + 14}\" text-anchor=\"end\">{hi:.3g}</text>",
             f"<text x=\"{left - 4}\" y=\"{ceiling + 4}\" text-anchor=\"end\">{top}</text>"]
    if threshold is not None:
        x = left + threshold / hi * (w - left - 8)
        parts.append(f"<line x1=\"{x:.1f}\" y1=\"17\" x2=\"{x:.1f}\" y2=\"{h - bottom}\" stroke=\"#000\" "
                     f"stroke-dasharray=\"4 3\"/><text x=\"{x + 3:.1f}\" y=\"25\">{esc(threshold_label)}</text>")
    return f"<svg class=\"hist\" viewBox=\"0 0 {w} {h}\">{''.join(parts)}</svg>"
