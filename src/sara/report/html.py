"""`report.html`: one self-contained page that shows why the pairs were chosen and what came of them.

Opens without a network: inline CSS, inline SVG figures, thumbnails as base64 JPEG, a few lines of
inline JavaScript (legend toggles). Sections, each present when the run has the data for it:

1. summary cards; 2. the view graph over the reconstructed camera positions seen from above (a
force-directed layout when there is no model), edges coloured by role, rejected candidates faint;
3. a top-down plot of the cameras and the coloured 3D points; 4. pairs against exhaustive matching;
5. histograms of overlap O, parallax P, RANSAC inliers and weight w with the scorer's thresholds;
6. thumbnails of the weakest views and of selected and rejected pairs with O, P and w;
7. time per stage; 8. the reconstruction; 9. the evaluation against ground truth (`metrics.json`).

Top-down frame: "up" is the mean of the cameras' up axes (COLMAP cameras look along +z with y
down, so up is -y); the plot's x axis is the main direction of the camera centres in the plane
orthogonal to up.
"""

from __future__ import annotations

import base64
import html
import io
import logging
import math
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..io import write_text_atomic
from ..io.pairs import Pair
from . import ADDED_ROLES, SELECTED_ROLES, RunData, Scores, load_run

logger = logging.getLogger(__name__)

REPORT_NAME = "report.html"
# role -> (colour, stroke width, opacity, dash pattern)
ROLE_STYLE: dict[str, tuple[str, float, float, str]] = {
    "tree": ("#1f4e9c", 2.6, 0.95, ""),
    "loop": ("#2a9d3f", 2.0, 0.9, ""),
    "anchor": ("#e08a00", 2.0, 0.9, ""),
    "weak": ("#8e44ad", 2.0, 0.9, ""),
    "rescue": ("#8b5a2b", 2.0, 0.9, "6 3"),
    "support": ("#00897b", 2.0, 0.9, "6 3"),
    "pose-guided": ("#f06292", 2.0, 0.9, "6 3"),
    "repair": ("#c2185b", 2.0, 0.9, "6 3"),
    "selected": ("#1f4e9c", 2.0, 0.9, ""),
    "unselected": ("#8a96a3", 0.8, 0.35, ""),
    "rejected": ("#d62728", 0.8, 0.22, "2 3"),
}
ROLE_ORDER = ("rejected", "unselected", "repair", "pose-guided", "support", "rescue", "weak", "anchor", "loop", "tree",
              "selected")
MAX_POINTS_DRAWN = 6000
MAX_FAINT_EDGES = 20000
THUMB_PX = 200
FIG_W, FIG_H = 560, 460  # px of the two plots seen from above


def write_report(out_dir: Path, dest: Path | None = None) -> Path:
    """Write `out_dir/report.html` (or `dest`) for the run in `out_dir`; returns its path.

    Works for every pair source (SARA's scores are optional) and for runs without a model.
    """
    data = load_run(Path(out_dir))
    dest = Path(dest) if dest is not None else Path(out_dir) / REPORT_NAME
    write_text_atomic(dest, render(data))
    logger.info("report: %s", dest)
    return dest


def render(data: RunData) -> str:
    """The whole page as one HTML string."""
    thumbs = Thumbnails(data.images_root)
    figures = f"<div class=\"row\">{_graph_section(data)}{_topdown_section(data)}</div>"
    tables = f"<div class=\"row\">{_reconstruction_section(data)}{_evaluation_section(data)}</div>"
    sections = [_summary(data), figures, _pairs_section(data), _scores_section(data),
                _thumbnails_section(data, thumbs), _timing_section(data), tables]
    title = f"sara report: {data.out_dir.resolve().name}"
    body = "".join(s for s in sections if s)
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            f"<title>{_esc(title)}</title><style>{CSS}</style></head><body>"
            f"<h1>{_esc(title)}</h1><p class=\"sub\">{_esc(str(data.out_dir.resolve()))} &middot; pair source "
            f"<b>{_esc(data.method)}</b>{_versions(data)}</p>{body}<script>{JS}</script></body></html>\n")


