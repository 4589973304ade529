"""`ShapeEstimator`: the stateful estimator of a stream, holding its warm start itself.

Truth: exact Chebyshev nets (`virtual_sheet.shapes.make_sheet`), sheared, 1 % g noise (seeded
MT19937). The reference is `estimate(..., previous=last)` in a loop, the call it replaces: the same
arithmetic, so the comparisons are exact (array_equal), not within a tolerance.
"""

from __future__ import annotations

import numpy as np
import pytest

from host.estimator import ShapeEstimator, error_percent_of_side, estimate
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import noisy_readings
from virtual_sheet.shapes import make_sheet

L = 0.01


def snapshots(n: int, count: int, seed: int, shear: float = 0.2):
    P = make_sheet("gaussian", n, n, L, shear=shear)
    r0 = ideal_readings(P)
    g = np.random.Generator(np.random.MT19937(seed))
    return P, np.stack([noisy_readings(r0, 1.0, g) for _ in range(count)])


def same(a, b) -> bool:
    """Every output of two estimates equal, NaN where NaN."""
    arrays = ("joints", "directions", "normals", "yaws", "alpha", "beta", "solvability", "valid")
    return (all(np.array_equal(getattr(a, k), getattr(b, k), equal_nan=True) for k in arrays)
            and a.residual == b.residual and a.iterations == b.iterations
            and a.factorisations == b.factorisations)


def chain(R, n, valid=None, **kw):
    out, prev = [], None
    for k, r in enumerate(R):
        prev = estimate(r, n, n, L, previous=prev, valid=None if valid is None else valid[k], **kw)
        out.append(prev)
    return out


@pytest.mark.parametrize("n, kw", [(12, {}), (14, {"prior": "level"}), (10, {"model": "eq6"})])
def test_updates_equal_the_previous_chain_exactly(n, kw):
    P, R = snapshots(n, 12, seed=n)
    est = ShapeEstimator(n, n, L, **kw)
    got = [est.update(r, now=0.1 * k) for k, r in enumerate(R)]
    ref = chain(R, n, **kw)
    assert all(same(a, b) for a, b in zip(got, ref))
    # the warm start was used: after the cold first snapshot, the factorisation is mostly reused
    assert got[0].factorisations >= 1
    assert sum(e.factorisations for e in got[1:]) < len(got) - 1
    assert est.updates == 12 and est.last is got[-1] and est.last_update == pytest.approx(1.1)
    assert error_percent_of_side(got[-1].joints, P, L).mean() <= 1.0


def test_a_new_mask_rebuilds_the_structure_and_refactorises():
    n = 12
    _, R = snapshots(n, 9, seed=3)
    nl = R.shape[1]
    hole = np.ones(nl, bool)
    hole[[5, 40]] = False
    masks = [None, None, None, hole, hole, hole, None, None, None]
    est = ShapeEstimator(n, n, L)
    got, structures = [], []
    for r, v in zip(R, masks):
        got.append(est.update(r, valid=v))
        structures.append(est.structure)
    ref = chain(R, n, valid=masks)
    assert all(same(a, b) for a, b in zip(got, ref))
    full, holed = structures[0], structures[3]
    assert structures[1] is full and structures[2] is full  # unchanged mask: held
    assert holed is not full and np.array_equal(holed.valid, hole)
    assert structures[4] is holed and structures[5] is holed
    assert structures[6].valid.all() and structures[6] is not holed
    # a factorisation belongs to its structure: the hole makes a new one; with every link back the
    # chain starts from its fallback, the last estimate that had them all (#2): its structure,
    # whose factorisation it may reuse, never the holed one's (WarmStart.covering)
    assert got[3].factorisations >= 1
    assert got[5].warm_fallback.solution is got[2].solution
    assert got[6].solution.structure is got[2].solution.structure
    assert got[6].solution.factorisation is not got[5].solution.factorisation
    assert np.isnan(got[3].normals[[5, 40]]).all() and not got[3].valid[[5, 40]].any()
    assert est.factorisation is got[-1].solution.factorisation


def test_reset_starts_cold_and_a_rejected_snapshot_keeps_the_warm_start():
    n = 10
    _, R = snapshots(n, 6, seed=7)
    est = ShapeEstimator(n, n, L)
    for r in R[:3]:
        est.update(r)
    bad = R[3].copy()
    bad[17] = np.nan
    with pytest.raises(ValueError, match=r"Non-finite readings on valid links \[17\]"):
        est.update(bad)
    assert est.updates == 3
    nxt = est.update(R[3])
    assert same(nxt, estimate(R[3], n, n, L, previous=chain(R[:3], n)[-1]))
    est.reset()
    assert est.last is None and est.updates == 0 and est.factorisation is None
    assert same(est.update(R[4]), estimate(R[4], n, n, L))


