"""`protocol.rotations` held to scipy's ``Rotation`` (an independent implementation): every angle
the simulator and the calibration meet, half turns and the smallest included, and any leading
shape."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from protocol.rotations import matrix_rotvecs, rotvec_matrices


def _rng(seed: int) -> np.random.Generator:
    return np.random.Generator(np.random.MT19937(seed))


def test_rotvec_matrices_are_scipys_rotations():
    g = _rng(11)
    for scale in (0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.1, 1.0, 3.0):
        v = g.standard_normal((400, 3)) * scale
        np.testing.assert_allclose(rotvec_matrices(v), Rotation.from_rotvec(v).as_matrix(), rtol=0, atol=4e-15)


def test_matrix_rotvecs_are_scipys_rotation_vectors_and_undo_rotvec_matrices():
    g = _rng(5)
    for angle in (0.0, 1e-12, 1e-8, 1e-4, 1e-3, 2e-3, 0.1, 1.0, 2.0, 3.0, np.pi - 1e-3, np.pi - 1e-6):
        axes = g.standard_normal((300, 3))
        v = axes / np.linalg.norm(axes, axis=1, keepdims=True) * angle
        R = rotvec_matrices(v)
        np.testing.assert_allclose(matrix_rotvecs(R), Rotation.from_matrix(R).as_rotvec(), rtol=0, atol=1e-12)
        np.testing.assert_allclose(rotvec_matrices(matrix_rotvecs(R)), R, rtol=0, atol=1e-12)


def test_one_vector_and_a_grid_of_vectors_keep_their_leading_shape():
    g = _rng(2)
    v = g.standard_normal((4, 5, 3))
    R = rotvec_matrices(v)
    assert R.shape == (4, 5, 3, 3) and rotvec_matrices(v[0, 0]).shape == (3, 3)
    np.testing.assert_allclose(R.reshape(-1, 3, 3), Rotation.from_rotvec(v.reshape(-1, 3)).as_matrix(), rtol=0, atol=4e-15)
    back = matrix_rotvecs(R)
    assert back.shape == (4, 5, 3) and matrix_rotvecs(R[1, 2]).shape == (3,)
    np.testing.assert_allclose(back.reshape(-1, 3), Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec(), rtol=0, atol=1e-12)
