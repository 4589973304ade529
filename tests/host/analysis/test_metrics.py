"""The rigid overlay (host.analysis.metrics), the one definition the estimator and tactile share."""

import numpy as np
import pytest

from host.analysis import estimator, metrics, tactile


def _rot(a, b, c):
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    rz = np.array([[cc, -sc, 0], [sc, cc, 0], [0, 0, 1]])
    ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    return rz @ ry @ rx


def test_estimator_and_tactile_use_the_same_overlay():
    assert estimator.overlay is metrics.overlay
    assert tactile.rigid_fit is metrics.rigid_fit


@pytest.mark.parametrize("planar", [False, True])
def test_a_rigid_motion_is_undone_exactly(planar):
    rng = np.random.Generator(np.random.MT19937(4))
    q = rng.normal(size=(30, 3))
    if planar:  # a flat sheet: det(H) has sign 0 in exact arithmetic
        q[:, 2] = 0.0
    p = q @ _rot(0.4, -0.2, 1.1).T + [0.3, -0.1, 2.0]
    np.testing.assert_allclose(metrics.rigid_fit(p, q), q, atol=1e-12)


def test_a_mirror_image_is_never_matched_by_a_reflection():
    rng = np.random.Generator(np.random.MT19937(5))
    q = rng.normal(size=(20, 3))
    p = q * [1, 1, -1]  # mirrored: only a reflection would match it exactly
    moved = metrics.rigid_fit(p, q)
    # the motion used is proper: distances between moved points equal p's, and it does not match q
    H = (moved - moved.mean(0)).T @ (p - p.mean(0))
    assert np.linalg.det(H) != 0
    assert np.linalg.norm(moved - q) > 1.0
    d_moved = np.linalg.norm(moved[:, None] - moved[None], axis=-1)
    d_p = np.linalg.norm(p[:, None] - p[None], axis=-1)
    np.testing.assert_allclose(d_moved, d_p, atol=1e-12)


def test_weights_pick_which_points_are_fitted():
    q = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 5, 5]])
    p = q.copy()
    p[4] += [3.0, 0, 0]  # an outlier
    w = np.array([1.0, 1, 1, 1, 0])
    np.testing.assert_allclose(metrics.rigid_fit(p, q, w)[:4], q[:4], atol=1e-12)
    assert np.abs(metrics.rigid_fit(p, q)[:4] - q[:4]).max() > 1e-3
