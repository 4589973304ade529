"""The estimator's compiled kernel (host/analysis/_kernel/*.c) against its numpy code.

Two independent implementations of the same terms: the kernel's single-pass loops and
`YawProblem.evaluate`'s numpy (`_roll_grad`, reverse mode), and the kernel's triangular sweeps
against SuperLU's own solve. Metric: difference of the cost (relative), of the gradient (to its
largest entry, or to 1 where that is smaller: at a minimum, terms of order 1 cancel) and of the
step (relative); tolerance 1e-12 (rounding: the two sum in different orders), 1e-6 for the
solve (its factor is kept in float32, `SOLVE_TOL`).
Whole warm-started runs (the benchmark's: 1 % g, a sheared Gaussian, a masked lattice) must give
the same joints within 1e-8 of the side (1e-9 before the factor went float32) and the same
iteration counts with the kernel and without.
"""

from __future__ import annotations

import numpy as np
import pytest

from host.analysis import estimator as E
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import noisy_readings
from virtual_sheet.shapes import make_sheet

pytestmark = pytest.mark.skipif(not E.USE_KERNEL, reason="the estimator's kernel is not built")

L = 0.01
TOL = 1e-12


def rng(seed: int) -> np.random.Generator:
    return np.random.Generator(np.random.MT19937(seed))


def _problem(n, shape="gaussian", shear=0.0, noise=1.0, valid=None, prior="adaptive", seed=3):
    P = make_sheet(shape, n, n, L, shear=shear)
    r = noisy_readings(ideal_readings(P), noise, rng(seed))
    est = E.estimate(r, n, n, L, valid=valid, prior=prior)
    return est.solution[:4]  # structure, factorisation, problem, yaws


def _both(prob, gamma, monkeypatch):
    monkeypatch.setattr(E.kernel, "USE_KERNEL", False)
    c0, g0, _ = prob.evaluate(gamma, jac=False)
    monkeypatch.setattr(E.kernel, "USE_KERNEL", True)
    c1, g1, b1 = prob.evaluate(gamma, jac=False)
    assert b1 is None
    return c0, g0, c1, g1


