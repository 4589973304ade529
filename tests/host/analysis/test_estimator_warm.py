"""Warm starts across changes of the links present (`pipeline.WarmStart.covering`).

A sheet whose chips start answering at different SYNCs is estimated on growing masks: islands of
links, each with yaws that agree with the others only up to a rotation. Warm-starting where they
join ended in a wrong minimum that every later estimate inherited (a 64x64 virtual sheet: residual
2,410 instead of 0.03 for the rest of the run, estimates of up to 3 s). A warm start now needs the
estimate it comes from to have had every link present; else the chain's fallback (the last
estimate that had them), else a cold start.
"""

import numpy as np
import pytest

from host.analysis.estimator import ShapeEstimator, estimate
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import noisy_readings
from virtual_sheet.shapes import make_sheet

L = 0.01
NOISE = 0.2  # % of g per axis


def staggered(shape: str, n: int, seed: int, steps: int = 30):
    """Readings and masks of a sheet whose chips start at random SYNCs over ``steps``, then a
    few SYNCs with all of them."""
    r0 = ideal_readings(make_sheet(shape, n, n, L))
    rng = np.random.default_rng(seed)
    start = rng.integers(0, steps, r0.shape[0])
    out = []
    for k in range(steps + 5):
        v = start <= k
        if v.any():
            out.append((noisy_readings(r0, NOISE, rng), v))
    return out, r0, rng


# (shape, n, seed): chains that ended in a wrong minimum before (residual 48, 33 against 0.04, 0.08)
CASES = [("cylinder", 16, 4), ("sphere", 16, 5)]


@pytest.mark.parametrize("shape,n,seed", CASES)
def test_a_chain_through_a_staggered_start_ends_where_a_cold_start_does(shape, n, seed):
    snaps, r0, rng = staggered(shape, n, seed)
    prev = None
    for r, v in snaps:
        prev = estimate(r, n, n, L, valid=v, previous=prev, bad_readings="mask")
    last_r = snaps[-1][0]
    cold = estimate(last_r, n, n, L)
    assert prev.valid.all()
    assert prev.residual < 1.5 * cold.residual, (prev.residual, cold.residual)
    assert np.max(np.linalg.norm(prev.joints - cold.joints, axis=2)) < 0.05 * L


@pytest.mark.parametrize("shape,n,seed", CASES)
def test_the_stateful_estimator_takes_the_same_starts(shape, n, seed):
    snaps, _, _ = staggered(shape, n, seed)
    est = ShapeEstimator(n, n, L)
    prev = None
    for r, v in snaps:
        got = est.update(r, valid=v)
        prev = estimate(r, n, n, L, valid=v, previous=prev, bad_readings="mask")
        assert np.array_equal(got.joints, prev.joints) and got.iterations == prev.iterations


def test_after_a_gap_the_chain_starts_from_the_last_estimate_that_had_every_link():
    n = 14
    r0 = ideal_readings(make_sheet("gaussian", n, n, L))
    rng = np.random.default_rng(2)
    gap = np.ones(r0.shape[0], bool)
    gap[: r0.shape[0] // 5] = False  # a gateway's links late once
    before = estimate(noisy_readings(r0, NOISE, rng), n, n, L)
    before = estimate(noisy_readings(r0, NOISE, rng), n, n, L, previous=before)
    holed = estimate(noisy_readings(r0, NOISE, rng), n, n, L, valid=gap, previous=before, bad_readings="mask")
    assert holed.warm_fallback.solution is before.solution  # the holed one covers less: kept
    r = noisy_readings(r0, NOISE, rng)
    after = estimate(r, n, n, L, previous=holed)
    from_before = estimate(r, n, n, L, previous=before)
    cold = estimate(r, n, n, L)
    assert np.array_equal(after.joints, from_before.joints) and after.iterations == from_before.iterations
    assert after.iterations < cold.iterations
    # a chain that never had every link: a cold start
    assert np.array_equal(estimate(r, n, n, L, previous=estimate(r, n, n, L, valid=gap, bad_readings="mask")).joints,
                          cold.joints)