def _esc(text: object) -> str:
    return html.escape(str(text), quote=True)


def _fmt(value: object, digits: int = 3) -> str:
    if value is None:
        return "&ndash;"
    if isinstance(value, bool | int | np.integer):
        return str(value)
    if isinstance(value, float | np.floating):
        if not math.isfinite(float(value)):
            return _esc(value)
        return f"{float(value):.{digits}g}" if abs(float(value)) < 1e3 else f"{float(value):,.0f}"
    return _esc(value)


def _versions(data: RunData) -> str:
    versions = data.run.get("versions", {})
    parts = [f"sara {data.run['sara_version']}"] if data.run.get("sara_version") else []
    parts += [f"{k} {v}" for k, v in versions.items() if k != "python"]
    return (" &middot; " + _esc(", ".join(parts))) if parts else ""


def _section(title: str, body: str, note: str = "") -> str:
    note_html = f"<p class=\"note\">{note}</p>" if note else ""
    return f"<section><h2>{_esc(title)}</h2>{note_html}{body}</section>"


# ---------------------------------------------------------------------------------------------
# Summary
# ---------------------------------------------------------------------------------------------


def _summary(data: RunData) -> str:
    n = len(data.names)
    registered = len(data.model.names) if data.model is not None else 0
    total_s = sum(float(s.get("time_s", 0.0)) for s in data.stages.values() if isinstance(s, dict))
    cards = [("images", str(n)),
             ("registered", f"{registered} / {n}" if data.model is not None else "no model"),
             ("pairs matched", f"{len(data.pairs)}"),
             ("of exhaustive", f"{100 * len(data.pairs) / max(data.num_exhaustive, 1):.1f}%"),
             ("verified pairs", str(len(data.verified)) if data.verified else "&ndash;"),
             ("3D points", str(len(data.model.points_xyz)) if data.model is not None else "&ndash;"),
             ("models", str(len(data.model_sizes))),
             ("total time", f"{total_s:.1f} s" if total_s else "&ndash;")]
    if data.metrics and isinstance(data.metrics.get("auc"), dict) and "5" in data.metrics["auc"]:
        cards.append(("AUC@5&deg;", f"{100 * float(data.metrics['auc']['5']):.1f}"))
    return "<div class=\"cards\">" + "".join(
        f"<div class=\"card\"><div class=\"v\">{v}</div><div class=\"k\">{k}</div></div>" for k, v in cards) + "</div>"


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