def _mask(n, seed=5):
    lat_links = 2 * n * (n - 1)
    v = np.ones(lat_links, bool)
    v[rng(seed).choice(lat_links, size=lat_links // 20, replace=False)] = False
    return v


@pytest.mark.parametrize("case", [
    dict(n=5), dict(n=14), dict(n=14, shape="cylinder", shear=0.2),
    dict(n=14, prior="fixed"), dict(n=14, valid="mask"), dict(n=9, noise=0.0),
    dict(n=14, shape="sphere", shear=0.3, noise=5.0),
])
def test_the_kernels_cost_and_gradient_are_the_numpy_codes(case, monkeypatch):
    case = dict(case)
    if case.get("valid") == "mask":
        case["valid"] = _mask(case["n"])
    st, _, prob, gamma = _problem(**case)
    g = rng(11)
    for scale in (0.0, 0.01, 0.3, 2.0):  # at the estimate, near it, far from it
        gg = gamma + g.normal(0.0, scale, gamma.shape)
        c0, g0, c1, g1 = _both(prob, gg, monkeypatch)
        assert abs(c1 - c0) <= TOL * max(abs(c0), 1e-300)
        assert g1.shape == g0.shape == (st.n_var,)
        assert np.max(np.abs(g1 - g0)) <= TOL * max(np.max(np.abs(g0)), 1.0)


def test_the_comparison_sees_a_wrong_gradient(monkeypatch):
    # the check proves itself: one yaw moved by 1e-6 rad changes the gradient beyond TOL
    st, _, prob, gamma = _problem(14)
    c0, g0, _, _ = _both(prob, gamma, monkeypatch)
    moved = gamma.copy()
    moved[st.var_links[7]] += 1e-6
    _, _, c1, g1 = _both(prob, moved, monkeypatch)
    assert np.max(np.abs(g1 - g0)) > TOL * max(np.max(np.abs(g0)), 1.0)


#: The supernodal solve keeps L in float32 (half the memory a solve streams through; the chord
#: iteration's step matrix is an approximation already, and its fixed point, grad = 0, does not
#: depend on it): entries rounded by 2^-24 relative, measured 4e-8 relative error in the solve.
SOLVE_TOL = 1e-6


@pytest.mark.parametrize("n", [5, 14, 32, 40])  # 32 and 40: nested dissection ordering
def test_the_kernels_supernodal_solve_solves_as_superlu_does(n):
    st, lu, prob, gamma = _problem(n)
    assert lu[0] == "splu" and lu[2] is not None
    assert (st.n_var >= E.ND_MIN_VARS) == (n >= 32)
    b = rng(n).normal(size=st.n_var)
    x_superlu = lu[1].solve(b)
    x = E.linalg.solve(lu, b)
    assert np.max(np.abs(x - x_superlu)) <= SOLVE_TOL * np.max(np.abs(x_superlu))
    B = np.stack([b, 2 * b], axis=1)  # several right-hand sides stay with SuperLU
    assert np.array_equal(E.linalg.solve(lu, B), lu[1].solve(B))
    # supernodes of more than one column exist (else this is the plain column solve)
    assert np.diff(lu[2][0][2]["arrays"][0]).max() > 1


def test_the_solve_comparison_sees_a_wrong_factor():
    st, lu, prob, gamma = _problem(14)
    b = rng(3).normal(size=st.n_var)
    val = lu[2][0][0]
    k = int(np.argmax(np.abs(val)))
    val[k] *= 1.001  # one entry of L off by 0.1 %
    x = E.linalg.solve(lu, b)
    val[k] /= 1.001
    assert np.max(np.abs(x - lu[1].solve(b))) > SOLVE_TOL * np.max(np.abs(lu[1].solve(b)))


def test_nested_dissection_orders_a_grid_with_less_fill_than_its_rows():
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu
    m = 40  # a 40x40 five-point grid: row by row fills ~m^3, nested dissection ~m^2 log m
    idx = np.arange(m * m).reshape(m, m)
    e = np.concatenate([np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1),
                        np.stack([idx[:-1].ravel(), idx[1:].ravel()], 1)])
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(m * m, m * m))
    A = (A + A.T + 5 * sp.identity(m * m)).tocsr()
    xy = np.stack([idx.ravel() // m, idx.ravel() % m], 1).astype(float)
    order = E.structure.nested_dissection(A, xy)
    assert np.array_equal(np.sort(order), np.arange(m * m))

    def fill(o):
        M = A[o][:, o].tocsc()
        return splu(M, permc_spec="NATURAL", diag_pivot_thresh=0.0,
                    options=dict(SymmetricMode=True)).L.nnz
    assert fill(order) < 0.5 * fill(np.arange(m * m))


def _warm_run(n, snaps, valid):
    prev, out = None, []
    for r in snaps:
        prev = E.estimate(r, n, n, L, valid=valid, previous=prev)
        out.append((prev.joints, prev.iterations, prev.factorisations))
    return out


@pytest.mark.parametrize("n,shape,shear,masked", [(14, "gaussian", 0.0, False),
                                                   (14, "saddle", 0.2, True),
                                                   (24, "gaussian", 0.1, False),
                                                   (32, "saddle", 0.2, True)])  # ND ordering
def test_warm_runs_give_the_same_joints_with_the_kernel_and_without(n, shape, shear, masked,
                                                                     monkeypatch):
    P = make_sheet(shape, n, n, L, shear=shear)
    r0 = ideal_readings(P)
    g = rng(1)
    snaps = [noisy_readings(r0, 1.0, g) for _ in range(12)]
    valid = _mask(n) if masked else None
    E.structure.cached_structure.cache_clear()  # each run starts without a cached factorisation
    monkeypatch.setattr(E.kernel, "USE_KERNEL", False)
    ref = _warm_run(n, snaps, valid)
    E.structure.cached_structure.cache_clear()
    monkeypatch.setattr(E.kernel, "USE_KERNEL", True)
    new = _warm_run(n, snaps, valid)
    side = (n - 1) * L
    for (j0, i0, f0), (j1, i1, f1) in zip(ref, new):
        assert (i1, f1) == (i0, f0)
        # the kernel's steps carry its float32 factor's error (SOLVE_TOL-level, relative), the
        # iterations shrink it but not to float64 rounding: 1.5e-10 m = 1.2e-9 of side measured
        assert np.max(np.abs(j1 - j0)) <= 1e-8 * side


@pytest.mark.parametrize("masked", [False, True])
def test_the_kernels_directions_residual_and_solvability_are_the_numpy_codes(masked, monkeypatch):
    n = 14
    P = make_sheet("saddle", n, n, L, shear=0.2)
    r = noisy_readings(ideal_readings(P), 1.0, rng(7))
    valid = _mask(n) if masked else None
    est = E.estimate(r, n, n, L, valid=valid)
    st = est.solution[0]
    alpha, beta = est.alpha, est.beta  # NaN on missing links: those units' solvability is NaN
    gamma = est.yaws + rng(8).normal(0.0, 0.5, est.yaws.shape)
    out = {}
    for use in (False, True):
        monkeypatch.setattr(E.kernel, "USE_KERNEL", use)
        d, nrm = E.joints.directions_normals(np.nan_to_num(alpha), np.nan_to_num(beta), gamma)
        out[use] = (d, nrm, E.joints.eq8_residual(st.units, d, nrm), E.solvability(alpha, beta, n, n))
    (d0, n0, e0, s0), (d1, n1, e1, s1) = out[False], out[True]
    assert np.max(np.abs(d1 - d0)) <= TOL and np.max(np.abs(n1 - n0)) <= TOL
    assert abs(e1 - e0) <= TOL * e0
    assert np.array_equal(np.isnan(s1), np.isnan(s0)) and np.isnan(s0).any() == masked
    assert np.nanmax(np.abs(s1 - s0)) <= TOL


def test_the_readings_trig_is_the_cosine_and_sine_of_their_angles():
    """`roll_pitch_trig`: the kernel's (cos α, sin α, cos β, sin β) from the readings' ratios
    against numpy's cos and sin of `roll_pitch`'s angles, on random readings of every scale and
    on the axis cases where the ratios are undefined (atan2's signed zeros decide there)."""
    g = rng(11)
    r = g.normal(0.0, 1.0, (4000, 3)) * 10.0 ** g.uniform(-6, 6, (4000, 1))
    axis = np.array([[1.0, 0.0, 0.0], [-2.0, 0.0, 0.0], [3.0, -0.0, 0.0], [1.0, 0.0, -0.0],
                     [-1.0, -0.0, -0.0], [0.0, 0.0, 0.0], [0.0, 0.0, -5.0], [0.0, 7.0, 0.0],
                     [np.nan, 1.0, 1.0], [1.0, np.nan, 1.0], [1e-200, 1e-200, 1e-200],
                     [1e200, 1e200, -1e200]])
    r = np.vstack([r, axis])
    alpha, beta, trig = E.angles.roll_pitch_trig(r)
    a0, b0 = E.roll_pitch(r)
    assert np.array_equal(alpha, a0, equal_nan=True) and np.array_equal(beta, b0, equal_nan=True)
    want = np.stack([np.cos(a0), np.sin(a0), np.cos(b0), np.sin(b0)], axis=1)
    assert np.array_equal(np.isnan(trig), np.isnan(want))
    assert np.isnan(want[-4:-2]).any(axis=1).all()  # the NaN readings are in the comparison
    assert np.nanmax(np.abs(trig - want)) <= 4e-16
    assert np.array_equal(E.angles.angle_trig(a0, b0), want, equal_nan=True)


@pytest.mark.parametrize("masked", [False, True])
def test_an_estimate_is_the_same_with_the_kernel_and_without(masked, monkeypatch):
    """One cold estimate through `estimate` (the kernel's trig shared by every stage) against the
    numpy code: solvability NaN on exactly the units of missing links, the rest within TOL."""
    n = 14
    P = make_sheet("sphere", n, n, L, shear=0.2)
    r = noisy_readings(ideal_readings(P), 0.3, rng(12))
    valid = _mask(n) if masked else None
    out = {}
    for use in (False, True):
        monkeypatch.setattr(E.kernel, "USE_KERNEL", use)
        E.structure.cached_structure.cache_clear()
        out[use] = E.estimate(r, n, n, L, valid=valid)
    e0, e1 = out[False], out[True]
    assert np.array_equal(np.isnan(e1.solvability), np.isnan(e0.solvability))
    assert np.isnan(e0.solvability).any() == masked
    assert np.nanmax(np.abs(e1.solvability - e0.solvability)) <= TOL
    assert e1.iterations == e0.iterations
    assert np.array_equal(e1.alpha, e0.alpha, equal_nan=True)
    # the closed pitches' height fit runs in the kernel too (its sums in another order)
    assert np.array_equal(np.isnan(e1.beta), np.isnan(e0.beta))
    assert np.nanmax(np.abs(e1.beta - e0.beta)) <= TOL
    assert np.nanmax(np.abs(e1.normals - e0.normals)) <= 1e-8
    assert np.max(np.abs(e1.joints - e0.joints)) <= 1e-8 * L * (n - 1)


@pytest.mark.parametrize("rows,cols,shape", [(14, 14, "cylinder"), (3, 3, "gaussian"),
                                             (2, 9, "tilted"), (20, 11, "flat")])
def test_the_kernels_flatness_is_the_numpy_codes(rows, cols, shape, monkeypatch):
    P = make_sheet(shape, rows, cols, L)
    r = noisy_readings(ideal_readings(P), 1.0, rng(9))
    norm_g = np.linalg.norm(r, axis=1) / E.G0
    st = E.structure.structure_of(rows, cols, None)
    out = {}
    for use in (False, True):
        monkeypatch.setattr(E.kernel, "USE_KERNEL", use)
        out[use] = [E.priors.flatness(st, r, norm_g, s) for s in (0.003, 0.01, 0.05)]
    for h0, h1 in zip(out[False], out[True]):
        assert h1.shape == h0.shape == ((rows - 1) * (cols - 1),)
        assert np.max(np.abs(h1 - h0)) <= TOL
    if shape == "flat":
        assert np.max(out[True][1]) > 0.5  # a level region: the comparison is not of zeros


@pytest.mark.parametrize("masked", [False, True])
def test_the_kernels_yaw_coefficients_are_the_numpy_codes(masked, monkeypatch):
    n = 14
    st, _, prob, gamma = _problem(n, shape="cylinder", shear=0.1,
                                  valid=_mask(n) if masked else None)
    a = rng(4).uniform(-np.pi, np.pi, st.n_links)
    b = rng(5).uniform(-np.pi / 2, np.pi / 2, st.n_links)
    out = {}
    for use in (False, True):
        monkeypatch.setattr(E.kernel, "USE_KERNEL", use)
        out[use] = E.yawproblem.YawProblem(st, a, b, st.rest_yaw, prob.lam, prob.lam_b)
    for name in ("c_loop", "Az", "Cz", "y_c", "y_z", "w", "pair_t", "target"):
        v0, v1 = getattr(out[False], name), getattr(out[True], name)
        assert v1.shape == v0.shape and v1.dtype == v0.dtype, name
        assert np.max(np.abs(v1 - v0)) <= TOL, name


def test_the_kernels_chord_loop_takes_the_python_loops_steps(monkeypatch):
    """`capsheet_chord` (the warm chord iterations in C) against `solve_global`'s Python loop on
    the same kernel evaluations and solves: the same iteration and factorisation counts, the same
    joints to rounding, over warm runs that also hand back to Python for a refactorisation."""
    statuses = []
    real = E.yawproblem.YawProblem.chord_kernel

    def spy(self, *a):
        out = real(self, *a)
        statuses.append(out[0])
        return out
    runs = {}
    for in_c in (False, True):
        if in_c:
            monkeypatch.setattr(E.yawproblem.YawProblem, "chord_kernel", spy)
        else:
            monkeypatch.setattr(E.solver, "chord_in_kernel", lambda *a: False)
        out = []
        for n, shapes, shear, noise in ((14, ("saddle",), 0.2, 1.0), (14, ("sphere",), 0.3, 5.0),
                                        (24, ("gaussian", "saddle"), 0.1, 1.0)):
            # two shapes in turn: a warm start far from the answer, refactorised
            r0 = [ideal_readings(make_sheet(sh, n, n, L, shear=shear)) for sh in shapes]
            g = rng(21)
            snaps = [noisy_readings(r0[k % len(r0)], noise, g) for k in range(15)]
            E.structure.cached_structure.cache_clear()
            out.append(_warm_run(n, snaps, None))
        runs[in_c] = out
        monkeypatch.undo()
    assert statuses.count(0) > 10 and {1, 2} & set(statuses)  # converged, and handed back
    for r0, r1 in zip(runs[False], runs[True]):
        for (j0, i0, f0), (j1, i1, f1) in zip(r0, r1):
            assert (i1, f1) == (i0, f0)
            assert np.max(np.abs(j1 - j0)) <= 1e-12


def _angles_of(n, masked, seed=4):
    P = make_sheet("sphere", n, n, L, shear=0.2)
    r = noisy_readings(ideal_readings(P), 2.0, rng(seed))
    valid = _mask(n) if masked else np.ones(r.shape[0], bool)
    st = E.structure.structure_of(n, n, None if valid.all() else valid)
    rr, alpha, beta, trig = E.pipeline.link_angles(r, valid, None if valid.all() else valid)
    return st, alpha, beta, trig


@pytest.mark.parametrize("n, masked", [(14, False), (14, True), (33, False), (6, True)])
def test_the_kernels_closed_pitches_are_the_numpy_codes(n, masked, monkeypatch):
    """`closed_pitches` in the kernel (``capsheet_closed_pitches``: the height fit with the
    Laplacian's solves in C, the new pitches' cosines and sines from the fitted steps) against the
    numpy code (SuperLU's solves, then `angle_trig`)."""
    st, alpha, beta, trig = _angles_of(n, masked)
    assert trig is not None
    b1, t1 = E.pipeline.closed_pitches(st, alpha, beta, trig)
    monkeypatch.setattr(E.kernel, "USE_KERNEL", False)
    b0, none = E.pipeline.closed_pitches(st, alpha, beta)
    assert none is None
    assert np.max(np.abs(b0 - beta)) > 1e-3  # the fit moves the pitches (by about the noise)
    assert np.max(np.abs(b1 - b0)) <= TOL
    assert np.max(np.abs(t1 - E.angles.angle_trig(alpha, b0))) <= TOL


def test_the_closed_pitches_comparison_sees_a_wrong_input():
    st, alpha, beta, trig = _angles_of(14, False)
    b0, _ = E.pipeline.closed_pitches(st, alpha, beta, trig)
    bad = trig.copy()
    bad[40, 3] += 1e-9  # one link's sine off by a billionth: the fit uses the readings' sines
    b1, _ = E.pipeline.closed_pitches(st, alpha, beta, bad)
    assert np.max(np.abs(b1 - b0)) > TOL


@pytest.mark.parametrize("n, masked", [(5, False), (14, True), (40, False)])
def test_the_kernels_laplacian_solve_is_superlus(n, masked):
    """One column of the joints' Laplacian (`linalg.lap_solve`: the kernel's double supernodal
    L D Lᵀ on SuperLU's ordering) against SuperLU's own solve, on right-hand sides as the heights
    and the joints have them (``Bᵀ v``: they sum to zero)."""
    valid = _mask(n) if masked else None
    st = E.structure.structure_of(n, n, valid)
    assert E.linalg.laplacian_kernel(st) is not None
    v = rng(n).normal(size=st.valid_links.size)
    b = st.incidence_T @ v
    x0, x1 = st.lap_lu.solve(b), E.linalg.lap_solve(st, b)
    d0, d1 = x0 - x0[0], x1 - x1[0]  # the heights' differences (the constant is the prior's)
    assert np.max(np.abs(d1 - d0)) <= TOL * np.max(np.abs(d0))
    B = np.stack([b, -2 * b, st.incidence_T @ np.cos(v)], axis=1)  # the joints' three columns at once
    X0, X1 = st.lap_lu.solve(B), E.linalg.lap_solve(st, B)
    D0, D1 = X0 - X0[0], X1 - X1[0]
    assert np.max(np.abs(D1 - D0)) <= TOL * np.max(np.abs(D0))
    many = np.repeat(b[:, None], 6, axis=1)  # more than four stay with SuperLU
    assert np.array_equal(E.linalg.lap_solve(st, many), st.lap_lu.solve(many))


def test_the_laplacian_comparison_sees_a_wrong_factor():
    st = E.structure.structure_of(14, 14, None)
    b = st.incidence_T @ rng(2).normal(size=st.valid_links.size)
    x0 = st.lap_lu.solve(b)
    val = E.linalg.laplacian_kernel(st)[1][1]
    k = int(np.argmax(np.abs(val)))
    kept = val[k]
    val[k] *= 1.000001  # one entry of L off by a millionth
    try:
        x1 = E.linalg.lap_solve(st, b)
    finally:
        val[k] = kept
    d0, d1 = x0 - x0[0], x1 - x1[0]
    assert np.max(np.abs(d1 - d0)) > TOL * np.max(np.abs(d0))


@pytest.mark.parametrize("prior", ["level", "adaptive"])
@pytest.mark.parametrize("n, shape, noise, masked", [(14, "cylinder", 1.0, False),
                                                     (20, "flat", 0.02, True),
                                                     (33, "gaussian", 3.0, False)])
def test_the_kernels_pair_weights_are_the_numpy_codes(prior, n, shape, noise, masked, monkeypatch):
    """The prior's pair weights in the kernel (``capsheet_pair_weights``) against `prior_weights`'
    numpy code on the same flatness: the same numbers to the bit (the same operations in the
    same order), with and without a rest shape."""
    r = noisy_readings(ideal_readings(make_sheet(shape, n, n, L, shear=0.1)), noise, rng(n))
    valid = _mask(n) if masked else np.ones(r.shape[0], bool)
    st = E.structure.structure_of(n, n, None if valid.all() else valid)
    norm = np.where(valid, np.linalg.norm(r, axis=1) / E.G0, 1.0)
    sigma = noise / 100
    monkeypatch.setattr(E.kernel, "USE_KERNEL", False)
    hu = E.priors.flatness(st, r, norm, sigma)
    assert 0.0 < hu.max() and (hu.min() < 0.5 or shape == "flat")
    for rest_given in (False, True):
        lam, w0 = E.priors.prior_weights(prior, st, r, norm, sigma, rest_given)
        w1 = E.priors._pair_weights_kernel(prior, st, hu, sigma, rest_given)
        assert np.array_equal(w1, w0)
    # the comparison sees a wrong weight: another share of the bending on tilted pairs
    monkeypatch.setattr(E.priors, "LEVEL_TILTED_SHARE", 0.004)
    w2 = E.priors._pair_weights_kernel(prior, st, hu, sigma, False)
    monkeypatch.setattr(E.priors, "LEVEL_TILTED_SHARE", 0.003)
    # ("adaptive" holds every bending pair alike: no share, the same weights)
    assert np.array_equal(w2, E.priors.prior_weights(prior, st, r, norm, sigma, False)[1]) == (
        prior == "adaptive")
