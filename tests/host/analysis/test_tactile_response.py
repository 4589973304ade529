"""The contact model's templates (host/analysis/tactile/response.py): the Vlasov layer's response
to a uniform disc and to a line of discs, checked against the layer's equation (finite
differences), its force balance (quadrature), finite-difference Jacobians, the compiled kernel
against the numpy code, and the half-depth footprint table against a direct computation."""

import numpy as np
import pytest

from host.analysis.tactile import Foam
from host.analysis.tactile import response as R

FOAM = Foam()
LAM = FOAM.shear_length_m
K = FOAM.k_pa_per_m


def rng(seed):
    return np.random.Generator(np.random.MT19937(seed))


@pytest.mark.parametrize("a", [0.002, 0.0075, 0.015])
def test_disc_response_solves_the_layer_equation(a):
    """k (w − λ² ∇²w) = p: 1 / (π a²) per newton inside the disc, 0 outside (axisymmetric
    Laplacian by finite differences, not the Bessel identities the code uses); continuous with
    its slope at the rim."""
    h = 1e-6
    for r in (0.3 * a, 0.8 * a, 1.2 * a, a + 2 * LAM, a + 5 * LAM):
        w0, wp, wm = (float(R.disc_response(np.array(x), a, LAM, K)) for x in (r, r + h, r - h))
        lap = (wp - 2 * w0 + wm) / h ** 2 + (wp - wm) / (2 * h * r)
        p = K * (w0 - LAM ** 2 * lap)
        expect = 1.0 / (np.pi * a * a) if r < a else 0.0
        assert p == pytest.approx(expect, abs=2e-4 / (np.pi * a * a))
    w_in, w_at, w_out = (float(R.disc_response(np.array(a + s), a, LAM, K))
                         for s in (-1e-11, 0.0, 1e-11))
    assert w_in == pytest.approx(w_out, rel=1e-8) and w_at == pytest.approx(w_out, rel=1e-8)
    slope_in = (w_in - float(R.disc_response(np.array(a - h), a, LAM, K))) / h
    slope_out = (float(R.disc_response(np.array(a + h), a, LAM, K)) - w_out) / h
    assert slope_in == pytest.approx(slope_out, rel=1e-3)


@pytest.mark.parametrize("a,half_length,angle", [(0.006, 0.0, 0.0), (0.004, 0.02, 0.7),
                                                 (0.01, 0.03, -1.2)])
def test_every_template_carries_one_newton(a, half_length, angle):
    """k ∫ w dA = 1 for a disc and a line of discs: the fitted amplitude is the force."""
    u = np.arange(-0.12, 0.12, 0.0004)
    U, V = np.meshgrid(u, u)
    xy = np.stack([U.ravel(), V.ravel()], axis=1)
    w = R.line_response(xy, np.zeros(2), a, half_length, angle, LAM, K)
    assert K * w.sum() * 0.0004 ** 2 == pytest.approx(1.0, rel=2e-3)


@pytest.mark.parametrize("use_kernel", [False, True], ids=["numpy", "kernel"])
def test_line_response_jacobian_matches_finite_differences(use_kernel, monkeypatch):
    if use_kernel and not R.USE_KERNEL:
        pytest.skip("the compiled response kernel is not built (pip install -e .)")
    monkeypatch.setattr(R, "USE_KERNEL", use_kernel)
    xy = rng(1).uniform(-0.03, 0.03, (60, 2))
    p = np.array([0.002, -0.001, 0.006, 0.015 * np.cos(0.4), 0.015 * np.sin(0.4)])

    def f(q):
        return R.line_response(xy, q[:2], q[2], np.hypot(q[3], q[4]), np.arctan2(q[4], q[3]),
                               LAM, K)

    w, J = R.line_response(xy, p[:2], p[2], np.hypot(p[3], p[4]), np.arctan2(p[4], p[3]), LAM,
                           K, jacobian=True)
    assert np.allclose(w, f(p))
    for j in range(5):
        e = np.zeros(5)
        e[j] = 1e-7
        num = (f(p + e) - f(p - e)) / 2e-7
        assert np.max(np.abs(num - J[:, j])) <= 1e-5 * np.max(np.abs(num))


def test_the_kernel_gives_the_numpy_numbers():
    """The compiled kernel (Abramowitz & Stegun's Bessel approximations) against scipy's."""
    if not R.USE_KERNEL:
        pytest.skip("the compiled response kernel is not built (pip install -e .)")
    xy = rng(2).uniform(-0.05, 0.05, (300, 2))
    for a, hl, th in [(0.006, 0.0, 0.0), (0.004, 0.02, 0.4), (0.001, 0.005, -1.0),
                      (0.015, 0.03, 2.0)]:
        wk, Jk = R._line_kernel(xy, np.array([0.001, -0.002]), a, hl, th, LAM, K, True)
        wn, Jn = R._line_numpy(xy, np.array([0.001, -0.002]), a, hl, th, LAM, K, True)
        assert np.max(np.abs(wk - wn)) <= 1e-6 * np.max(np.abs(wn))
        for j in range(3):   # the ℓ columns vanish for ℓ = 0: compared absolutely below
            assert np.max(np.abs(Jk[:, j] - Jn[:, j])) <= 1e-5 * np.max(np.abs(Jn[:, j]))
        assert np.max(np.abs(Jk[:, 3:] - Jn[:, 3:])) <= 1e-5 * np.max(np.abs(Jn[:, :2]))
    with pytest.raises(ValueError, match="a=0"):
        R._line_kernel(xy, np.zeros(2), 0.0, 0.0, 0.0, LAM, K, False)


@pytest.mark.parametrize("a,half_length", [(0.004, 0.0), (0.008, 0.0), (0.004, 0.025),
                                           (0.007, 0.012)])
def test_half_depth_footprint_table_matches_a_direct_computation(a, half_length):
    """The table (rays and bisection, interpolated) against the region on a fine grid."""
    axes, area = R.half_depth_footprint(a, half_length, LAM)
    u = np.arange(-0.06, 0.06, 0.0002)
    U, V = np.meshgrid(u, u)
    xy = np.stack([U.ravel(), V.ravel()], axis=1)
    w = R.line_response(xy, np.zeros(2), a, half_length, 0.0, LAM, K)
    half = w >= 0.5 * float(R.line_response(np.zeros((1, 2)), np.zeros(2), a, half_length, 0.0,
                                             LAM, K)[0])
    pts = xy[half]
    sx, sy = 2 * np.sqrt(np.mean(pts[:, 0] ** 2)), 2 * np.sqrt(np.mean(pts[:, 1] ** 2))
    assert axes[0] == pytest.approx(sx, rel=0.01)
    assert axes[1] == pytest.approx(sy, rel=0.01)
    assert area == pytest.approx(half.sum() * 0.0002 ** 2, rel=0.02)
