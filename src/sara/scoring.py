"""The pre-matching scorer: a cheap two-view geometry per candidate pair.

For a pair of images, the scorer

1. matches the top-M keypoints of each image (largest scale first) by mutual nearest neighbours
   of their L2-normalised descriptors and keeps the best ``num_matches`` by similarity;
2. runs a short, seeded 5-point RANSAC for the essential matrix (poselib) on those matches;
3. triangulates the inliers (midpoint method) with the recovered relative pose and takes the
   parallax ``P`` as the median triangulation angle of the points in front of both cameras;
   but ``P = 0`` when a pure rotation (allowing for a wrong focal length) fits the inliers about
   as well as the essential matrix: then the 5-point pose is degenerate and its baseline spurious.

The triangulation angle is the angle at the 3D point between the rays to the two camera centres,
so the relative rotation does not count: a pure rotation or a near-duplicate pair has ``P ~ 0``.
From the inlier count and ``P`` come the overlap ``O = num_inliers / sqrt(N_i N_j)`` and the
weight ``w = O^alpha * g(P)^beta``, ``g(P) = min(P, sat) / sat``.

Frames: ``R, t`` is ``cam1_from_cam0`` (``x_cam1 = R x_cam0 + t``); normalised camera
coordinates are ``(x / z, y / z)`` of the point in the camera frame (undistorted).
"""

from __future__ import annotations

import csv
import logging
import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import poselib
from tqdm import tqdm

from . import colmap
from .config import ScoreConfig
from .io.h5 import Features, read_features
from .io import atomic_path

logger = logging.getLogger(__name__)

#: Why a pair is rejected, in the order the conditions are checked ("" when accepted).
REASONS = ("no_model", "few_inliers", "low_overlap", "low_parallax")

CSV_COLUMNS = (
    "name0", "name1", "num_matches", "num_inliers", "overlap", "parallax_deg", "weight",
    "accepted", "reason", "role",
)

#: A pure rotation "explains" a pair's inliers when its median residual is at most this many
#: times the essential matrix's median Sampson error; the pair then gets P = 0. Measured: pure
#: rotations (synthetic, 0.5-1.5 px noise) 2.3-5.2; real pairs with >= 2 deg of parallax >= 6.1
#: (strecha, middlebury; 700 pairs).
ROTATION_RESIDUAL_FACTOR = 5.0
#: Floor of that Sampson error, as a fraction of the RANSAC threshold (very precise matches).
SAMPSON_FLOOR = 0.05
#: Focal-length errors allowed for when testing for a rotation (COLMAP's prior can be 2x off).
FOCAL_SCALES = np.exp(np.linspace(np.log(0.5), np.log(2.0), 41))

_MIN_SAMPLE = 5  # points of the 5-point solver
_PARALLEL_RAYS = 1e-12  # sin^2 of the ray angle below which two rays count as parallel


# ----------------------------------------------------------------------------------------
# Mutual nearest neighbours
# ----------------------------------------------------------------------------------------


def normalize_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """(N, D) descriptors (uint8 RootSIFT or float) -> (N, D) float32 with unit L2 rows.

    All-zero rows stay zero.
    """
    desc = np.asarray(descriptors)
    if desc.ndim != 2:
        raise ValueError(f"descriptors must be (N, D), got shape {desc.shape}")
    desc = desc.astype(np.float32)  # a copy, also for float32 input
    norm = np.linalg.norm(desc, axis=1, keepdims=True)
    np.divide(desc, norm, out=desc, where=norm > 0)
    return desc