def test_the_options_are_checked_once_at_construction():
    with pytest.raises(ValueError, match="Invalid link_length"):
        ShapeEstimator(4, 4, -1.0)
    with pytest.raises(ValueError, match="Invalid method"):
        ShapeEstimator(4, 4, L, method="fast")
    with pytest.raises(ValueError, match="Invalid rows"):
        ShapeEstimator(1, 4, L)
    with pytest.raises(ValueError, match="Invalid noise_pct_g"):
        ShapeEstimator(4, 4, L, noise_pct_g=-1)
    with pytest.raises(ValueError, match=r"Expected `readings` to have shape \(24, 3\)"):
        ShapeEstimator(4, 4, L).update(np.zeros((5, 3)))


def test_the_paper_method_has_no_warm_start_and_no_missing_links():
    n = 6
    _, R = snapshots(n, 2, seed=11, shear=0.0)
    est = ShapeEstimator(n, n, L, method="paper")
    a = est.update(R[0])
    assert same(a, estimate(R[0], n, n, L, method="paper"))
    valid = np.ones(R.shape[1], bool)
    valid[0] = False
    with pytest.raises(ValueError, match="does not support missing links"):
        est.update(R[1], valid=valid)


def test_a_rest_shape_is_the_prior_target_as_in_estimate():
    n = 8
    _, R = snapshots(n, 5, seed=13, shear=0.1)
    rest = estimate(R[0], n, n, L)
    est = ShapeEstimator(n, n, L, rest=rest)
    got = [est.update(r) for r in R[1:]]
    assert all(same(a, b) for a, b in zip(got, chain(R[1:], n, rest=rest)))
    # the rest changes the answer (the comparison could fail): not the default target
    assert not np.array_equal(got[0].yaws, estimate(R[1], n, n, L).yaws)
    with pytest.raises(ValueError, match="Invalid rest: its yaws contain NaN or inf"):
        ShapeEstimator(n, n, L, rest=np.full(R.shape[1], np.nan))


def _live_stream(n: int, count: int, seed: int = 7):
    """Consecutive snapshots at 145 Hz of a bump rising (`GrowScene`, from t = 1 s), through the
    virtual chips' 12-bit ADC with `capsheet virtual`'s default noise: what the estimator process
    is sent live."""
    from protocol.constants import counts_to_si
    from virtual_sheet.sensor import SensorModel
    from virtual_sheet.shapes import GrowScene

    scene, adc = GrowScene(n, n, L), SensorModel(noise_pct_g=0.02)
    g = np.random.Generator(np.random.MT19937(seed))
    return [counts_to_si(adc.sample(ideal_readings(scene.joints(1.0 + k / 145.0)), g)[0])
            for k in range(count)]


def test_a_live_stream_is_estimated_as_a_cold_estimate_of_each_snapshot(monkeypatch):
    """Every warm estimate of a moving sheet's stream (one or two chord steps each, on kept
    factorisations) is within the solver's bound of the cold estimate of the same readings (from
    the rest layout, factorised afresh): 0.03 % of the side, the bound test_estimate_batch.py
    holds every path to. A chain that stops at a loose tolerance (1e-2 rad) is not."""
    n = 24
    R = _live_stream(n, 24)

    def far(monkeypatch_tol=None):
        if monkeypatch_tol is not None:
            monkeypatch.setattr("host.analysis.estimator.solver.YAW_TOL_RAD", monkeypatch_tol)
        est = ShapeEstimator(n, n, L)
        got = [est.update(r) for r in R]
        monkeypatch.undo()
        cold = [estimate(R[k], n, n, L) for k in range(1, len(R), 4)]
        return max(np.abs(got[k].joints - c.joints).max()
                   for k, c in zip(range(1, len(R), 4), cold)) / ((n - 1) * L) * 100, got, cold
    pct, got, cold = far()
    assert pct <= 0.03
    # warm: a few chord steps on kept factorisations, a cold solve several and its own factorisations
    assert np.mean([e.iterations for e in got[2:]]) < np.mean([c.iterations for c in cold])
    assert sum(e.factorisations for e in got[2:]) < sum(c.factorisations for c in cold)
    assert far(1e-2)[0] > 0.03  # the comparison sees an early stop


@pytest.mark.parametrize("axis, bad", [(0, np.nan), (1, np.inf), (2, -np.inf)])
def test_a_reading_with_one_axis_not_finite_is_named_unless_masked(axis, bad):
    n = 6
    _, R = snapshots(n, 1, seed=2)
    r = R[0].copy()
    r[9, axis] = bad
    with pytest.raises(ValueError, match=r"Non-finite readings on valid links \[9\]"):
        estimate(r, n, n, L)
    valid = np.ones(r.shape[0], bool)
    valid[9] = False
    assert np.all(np.isfinite(estimate(r, n, n, L, valid=valid).joints))