def _robust_bounds(xy: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Corner points that hold `keep` and the middle 96% of `xy` (outlying 3D points are cut)."""
    parts = [keep.reshape(-1, 2)]
    if len(xy) >= 10:
        parts.append(np.percentile(xy, [2, 98], axis=0))
    elif len(xy):
        parts.append(xy)
    return np.concatenate(parts)


def _subsample(count: int, limit: int) -> np.ndarray:
    return np.arange(count) if count <= limit else np.random.default_rng(0).choice(count, limit, replace=False)


# ---------------------------------------------------------------------------------------------
# View graph
# ---------------------------------------------------------------------------------------------


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


def _degrees(value: float) -> str:
    """An angle for a caption; a parallax the scorer did not measure says so."""
    return f"{value:.2f}\u00b0" if np.isfinite(value) else "not measured"


def _inliers(s: Scores, e: int) -> str:
    """The pre-match's inliers: among the best matches, and among all mutual matches when known."""
    text = f"{s.num_inliers[e]} inliers"
    if s.num_inliers_all is not None and s.num_inliers_all[e] > s.num_inliers[e]:
        text += f" ({s.num_inliers_all[e]} of all matches)"
    return text


def _edge_title(pair: Pair, role: str, data: RunData, score_index: dict[Pair, int]) -> str:
    text = f"{pair[0]} \u2013 {pair[1]}: {role}"
    s = data.scores
    if s is not None and pair in score_index:
        e = score_index[pair]
        text += (f"; O={s.overlap[e]:.4f}, P={_degrees(s.parallax_deg[e])}, w={s.weight[e]:.4f}, "
                 f"{_inliers(s, e)}" + (f", {s.reason[e]}" if s.reason[e] else ""))
    if pair in data.verified:
        text += f"; {data.verified[pair]} verified matches"
    return text


def _graph_section(data: RunData) -> str:
    if not data.names:
        return ""
    pos, registered, how = node_positions(data)
    roles = data.edge_roles()
    view = Viewport(_robust_bounds(_model_points_2d(data), pos), FIG_W, FIG_H, pad=30)
    uv = view(pos)
    index = {n: i for i, n in enumerate(data.names)}
    score_index = {p: e for e, p in enumerate(data.scores.pairs)} if data.scores is not None else {}
    counts = Counter(roles.values())
    parts = [_faint_points(data, view)]
    for role in ROLE_ORDER:
        pairs = [p for p, r in roles.items() if r == role]
        if role in ("unselected", "rejected"):
            pairs = [pairs[i] for i in np.sort(_subsample(len(pairs), MAX_FAINT_EDGES))]
        colour, width, opacity, dash = ROLE_STYLE[role]
        dash_attr = f" stroke-dasharray=\"{dash}\"" if dash else ""
        lines = []
        for pair in pairs:
            (x0, y0), (x1, y1) = uv[index[pair[0]]], uv[index[pair[1]]]
            lines.append(f"<line x1=\"{x0:.1f}\" y1=\"{y0:.1f}\" x2=\"{x1:.1f}\" y2=\"{y1:.1f}\">"
                         f"<title>{_esc(_edge_title(pair, role, data, score_index))}</title></line>")
        parts.append(f"<g class=\"edges role-{role}\" stroke=\"{colour}\" stroke-width=\"{width}\" "
                     f"stroke-opacity=\"{opacity}\"{dash_attr}>{''.join(lines)}</g>")
    parts.append(_graph_nodes(data, uv, registered, roles))
    svg = f"<svg id=\"viewgraph\" class=\"fig\" viewBox=\"0 0 {view.width} {view.height}\">{''.join(parts)}</svg>"
    note = (f"Nodes at {how}; hover an edge or a node for its numbers. "
            + ("Hollow red nodes: images the model left out. " if data.model is not None and not registered.all() else "")
            + "Untick a role to hide it.")
    return _section("View graph", _legend(counts) + svg, note)


def _model_points_2d(data: RunData, limit: int = 3000) -> np.ndarray:
    """(P, 2) top-down positions of at most `limit` 3D points of model 0 (none without a model)."""
    if data.model is None or len(data.model.names) < 2 or not len(data.model.points_xyz):
        return np.zeros((0, 2))
    basis = top_down_frame(data.model.centers, data.model.rotations)
    return data.model.points_xyz[_subsample(len(data.model.points_xyz), limit)] @ basis.T


def _faint_points(data: RunData, view: Viewport) -> str:
    xy = _model_points_2d(data)
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
        nodes.append(f"<circle cx=\"{x:.1f}\" cy=\"{y:.1f}\" r=\"{radius:.1f}\" {style}><title>{_esc(info)}</title></circle>")
        if label_all or left_out:
            right = x > 0.7 * FIG_W  # near the right edge: the label goes left of the node
            lx = x - radius - 2 if right else x + radius + 2
            anchor = " text-anchor=\"end\"" if right else ""
            labels.append(f"<text x=\"{lx:.1f}\" y=\"{y - radius:.1f}\"{anchor}>{_esc(short_label(name))}</text>")
    return f"<g>{''.join(nodes)}</g><g class=\"labels\">{''.join(labels)}</g>"


def short_label(name: str, max_chars: int = 14) -> str:
    """A node label: the file name without extension, its last `max_chars` characters when longer."""
    stem = Path(name).stem
    return stem if len(stem) <= max_chars else "\u2026" + stem[-(max_chars - 1):]


def _legend(counts: Counter) -> str:
    items = []
    for role in reversed(ROLE_ORDER):
        if not counts.get(role):
            continue
        colour, width, opacity, dash = ROLE_STYLE[role]
        dash_attr = f" stroke-dasharray=\"{dash}\"" if dash else ""
        swatch = (f"<svg width=\"28\" height=\"10\"><line x1=\"1\" y1=\"5\" x2=\"27\" y2=\"5\" stroke=\"{colour}\" "
                  f"stroke-width=\"{max(width, 1.5)}\" stroke-opacity=\"{max(opacity, 0.5)}\"{dash_attr}/></svg>")
        items.append(f"<label><input type=\"checkbox\" checked data-role=\"{role}\"> {swatch} {role} "
                     f"<span class=\"count\">{counts[role]}</span></label>")
    return f"<div class=\"legend\" data-for=\"viewgraph\">{''.join(items)}</div>"


# ---------------------------------------------------------------------------------------------
# Top-down plot of cameras and points
# ---------------------------------------------------------------------------------------------


def _topdown_section(data: RunData) -> str:
    if data.model is None or len(data.model.names) < 2:
        return _section("Cameras and points from above", "<p>No model: nothing to plot.</p>")
    m = data.model
    basis = top_down_frame(m.centers, m.rotations)
    cams = m.centers @ basis.T
    keep = _subsample(len(m.points_xyz), MAX_POINTS_DRAWN)
    pts = m.points_xyz[keep] @ basis.T
    view = Viewport(_robust_bounds(pts, cams), FIG_W, FIG_H)
    uv = view(pts)
    inside = view.inside(uv)
    dots = "".join(f"<rect x=\"{u:.1f}\" y=\"{v:.1f}\" width=\"1.6\" height=\"1.6\" fill=\"rgb({r},{g},{b})\"/>"
                   for (u, v), (r, g, b) in zip(uv[inside], m.points_rgb[keep][inside].tolist()))
    span = float(np.ptp(cams, axis=0).max()) if len(cams) > 1 else 1.0
    tips = view(cams + (m.viewing_directions @ basis.T) * 0.06 * span)
    cam_uv = view(cams)
    glyphs = "".join(
        f"<g><title>{_esc(name)}</title><line x1=\"{a[0]:.1f}\" y1=\"{a[1]:.1f}\" x2=\"{b[0]:.1f}\" y2=\"{b[1]:.1f}\"/>"
        f"<circle cx=\"{a[0]:.1f}\" cy=\"{a[1]:.1f}\" r=\"3\"/></g>" for name, a, b in zip(m.names, cam_uv, tips))
    svg = (f"<svg class=\"fig dark\" viewBox=\"0 0 {view.width} {view.height}\"><g>{dots}</g>"
           f"<g class=\"cams\" stroke=\"#ff4d4d\" stroke-width=\"2\" fill=\"#ff4d4d\">{glyphs}</g></svg>")
    note = (f"{len(m.names)} cameras (red: centre and viewing direction) and {len(keep)} of "
            f"{len(m.points_xyz)} points of model 0 in their colours, seen from above.")
    return _section("Cameras and points from above", svg, note)


# ---------------------------------------------------------------------------------------------
# Pairs against exhaustive, and the scores
# ---------------------------------------------------------------------------------------------


def _pairs_section(data: RunData) -> str:
    rows = [("exhaustive", data.num_exhaustive)]
    if data.scores is not None:
        rows += [("retrieval candidates", len(data.scores.pairs)),
                 ("accepted by the scorer", int(data.scores.accepted.sum()))]
    rows += [("matched (pairs.txt)", len(data.pairs))]
    if data.verified:
        rows.append(("verified by COLMAP", len(data.verified)))
    top = max(max(v for _, v in rows), 1)
    bars = "".join(
        f"<div class=\"bar\"><span class=\"lbl\">{_esc(k)}</span><span class=\"track\"><span class=\"fill\" "
        f"style=\"width:{100 * v / top:.2f}%\"></span></span><span class=\"val\">{v:,} "
        f"({100 * v / max(data.num_exhaustive, 1):.1f}%)</span></div>" for k, v in rows)
    roles = Counter(data.edge_roles().values())
    table = "".join(f"<tr><td>{_esc(r)}</td><td>{roles[r]}</td></tr>" for r in reversed(ROLE_ORDER) if roles.get(r))
    body = f"<div class=\"bars\">{bars}</div>"
    if table:
        body = (f"<div class=\"side\">{body}<table class=\"small\"><tr><th>role</th><th>pairs</th></tr>"
                f"{table}</table></div>")
    return _section("Pairs against exhaustive matching", body,
                    "Percentages are of the exhaustive n(n-1)/2 pairs.")


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
                             f"height=\"{c / top * height:.1f}\" fill=\"{colour}\"><title>{_esc(label)}: {c} "
                             f"in [{edges[i]:.3g}, {edges[i + 1]:.3g})</title></rect>")
        base += count
    parts = [f"<text x=\"{left}\" y=\"11\" class=\"t\">{_esc(title)}</text>", "".join(rects),
             f"<line x1=\"{left}\" y1=\"{h - bottom}\" x2=\"{w - 8}\" y2=\"{h - bottom}\" stroke=\"#555\"/>",
             f"<text x=\"{left}\" y=\"{h - bottom + 14}\">0</text>",
             f"<text x=\"{w - 8}\" y=\"{h - bottom + 14}\" text-anchor=\"end\">{hi:.3g}</text>",
             f"<text x=\"{left - 4}\" y=\"{ceiling + 4}\" text-anchor=\"end\">{top}</text>"]
    if threshold is not None:
        x = left + threshold / hi * (w - left - 8)
        parts.append(f"<line x1=\"{x:.1f}\" y1=\"17\" x2=\"{x:.1f}\" y2=\"{h - bottom}\" stroke=\"#000\" "
                     f"stroke-dasharray=\"4 3\"/><text x=\"{x + 3:.1f}\" y=\"25\">{_esc(threshold_label)}</text>")
    return f"<svg class=\"hist\" viewBox=\"0 0 {w} {h}\">{''.join(parts)}</svg>"


