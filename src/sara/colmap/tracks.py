"""Track extension: longer tracks without matching more pairs.

Each registered view's keypoints are compared with the 3D points the model says it sees: a keypoint
at the point's projection joins the point's track when its descriptor (and, for SIFT, its scale)
fits the track's. No pair is matched; the tracks get the observations that exhaustive matching
would have found, which the bundle adjustment that follows uses.

Conventions (COLMAP's): poses are ``cam_from_world`` (``x_cam = R @ X + t``), pixels have the
centre of the top-left pixel at (0.5, 0.5); keypoints of a features file are hloc's (+0.5 px).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pycolmap

from ..io.h5 import FeatureCache

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackExtension:
    """How `extend_tracks` accepts a keypoint as a new observation of a 3D point.

    The keypoint must be one of the two nearest free keypoints (no 3D point yet) within
    `radius_px` of the point's projection; its descriptor distance (unit vectors, L2) to the
    nearest descriptor of the track at most the distance threshold, and below `max_ratio` times
    that of the other candidate keypoint when there are two; the view must see the point from a
    direction at most `max_view_angle_deg` from a view that observes it.

    The distance threshold is `max_distance` (COLMAP's SIFT matching uses 0.7, and 0.8 for the
    ratio) or, when larger, the `track_distance_quantile` of the model's own tracks: the distance
    from an observation's descriptor to the nearest other descriptor of its track
    (`track_distance_threshold`). SIFT's matched tracks stay far below 0.7 (99th percentile
    0.31-0.36 on the six shared scenes), so for SIFT the threshold is 0.7. Learned descriptors spread
    more (ALIKED, DISK: 1.03-1.09 on bm-moldGoldCape), and at 0.7 the extension added half the
    observations there that it adds with their own threshold.

    With `scale_quantile` (for features whose scores are keypoint scales, SIFT's), the keypoint's
    size in the scene, scale x depth / focal length, must also be within that quantile of the
    tracks' own spread from their median size (`track_sizes`): a keypoint of another scale at the
    projection is another feature.
    """

    radius_px: float = 1.5
    max_distance: float = 0.7
    max_ratio: float = 0.8
    track_distance_quantile: float = 0.99
    max_view_angle_deg: float = 45.0
    #: the scale test's quantile; 0: not tested (the scores are not scales)
    scale_quantile: float = 0.0
    #: observation descriptor values held in memory as float32 (one array: 2 GiB); up to twice as
    #: many as float16 (the same 2 GiB: the 10,000-image synthetic street's final model needs about
    #: 4.3 million observations x 128); larger models are left as they are
    max_values: int = 2**29
    #: views x points projected; above it each view is compared with the points of the views it
    #: shares points with, and the extension stops when those add up to this many
    max_projections: int = 5 * 10**8


@dataclass(frozen=True)
class _Observations:
    """The observations of a model's registered views, one row each, in track order.

    point, view: (M,) int64 rows of `point_ids` and `views`; keypoint: (M,) int64 index in the
    view; xyz: (P, 3) points; centers: (V, 3) camera centres; order: the rows grouped by point
    (stable) and position its inverse; by_view: the rows grouped by view, those of view v being
    ``by_view[view_start[v]:view_start[v + 1]]``.
    """

    point: np.ndarray
    view: np.ndarray
    keypoint: np.ndarray
    xyz: np.ndarray
    centers: np.ndarray
    order: np.ndarray
    position: np.ndarray
    by_view: np.ndarray
    view_start: np.ndarray

    def of_view(self, v: int) -> np.ndarray:
        return self.by_view[self.view_start[v]:self.view_start[v + 1]]


@dataclass(frozen=True)
class _Tracks:
    """What each track's observations look like, in point order (observations of views whose
    features are unknown left out): point, view (M',), unit descriptors (M', D), log sizes (M',);
    track k's rows are [start[k], start[k] + count[k])."""

    point: np.ndarray
    view: np.ndarray
    desc: np.ndarray
    size: np.ndarray
    start: np.ndarray
    count: np.ndarray


def extend_tracks(rec: pycolmap.Reconstruction, features_path: Path,
                  ext: TrackExtension = TrackExtension()) -> int:
    """Add to the tracks of `rec` the keypoints of registered views that observe its 3D points
    without a match saying so; returns the number of observations added.

    Each view is compared with the points it should see (in front of it, inside the image, seen
    from a similar direction by a view of the track): the same test as a descriptor match, limited
    to a keypoint at the point's projection. Keypoints are those of `features_path` (hloc's
    convention, +0.5 px for COLMAP's); a view whose keypoint count differs from the model's is left out.
    """
    views = sorted(rec.reg_image_ids())
    point_ids = np.array(sorted(rec.point3D_ids()), dtype=np.int64)
    if len(views) < 2 or len(point_ids) == 0:
        return 0
    obs = _observations(rec, views, point_ids)
    with FeatureCache(features_path, capacity=1) as cache:
        dim = cache.get(rec.images[views[0]].name).descriptors.shape[1]
        values = len(obs.point) * dim
        if values > 2 * ext.max_values:
            logger.info("track extension: %d views, %d points, %d observations: too large, skipped", len(views),
                        len(point_ids), len(obs.point))
            return 0
        half = values > ext.max_values
        if half:
            logger.info("track extension: %d observations: their descriptors held as float16", len(obs.point))
        usable, tracks = _tracks(rec, views, obs, cache, dim, ext, np.float16 if half else np.float32)
        size, size_tol = None, np.inf
        if ext.scale_quantile > 0:
            size, size_tol = track_sizes(tracks.size, tracks.start, tracks.count, ext.scale_quantile)
            logger.info("track extension: keypoint scales within %.2fx of the track's", np.exp(size_tol))
        max_distance = max(ext.max_distance, track_distance_threshold(tracks.desc, tracks.start, tracks.count,
                                                                      ext.track_distance_quantile))
        if max_distance > ext.max_distance:
            logger.info("track extension: descriptor distance threshold %.2f (the %g quantile of the tracks' own; "
                        "at least %.2f)", max_distance, ext.track_distance_quantile, ext.max_distance)
        ext = replace(ext, max_distance=max_distance)
        return _extend_views(rec, views, point_ids, obs, tracks, usable, cache, ext, size, size_tol)


def _observations(rec: pycolmap.Reconstruction, views: list[int], point_ids: np.ndarray) -> _Observations:
    """The observations of the registered `views` of `point_ids`' tracks, with their indices."""
    row = {iid: k for k, iid in enumerate(views)}
    obs_point, obs_view, obs_idx = [], [], []
    for k, pid in enumerate(point_ids):
        for element in rec.points3D[int(pid)].track.elements:
            if element.image_id in row:
                obs_point.append(k)
                obs_view.append(row[element.image_id])
                obs_idx.append(element.point2D_idx)
    obs_point, obs_view, obs_idx = (np.asarray(a, dtype=np.int64) for a in (obs_point, obs_view, obs_idx))
    order = np.argsort(obs_point, kind="stable")
    position = np.empty(len(order), np.int64)
    position[order] = np.arange(len(order))
    by_view = np.argsort(obs_view, kind="stable")
    return _Observations(
        point=obs_point, view=obs_view, keypoint=obs_idx,
        xyz=np.array([rec.points3D[int(pid)].xyz for pid in point_ids], dtype=np.float64),
        centers=np.array([rec.images[iid].projection_center() for iid in views], dtype=np.float64),
        order=order, position=position, by_view=by_view,
        view_start=np.searchsorted(obs_view[by_view], np.arange(len(views) + 1)))


def _tracks(rec: pycolmap.Reconstruction, views: list[int], obs: _Observations, cache: FeatureCache, dim: int,
            ext: TrackExtension, dtype: type = np.float32) -> tuple[np.ndarray, _Tracks]:
    """(V,) whether each view's features fit the model, and the tracks' descriptors (held as `dtype`;
    compared as float32) and sizes."""
    # the descriptors in point order, written once (no copy of a large array)
    o_desc = np.zeros((len(obs.point), dim), dtype)
    o_size = np.zeros(len(obs.point), np.float64)  # log(scale * depth / focal)
    usable = np.zeros(len(views), bool)
    for v, iid in enumerate(views):
        feats = cache.get(rec.images[iid].name)
        if len(feats.keypoints) != rec.images[iid].num_points2D():
            continue
        usable[v] = True
        here = obs.of_view(v)
        o_desc[obs.position[here]] = _unit(feats.descriptors[obs.keypoint[here]])
        if ext.scale_quantile > 0:
            image = rec.images[iid]
            pose = image.cam_from_world()
            depth = obs.xyz[obs.point[here]] @ pose.rotation.matrix()[2] + pose.translation[2]
            focal = rec.cameras[image.camera_id].mean_focal_length()
            o_size[obs.position[here]] = _log_size(feats.scores[obs.keypoint[here]], depth, focal)
    o_point, o_view = obs.point[obs.order], obs.view[obs.order]
    if not usable.all():  # observations whose descriptors are unknown leave the tracks' lists
        known = usable[o_view]
        o_point, o_view, o_size = o_point[known], o_view[known], o_size[known]
        o_desc = _keep_rows(o_desc, np.flatnonzero(known))
    count = np.bincount(o_point, minlength=len(obs.xyz))
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    return usable, _Tracks(point=o_point, view=o_view, desc=o_desc, size=o_size, start=start, count=count)


def _keep_rows(a: np.ndarray, rows: np.ndarray, chunk: int = 1 << 16) -> np.ndarray:
    """`a[rows]` for increasing `rows`, written over `a` itself a chunk at a time (the largest models'
    descriptors fill gigabytes: a copy would double them for a moment)."""
    for s in range(0, len(rows), chunk):
        part = rows[s:s + chunk]
        a[s:s + len(part)] = a[part]  # each row moves down or stays: nothing still needed is overwritten
    return a[:len(rows)]


def _extend_views(rec: pycolmap.Reconstruction, views: list[int], point_ids: np.ndarray, obs: _Observations,
                  tracks: _Tracks, usable: np.ndarray, cache: FeatureCache, ext: TrackExtension,
                  size: np.ndarray | None, size_tol: float) -> int:
    """`_extend_view` for every usable view, each against the points it does not observe yet."""
    o_dir = obs.xyz[tracks.point] - obs.centers[tracks.view]
    o_dir /= np.linalg.norm(o_dir, axis=1, keepdims=True)
    cos_max = np.cos(np.radians(ext.max_view_angle_deg))
    covisible = len(views) * len(point_ids) > ext.max_projections
    if covisible:
        seen = _incidence(tracks.view, tracks.point, len(views), len(point_ids))
        covisibility = (seen @ seen.T).tocsr()
        logger.info("track extension: %d views x %d points: each view is compared with the points of the views "
                    "it shares points with", len(views), len(point_ids))
    described = tracks.count > 0  # points with known descriptors
    added = projected = 0
    for v, iid in enumerate(views):
        if not usable[v]:
            continue
        if covisible:  # the points of the views that share a point with this one
            near = covisibility.indices[covisibility.indptr[v]:covisibility.indptr[v + 1]]
            candidate = np.zeros(len(point_ids), bool)
            candidate[seen[near].indices] = True
            candidate &= described
        else:
            candidate = described.copy()
        candidate[obs.point[obs.of_view(v)]] = False  # not yet observed here
        if covisible:
            projected += int(candidate.sum())
            if projected > ext.max_projections:
                logger.info("track extension: stopped after %d of %d views (%d projections)", v, len(views),
                            projected)
                break
        added += _extend_view(rec, iid, cache.get(rec.images[iid].name), point_ids, obs.xyz, obs.centers[v],
                              candidate, o_dir, tracks.desc, tracks.start, tracks.count, cos_max, ext, size, size_tol)
    return added


def track_sizes(o_size: np.ndarray, start: np.ndarray, count: np.ndarray, quantile: float):
    """Each track's median log size (keypoint scale x depth / focal) and the `quantile` of an
    observation's distance to its track's median, over tracks of two or more observations."""
    point = np.repeat(np.arange(len(count)), count)
    median = np.full(len(count), np.nan)
    order = np.lexsort((o_size, point))
    sorted_size = o_size[order]
    has = count > 0
    lo = start[has] + (count[has] - 1) // 2
    hi = start[has] + count[has] // 2
    median[has] = 0.5 * (sorted_size[lo] + sorted_size[hi])
    multi = count[point] >= 2
    if not multi.any():
        return median, np.inf
    return median, float(np.quantile(np.abs(o_size[multi] - median[point[multi]]), quantile))


def _log_size(scale: np.ndarray, depth: np.ndarray, focal: float) -> np.ndarray:
    """log(keypoint scale x depth / focal length): the keypoint's size in the scene (log units)."""
    return np.log(np.maximum(np.asarray(scale, np.float64), 1e-6) * np.maximum(depth, 1e-9) / focal)


def _incidence(view: np.ndarray, point: np.ndarray, num_views: int, num_points: int):
    """(V, P) sparse 0/1 matrix: view v observes point p (CSR, int32 counts)."""
    from scipy.sparse import csr_matrix

    matrix = csr_matrix((np.ones(len(view), np.int32), (view, point)), shape=(num_views, num_points))
    matrix.sum_duplicates()
    matrix.data[:] = 1
    return matrix


#: most tracks whose descriptors `track_distance_threshold` compares (evenly spread over all)
TRACK_DISTANCE_SAMPLE = 5000


def track_distance_threshold(o_desc: np.ndarray, start: np.ndarray, count: np.ndarray, quantile: float) -> float:
    """The `quantile` of the distance from an observation's unit descriptor to the nearest other
    descriptor of its track, over up to TRACK_DISTANCE_SAMPLE tracks of two or more observations
    (evenly spaced, so the same model always gives the same value); 0 when there are none or
    `quantile` is 0. Track k's descriptors are ``o_desc[start[k]:start[k] + count[k]]``."""
    tracks = np.flatnonzero(count >= 2)
    if quantile <= 0 or len(tracks) == 0:
        return 0.0
    tracks = tracks[np.linspace(0, len(tracks) - 1, min(len(tracks), TRACK_DISTANCE_SAMPLE)).astype(np.int64)]
    nearest = []
    for k in tracks:
        desc = np.asarray(o_desc[start[k]:start[k] + count[k]], dtype=np.float32)
        sim = desc @ desc.T
        np.fill_diagonal(sim, -np.inf)
        nearest.append(sim.max(axis=1))
    similarity = np.concatenate(nearest).astype(np.float64)
    return float(np.quantile(np.sqrt(np.maximum(0.0, 2.0 - 2.0 * similarity)), quantile))


def _ranges(start: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Concatenation of arange(s, s + c) for each (s, c)."""
    total = int(count.sum())
    offsets = np.repeat(np.cumsum(count) - count, count)
    return np.repeat(start, count) + np.arange(total) - offsets


def _unit(desc: np.ndarray) -> np.ndarray:
    d = np.asarray(desc, dtype=np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def _extend_view(rec: pycolmap.Reconstruction, iid: int, feats, point_ids: np.ndarray, xyz: np.ndarray,
                 center: np.ndarray, candidate: np.ndarray, o_dir: np.ndarray, o_desc: np.ndarray,
                 start: np.ndarray, count: np.ndarray, cos_max: float, ext: TrackExtension,
                 size: np.ndarray | None = None, size_tol: float = np.inf) -> int:
    """`extend_tracks` for one view: returns the observations added to it."""
    image = rec.images[iid]
    camera = rec.cameras[image.camera_id]
    idx, uv, depth = _in_view(image, camera, xyz, np.nonzero(candidate)[0])
    if len(idx) == 0:
        return 0
    ray = xyz[idx] - center
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    rep = np.repeat(np.arange(len(idx)), count[idx])  # candidate of each observation taken
    obs = _ranges(start[idx], count[idx])
    cos = np.full(len(idx), -1.0)
    np.maximum.at(cos, rep, np.einsum("nd,nd->n", o_dir[obs], ray[rep]))
    near = cos >= cos_max
    taken = np.zeros(image.num_points2D(), bool)
    taken[np.asarray(image.get_observation_point2D_idxs(), dtype=np.int64)] = True
    free = np.nonzero(~taken)[0]
    if len(free) == 0 or not near.any():
        return 0
    keypoints = np.asarray(feats.keypoints, dtype=np.float64)[free] + 0.5  # hloc -> COLMAP pixel convention
    from scipy.spatial import cKDTree  # here: importing the pipeline stays light for `sara extract`

    dist, nn = cKDTree(keypoints).query(uv[near], k=2, distance_upper_bound=ext.radius_px)
    cand_rows = np.nonzero(near)[0]
    best_d = _descriptor_distances(cand_rows, dist, nn, free, rep, obs, o_desc, _unit(feats.descriptors), len(idx))
    first = np.argmin(best_d, axis=1)
    d1 = best_d[np.arange(len(cand_rows)), first]
    d2 = best_d[np.arange(len(cand_rows)), 1 - first]
    accept = (d1 <= ext.max_distance) & ((~np.isfinite(d2)) | (d1 < ext.max_ratio * d2))
    chosen = nn[np.arange(len(cand_rows)), first]  # len(free) where no keypoint was found
    if size is not None:
        got = _log_size(feats.scores[free[chosen.clip(0, len(free) - 1)]], depth[cand_rows],
                        camera.mean_focal_length())
        accept &= np.abs(got - size[idx[cand_rows]]) <= size_tol
    if not accept.any():
        return 0
    keypoint = free[chosen[accept]]
    point = idx[cand_rows[accept]]
    order = np.argsort(d1[accept], kind="stable")  # a keypoint claimed by several points: the closest wins
    _, once = np.unique(keypoint[order], return_index=True)
    for j in order[once]:
        rec.add_observation(int(point_ids[point[j]]), pycolmap.TrackElement(iid, int(keypoint[j])))
    return len(once)


def _in_view(image: pycolmap.Image, camera: pycolmap.Camera, xyz: np.ndarray,
             idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points `idx` of `xyz` in front of the view and inside its image: (idx (K,), their
    projections (K, 2) in COLMAP pixels, their depths (K,))."""
    pose = image.cam_from_world()
    in_cam = xyz[idx] @ pose.rotation.matrix().T + pose.translation
    idx, in_cam = idx[in_cam[:, 2] > 1e-9], in_cam[in_cam[:, 2] > 1e-9]
    if len(idx) == 0:
        return idx, np.zeros((0, 2)), np.zeros(0)
    uv = np.asarray(camera.img_from_cam(in_cam), dtype=np.float64).reshape(-1, 2)
    inside = np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < camera.width) \
        & (uv[:, 1] < camera.height)
    return idx[inside], uv[inside], in_cam[inside, 2]


def _descriptor_distances(cand_rows: np.ndarray, dist: np.ndarray, nn: np.ndarray, free: np.ndarray,
                          rep: np.ndarray, obs: np.ndarray, o_desc: np.ndarray, desc: np.ndarray,
                          num_candidates: int) -> np.ndarray:
    """(C, 2) distance from each of the two nearest free keypoints (columns, as `dist` and `nn` of
    the candidates `cand_rows`) to the nearest descriptor of the candidate point's track; inf where
    there is no keypoint. rep, obs: the candidate and the row of `o_desc` of each observation."""
    best_d = np.full((len(cand_rows), 2), np.inf)
    for c in range(2):
        has = np.isfinite(dist[:, c])
        rows = cand_rows[has]
        if len(rows) == 0:
            continue
        kp = free[nn[has, c]]
        sel = np.isin(rep, rows)  # observations of these candidates
        lookup = np.full(num_candidates, -1)
        lookup[rows] = np.arange(len(rows))
        sim = np.full(len(rows), -1.0)
        np.maximum.at(sim, lookup[rep[sel]], np.einsum(
            "nd,nd->n", o_desc[obs[sel]].astype(np.float32, copy=False), desc[kp[lookup[rep[sel]]]]))
        best_d[np.nonzero(has)[0], c] = np.sqrt(np.maximum(0.0, 2.0 - 2.0 * sim))
    return best_d
