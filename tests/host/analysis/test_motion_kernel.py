"""The fused estimator's per-link steps in C (host/analysis/motion/_kernel/link_filter.c) give the
numpy code's numbers (host/analysis/motion/fused.py `_np_*`), on random states of many links."""

from __future__ import annotations

import numpy as np
import pytest

from host.analysis.motion import fused

pytestmark = pytest.mark.skipif(fused._klib is None, reason="the motion kernel is not built "
                                "(no C compiler at install, or CAPSHEET_NO_KERNEL set)")


def _state(n, seed):
    g = np.random.Generator(np.random.MT19937(seed))
    R = fused.rotation_matrices(g.normal(0, 1.5, (n, 3)))
    A = g.normal(0, 1e-3, (n, 6, 6))
    P = A @ A.transpose(0, 2, 1) + 1e-6 * np.eye(6)
    return g, R, P


def _both(name, n, args_of):
    """Run step ``name`` through the kernel and through numpy on copies of the same arrays."""
    out = []
    for use in (fused._kernel_step, lambda nm, *a: fused.NUMPY_STEPS[nm](*a)):
        args = args_of()
        use(name, *args)
        out.append(args)
    return out


@pytest.mark.parametrize("name", ["propagate", "accel", "yaw", "apply"])
def test_each_per_link_step_is_the_same_in_c_and_numpy(name):
    n = 57

    def args_of():
        g, R, P = _state(n, 11)
        if name == "propagate":
            return (R, P, g.normal(0, 3, (n, 3)), g.normal(0, 3, (n, 3)),
                    g.uniform(0.005, 0.01, n), g.uniform(0, 1e-6, n), g.uniform(0, 1e-9, n))
        if name == "accel":
            valid = g.random(n) > 0.2
            return (R, P, g.normal(0, 10, (n, 3)), g.normal(0, 10, (n, 3)),
                    g.uniform(1e-3, 1e-2, n), 25.0, valid, np.zeros((n, 6)), np.zeros(n))
        if name == "yaw":
            return (P, g.normal(0, 1e-3, n), g.uniform(1e6, 1e7, n), np.zeros((n, 6)))
        return (R, g.normal(0, 1e-3, (n, 3)), P, g.normal(0, 1e-3, (n, 6)))

    c, p = _both(name, n, args_of)
    for a, b in zip(c, p):
        if isinstance(a, np.ndarray) and a.dtype == np.float64:
            assert np.array_equal(np.isnan(a), np.isnan(b)), name  # NaN in the same places
            a, b = np.nan_to_num(a), np.nan_to_num(b)
            scale = max(np.abs(b).max(), 1e-300)
            assert np.abs(a - b).max() <= 1e-12 * scale, (name, np.abs(a - b).max(), scale)
    # the check can fail: a different rate in the kernel's propagation shows
    if name == "propagate":
        args = args_of()
        args[3][0, 0] += 1e-6
        fused._kernel_step(name, *args)
        assert np.abs(args[0] - p[0]).max() > 1e-12


def test_a_mask_handed_to_the_kernel_stays_alive_until_the_call():
    """A boolean mask goes to the kernel as a uint8 copy; the arguments must keep that copy alive.
    A cast pointer to it did not: the copy was freed before the call, numpy's allocator gave its
    bytes to the next array of that size (here 64 arrays of zeros; live, another thread's while
    cffi had released the interpreter lock) and the kernel read the links' valid flags as 0 — a
    6-axis recording replayed 0.004 % of side apart from its live estimates."""
    valid = np.ones(12, dtype=bool)
    args = fused._kernel_args("accel", (np.zeros((12, 3, 3)), valid))
    junk = [np.zeros(12, dtype=np.uint8) for _ in range(64)]
    assert [args[1][k] for k in range(12)] == [1] * 12
    assert len(junk) == 64


def _bent_frames(rows, cols, seed):
    """Frames of a smoothly bent, twisted sheet with noise: every cell a real cell (its normal
    defined), plus one squashed cell whose terms must drop out."""
    g = np.random.Generator(np.random.MT19937(seed))
    n = 2 * rows * cols - rows - cols
    alpha = 0.3 * np.sin(np.linspace(0, 3, n)) + g.normal(0, 0.02, n)
    beta = 0.2 * np.cos(np.linspace(0, 2, n)) + g.normal(0, 0.02, n)
    n_i = (rows - 1) * cols
    gamma = np.where(np.arange(n) < n_i, 0.0, np.pi / 2) + g.normal(0, 0.05, n)
    R = fused.frames_from_angles(alpha, beta, gamma)
    units = fused.topology(rows, cols).units
    R[units[0, 1]] = R[units[0, 0]]  # the first cell's i-link along its j-link: no normal
    A = g.normal(0, 1e-3, (n, 6, 6))
    P = A @ A.transpose(0, 2, 1) + 1e-6 * np.eye(6)
    return R, P