def _scores_section(data: RunData) -> str:
    s = data.scores
    if s is None:
        return _section("Pre-matching scores", "<p>No scores.csv: only the SARA pair source scores pairs before "
                        f"matching, and this run's pairs came from <b>{_esc(data.method)}</b>.</p>")
    score_conf = data.config.get("score", {})
    selected = np.array([r in SELECTED_ROLES for r in s.role], dtype=bool)
    split = [("accepted", s.accepted, "#4c78a8"), ("rejected", ~s.accepted, "#e45756")]
    by_role = [("selected", selected, "#1f4e9c"), ("accepted, not selected", s.accepted & ~selected, "#9ecae9"),
               ("rejected", ~s.accepted, "#e45756")]
    figs = [
        histogram_svg(s.overlap, split, title="overlap O = inliers / sqrt(Ni Nj)",
                      threshold=score_conf.get("min_overlap"), threshold_label=f"min {score_conf.get('min_overlap')}"),
        histogram_svg(s.parallax_deg, split, title="parallax P (deg, median triangulation angle)",
                      threshold=score_conf.get("min_parallax_deg"),
                      threshold_label=f"min {score_conf.get('min_parallax_deg')}\u00b0"),
        histogram_svg(s.num_inliers.astype(float), split, title="RANSAC inliers of the pre-match",
                      threshold=score_conf.get("min_inliers"), threshold_label=f"min {score_conf.get('min_inliers')}"),
        histogram_svg(s.weight, by_role, title="weight w = O \u00b7 g(P)^\u03b2"),
    ]
    reasons = Counter(r for r in s.reason if r)
    legend = ("<p class=\"keys\"><span style=\"background:#4c78a8\"></span>accepted <span style=\"background:#e45756\">"
              "</span>rejected <span style=\"background:#1f4e9c\"></span>selected <span style=\"background:#9ecae9\">"
              "</span>accepted, not selected</p>")
    why = ", ".join(f"{_esc(k)}: {v}" for k, v in reasons.most_common()) or "none"
    return _section("Pre-matching scores", legend + f"<div class=\"hists\">{''.join(figs)}</div>",
                    f"{len(s.pairs)} candidate pairs; rejected by reason: {why}. Dashed lines: the scorer's "
                    "thresholds from run.json; values above the 99th percentile are counted in the last bin.")


