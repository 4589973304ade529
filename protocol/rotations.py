"""Rotation vectors and matrices, defined once for the simulator, the host's calibration and the
science: Rodrigues' formula one way, the unit quaternion the other.

Pure computation on arrays (numpy, no I/O). What scipy's ``Rotation.from_rotvec(v).as_matrix()``
and ``Rotation.from_matrix(R).as_rotvec()`` give (to ~1e-15; tests/protocol/test_rotations.py holds
them to scipy's), without importing scipy.spatial: ~0.6 s of CPU at the start of every process that
makes a sheet or a calibration board.

>>> R = rotvec_matrices(np.array([0.0, 0.0, np.pi / 2]))
>>> (R @ [1.0, 0.0, 0.0]).round(12).tolist()
[0.0, 1.0, 0.0]
>>> np.round(matrix_rotvecs(rotvec_matrices(np.array([[0.1, -0.2, 3.0]]))), 12).tolist()
[[0.1, -0.2, 3.0]]
"""

from __future__ import annotations

import numpy as np

__all__ = ["rotvec_matrices", "matrix_rotvecs"]


def rotvec_matrices(v) -> np.ndarray:
    """``(..., 3)`` rotation vectors -> ``(..., 3, 3)`` rotation matrices: Rodrigues' formula, with
    its series below 1e-8 rad."""
    v = np.asarray(v, dtype=float)
    th = np.linalg.norm(v, axis=-1)[..., None, None]
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th ** 2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th ** 2 / 24.0, (1.0 - np.cos(ths)) / ths ** 2)
    return np.eye(3) + a * K + b * (K @ K)


def matrix_rotvecs(R) -> np.ndarray:
    """``(..., 3, 3)`` rotation matrices -> ``(..., 3)`` rotation vectors, angles in [0, π]: through
    the unit quaternion (Shepperd's choice of the largest of its four squared terms, so a half turn
    is as exact as a small one), with the series of ``θ / sin(θ/2)`` below 1e-3 rad."""
    R = np.asarray(R, dtype=float)
    lead = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    n = len(R)
    d = np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2], R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]], axis=1)
    choice = np.argmax(d, axis=1)
    q = np.empty((n, 4))  # x, y, z, w
    rows = np.arange(n)
    on_axis = choice != 3
    if on_axis.any():
        r, i = rows[on_axis], choice[on_axis]
        j, k = (i + 1) % 3, (i + 2) % 3
        q[r, i] = 1.0 - d[r, 3] + 2.0 * R[r, i, i]
        q[r, j] = R[r, j, i] + R[r, i, j]
        q[r, k] = R[r, k, i] + R[r, i, k]
        q[r, 3] = R[r, k, j] - R[r, j, k]
    if (~on_axis).any():
        r = rows[~on_axis]
        q[r, 0] = R[r, 2, 1] - R[r, 1, 2]
        q[r, 1] = R[r, 0, 2] - R[r, 2, 0]
        q[r, 2] = R[r, 1, 0] - R[r, 0, 1]
        q[r, 3] = 1.0 + d[r, 3]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1.0
    v = q[:, :3]
    angle = 2.0 * np.arctan2(np.linalg.norm(v, axis=1), q[:, 3])
    small = angle <= 1e-3
    a2 = angle ** 2
    safe = np.where(small, 1.0, angle)
    scale = np.where(small, 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0, safe / np.sin(safe / 2.0))
    return (scale[:, None] * v).reshape(lead + (3,))