def test_the_lattice_step_is_the_same_in_c_and_numpy():
    """The lattice step's residuals, weights, Jacobian and normal-matrix products (the bulk of a
    64x64 snapshot's time) from the kernel are numpy's to rounding, on a lattice with more rows
    than columns (a transposed index would show)."""
    rows, cols = 7, 5
    topo = fused.topology(rows, cols)
    R, P = _bent_frames(rows, cols, 3)
    out_c = fused._lattice_terms(R, P, topo, 1e-6)
    out_n = [np.empty_like(a) for a in out_c]
    fused._np_lattice(R, P, topo, 1e-6, *out_n)
    for name, a, b in zip(("res", "wts", "jd", "lat_diag"), out_c, out_n):
        assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max(), name
    # Jᵀ v (the solve's right-hand side) and what the loops say of each group's offset
    from host.analysis.motion import _linalg as la
    v = np.random.Generator(np.random.MT19937(7)).normal(size=topo.n_rows)
    saved = la.USE_KERNEL
    try:
        la.USE_KERNEL = False
        want_jt = la.jt_times(topo, out_n[2], v)
        want_info = la.group_info(topo, out_n[2], out_n[1], out_n[3])
    finally:
        la.USE_KERNEL = saved
    got_jt = la.jt_times(topo, out_c[2], v)
    assert np.abs(got_jt - want_jt).max() <= 1e-12 * np.abs(want_jt).max()
    for got_i, want_i in zip(la.group_info(topo, out_c[2], out_c[1], out_c[3]), want_info):
        assert np.abs(got_i - want_i).max() <= 1e-12 * np.abs(want_i).max()
    # the check can fail: another right-hand side gives another product
    assert np.abs(la.jt_times(topo, out_c[2], v + 1e-6) - want_jt).max() > 1e-9
    x = np.random.Generator(np.random.MT19937(4)).normal(size=topo.n_links)
    J = topo.jac.copy()
    J.data = out_n[2]
    want = J.T @ (out_n[1] * (J @ x))
    got = fused._normal_matvec(topo, out_c[2], out_c[1])(x)
    assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()
    # the check can fail: one link turned by 1e-6 rad about z moves the kernel's residuals
    R2 = fused.rotate_all(np.eye(3), R)
    R2[10] = fused.rotation_matrices(np.array([0.0, 0.0, 1e-6])) @ R2[10]
    res2 = fused._lattice_terms(R2, P, topo, 1e-6)[0]
    assert np.abs(res2 - out_n[0]).max() > 1e-8


def test_the_yaw_solve_is_the_same_in_c_and_numpy():
    """The lattice step's conjugate gradients with the nested yaw prior (a real estimator's, 9-axis,
    after a few snapshots of a bent sheet) give numpy's solution to the solver's tolerance."""
    rows, cols = 6, 5
    R, _P = _bent_frames(rows, cols, 5)
    n = R.shape[0]
    g = np.random.Generator(np.random.MT19937(6))
    est = fused.MotionEstimator(rows, cols, 0.01)
    f = np.einsum("kji,j->ki", R, [0.0, 0.0, 9.80665])
    m = np.einsum("kji,j->ki", R, [25e-6, 0.0, -43e-6])
    for k in range(20):
        est.update(k / 145.0, f + g.normal(0, 0.01, (n, 3)), g.normal(0, 0.01, (n, 3)),
                   m + g.normal(0, 0.3e-6, (n, 3)))
    topo = est.topo
    res, wts, jd, lat_diag = fused._lattice_terms(est.R, est.P, topo, 1e-6)
    prior, prior_diag = est._yaw_prior(est.P[:, 2, 2])
    mw = g.uniform(0, 1e4, n)
    b = g.normal(0, 1.0, n)
    inv = 1.0 / (prior_diag + lat_diag + mw)
    normal = fused._normal_matvec(topo, jd, wts)
    want = fused.pcg(lambda x: normal(x) + prior(x) + mw * x, b, inv)
    got = fused._yaw_solve(topo, jd, wts, est._prior_terms, mw, b, inv)
    assert np.abs(got - want).max() <= 1e-7 * np.abs(want).max(), np.abs(got - want).max()
    # the check can fail: a prior with another group weight gives another solution
    D, dg, Eg, sE, I0 = est._prior_terms
    off = fused._yaw_solve(topo, jd, wts, (D, dg, 2.0 * Eg, sE, I0), mw, b, inv)
    assert np.abs(off - want).max() > 1e-6 * np.abs(want).max()