# ---------------------------------------------------------------------------------------------
# Thumbnails
# ---------------------------------------------------------------------------------------------


class Thumbnails:
    """Base64 JPEG thumbnails of the run's images, made once each."""

    def __init__(self, root: Path | None, max_px: int = THUMB_PX):
        self.root, self.max_px = root, max_px
        self._cache: dict[str, str | None] = {}

    def __call__(self, name: str) -> str | None:
        if name not in self._cache:
            self._cache[name] = self._make(name)
        return self._cache[name]

    def _make(self, name: str) -> str | None:
        if self.root is None or not (self.root / name).is_file():
            return None
        from PIL import Image

        try:
            with Image.open(self.root / name) as im:
                im.draft("RGB", (self.max_px * 2, self.max_px * 2))
                rgb = im.convert("RGB")
                rgb.thumbnail((self.max_px, self.max_px))
                buf = io.BytesIO()
                rgb.save(buf, format="JPEG", quality=72)
        except OSError as err:
            logger.warning("report: no thumbnail of %s (%s)", name, err)
            return None
        return "data:image/jpeg;base64," + base64.b64encode(buf.getvalue()).decode("ascii")

    def img(self, name: str) -> str:
        uri = self(name)
        if uri is None:
            return f"<div class=\"noimg\">{_esc(name)}</div>"
        return f"<img src=\"{uri}\" alt=\"{_esc(name)}\" title=\"{_esc(name)}\">"


