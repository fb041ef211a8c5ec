"""sara.rotations against scipy's rotations (which the scorer and the cycle check used before)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sara.rotations import angle_between_deg, matrix_from_rotvec, rotvec_from_matrix


def _rotvecs(rng: np.random.Generator, n: int, angles: np.ndarray | None = None) -> np.ndarray:
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = rng.uniform(0, math.pi, n) if angles is None else angles
    return axes * angles[:, None]


@pytest.mark.parametrize("angles", ["any", "tiny", "zero", "near a half turn"])
def test_matrices_and_rotation_vectors_agree_with_scipy(angles):
    rng = np.random.default_rng(7)
    n = 200
    chosen = {"any": None, "tiny": rng.uniform(0, 1e-7, n), "zero": np.zeros(n),
              "near a half turn": math.pi - rng.uniform(0, 1e-4, n)}[angles]
    rotvec = _rotvecs(rng, n, chosen)
    R = matrix_from_rotvec(rotvec)
    np.testing.assert_allclose(R, Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-12)
    back = np.array([rotvec_from_matrix(m) for m in R])
    # the same rotation (a half turn has two rotation vectors: compare the matrices)
    np.testing.assert_allclose(matrix_from_rotvec(back), R, atol=1e-9)
    if angles != "near a half turn":
        np.testing.assert_allclose(back, Rotation.from_matrix(R).as_rotvec(), atol=1e-9)
    assert np.all(np.linalg.norm(back, axis=1) <= math.pi + 1e-12)


def test_the_angle_between_two_rotations_is_scipys_magnitude():
    rng = np.random.default_rng(3)
    a, b = Rotation.from_rotvec(_rotvecs(rng, 100)), Rotation.from_rotvec(_rotvecs(rng, 100))
    expected = np.degrees((a.inv() * b).magnitude())
    np.testing.assert_allclose(angle_between_deg(a.as_matrix(), b.as_matrix()), expected, atol=1e-6)
    same = a.as_matrix()
    assert np.all(angle_between_deg(same, same) == 0.0)
