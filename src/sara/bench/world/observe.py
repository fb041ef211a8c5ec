"""One image: the points it truly sees (in front, in view, facing it, not hidden, large enough),
with pixel noise, plus outliers, as keypoints, descriptors and scores."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .city import City
from .config import OUTLIER_KEY_BIT
from .descriptors import observe_descriptors


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
    out_keys = OUTLIER_KEY_BIT | rng.integers(0, 1 << 60, size=num_out, dtype=np.uint64)
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