def weakest_views(data: RunData, count: int = 5) -> list[tuple[str, str]]:
    """(name, why) of the views most at risk: left out of the model, then fewest 3D points (or matched pairs)."""
    roles = data.edge_roles()
    degree = Counter(n for p, r in roles.items() if r not in ("unselected", "rejected") for n in p)
    if data.model is not None:
        obs = dict(zip(data.model.names, data.model.num_observations.tolist()))
        left_out = [(n, "not registered") for n in data.names if n not in obs]
        weak = sorted(obs, key=lambda n: (obs[n], n))
        ranked = left_out + [(n, f"{obs[n]} 3D points") for n in weak]
    else:
        ranked = [(n, "") for n in sorted(data.names, key=lambda n: (degree[n], n))]
    return [(n, ", ".join(x for x in (why, f"{degree[n]} matched pairs") if x)) for n, why in ranked[:count]]


def example_pairs(data: RunData, count: int = 4) -> tuple[list[int], list[int]]:
    """Rows of `scores.csv` to show: selected (the best of each role, then the weakest) and rejected
    (the most overlapping of each reason first)."""
    s = data.scores
    if s is None:
        return [], []
    selected = [e for e in np.argsort(-s.weight, kind="stable") if s.role[e] in SELECTED_ROLES]
    chosen: list[int] = []
    for role in SELECTED_ROLES:
        chosen += [e for e in selected if s.role[e] == role and e not in chosen][:1]
    if selected and selected[-1] not in chosen:
        chosen.append(selected[-1])
    chosen += [e for e in selected if e not in chosen]
    rejected = [e for e in np.argsort(-s.overlap, kind="stable") if s.role[e] == "rejected"]
    first: list[int] = []
    for reason in dict.fromkeys(s.reason[e] for e in rejected):
        first.append(next(e for e in rejected if s.reason[e] == reason))
    first += [e for e in rejected if e not in first]
    return [int(e) for e in chosen[:count]], [int(e) for e in first[:count]]


def _thumbnails_section(data: RunData, thumbs: Thumbnails) -> str:
    views = "".join(f"<figure>{thumbs.img(n)}<figcaption><b>{_esc(n)}</b><br>{_esc(why)}</figcaption></figure>"
                    for n, why in weakest_views(data))
    body = f"<h3>Weakest views</h3><div class=\"thumbs\">{views}</div>"
    selected, rejected = example_pairs(data)
    s = data.scores
    for title, rows in (("Selected pairs", selected), ("Rejected candidates", rejected)):
        if not rows or s is None:
            continue
        cards = []
        for e in rows:
            a, b = s.pairs[e]
            label = s.role[e] if s.accepted[e] else f"rejected: {s.reason[e] or 'not accepted'}"
            cards.append(f"<figure class=\"pair\"><div>{thumbs.img(a)}{thumbs.img(b)}</div><figcaption>"
                         f"<b>{_esc(label)}</b> &middot; O={s.overlap[e]:.4f} &middot; P={_degrees(s.parallax_deg[e])} "
                         f"&middot; w={s.weight[e]:.4f} &middot; {_inliers(s, e)}<br>{_esc(a)} &ndash; "
                         f"{_esc(b)}</figcaption></figure>")
        body += f"<h3>{title}</h3><div class=\"pairs\">{''.join(cards)}</div>"
    note = "" if data.images_root is not None else "The image folder recorded in run.json is not here: no thumbnails."
    return _section("Views and pairs", body, note)


