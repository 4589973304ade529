"""A warm chain stops after one chord step when its measured contraction says it may
(`solver.Contraction`, `solver.CHAIN_SAFETY`, `solver.CHAIN_REMEASURE`).

On a quiet stream (a 64x64 virtual sheet at its default 0.02 % g: readings a count of the ADC
apart) a warm solve's first step is ~3e-3 rad and its second ~7e-6, far below the 1e-4
tolerance: the second solve and the evaluation before it were a quarter of an estimate spent to
learn that the first step had converged. The chain now predicts the second step from the
contraction measured on the same factorisation (the larger of ``rho s`` and ``kappa s²``, times
`CHAIN_SAFETY`), and measures it again every `CHAIN_REMEASURE` snapshots.
"""

import numpy as np
import pytest

import host.analysis.estimator as E
from host.analysis.estimator import ShapeEstimator, estimate
from host.analysis.estimator.pipeline import WarmStart
from host.analysis.estimator.solver import CHAIN_REMEASURE, CHAIN_SAFETY, Contraction
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import noisy_readings
from virtual_sheet.shapes import make_sheet

L = 0.01
N = 24
QUIET = 0.03  # % of g per axis: about the quantisation of a 12-bit, ±2 g reading


def _stream(noise: float, count: int = 30, seed: int = 2, shape: str = "gaussian"):
    r0 = ideal_readings(make_sheet(shape, N, N, L))
    g = np.random.default_rng(seed)
    return [noisy_readings(r0, noise, g) for _ in range(count)]


def _chain(snaps, **kw):
    prev, out = None, []
    for r in snaps:
        prev = estimate(r, N, N, L, previous=prev, **kw)
        out.append(prev)
    return out


def _no_chain(monkeypatch):
    """Every solve measures (the chain is never passed): the steps before this change."""
    monkeypatch.setattr(E.solver, "CHAIN_REMEASURE", 0)


def test_the_contractions_prediction_is_the_larger_of_linear_and_quadratic():
    c = Contraction.measured(2e-3, 4e-6)
    assert c == Contraction(2e-3, 1.0, 0)
    tol = 1e-4
    # linear: 4 * 2e-3 * s; quadratic: 4 * s²  -> the quadratic rules above s = 2e-3
    assert c.predicts_converged(5e-3 - 1e-9, tol) and not c.predicts_converged(5.1e-3, tol)
    c_lin = Contraction(0.02, 1.0, 0)  # linear rules below s = 0.02
    assert not c_lin.predicts_converged(1.26e-3, tol) and c_lin.predicts_converged(1.24e-3, tol)
    assert CHAIN_SAFETY > 1.0
    assert Contraction.measured(0.0, 1e-6) is None and Contraction.measured(np.nan, 1e-6) is None


def test_a_quiet_stream_stops_after_one_step_and_measures_again_every_few_snapshots(monkeypatch):
    snaps = _stream(QUIET)
    got = _chain(snaps)
    its = [e.iterations for e in got]
    # after the cold start and its first warm snapshot (which measures): one step, CHAIN_REMEASURE
    # times, then a measuring snapshot of two, and so on
    first = its.index(1)
    assert first == 2 and its[:first] == [6, 2]
    period = [1] * CHAIN_REMEASURE + [2]
    assert its[first:] == (period * 10)[:len(its) - first]
    ages = [e.solution.contraction.age for e in got[first:first + CHAIN_REMEASURE + 1]]
    assert ages == list(range(1, CHAIN_REMEASURE + 1)) + [0]
    assert all(e.factorisations == 0 for e in got[1:])

    _no_chain(monkeypatch)
    ref = _chain(snaps)
    assert [e.iterations for e in ref][1:] == [2] * (len(snaps) - 1)
    # the one-step estimates differ from the two-step ones by far less than the noise moves an
    # estimate from one snapshot to the next, and they are as close to the truth
    diff = max(np.max(np.linalg.norm(a.joints - b.joints, axis=-1)) for a, b in zip(got, ref))
    jitter = np.median([np.max(np.linalg.norm(ref[k + 1].joints - ref[k].joints, axis=-1))
                        for k in range(2, len(ref) - 1)])
    assert 0.0 < diff < 0.05 * jitter
    truth = make_sheet("gaussian", N, N, L)

    def err(e):
        P = e.joints - e.joints.mean(axis=(0, 1)) - (truth - truth.mean(axis=(0, 1)))
        return float(np.mean(np.linalg.norm(P, axis=-1)))
    e_got = np.mean([err(e) for e in got[2:]])
    e_ref = np.mean([err(e) for e in ref[2:]])
    assert abs(e_got - e_ref) < 0.01 * e_ref


