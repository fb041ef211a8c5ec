"""Pose-guided pairs: once a first model exists, predict what matching an unmatched pair would add.

With the poses and the 3D points of a first model, the overlap of two registered views is no
longer a guess from a 50-match sample: every point that view ``i`` observes can be projected into
view ``j``. For a pair ``(i, j)`` this module counts, from each side,

- ``covisible``: points observed in one view that project inside the other, in front of it, seen
  from directions at most ``max_view_angle_deg`` apart (SIFT seldom matches across wider angles);
- ``linked``: points whose track already holds both views (tied through other pairs already);

and the median triangulation angle of the covisible points. From these come SARA's pair weight,
predicted instead of sampled (`pair_scores`).

The core works on arrays: a `ModelGeometry`-like object (names, rotations, translations,
focal_px, principal_px, sizes_px, points_xyz, obs_point, obs_view; see `sara.colmap.refine`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .spanning import take_capped_per_view

#: ways to rank unmatched pairs (see `pair_scores`)
RULES = ("weight", "covisible")


@dataclass(frozen=True)
class Covisibility:
    """Predicted overlap of K view pairs: means of the two directions."""

    covisible: np.ndarray  # (K,) float64 points
    linked: np.ndarray  # (K,) float64 points whose track holds both views
    tri_angle_deg: np.ndarray  # (K,) float64 median triangulation angle, 0 when nothing is covisible
    observed: np.ndarray  # (V,) int64 points observed by every view


def _points_by_view(num_views: int, obs_point: np.ndarray, obs_view: np.ndarray) -> list[np.ndarray]:
    """The sorted, unique points that each view observes."""
    order = np.argsort(obs_view, kind="stable")
    bounds = np.searchsorted(obs_view[order], np.arange(num_views + 1))
    return [np.unique(obs_point[order[bounds[v]:bounds[v + 1]]]) for v in range(num_views)]


def _visible_in(geom, points: np.ndarray, view: int, source_center: np.ndarray,
                max_view_angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(visible mask, angle at the point between the rays to both centres, degrees) of `points` in `view`."""
    xyz = geom.points_xyz[points]
    cam = xyz @ geom.rotations[view].T + geom.translations[view]
    z = cam[:, 2]
    front = z > 1e-9
    uv = geom.focal_px[view] * cam[:, :2] / np.where(front, z, 1.0)[:, None] + geom.principal_px[view]
    inside = front & np.all((uv >= 0) & (uv <= geom.sizes_px[view]), axis=1)
    center = -geom.rotations[view].T @ geom.translations[view]
    ray_a, ray_b = source_center - xyz, center - xyz
    norms = np.maximum(np.linalg.norm(ray_a, axis=1) * np.linalg.norm(ray_b, axis=1), 1e-12)
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", ray_a, ray_b) / norms, -1.0, 1.0)))
    return inside & (angle <= max_view_angle_deg), angle


def covisibility(geom, pairs: np.ndarray, *, max_view_angle_deg: float = 45.0) -> Covisibility:
    """Predicted overlap of view pairs `pairs` ((K, 2) int64 rows of `geom.names`)."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    points = _points_by_view(len(geom.names), geom.obs_point, geom.obs_view)
    centers = -np.einsum("nji,nj->ni", geom.rotations, geom.translations)
    covisible = np.zeros((len(pairs), 2))
    linked = np.zeros(len(pairs))
    tri = np.zeros(len(pairs))
    for k, (a, b) in enumerate(pairs):
        angles = []
        for side, (src, dst) in enumerate(((a, b), (b, a))):
            visible, angle = _visible_in(geom, points[src], dst, centers[src], max_view_angle_deg)
            covisible[k, side] = visible.sum()
            angles.append(angle[visible])
        linked[k] = len(np.intersect1d(points[a], points[b], assume_unique=True))
        both = np.concatenate(angles)
        tri[k] = float(np.median(both)) if len(both) else 0.0
    observed = np.array([len(p) for p in points], dtype=np.int64)
    return Covisibility(covisible.mean(axis=1), linked, tri, observed)


def bounded_by(cov: Covisibility, measured: np.ndarray) -> Covisibility:
    """`cov` with each pair's covisible points at most `measured` ((K,) float64, inf where nothing
    was measured): where the scorer counted a pair's matches among every keypoint of both views, the
    matches are what matching will find, and a model's points two views could share are not."""
    measured = np.asarray(measured, dtype=np.float64).reshape(len(cov.covisible))
    return Covisibility(np.minimum(cov.covisible, measured), cov.linked, cov.tri_angle_deg, cov.observed)


def pair_scores(cov: Covisibility, pairs: np.ndarray, rule: str, *, alpha: float = 1.0, beta: float = 0.5,
                parallax_saturation_deg: float = 10.0) -> np.ndarray:
    """(K,) float64 how much matching each pair of `pairs` ((K, 2) view rows) is expected to add.

    ``weight``: SARA's pair weight ``w = O^alpha * g(P)^beta`` (as the scorer's, see
    `sara.scoring.pair_weight`) with the overlap ``O = covisible / sqrt(n_i n_j)`` (``n``: points
    each view observes) and the parallax ``P`` (median triangulation angle) predicted by the model
    instead of sampled from 50 matches; ``covisible``: all covisible points (the most new 3D
    points: `densify`).
    """
    if rule == "covisible":
        return cov.covisible.astype(np.float64)
    if rule != "weight":
        raise ValueError(f"unknown pose-guided rule {rule!r}; choose one of {', '.join(RULES)}")
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    observed = cov.observed.astype(np.float64)
    norm = np.sqrt(np.maximum(observed[pairs[:, 0]] * observed[pairs[:, 1]], 1.0))
    saturated = np.minimum(np.maximum(cov.tri_angle_deg, 0.0), parallax_saturation_deg) / parallax_saturation_deg
    return (cov.covisible / norm) ** alpha * saturated ** beta


def choose_pairs(pairs: np.ndarray, cov: Covisibility, budget: int, *, rule: str = "weight",
                 min_covisible: float = 0.0, max_per_view: int = 0, **weight_params: float) -> np.ndarray:
    """Indices into `pairs` of at most `budget` pairs, best first (ties: by pair index).

    Pairs with fewer than `min_covisible` predicted covisible points (or none) are never chosen:
    matching them would not pass geometric verification. With `max_per_view` > 0, a pair is skipped
    once one of its views is in that many chosen pairs. `weight_params`: alpha, beta,
    parallax_saturation_deg of `pair_scores`.
    """
    if budget <= 0 or len(pairs) == 0:
        return np.zeros(0, dtype=np.int64)
    score = pair_scores(cov, pairs, rule, **weight_params)
    usable = np.flatnonzero((cov.covisible >= max(min_covisible, 1e-9)) & (score > 0))
    order = usable[np.argsort(-score[usable], kind="stable")]
    if max_per_view <= 0:
        return order[:budget].astype(np.int64)
    return np.asarray(take_capped_per_view(order, pairs, budget, max_per_view), dtype=np.int64)