# ---------------------------------------------------------------------------------------------
# Time, reconstruction, evaluation
# ---------------------------------------------------------------------------------------------


def _timing_section(data: RunData) -> str:
    rows = [(name, float(info["time_s"])) for name, info in data.stages.items()
            if isinstance(info, dict) and isinstance(info.get("time_s"), int | float)]
    if not rows:
        return ""
    sub = data.stages.get("pairs", {}).get("timings_s", {})
    total = max(sum(t for _, t in rows), 1e-9)
    top = max(t for _, t in rows) or 1.0
    html_rows = []
    for name, t in rows:
        html_rows.append(_time_bar(name, t, top, total))
        if name == "pairs":
            html_rows += [_time_bar(f"\u2003{k}", float(v), top, total, sub=True) for k, v in sub.items()]
    return _section("Time per stage", f"<div class=\"bars\">{''.join(html_rows)}</div>",
                    f"Total {total:.1f} s (from run.json; stages skipped on resume count their first run).")


def _time_bar(name: str, seconds: float, top: float, total: float, *, sub: bool = False) -> str:
    cls = "fill sub" if sub else "fill"
    return (f"<div class=\"bar\"><span class=\"lbl\">{_esc(name)}</span><span class=\"track\"><span class=\"{cls}\" "
            f"style=\"width:{100 * seconds / top:.2f}%\"></span></span><span class=\"val\">{seconds:.2f} s "
            f"({100 * seconds / total:.0f}%)</span></div>")


def _reconstruction_section(data: RunData) -> str:
    if data.model is None:
        return _section("Reconstruction", "<p>No model was built (no sparse/0). Too few verified pairs, or the "
                        "map stage did not run.</p>")
    m = data.model
    cams = Counter(c.model for c in m.cameras.values())
    rows = [("models (registered images each)", ", ".join(map(str, data.model_sizes))),
            ("registered images (model 0)", f"{len(m.names)} of {len(data.names)}"),
            ("3D points", f"{len(m.points_xyz):,}"),
            ("observations", f"{int(m.track_lengths.sum()):,}"),
            ("mean track length", _fmt(float(m.track_lengths.mean()) if len(m.track_lengths) else None)),
            ("mean reprojection error (px)", _fmt(float(m.points_error_px.mean()) if len(m.points_error_px) else None)),
            ("3D points per image (median)", f"{np.median(m.num_observations):,.0f}" if len(m.names) else "&ndash;"),
            ("cameras", ", ".join(f"{v} {_esc(k)}" for k, v in cams.items()))]
    left_out = [n for n in data.names if n not in set(m.names)]
    if left_out:
        shown = ", ".join(_esc(n) for n in left_out[:20]) + (" ..." if len(left_out) > 20 else "")
        rows.append(("not in model 0", shown))
    return _section("Reconstruction", _table(rows))


def _table(rows: Sequence[tuple[str, str]]) -> str:
    return "<table>" + "".join(f"<tr><th>{_esc(k)}</th><td>{v}</td></tr>" for k, v in rows) + "</table>"


def _evaluation_section(data: RunData) -> str:
    if not data.metrics:
        return ""
    rows = []
    for key, value in data.metrics.items():
        if isinstance(value, dict):
            rows += [(f"{key}@{k}", _fmt(v)) for k, v in value.items()]
        elif not isinstance(value, list):
            rows.append((key, _fmt(value)))
    return _section("Evaluation against ground truth", _table(rows), "From metrics.json (`sara run --gt` or "
                    "`sara evaluate`); angles in degrees, AUC as a fraction.")