def test_the_whole_sheet_steps_are_the_same_in_c_and_numpy():
    """The magnetometers' terms, the sheet's turn, the output covariance and the links' direction
    accelerations from the kernel are numpy's to rounding (wrapped headings included: fields
    pointing near ±180° from north)."""
    from host.analysis.motion import _linalg as la
    n = 57
    g, R, P = _state(n, 21)
    m = g.normal(0, 30e-6, (n, 3))
    m[:5, 1] = 1e-12  # headings at the wrap: field along -x in some frames
    args = (R, m, 0.3, 50e-6, 1.0, 0.01, 0.0087)
    for a, b in zip(la.mag_terms(*args), la.np_mag_terms(*args)):
        assert np.abs(a - b).max() <= 1e-12 * max(np.abs(b).max(), 1.0)
    Q = fused.rotation_matrices(np.array([0.01, -0.02, 0.3]))
    Rc = R.copy()
    la.turn_all(Q, Rc)
    assert np.abs(Rc - fused.rotate_all(Q, R)).max() <= 1e-14
    tc = np.array([[2e-6, 1e-7], [1e-7, 3e-6]])
    add = g.uniform(0, 1e-4, n)
    for ya in (add, None):
        assert np.abs(la.orientation_cov(P, tc, ya) - la.np_orientation_cov(P, tc, ya)).max() <= 1e-18
    w, wd = g.normal(0, 3, (n, 3)), g.normal(0, 30, (n, 3))
    assert np.abs(la.ddot(R, w, wd) - la.np_ddot(R, w, wd)).max() <= 1e-12 * np.abs(la.np_ddot(R, w, wd)).max()
    # the check can fail: a declination off by 1e-9 rad moves every heading
    assert np.abs(la.mag_terms(R, m, 0.3 + 1e-9, *args[3:])[0] - la.np_mag_terms(*args)[0]).max() > 5e-10


def test_the_magnetometers_weights_are_the_same_in_c_and_numpy():
    """Every branch of the weights: links not ok (their heading error zeroed, NaN fields
    included), not yet warm, tests under and over their noise, headings off their group."""
    from host.analysis.motion import _linalg as la
    n = 64
    g, _R, P = _state(n, 22)
    hz = g.uniform(5e-6, 30e-6, n)
    ok = g.uniform(size=n) > 0.2
    hz[~ok][:3] = np.nan
    dist = g.normal(0, 3, (n, 3)) * g.uniform(0, 1, (n, 1)) ** 3  # many small, some large
    count = g.integers(0, 40, n).astype(float)
    dt = g.uniform(0.005, 0.008, n)
    args = (hz, ok, dist, P, count, dt, (0.35e-6) ** 2, np.radians(0.5) ** 2, 50e-6, 0.01,
            np.radians(0.5), 0.3, 5.0 / 0.0069, 4.0, 0.0069, 0.1)
    e = g.normal(0, 0.1, n)
    e_c, e_np = e.copy(), e.copy()
    (w_c, mw_c), (w_np, mw_np) = la.mag_weights(*args, e_c), la.np_mag_weights(*args, e_np)
    assert np.abs(w_c - w_np).max() <= 1e-15 and np.abs(mw_c - mw_np).max() <= 1e-12 * mw_np.max()
    assert np.array_equal(e_c, e_np) and np.all(e_np[~ok] == 0) and np.all(e_np[ok] == e[ok])
    # every branch was met: unused links, cold ones, warm ones at full and at reduced weight
    warm = ok & (count * 0.0069 >= 0.1)
    assert (~ok).any() and (ok & ~warm).any() and np.all(w_np[~warm] == 0)
    assert (w_np[warm] > 0.99).any() and (w_np[warm] < 0.1).any()
    # the check can fail: the magnetometer's noise off by 1 % changes every used link's
    # information by up to as much
    _w, mw_off = la.mag_weights(*args[:6], args[6] * 1.01, *args[7:], e.copy())
    assert np.abs(mw_off - mw_np).max() > 1e-3 * mw_np.max()