def mutual_nearest_neighbours(
    desc0: np.ndarray, desc1: np.ndarray, max_matches: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours by cosine similarity of L2-normalised descriptors.

    Args:
        desc0: (N0, D) descriptors of image 0 (uint8 or float; normalised here).
        desc1: (N1, D) descriptors of image 1.
        max_matches: keep only the best this many matches (all when None).
    Returns:
        See :func:`mutual_matches_from_similarity`.
    """
    d0, d1 = normalize_descriptors(desc0), normalize_descriptors(desc1)
    if d0.shape[1] != d1.shape[1]:
        raise ValueError(f"descriptor sizes differ: {d0.shape[1]} and {d1.shape[1]}")
    return mutual_matches_from_similarity(d0 @ d1.T, max_matches)


def mutual_matches_from_similarity(
    similarity: np.ndarray, max_matches: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours in a similarity matrix (larger is more similar).

    Args:
        similarity: (N0, N1) float, e.g. dot products of unit descriptors.
        max_matches: keep only the best this many matches (all when None).
    Returns:
        matches: (K, 2) int32 indices ``(i0, i1)``; i1 is the nearest neighbour of i0 in image 1
            and i0 the nearest neighbour of i1 in image 0.
        similarity: (K,) float32, in decreasing order; equal similarities are ordered by i0.
            Equal-similarity neighbours resolve to the lowest index.
    """
    sim = np.asarray(similarity)
    if sim.ndim != 2:
        raise ValueError(f"similarity must be (N0, N1), got shape {sim.shape}")
    if max_matches is not None and max_matches < 0:
        raise ValueError(f"max_matches must be >= 0, got {max_matches}")
    if sim.size == 0:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
    best1 = sim.argmax(axis=1)  # nearest neighbour in image 1 of each i0 (first on ties)
    best_sim = sim[np.arange(len(sim)), best1]
    # i0 is also the nearest neighbour of best1[i0] when it reaches that column's maximum.
    # (A column max is cheap; a column argmax of a C-ordered matrix is not.)
    i0 = np.flatnonzero(best_sim >= sim.max(axis=0)[best1])
    # On an exact tie several rows may reach one column's maximum: keep the lowest row.
    i1, first = np.unique(best1[i0], return_index=True)
    i0 = i0[first]
    values = best_sim[i0]
    order = np.lexsort((i0, -values))[:max_matches]
    matches = np.stack([i0[order], i1[order]], axis=1).astype(np.int32)
    return matches, values[order].astype(np.float32)


# ----------------------------------------------------------------------------------------
# Two-view geometry
# ----------------------------------------------------------------------------------------


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (..., 3) arrays (np.cross has a large fixed cost)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _unit_rays(x_norm: np.ndarray) -> np.ndarray:
    """(K, 2) normalised coordinates -> (K, 3) unit bearing vectors."""
    rays = np.concatenate([x_norm, np.ones((len(x_norm), 1))], axis=1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def triangulation_angles_deg(
    R: np.ndarray, t: np.ndarray, x0_norm: np.ndarray, x1_norm: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Triangulation angles of correspondences under a relative pose (midpoint triangulation).

    Each correspondence is triangulated at the midpoint of the shortest segment between its two
    rays; its angle is the one at that point between the directions to the two camera centres.
    Parallel rays (a point at infinity) and a zero baseline give angle 0 and ``in_front`` False.

    Args:
        R: (3, 3) rotation and t: (3,) translation of ``cam1_from_cam0``.
        x0_norm: (K, 2) normalised camera coordinates in image 0.
        x1_norm: (K, 2) normalised camera coordinates in image 1.
    Returns:
        angles: (K,) float64 degrees in [0, 180].
        in_front: (K,) bool, the point has positive depth in both cameras.
    """
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    x0 = np.asarray(x0_norm, dtype=np.float64).reshape(-1, 2)
    x1 = np.asarray(x1_norm, dtype=np.float64).reshape(-1, 2)
    if len(x0) != len(x1):
        raise ValueError(f"x0_norm and x1_norm differ in length: {len(x0)} and {len(x1)}")
    center1 = -R.T @ t  # centre of camera 1 in the frame of camera 0
    if not np.any(center1):
        return np.zeros(len(x0)), np.zeros(len(x0), dtype=bool)
    ray0 = _unit_rays(x0)
    ray1 = _unit_rays(x1) @ R  # rows R^T r1: camera 1's rays in the frame of camera 0
    cos_rays = np.sum(ray0 * ray1, axis=1)
    sin2 = 1.0 - cos_rays**2
    finite = sin2 > _PARALLEL_RAYS
    # Closest points lam0 * ray0 and center1 + lam1 * ray1 (normal equations of the 2x2 system).
    p, q = ray0 @ center1, ray1 @ center1
    denom = np.where(finite, sin2, 1.0)
    lam0 = (p - cos_rays * q) / denom
    lam1 = (cos_rays * p - q) / denom
    points = 0.5 * (lam0[:, None] * ray0 + center1 + lam1[:, None] * ray1)
    depth0 = points[:, 2]
    depth1 = points @ R[2] + t[2]
    to0, to1 = -points, center1 - points
    cross = np.linalg.norm(_cross(to0, to1), axis=1)
    angles = np.degrees(np.arctan2(cross, np.sum(to0 * to1, axis=1)))
    angles[~finite] = 0.0
    in_front = finite & (depth0 > 0) & (depth1 > 0)
    return angles, in_front


_IDENTITY_CAMERA = poselib.Camera("PINHOLE", [1.0, 1.0, 0.0, 0.0], 2, 2)


@dataclass(frozen=True)
class RelativePose:
    """A relative pose ``cam1_from_cam0`` and the RANSAC inliers it was found with."""

    R: np.ndarray  # (3, 3) float64
    t: np.ndarray  # (3,) float64, arbitrary scale
    inliers: np.ndarray  # (K,) bool over the input correspondences


def estimate_relative_pose(
    x0_norm: np.ndarray, x1_norm: np.ndarray, *, max_error: float, iterations: int, seed: int = 0
) -> RelativePose | None:
    """Seeded 5-point RANSAC (poselib) with exactly ``iterations`` iterations, then refinement.

    Args:
        x0_norm, x1_norm: (K, 2) normalised camera coordinates of the correspondences.
        max_error: Sampson error threshold in normalised units (pixels / focal).
        iterations: RANSAC iterations (poselib's min and max iterations).
        seed: RANSAC random seed; the same inputs and seed give the same pose.
    Returns:
        The pose, or None with fewer than 5 correspondences or when no model was found.
    """
    if len(x0_norm) < _MIN_SAMPLE:
        return None
    ransac = {
        "max_iterations": int(iterations), "min_iterations": int(iterations),
        "max_epipolar_error": float(max_error), "seed": int(seed),
    }
    pose, info = poselib.estimate_relative_pose(
        np.asarray(x0_norm, dtype=np.float64), np.asarray(x1_norm, dtype=np.float64),
        _IDENTITY_CAMERA, _IDENTITY_CAMERA, ransac, {},
    )
    inliers = np.asarray(info["inliers"], dtype=bool)
    R, t = np.asarray(pose.R, dtype=np.float64), np.asarray(pose.t, dtype=np.float64)
    if inliers.sum() < _MIN_SAMPLE or not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return None
    return RelativePose(R=R, t=t, inliers=inliers)


def sampson_errors(R: np.ndarray, t: np.ndarray, x0_norm: np.ndarray, x1_norm: np.ndarray) -> np.ndarray:
    """(K,) Sampson distances (normalised units) of correspondences to ``E = [t]x R``."""
    t = np.asarray(t, dtype=np.float64).reshape(3)
    skew = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    essential = skew @ np.asarray(R, dtype=np.float64).reshape(3, 3)
    h0 = np.concatenate([x0_norm, np.ones((len(x0_norm), 1))], axis=1)
    h1 = np.concatenate([x1_norm, np.ones((len(x1_norm), 1))], axis=1)
    line1, line0 = h0 @ essential.T, h1 @ essential  # epipolar lines in image 1 and image 0
    denom = line1[:, 0] ** 2 + line1[:, 1] ** 2 + line0[:, 0] ** 2 + line0[:, 1] ** 2
    return np.abs(np.sum(h1 * line1, axis=1)) / np.sqrt(np.maximum(denom, 1e-300))


# ----------------------------------------------------------------------------------------
# Is the motion a pure rotation?
# ----------------------------------------------------------------------------------------


def _kabsch_rotation(rays0: np.ndarray, rays1: np.ndarray) -> np.ndarray:
    """(3, 3) rotation R maximising sum_k rays1_k . (R rays0_k); rays: (K, 3) unit vectors."""
    u, _, vt = np.linalg.svd(rays1.T @ rays0)
    if np.linalg.det(u @ vt) < 0:
        u[:, 2] *= -1.0
    return u @ vt


def _two_ray_rotations(a0: np.ndarray, b0: np.ndarray, a1: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """(S, 3, 3) rotations taking ray a0 onto a1 and the plane (a0, b0) onto (a1, b1); rays (S, 3)."""

    def frame(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        normal = _cross(a, b)
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
        return np.stack([a, normal, _cross(a, normal)], axis=2)  # columns

    return frame(a1, b1) @ frame(a0, b0).transpose(0, 2, 1)


def rotation_residuals(
    x0_norm: np.ndarray, x1_norm: np.ndarray, *, max_error: float, iterations: int, seed: int = 0
) -> np.ndarray:
    """Residuals of the pure rotation that best maps the rays of image 0 onto those of image 1.

    A short RANSAC over 2-ray rotations, then a least-squares refit on the best one's inliers.

    Args:
        x0_norm, x1_norm: (K, 2) normalised camera coordinates, K >= 2.
        max_error: inlier threshold on the residual (normalised units: pixels / focal).
        iterations: rotation hypotheses tried.
        seed: sampling seed.
    Returns:
        (K,) float64 ``|ray1 - R ray0|`` of unit rays (about the angle in radians).
    """
    num = len(x0_norm)
    if num < 2:
        raise ValueError(f"a rotation needs at least 2 correspondences, got {num}")
    rays0 = _unit_rays(np.asarray(x0_norm, np.float64))
    rays1 = _unit_rays(np.asarray(x1_norm, np.float64))
    rng = np.random.default_rng(seed)
    first = rng.integers(num, size=iterations)
    second = (first + rng.integers(1, num, size=iterations)) % num
    hypotheses = _two_ray_rotations(rays0[first], rays0[second], rays1[first], rays1[second])
    errors = np.linalg.norm(hypotheses @ rays0.T - rays1.T, axis=1)  # (S, K)
    best = int(np.argmax(np.sum(errors < max_error, axis=1)))
    inliers = errors[best] < max_error
    if inliers.sum() < 2:
        return errors[best]
    refit = np.linalg.norm(rays0 @ _kabsch_rotation(rays0[inliers], rays1[inliers]).T - rays1, axis=1)
    return refit if np.sum(refit < max_error) >= inliers.sum() else errors[best]


def rotation_focal_scale(homography: np.ndarray) -> float:
    """Scale of normalised coordinates that makes a homography most like a pure rotation.

    When the focal length used is wrong, the true normalised coordinates are ``c x`` for some
    ``c``; a camera that only rotates then maps ``x0`` to ``x1`` by ``H ~ C^-1 R C`` with
    ``C = diag(c, c, 1)``. Returns the ``c`` in :data:`FOCAL_SCALES` for which ``C H C^-1`` is
    closest to a rotation (smallest ratio of its largest to its smallest singular value).

    Args:
        homography: (3, 3) ``x1 ~ H x0`` in normalised camera coordinates.
    """
    scales = FOCAL_SCALES
    conj = np.broadcast_to(np.asarray(homography, dtype=np.float64), (len(scales), 3, 3)).copy()
    conj[:, :2, 2] *= scales[:, None]
    conj[:, 2, :2] /= scales[:, None]
    singular = np.linalg.svd(conj, compute_uv=False)
    spread = singular[:, 0] / np.maximum(singular[:, 2], 1e-300)
    return float(scales[int(np.argmin(spread))])


def estimate_homography(
    x0_norm: np.ndarray, x1_norm: np.ndarray, *, max_error: float, iterations: int, seed: int = 0
) -> np.ndarray | None:
    """(3, 3) homography ``x1 ~ H x0`` (poselib, seeded short RANSAC); None with < 4 points."""
    if len(x0_norm) < 4:
        return None
    ransac = {
        "max_iterations": int(iterations), "min_iterations": int(iterations),
        "max_reproj_error": float(max_error), "seed": int(seed),
    }
    homography, _ = poselib.estimate_homography(
        np.asarray(x0_norm, dtype=np.float64), np.asarray(x1_norm, dtype=np.float64), ransac, {}
    )
    homography = np.asarray(homography, dtype=np.float64)
    return homography if np.all(np.isfinite(homography)) and np.linalg.det(homography) != 0 else None


def explained_by_rotation(
    pose: RelativePose, x0_norm: np.ndarray, x1_norm: np.ndarray, *, max_error: float,
    iterations: int, seed: int = 0,
) -> bool:
    """Whether a pure rotation fits the inliers about as well as the essential matrix does.

    True when the median rotation residual is at most :data:`ROTATION_RESIDUAL_FACTOR` times
    the median Sampson error of ``pose`` (floored at ``SAMPSON_FLOOR * max_error``). Then the
    parallax is below what the matches can measure: a pure rotation, a near-duplicate, or a
    baseline too short for its depth. (On such data the 5-point pose is degenerate and trades
    a wrong rotation for a spurious baseline, so its triangulation angles mean nothing.)

    The focal length may be wrong (COLMAP's prior is often off by 1.5x), and then a rotation is
    no rotation in normalised coordinates; so when the plain rotation falls short, it is fitted
    again with the focal scale that makes the pair's homography most like a rotation
    (:func:`rotation_focal_scale`).

    Args:
        pose: the essential-matrix pose; x0_norm, x1_norm: (K, 2) its inliers, K >= 2.
        max_error, iterations, seed: as for :func:`rotation_residuals`.
    """
    essential = float(np.median(sampson_errors(pose.R, pose.t, x0_norm, x1_norm)))
    bound = ROTATION_RESIDUAL_FACTOR * max(essential, SAMPSON_FLOOR * max_error)
    options = {"max_error": max_error, "iterations": iterations, "seed": seed}
    rotation = float(np.median(rotation_residuals(x0_norm, x1_norm, **options)))
    if rotation <= bound:
        return True
    homography = estimate_homography(x0_norm, x1_norm, **options)
    if homography is None:
        return False
    scale = rotation_focal_scale(homography)
    scaled = rotation_residuals(
        scale * np.asarray(x0_norm), scale * np.asarray(x1_norm), max_error=scale * max_error,
        iterations=iterations, seed=seed,
    )
    return float(np.median(scaled)) / scale <= bound


# ----------------------------------------------------------------------------------------
# One pair
# ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ViewFeatures:
    """What the scorer needs of one image (its top-M keypoints).

    Attributes:
        descriptors: (M, D) uint8 or float, as stored; normalised when matched.
        points_norm: (M, 2) float64 normalised, undistorted camera coordinates.
        focal_px: mean focal length in pixels (converts the pixel threshold).
    """

    descriptors: np.ndarray
    points_norm: np.ndarray
    focal_px: float

    def __post_init__(self) -> None:
        if len(self.descriptors) != len(self.points_norm):
            raise ValueError(
                f"{len(self.descriptors)} descriptors but {len(self.points_norm)} keypoints"
            )

    @property
    def num_keypoints(self) -> int:
        return len(self.points_norm)

    @classmethod
    def from_features(cls, feats: Features, camera: Any) -> ViewFeatures:
        """From hloc-convention features and the image's pycolmap camera."""
        xy = colmap.hloc_to_colmap_keypoints(feats.keypoints)
        return cls(
            descriptors=np.asarray(feats.descriptors),
            points_norm=colmap.image_to_normalized(camera, xy),
            focal_px=colmap.mean_focal_px(camera),
        )


@dataclass(frozen=True)
class PairScore:
    """The score of one pair; see :func:`score_pair`."""

    num_matches: int
    num_inliers: int
    overlap: float
    parallax_deg: float
    weight: float
    accepted: bool
    reason: str  # one of REASONS, "" when accepted


def pair_weight(overlap: float, parallax_deg: float, conf: ScoreConfig) -> float:
    """``w = O^alpha * g(P)^beta`` with ``g(P) = min(P, sat) / sat``."""
    saturated = min(max(parallax_deg, 0.0), conf.parallax_saturation_deg) / conf.parallax_saturation_deg
    return float(max(overlap, 0.0) ** conf.alpha * saturated**conf.beta)


def rejection_reason(
    found_model: bool, num_inliers: int, overlap: float, parallax_deg: float, conf: ScoreConfig
) -> str:
    """The first failed condition of :data:`REASONS`, or "" when the pair is accepted."""
    if not found_model:
        return "no_model"
    if num_inliers < conf.min_inliers:
        return "few_inliers"
    if overlap < conf.min_overlap:
        return "low_overlap"
    if parallax_deg < conf.min_parallax_deg:
        return "low_parallax"
    return ""


def inlier_parallax_deg(
    pose: RelativePose, x0_norm: np.ndarray, x1_norm: np.ndarray, *, max_error: float,
    iterations: int, seed: int = 0,
) -> float:
    """Parallax P of a pair's RANSAC inliers (normalised coordinates (K, 2)), degrees.

    0 when :func:`explained_by_rotation`; otherwise the median triangulation angle of the
    inliers in front of both cameras (0 when none is).
    """
    if len(x0_norm) < 2 or explained_by_rotation(
        pose, x0_norm, x1_norm, max_error=max_error, iterations=iterations, seed=seed
    ):
        return 0.0
    angles, in_front = triangulation_angles_deg(pose.R, pose.t, x0_norm, x1_norm)
    return float(np.median(angles[in_front])) if in_front.any() else 0.0


def score_pair(view0: ViewFeatures, view1: ViewFeatures, conf: ScoreConfig, *, seed: int = 0) -> PairScore:
    """Score one pair: mutual NN, short RANSAC, parallax, overlap, weight.

    ``num_inliers`` counts the RANSAC inliers; ``parallax_deg`` is :func:`inlier_parallax_deg`;
    ``overlap`` is ``num_inliers / sqrt(N0 * N1)`` with N the keypoints used (at most M per image).
    The same views, settings and seed always give the same score.
    """
    matches, _ = mutual_nearest_neighbours(view0.descriptors, view1.descriptors, conf.num_matches)
    x0, x1 = view0.points_norm[matches[:, 0]], view1.points_norm[matches[:, 1]]
    max_error = conf.ransac_max_error_px * 2.0 / (view0.focal_px + view1.focal_px)
    pose = estimate_relative_pose(x0, x1, max_error=max_error, iterations=conf.ransac_iterations, seed=seed)
    num_inliers, parallax_deg = 0, 0.0
    if pose is not None:
        num_inliers = int(pose.inliers.sum())
        parallax_deg = inlier_parallax_deg(
            pose, x0[pose.inliers], x1[pose.inliers], max_error=max_error,
            iterations=conf.ransac_iterations, seed=seed,
        )
    denom = math.sqrt(view0.num_keypoints * view1.num_keypoints)
    overlap = num_inliers / denom if denom > 0 else 0.0
    reason = rejection_reason(pose is not None, num_inliers, overlap, parallax_deg, conf)
    return PairScore(
        num_matches=len(matches), num_inliers=num_inliers, overlap=overlap, parallax_deg=parallax_deg,
        weight=pair_weight(overlap, parallax_deg, conf), accepted=reason == "", reason=reason,
    )


# ----------------------------------------------------------------------------------------
# Many pairs
# ----------------------------------------------------------------------------------------


@dataclass(eq=False)
class PairScores:
    """Scores of P pairs, one entry per pair in the order scored.

    Attributes:
        name0, name1: image names, P each.
        num_matches: (P,) int64 mutual nearest neighbours used (at most ``num_matches``).
        num_inliers: (P,) int64 RANSAC inliers.
        overlap: (P,) float64 ``num_inliers / sqrt(N0 N1)``.
        parallax_deg: (P,) float64 median triangulation angle, degrees.
        weight: (P,) float64 ``w``.
        accepted: (P,) bool.
        reason: P strings, one of :data:`REASONS`, "" when accepted.
    """

    name0: list[str]
    name1: list[str]
    num_matches: np.ndarray
    num_inliers: np.ndarray
    overlap: np.ndarray
    parallax_deg: np.ndarray
    weight: np.ndarray
    accepted: np.ndarray
    reason: list[str]

    def __len__(self) -> int:
        return len(self.name0)

    @classmethod
    def from_scores(cls, pairs: Sequence[tuple[str, str]], scores: Sequence[PairScore]) -> PairScores:
        def column(name: str, dtype: Any) -> np.ndarray:
            return np.array([getattr(s, name) for s in scores], dtype=dtype).reshape(len(scores))

        return cls(
            name0=[p[0] for p in pairs], name1=[p[1] for p in pairs],
            num_matches=column("num_matches", np.int64), num_inliers=column("num_inliers", np.int64),
            overlap=column("overlap", np.float64), parallax_deg=column("parallax_deg", np.float64),
            weight=column("weight", np.float64), accepted=column("accepted", bool),
            reason=[s.reason for s in scores],
        )


def load_views(
    names: Iterable[str], features_path: Path, db_path: Path, num_keypoints: int, *, progress: bool = True
) -> dict[str, ViewFeatures]:
    """The top-``num_keypoints`` features of each image, normalised with its database camera."""
    names = sorted(set(names))
    cameras = colmap.cameras_by_image(Path(db_path))
    missing = [n for n in names if n not in cameras]
    if missing:
        raise ValueError(
            f"{len(missing)} images are not in the database {db_path} (e.g. {missing[0]!r}); "
            "score pairs with the database the features were extracted into"
        )
    views = {}
    for name in tqdm(names, desc="load features", unit="img", disable=not progress):
        try:
            feats = read_features(Path(features_path), name, top_k=num_keypoints)
        except KeyError as err:
            raise ValueError(f"image {name!r} has no features in {features_path}") from err
        views[name] = ViewFeatures.from_features(feats, cameras[name])
    return views


def score_pairs(
    pairs: Sequence[tuple[str, str]],
    features_path: Path,
    db_path: Path,
    conf: ScoreConfig,
    *,
    progress: bool = True,
    seed: int = 0,
) -> PairScores:
    """Score candidate pairs in one thread; each image's top-M features are read once.

    Args:
        pairs: (name0, name1) image names; both must have features and a database camera.
        features_path: features.h5 (hloc layout, keypoints in hloc's pixel convention).
        db_path: the COLMAP database with the images' cameras (EXIF focal or COLMAP's prior).
        conf: scorer settings.
        progress: show progress bars.
        seed: RANSAC seed, the same for every pair: a pair's score does not depend on the others.
    Returns:
        The scores, in the order of ``pairs``.
    """
    pairs = [(str(a), str(b)) for a, b in pairs]
    same = [a for a, b in pairs if a == b]
    if same:
        raise ValueError(f"a pair of an image with itself: {same[0]!r}")
    views = load_views(
        (n for p in pairs for n in p), features_path, db_path, conf.num_keypoints, progress=progress
    )
    start = time.perf_counter()
    results = [
        score_pair(views[name0], views[name1], conf, seed=seed)
        for name0, name1 in tqdm(pairs, desc="score pairs", unit="pair", disable=not progress)
    ]
    scores = PairScores.from_scores(pairs, results)
    _log_summary(scores, time.perf_counter() - start)
    return scores


def _log_summary(scores: PairScores, elapsed_s: float) -> None:
    count = len(scores)
    if count == 0:
        logger.info("score: no pairs")
        return
    rejected = {r: scores.reason.count(r) for r in REASONS if r in scores.reason}
    logger.info(
        "score: %d pairs in %.1f s (%.2f ms per pair); %d accepted, rejected: %s",
        count, elapsed_s, 1e3 * elapsed_s / count, int(scores.accepted.sum()), rejected or "none",
    )


# ----------------------------------------------------------------------------------------
# scores.csv
# ----------------------------------------------------------------------------------------


def write_scores_csv(path: Path, scores: PairScores, roles: Sequence[str] | None = None) -> Path:
    """Write one row per pair (columns :data:`CSV_COLUMNS`) atomically; returns ``path``.

    ``roles`` gives each pair's role in the selection (e.g. "tree", "loop", "rejected");
    the column is empty without it. Floats are written with full precision.
    """
    if roles is not None and len(roles) != len(scores):
        raise ValueError(f"{len(roles)} roles for {len(scores)} pairs")
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="", encoding="utf-8") as f:
            writer = csv.writer(f)
            writer.writerow(CSV_COLUMNS)
            for k in range(len(scores)):
                writer.writerow([
                    scores.name0[k], scores.name1[k],
                    int(scores.num_matches[k]), int(scores.num_inliers[k]),
                    repr(float(scores.overlap[k])), repr(float(scores.parallax_deg[k])),
                    repr(float(scores.weight[k])), "true" if scores.accepted[k] else "false",
                    scores.reason[k], roles[k] if roles is not None else "",
                ])
    return path


def _column(rows: list[dict[str, str]], key: str, convert: Any, path: Path) -> list[Any]:
    out = []
    for k, row in enumerate(rows):
        try:
            out.append(convert(row[key]))
        except (TypeError, ValueError):
            raise ValueError(f"{path}, line {k + 2}: bad {key} {row[key]!r}") from None
    return out


def _parse_bool(text: str) -> bool:
    low = text.strip().lower()
    if low in ("true", "1"):
        return True
    if low in ("false", "0"):
        return False
    raise ValueError(text)


def read_scores_csv(path: Path) -> tuple[PairScores, list[str] | None]:
    """Read a file of :func:`write_scores_csv`; roles are None when that column is empty."""
    path = Path(path)
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        missing = [c for c in CSV_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path} is not a scores file: columns {missing} are missing")
        rows = list(reader)

    def column(key: str, convert: Any, dtype: Any) -> np.ndarray:
        return np.array(_column(rows, key, convert, path), dtype=dtype).reshape(len(rows))

    scores = PairScores(
        name0=[r["name0"] for r in rows], name1=[r["name1"] for r in rows],
        num_matches=column("num_matches", int, np.int64),
        num_inliers=column("num_inliers", int, np.int64),
        overlap=column("overlap", float, np.float64),
        parallax_deg=column("parallax_deg", float, np.float64),
        weight=column("weight", float, np.float64),
        accepted=column("accepted", _parse_bool, bool),
        reason=[r["reason"] for r in rows],
    )
    roles = [r["role"] for r in rows]
    return scores, (roles if any(roles) else None)