CSS = """
body{font:14px/1.45 system-ui,-apple-system,Segoe UI,Roboto,sans-serif;color:#1d2733;background:#f5f7fa;margin:0 auto;
padding:18px 28px;max-width:1240px}
h1{font-size:22px;margin:0 0 2px}h2{font-size:17px;margin:0 0 8px}h3{font-size:14px;margin:14px 0 6px}
.sub{color:#5b6773;margin:0 0 14px;font-size:12px}
section{background:#fff;border:1px solid #dde3ea;border-radius:8px;padding:14px 18px;margin:0 0 16px}
.note{color:#5b6773;font-size:12px;margin:0 0 8px}
.cards{display:flex;flex-wrap:wrap;gap:10px;margin:0 0 16px}
.card{background:#fff;border:1px solid #dde3ea;border-radius:8px;padding:8px 14px;min-width:92px}
.card .v{font-size:20px;font-weight:600}.card .k{color:#5b6773;font-size:12px}
svg.fig{width:100%;height:auto;background:#fbfcfd;border:1px solid #e6ebf0;border-radius:6px}
.row{display:grid;grid-template-columns:repeat(auto-fit,minmax(460px,1fr));gap:16px;margin:0 0 16px}
.row section{margin:0}
svg.fig.dark{background:#1b2230}
svg text{font:10px system-ui,sans-serif;fill:#333}
svg .labels text{fill:#3d4852;paint-order:stroke;stroke:#fbfcfd;stroke-width:3px}
svg.hist{width:272px;height:auto}svg.hist .t{font-weight:600}
.hists{display:flex;flex-wrap:wrap;gap:10px}
.legend{display:flex;flex-wrap:wrap;gap:4px 14px;margin:0 0 8px;font-size:12px}
.legend label{display:flex;align-items:center;gap:4px;cursor:pointer}.legend .count{color:#5b6773}
.keys span{display:inline-block;width:12px;height:12px;margin:0 4px 0 10px;vertical-align:-2px;border-radius:2px}
.keys{font-size:12px;margin:0 0 6px}
.bars{max-width:900px;flex:1}
.side{display:flex;gap:28px;align-items:flex-start}.bar{display:flex;align-items:center;gap:8px;margin:3px 0;font-size:12px}
.bar .lbl{width:170px;white-space:pre}.bar .track{flex:1;background:#eef2f6;height:14px;border-radius:3px}
.bar .fill{display:block;height:14px;background:#4c78a8;border-radius:3px}.bar .fill.sub{background:#9ecae9}
.bar .val{width:150px;text-align:right;color:#333}
table{border-collapse:collapse;font-size:13px;margin:6px 0}th,td{padding:3px 10px;border-bottom:1px solid #eef1f4;
text-align:left;vertical-align:top}th{font-weight:500;color:#4a5561}table.small{font-size:12px}
.thumbs,.pairs{display:flex;flex-wrap:wrap;gap:12px}
figure{margin:0;background:#fafbfc;border:1px solid #e6ebf0;border-radius:6px;padding:6px;font-size:11px}
figure img{display:block;max-width:200px;max-height:150px}figure.pair div{display:flex;gap:4px}
figure.pair img{max-width:170px;max-height:128px}figcaption{margin-top:4px;max-width:350px;overflow-wrap:anywhere}
.noimg{width:150px;height:100px;display:flex;align-items:center;justify-content:center;background:#eef2f6;
color:#5b6773;font-size:10px;text-align:center;word-break:break-all}
"""

JS = """
(function () {
  document.querySelectorAll('.legend').forEach(function (legend) {
    var svg = document.getElementById(legend.getAttribute('data-for'));
    if (!svg) { return; }
    legend.querySelectorAll('input[data-role]').forEach(function (box) {
      box.addEventListener('change', function () {
        svg.querySelectorAll('.role-' + box.getAttribute('data-role')).forEach(function (g) {
          g.style.display = box.checked ? '' : 'none';
        });
      });
    });
  });
})();
"""


