"""The fused estimator's joints from link vectors by the cosine transform
(host.analysis.motion._lattice.joints_from_vectors) against a dense least-squares solve of the
same problem, built from the lattice's endpoints (protocol.lattice), and against the static
estimator's sparse one."""

from __future__ import annotations

import numpy as np
import pytest

from host.analysis.estimator import joints_from_directions
from host.analysis.motion._lattice import joints_from_vectors
from protocol.lattice import Lattice


def dense_joints(vectors, rows, cols, link_length):
    """``min Σ ‖p_b − p_a − L d‖²`` with joint (0, 0) fixed at the origin, by numpy's lstsq."""
    lat = Lattice(rows, cols)
    ep = lat.endpoints
    B = np.zeros((lat.n_links, rows * cols))
    B[np.arange(lat.n_links), ep[:, 1]] = 1.0
    B[np.arange(lat.n_links), ep[:, 0]] = -1.0
    x = np.linalg.lstsq(B[:, 1:], link_length * vectors, rcond=None)[0]
    return np.vstack([np.zeros((1, 3)), x]).reshape(rows, cols, 3)


@pytest.mark.parametrize("rows,cols", [(2, 2), (2, 5), (5, 2), (3, 7), (14, 14), (9, 16)])
def test_joints_from_link_vectors_by_the_cosine_transform_are_the_least_squares_ones(rows, cols):
    n = Lattice(rows, cols).n_links
    g = np.random.Generator(np.random.MT19937(rows * 100 + cols))
    d = g.normal(size=(n, 3))  # any vectors: the map is linear (directions, their accelerations)
    ref = dense_joints(d, rows, cols, 0.01)
    got = joints_from_vectors(d, rows, cols, 0.01)
    assert got.shape == (rows, cols, 3)
    assert np.abs(got - ref).max() < 1e-13 * max(1.0, np.abs(ref).max()) + 1e-15
    # and the static estimator's sparse factorisation gives the same to its own precision
    assert np.abs(got - joints_from_directions(d, rows, cols, 0.01)).max() < 1e-8
    # the check can fail: the same vectors in another link order are another sheet
    assert np.abs(joints_from_vectors(d[::-1], rows, cols, 0.01) - ref).max() > 1e-3