def test_the_disturbance_tests_and_the_heading_mode_are_the_same_in_c_and_numpy():
    """The tests' averages (links not ok keep theirs, NaN tests included; residuals beyond ±π
    wrapped; a group with no ok link) and the biweight mode from a start."""
    from host.analysis.motion import _linalg as la
    n, groups = 60, 7
    g = np.random.Generator(np.random.MT19937(23))
    group = np.arange(n, dtype=np.int64) % groups
    ok = g.uniform(size=n) > 0.25
    ok[group == 3] = False
    resid = g.normal(0, 0.02, n)
    resid[:4] += 2 * np.pi
    t_mag, t_dip = g.normal(0, 2, n), g.normal(0, 2, n)
    t_mag[~ok] = np.nan
    dt = g.uniform(0.005, 0.008, n)
    dist0, avg0, count0 = g.normal(0, 1, (n, 3)), g.normal(0, 0.01, n), g.integers(0, 9, n) * 1.0
    out = []
    for f in (la.dist_tests, la.np_dist_tests):
        d, a, c = dist0.copy(), avg0.copy(), count0.copy()
        d = f(group, groups, ok, resid, t_mag, t_dip, dt, 0.3, 0.0087, d, a, c)
        out.append((d, a, c))
    (dc, ac, cc), (dn, an, cn) = out
    assert np.abs(dc - dn).max() <= 1e-12 and np.abs(ac - an).max() <= 1e-15
    assert np.array_equal(cc, cn) and np.array_equal(cn, count0 + ok)
    assert np.array_equal(dn[~ok], dist0[~ok]) and np.all(np.isfinite(dn))
    # residuals a turn apart are the same residuals; the check can fail: residuals 0.01 rad
    # off move the averages
    d = dist0.copy()
    la.np_dist_tests(group, groups, ok, resid - 2 * np.pi * (np.arange(n) < 4), t_mag, t_dip, dt,
                     0.3, 0.0087, d, avg0.copy(), count0.copy())
    assert np.abs(d - dc).max() <= 1e-12  # wrapped alike: the same
    a2 = avg0.copy()
    la.np_dist_tests(group, groups, ok, resid + 0.01, t_mag, t_dip, dt, 0.3, 0.0087,
                     dist0.copy(), a2, count0.copy())
    assert np.abs(a2 - ac).max() > 1e-3
    # the mode from a start: C and numpy
    r = np.concatenate([g.normal(0.0, 0.002, 200), -g.uniform(0.014, 0.05, 120)])
    w = g.uniform(0, 1, r.size) * (g.uniform(size=r.size) > 0.1)
    for start in (0.0, -0.004, 0.01):
        c_psi = la.robust_mode(r, w, 0.013, start)
        assert abs(c_psi - la.np_robust_mode(r, w, 0.013, start)) <= 1e-15
        assert abs(c_psi) < 1e-3
    assert la.robust_mode(r, np.zeros(r.size), 0.013, 0.0) is None
    assert la.robust_mode(r, w, 0.013, 1.0) is None  # nothing within the width of the start


@pytest.mark.parametrize("name", ["accel", "yaw"])
def test_a_step_and_its_correction_in_one_pass_are_the_two_calls(name):
    """``step_apply`` in C (a block of links at a time) gives the numpy step followed by numpy's
    apply, on more links than one block (64) holds."""
    from host.analysis.motion import _linalg as la
    n = 150
    out = []
    for use_kernel in (True, False):
        g, R, P = _state(n, 31)
        bias = g.normal(0, 1e-3, (n, 3))
        if name == "accel":
            args = (g.normal(0, 10, (n, 3)), g.normal(0, 10, (n, 3)), g.uniform(1e-3, 1e-2, n),
                    25.0, g.random(n) > 0.2, np.zeros((n, 6)), np.zeros(n))
        else:
            args = (g.normal(0, 1e-3, n), g.uniform(1e6, 1e7, n), np.zeros((n, 6)))
        saved = la.USE_KERNEL
        la.USE_KERNEL = use_kernel
        try:
            la.step_apply(name, R, bias, P, *args)
        finally:
            la.USE_KERNEL = saved
        out.append((R, bias, P))
    for a, b in zip(*out):
        assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max(), name
    # the check can fail: the numpy step alone (no correction applied) leaves R where it was
    assert np.abs(out[0][0] - _state(n, 31)[1]).max() > 1e-6