def test_a_noisy_stream_is_estimated_exactly_as_without_the_chain(monkeypatch):
    """At 1 % g the second step is 2-5 % of the first: the prediction never lets a solve stop
    early, and every estimate is the one made without it, to the bit."""
    snaps = _stream(1.0, count=16)
    got = _chain(snaps)
    _no_chain(monkeypatch)
    ref = _chain(snaps)
    assert all(e.iterations >= 2 for e in got[1:])
    for a, b in zip(got, ref):
        assert np.array_equal(a.joints, b.joints) and a.iterations == b.iterations


def test_a_change_of_shape_is_not_stopped_by_a_linear_guess(monkeypatch):
    """After a quiet chain, the bump rises by 3 %: a first step of ~8e-3 rad. The chain's linear
    contraction (~2.5e-3) would predict a second step of ~8e-5, under the 1e-4 tolerance; the
    curvature makes it ~1.4e-4 and the quadratic prediction sees it. The solve takes its
    second step: the same estimate as without the chain."""
    side = L * (N - 1)
    quiet = _stream(QUIET, count=12)
    r1 = noisy_readings(ideal_readings(make_sheet("gaussian", N, N, L, amplitude=1.03 * side / 4)),
                        QUIET, np.random.default_rng(3))
    seen = []
    real = E.yawproblem.YawProblem.chord_kernel

    def spy(self, *a):
        out = real(self, *a)
        seen.append(out[5])
        return out
    prev = _chain(quiet)[-1]
    chain = prev.solution.contraction
    monkeypatch.setattr(E.yawproblem.YawProblem, "chord_kernel", spy)
    got = estimate(r1, N, N, L, previous=prev)
    monkeypatch.undo()
    s1, s2 = seen[-1][:2] if E.kernel.USE_KERNEL else (None, None)
    if s1 is not None:
        assert CHAIN_SAFETY * chain.rho * s1 < 1e-4 < s2  # the linear guess would have stopped
    assert got.iterations >= 2
    _no_chain(monkeypatch)
    ref = estimate(r1, N, N, L, previous=prev)
    assert np.array_equal(got.joints, ref.joints) and got.iterations == ref.iterations


def test_the_kernel_and_the_python_loop_stop_alike(monkeypatch):
    if not E.kernel.USE_KERNEL:
        pytest.skip("the estimator's kernel is not built (pip install -e . builds it)")
    snaps = _stream(QUIET, count=14)
    got = _chain(snaps)
    monkeypatch.setattr(E.solver, "chord_in_kernel", lambda *a: False)
    ref = _chain(snaps)
    assert [e.iterations for e in got] == [e.iterations for e in ref]
    assert sum(e.iterations == 1 for e in got) >= 2 * CHAIN_REMEASURE
    for a, b in zip(got, ref):
        assert np.max(np.abs(a.joints - b.joints)) <= 1e-12
        ca, cb = a.solution.contraction, b.solution.contraction
        assert (ca is None) == (cb is None)
        if ca is not None:
            assert ca.age == cb.age and ca.rho == pytest.approx(cb.rho, rel=1e-6)


def test_the_chain_is_used_only_on_the_factorisation_it_was_measured_on():
    snaps = _stream(QUIET, count=4)
    est = _chain(snaps)[-1]
    sol = est.solution
    warm = WarmStart.of(est)
    assert warm.chain(sol.factorisation) is sol.contraction is not None
    assert warm.chain(None) is None
    assert warm.chain(("splu", None, None)) is None  # another factorisation
    old = WarmStart(warm.yaws, warm.joints, sol._replace(
        contraction=sol.contraction._replace(age=CHAIN_REMEASURE)), warm.valid)
    assert old.chain(sol.factorisation) is None
    assert WarmStart().chain(sol.factorisation) is None


def test_the_stateful_estimator_takes_the_same_steps():
    snaps = _stream(QUIET, count=12)
    ref = _chain(snaps)
    se = ShapeEstimator(N, N, L)
    got = [se.update(r) for r in snaps]
    assert [e.iterations for e in got] == [e.iterations for e in ref]
    for a, b in zip(got, ref):
        assert np.array_equal(a.joints, b.joints)
