"""Pure two-view geometry for the pre-matching scorer: a seeded 5-point RANSAC (poselib),
Sampson errors, midpoint triangulation angles, and the test for a pure rotation.

Frames: ``R, t`` is ``cam1_from_cam0`` (``x_cam1 = R x_cam0 + t``); normalised camera
coordinates are ``(x / z, y / z)`` of the point in the camera frame (undistorted).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import poselib

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


def skew(v: np.ndarray) -> np.ndarray:
    """(3,) -> (3, 3) cross-product matrix: skew(a) @ b == cross(a, b)."""
    v = np.asarray(v, dtype=np.float64).reshape(3)
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def sampson_distance(F: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """(K,) Sampson distances (the square root of the Sampson error) of correspondences x0 <-> x1.

    F: (3, 3) with x1^T F x0 = 0 for homogeneous points (an essential matrix in normalised
    coordinates, or a fundamental matrix in pixels: the distance is then in those units).
    x0, x1: (K, 2).
    """
    h0 = np.concatenate([np.asarray(x0, np.float64), np.ones((len(x0), 1))], axis=1)
    h1 = np.concatenate([np.asarray(x1, np.float64), np.ones((len(x1), 1))], axis=1)
    line1, line0 = h0 @ F.T, h1 @ F  # epipolar lines in image 1 and image 0
    denom = line1[:, 0] ** 2 + line1[:, 1] ** 2 + line0[:, 0] ** 2 + line0[:, 1] ** 2
    return np.abs(np.sum(h1 * line1, axis=1)) / np.sqrt(np.maximum(denom, 1e-300))


def sampson_errors(R: np.ndarray, t: np.ndarray, x0_norm: np.ndarray, x1_norm: np.ndarray) -> np.ndarray:
    """(K,) Sampson distances (normalised units) of correspondences to ``E = [t]x R``."""
    return sampson_distance(skew(t) @ np.asarray(R, dtype=np.float64).reshape(3, 3), x0_norm, x1_norm)


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
# Parallax of a pair
# ----------------------------------------------------------------------------------------


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