def test_the_coarse_preconditioner_is_the_same_in_c_and_numpy():
    """The yaw solve's coarse matrix from the kernel is numpy's (scipy's sparse products) to
    rounding, and the conjugate gradients with it (C and numpy) reach the solution without it:
    a preconditioner changes the path, not the answer (its iterations are bench_motion's)."""
    from host.analysis.motion import _linalg as la
    rows, cols = 6, 5
    R, _P = _bent_frames(rows, cols, 5)
    n = R.shape[0]
    g = np.random.Generator(np.random.MT19937(6))
    est = fused.MotionEstimator(rows, cols, 0.01)
    f = np.einsum("kji,j->ki", R, [0.0, 0.0, 9.80665])
    for k in range(20):
        est.update(k / 145.0, f + g.normal(0, 0.01, (n, 3)), g.normal(0, 0.01, (n, 3)))
    topo = est.topo
    res, wts, jd, lat_diag = fused._lattice_terms(est.R, est.P, topo, 1e-6)
    jg = np.bincount(topo.jg_index, weights=jd, minlength=topo.jg_rows.size)
    est._s_group = np.full(topo.n_groups, 1.0)  # the groups free: the slow modes
    prior, prior_diag = est._yaw_prior(est.P[:, 2, 2], np.zeros(topo.n_groups), six_axis=True)
    mw = g.uniform(0, 1e2, n)
    c_kernel = la.coarse_inverse(topo, jg, wts, est._prior_terms, mw)
    saved = la.USE_KERNEL
    la.USE_KERNEL = False
    try:
        c_numpy = la.coarse_inverse(topo, jg, wts, est._prior_terms, mw)
    finally:
        la.USE_KERNEL = saved
    assert np.abs(c_kernel - c_numpy).max() <= 1e-9 * np.abs(c_numpy).max()
    b = g.normal(0, 1.0, n)
    inv = 1.0 / (prior_diag + lat_diag + mw)
    normal = fused._normal_matvec(topo, jd, wts)
    want = fused.pcg(lambda x: normal(x) + prior(x) + mw * x, b, inv, 1e-10, 500,
                     coarse=(topo.group, c_numpy))
    plain = fused.pcg(lambda x: normal(x) + prior(x) + mw * x, b, inv, 1e-10, 500)
    got = fused._yaw_solve(topo, jd, wts, est._prior_terms, mw, b, inv, 1e-10, 500, c_kernel)
    assert np.abs(got - want).max() <= 1e-6 * np.abs(want).max()
    assert np.abs(plain - want).max() <= 1e-6 * np.abs(want).max()
    # the check can fail: the magnetometers' weights doubled give another coarse matrix
    other = la.coarse_inverse(topo, jg, wts, est._prior_terms, 2.0 * mw)
    assert np.abs(other - c_kernel).max() > 1e-6 * np.abs(c_kernel).max()


@pytest.mark.parametrize("name,blocks", [("propagate", 1), ("propagate", 2), ("accel", 1),
                                         ("accel", 2), ("yaw", 1), ("yaw", 2)])
def test_the_fixed_errors_consider_steps_are_the_same_in_c_and_numpy(name, blocks):
    from host.analysis.motion import _consider
    n = 57

    def args_of():
        g, R, P = _state(n, 13)
        C = g.normal(0, 1e-5, (n, 6, 9 * blocks))
        if name == "propagate":
            return (R, P, C, g.normal(0, 3, (n, blocks, 3)), g.uniform(0.005, 0.01, n),
                    g.uniform(0, 4e-6, 9 * blocks))
        if name == "accel":
            return (R, P, C, g.normal(0, 10, (n, 3)), g.normal(0, 10, (n, 3)),
                    g.uniform(1e-3, 1e-2, n), 25.0, g.random(n) > 0.2)
        return (P, C, g.uniform(1e6, 1e7, n))

    out = []
    for fn in (getattr(_consider, name), getattr(_consider, "np_" + name)):
        args = args_of()
        fn(*args)
        out.append(args)
    if not _consider.USE_KERNEL:
        pytest.skip("the kernel is not used")
    for a, b in zip(*out):
        if isinstance(a, np.ndarray) and a.dtype == np.float64:
            scale = max(np.abs(b).max(), 1e-300)
            assert np.abs(a - b).max() <= 1e-12 * scale, (name, np.abs(a - b).max(), scale)
    # the steps change what they should: C in every step, P in the propagation
    fresh = args_of()
    ci = 1 if name == "yaw" else 2
    assert not np.array_equal(out[0][ci], fresh[ci]), name
    if name == "propagate":
        assert not np.array_equal(out[0][1], fresh[1])
