"""The kernel's factorisation of the yaw problem's Gauss-Newton matrix (`linalg._kernel_factor`,
``capsheet_ldl_factor``) against SuperLU's of the same matrix.

Two independent factorisations: SuperLU's supernodal LU (no pivoting, the structure's ordering)
and the kernel's left-looking supernodal L D Lᵀ on the supernodes SuperLU's first factor gave.
Metric: D relative to SuperLU's U diagonal, L's entries (to 1), and solves relative to the
solution's largest entry; tolerance 1e-10 (rounding: they sum in different orders; measured
2e-12 at 64x64). A matrix that is not positive definite, or has an entry outside the factor's
pattern, is left to SuperLU. Whole warm chains on a moving sheet give the same joints (1e-8 of
the side, the float32 solve's level) and the same iteration counts with either.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse.linalg import splu

from host.analysis import estimator as E
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import noisy_readings
from virtual_sheet.shapes import GrowScene, make_sheet

pytestmark = pytest.mark.skipif(not E.USE_KERNEL, reason="the estimator's kernel is not built")

L = 0.01
TOL = 1e-10


def rng(seed: int) -> np.random.Generator:
    return np.random.Generator(np.random.MT19937(seed))


def _matrix(n, masked=False, seed=3):
    """(structure, its Gauss-Newton matrix at an estimate, the supernodes of SuperLU's factor)."""
    P = make_sheet("saddle", n, n, L, shear=0.2)
    r = noisy_readings(ideal_readings(P), 1.0, rng(seed))
    valid = None
    if masked:
        valid = np.ones(r.shape[0], bool)
        valid[rng(seed).choice(valid.size, size=valid.size // 20, replace=False)] = False
    st, _, prob, gamma = E.estimate(r, n, n, L, valid=valid).solution[:4]
    A = prob.matrix(prob.evaluate(gamma)[2])
    lu = splu(A, permc_spec="NATURAL", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
    return st, A, lu


def _superlu_ldl(lu, sym):
    """SuperLU's L (in the kernel's supernodal layout, double) and D."""
    L_ = lu.L
    val = np.zeros(max(sym["n_val"], 1))
    fb = E.kernel.ffi.from_buffer
    E.kernel.lib.capsheet_ldl_fill_d(
        sym["n_super"], fb("int32_t[]", np.ascontiguousarray(L_.indptr, np.int32)),
        fb("int32_t[]", np.ascontiguousarray(L_.indices, np.int32)),
        fb("double[]", np.ascontiguousarray(L_.data, np.float64)), *sym["c_args"][:5],
        fb("int32_t[]", np.full(lu.shape[0], -1, np.int32)), fb("double[]", val))
    return val, lu.U.diagonal()


def _differences(A, lu, got, seed=1):
    """(D, L, one solve, three solves) of the kernel's factorisation ``got`` against SuperLU's."""
    sym = got[1].sym
    val, d = _superlu_ldl(lu, sym)
    b = rng(seed).normal(size=(A.shape[0], 3))
    x1, x3 = lu.solve(b[:, 0]), lu.solve(b)
    return (np.max(np.abs(got[1].diag - d) / np.abs(d)), np.max(np.abs(got[1].lval - val)),
            np.max(np.abs(got[1].solve(b[:, 0]) - x1)) / np.max(np.abs(x1)),
            np.max(np.abs(got[1].solve(b) - x3)) / np.max(np.abs(x3)))


@pytest.mark.parametrize("n,masked", [(5, False), (14, False), (14, True), (32, False),
                                      (40, True)])  # 32 and 40: nested dissection ordering
def test_the_kernels_factorisation_is_superlus(n, masked):
    st, A, lu = _matrix(n, masked)
    got = E.linalg._kernel_factor(A, E.linalg.structural_symbolic(st))
    assert got is not None and isinstance(got[1], E.linalg.KernelLDL)
    assert max(_differences(A, lu, got)) <= TOL
    # the float32 values the chord steps' solve reads are SuperLU's rounded alike
    ref = E.linalg._triangular(lu, st)
    assert np.max(np.abs(got[2][0][0] - ref[0][0])) <= 2.0 ** -23
    b = rng(2).normal(size=A.shape[0])
    x = lu.solve(b)
    assert np.max(np.abs(E.linalg.solve(got, b) - x)) <= 1e-6 * np.max(np.abs(x))


def test_the_factorisation_comparison_sees_a_wrong_matrix():
    st, A, lu = _matrix(14)
    B = A.tocsc(copy=True)
    k = int(np.flatnonzero(B.indices[B.indptr[3]:B.indptr[4]] != 3)[0]) + B.indptr[3]
    i = B.indices[k]
    B[i, 3] = B[3, i] = 1.001 * A[i, 3]  # one off-diagonal pair off by 0.1 %
    got = E.linalg._kernel_factor(B.tocsc(), E.linalg.structural_symbolic(st))
    assert got is not None and max(_differences(A, lu, got)) > TOL


def test_a_matrix_that_is_not_positive_definite_or_outside_the_pattern_goes_to_superlu():
    st, A, lu = _matrix(14)
    sym = E.linalg.structural_symbolic(st)
    B = A.tocsc(copy=True)
    B[5, 5] = -1.0
    assert E.linalg._kernel_factor(B.tocsc(), sym) is None
    fac = E.linalg.factorise(st, B.tocsc())
    assert type(fac[1]).__name__ == "SuperLU"
    C = A.tolil(copy=True)  # an entry where the factor has none (the first and the last variable)
    C[0, A.shape[0] - 1] = C[A.shape[0] - 1, 0] = 1e-3
    assert E.linalg._kernel_factor(C.tocsc(), sym) is None
    assert isinstance(E.linalg.factorise(st, A)[1], E.linalg.KernelLDL)


def _chain(n, snaps):
    est = E.ShapeEstimator(n, n, L)
    return [est.update(r) for r in snaps]


@pytest.mark.parametrize("n", [14, 24])
def test_a_moving_sheets_chain_is_the_same_with_the_kernels_factorisations(n, monkeypatch):
    scene = GrowScene(n, n, L)
    g = rng(n)
    snaps = [noisy_readings(ideal_readings(scene.joints(1.0 + k / 145.0)), 0.5, g)
             for k in range(60)]
    E.structure.cached_structure.cache_clear()
    monkeypatch.setattr(E.linalg, "KERNEL_FACTOR", False)
    ref = _chain(n, snaps)
    E.structure.cached_structure.cache_clear()
    monkeypatch.setattr(E.linalg, "KERNEL_FACTOR", True)
    new = _chain(n, snaps)
    assert sum(e.factorisations for e in new) >= 3  # the stream refactorises (else no test)
    # the kernel's from the first (SuperLU's first factor gives only its supernodes)
    assert {type(e.solution.factorisation[1]).__name__ for e in ref} == {"SuperLU"}
    assert {type(e.solution.factorisation[1]).__name__ for e in new} == {"KernelLDL"}
    side = (n - 1) * L
    for a, b in zip(ref, new):
        assert (a.iterations, a.factorisations) == (b.iterations, b.factorisations)
        assert np.max(np.abs(a.joints - b.joints)) <= 1e-8 * side


def test_an_estimate_does_not_depend_on_what_its_structure_factorised_before():
    """A level sheet's matrix has zeros its factor then lacks: the supernodes are the
    structure's (every entry nonzero), not those of whichever matrix came first."""
    n = 6
    P = make_sheet("saddle", n, n, L, shear=0.2)
    r = noisy_readings(ideal_readings(P), 1.0, rng(5))
    flat = np.tile([0.0, 0.0, 9.80665], (r.shape[0], 1))
    E.structure.cached_structure.cache_clear()
    first = E.estimate(r, n, n, L)
    E.structure.cached_structure.cache_clear()
    E.estimate(flat, n, n, L)
    after = E.estimate(r, n, n, L)
    assert isinstance(after.solution.factorisation[1], E.linalg.KernelLDL)
    assert np.array_equal(first.joints, after.joints) and first.iterations == after.iterations
