"""Rotations as numpy arrays: rotation vectors (axis times angle) and matrices, and the angle
between two rotations. A leaf (numpy only): the pair scorer and the cycle check use it on every
SARA run, where importing scipy's rotations took 75-89 ms (three measurements, numpy and scipy's
sparse module already loaded) of a few seconds on small scenes.
"""

from __future__ import annotations

import math

import numpy as np

#: below this angle (radians) the series of sin and cos stand in for their quotients
_SMALL = 1e-6


def _hat(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = np.zeros_like(x)
    return np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], -2)


def matrix_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 3, 3) rotation matrices (Rodrigues' formula)."""
    r = np.asarray(rotvec, dtype=np.float64)
    theta = np.linalg.norm(r, axis=-1)[..., None, None]
    small = theta < _SMALL
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)  # sin(t) / t
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)  # (1 - cos(t)) / t^2
    K = _hat(r)
    return np.eye(3) + a * K + b * (K @ K)


def rotvec_from_matrix(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix -> (3,) rotation vector, its angle in [0, pi]: through the unit
    quaternion, taken from the largest of the trace and the diagonal (accurate at every angle,
    half turns included)."""
    R = np.asarray(R, dtype=np.float64)
    d = (np.trace(R), R[0, 0], R[1, 1], R[2, 2])
    k = int(np.argmax(d))
    if k == 0:
        w = math.sqrt(max(1.0 + d[0], 0.0)) / 2.0
        q = (w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w))
    else:
        i, j, m = k - 1, k % 3, (k + 1) % 3  # the axis of the largest diagonal entry, then the next two
        v = [0.0, 0.0, 0.0]
        v[i] = math.sqrt(max(1.0 + R[i, i] - R[j, j] - R[m, m], 0.0)) / 2.0
        v[j] = (R[j, i] + R[i, j]) / (4 * v[i])
        v[m] = (R[m, i] + R[i, m]) / (4 * v[i])
        q = ((R[m, j] - R[j, m]) / (4 * v[i]), *v)
    w, xyz = q[0], np.array(q[1:])
    if w < 0:
        w, xyz = -w, -xyz
    n = float(np.linalg.norm(xyz))
    return xyz * (2.0 * math.atan2(n, w) / n if n > 1e-12 else 2.0 / w)


def angle_between_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angle of the rotation ``R_a^T R_b`` in degrees, for (..., 3, 3) stacks of rotations.

    Uses ``||R_a - R_b||_F = 2 sqrt(2) sin(angle / 2)``, which stays accurate near zero (unlike
    the arccos of the trace). Returns (...,) float64 in [0, 180].
    """
    frobenius = np.linalg.norm(np.asarray(R_a) - np.asarray(R_b), axis=(-2, -1))
    return np.degrees(2.0 * np.arcsin(np.clip(frobenius / (2.0 * math.sqrt(2.0)), 0.0, 1.0)))
