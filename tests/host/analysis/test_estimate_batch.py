"""`estimate_batch`: many snapshots per numpy pass, each what `estimate` would give.

Truth: exact Chebyshev nets (`virtual_sheet.shapes.make_sheet`), sheared, 1 % g noise (seeded).
The reference for "what `estimate` would give" is the minimiser of the same cost solved to 1e-12
rad by `estimate` on its own (its accuracy against the truth is tested in test_estimator.py):
both the one-at-a-time loop and the batch stop within their tolerance of it, and the bounds
below say how far (0.03 % of the side, against the 0.1-1 % the targets allow for the error).
"""

from __future__ import annotations

import numpy as np
import pytest

from host.analysis import estimator as E
from host.estimator import error_percent_of_side, estimate, estimate_batch
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import noisy_readings
from virtual_sheet.shapes import make_sheet

L = 0.01
#: max joint distance from the exact minimiser, % of side, for any snapshot
NEAR_EXACT_PCT = 0.03


def rng(seed: int) -> np.random.Generator:
    return np.random.Generator(np.random.MT19937(seed))


def snapshots(n: int, count: int, seed: int, shape: str = "gaussian", shear: float = 0.2,
              noise: float = 1.0):
    P = make_sheet(shape, n, n, L, shear=shear)
    r0 = ideal_readings(P)
    g = rng(seed)
    return P, np.stack([noisy_readings(r0, noise, g) for _ in range(count)])


def exact(readings, n, previous=None, valid=None, **kw):
    """The same cost minimised to 1e-12 rad, one snapshot at a time."""
    old = E.solver.YAW_TOL_RAD, E.solver.YAW_TOL_NOISE
    E.solver.YAW_TOL_RAD, E.solver.YAW_TOL_NOISE = 1e-12, 0.0
    try:
        out, prev = [], previous
        for k, r in enumerate(readings):
            prev = estimate(r, n, n, L, previous=prev,
                            valid=None if valid is None else valid[k], **kw)
            out.append(prev)
        return out
    finally:
        E.solver.YAW_TOL_RAD, E.solver.YAW_TOL_NOISE = old


def pct_from(a, b, n) -> np.ndarray:
    return np.array([np.abs(x.joints - y.joints).max() for x, y in zip(a, b)]) / (L * (n - 1)) * 100


@pytest.mark.parametrize("n, batch", [(14, 8), (14, 16), (20, 5)])
def test_batch_stops_as_near_the_minimiser_as_one_at_a_time(n, batch):
    P, R = snapshots(n, 48, seed=n + batch)
    first = estimate(R[-1], n, n, L)  # a cold estimate, its factorisation made far from these
    out = estimate_batch(R, n, n, L, previous=first, batch=batch)
    assert len(out) == R.shape[0]
    assert all(e.timings.get("batched") == 1.0 for e in out)  # none needed `estimate` alone
    ref = exact(R, n, previous=first)
    assert pct_from(out, ref, n).max() <= NEAR_EXACT_PCT
    # and against the truth: the error the loop makes, to the hundredth of a per cent
    err = np.array([error_percent_of_side(e.joints, P, L).mean() for e in out])
    err_ref = np.array([error_percent_of_side(e.joints, P, L).mean() for e in ref])
    assert np.abs(err - err_ref).max() <= 0.01
    assert err.mean() <= 1.0  # the bound at 5 % g; this is 1 % g


def test_batch_on_a_stale_factorisation_does_not_stop_early():
    """A `previous` whose factorisation was made at the rest layout (its cold start converged on
    that one factorisation): the shared chord steps then contract some snapshots slowly and
    unevenly (0.074, 0.78, 0.096 for one of them), and a stopping rule that trusted the last
    contraction stopped 1.3e-3 rad short (0.12 % of side). The factorisation is the former
    default prior's ("adaptive"): its cold start converges on the one made at the rest layout,
    where the default's takes a second one nearer the shape."""
    n = 32
    r0 = ideal_readings(make_sheet("gaussian", n, n, L))
    g = rng(1)
    R = np.stack([noisy_readings(r0, 1.0, g) for _ in range(128)])
    first = estimate(R[-1], n, n, L, prior="adaptive")
    assert first.factorisations == 1  # the case: its factorisation is the cold start's
    out = estimate_batch(R[:16], n, n, L, previous=first, batch=16)
    ref = exact(R[:16], n, previous=first)
    assert pct_from(out, ref, n).max() <= NEAR_EXACT_PCT


def test_batch_follows_a_moving_sheet():
    """Every group starts from the estimate before it: a bump that grows over the run."""
    n = 12
    R = []
    g = rng(5)
    for k in range(40):
        P = make_sheet("gaussian", n, n, L, shear=0.1, amplitude=0.004 + 0.0004 * k)
        R.append(noisy_readings(ideal_readings(P), 1.0, g))
    R = np.stack(R)
    out = estimate_batch(R, n, n, L, batch=10)
    ref = exact(R, n)
    assert pct_from(out, ref, n).max() <= NEAR_EXACT_PCT
    err_last = error_percent_of_side(out[-1].joints, P, L).mean()
    assert err_last <= 1.0


def test_a_dead_chip_inside_a_group_is_masked_in_its_snapshot_only():
    n = 10
    _, R = snapshots(n, 12, seed=3)
    R[5, 17] = 0.0  # a dead chip in snapshot 5
    out = estimate_batch(R, n, n, L, batch=6, bad_readings="mask")
    assert not out[5].valid[17] and out[5].valid.sum() == out[5].valid.size - 1
    assert all(e.valid.all() for k, e in enumerate(out) if k != 5)
    assert out[5].timings.get("batched") is None  # estimated on its own
    ref = exact(R[5:6], n, previous=out[4], bad_readings="mask")
    assert pct_from(out[5:6], ref, n).max() <= NEAR_EXACT_PCT
    with pytest.raises(ValueError, match=r"snapshot 5: Implausible readings on links \[17\]"):
        estimate_batch(R, n, n, L, batch=6)


def test_a_mask_shared_by_every_snapshot_stays_batched():
    n = 10
    _, R = snapshots(n, 16, seed=9)
    valid = np.ones(R.shape[1], bool)
    valid[[3, 40, 41]] = False
    R[:, ~valid] = np.nan  # what a missing link reads is not looked at
    out = estimate_batch(R, n, n, L, valid=valid, batch=8)
    # without `previous` the first is a cold start, alone; the rest start from it, in groups
    assert out[0].timings.get("batched") is None
    assert all(e.timings.get("batched") == 1.0 for e in out[1:])
    assert all(np.isnan(e.alpha[~valid]).all() and (e.valid == valid).all() for e in out)
    ref = exact(R, n, valid=np.broadcast_to(valid, (R.shape[0], valid.size)))
    assert pct_from(out, ref, n).max() <= NEAR_EXACT_PCT


def test_batched_estimates_warm_start_and_give_uncertainty():
    n = 10
    _, R = snapshots(n, 9, seed=11)
    out = estimate_batch(R[:8], n, n, L, batch=4)
    nxt = estimate(R[8], n, n, L, previous=out[-1])
    assert nxt.factorisations == 0  # the group's factorisation is reused
    alone = estimate(R[3], n, n, L, previous=out[2])
    np.testing.assert_allclose(out[3].yaw_std, alone.yaw_std, rtol=0.02)


@pytest.mark.parametrize("bad, match", [
    (np.zeros((4, 5, 3)), r"shape \(S, 180, 3\)"),
    (np.zeros((4, 180, 3), complex), "dtype complex"),
    (np.zeros((180, 3)), r"shape \(S, 180, 3\)"),
])
def test_wrong_input_is_a_value_error_that_names_it(bad, match):
    with pytest.raises(ValueError, match=match):
        estimate_batch(bad, 10, 10, L)


def test_wrong_mask_and_batch_are_value_errors():
    _, R = snapshots(10, 3, seed=1)
    with pytest.raises(ValueError, match="boolean mask"):
        estimate_batch(R, 10, 10, L, valid=np.ones((3, 180)))
    with pytest.raises(ValueError, match=r"shape \(3, 180\) or \(180,\)"):
        estimate_batch(R, 10, 10, L, valid=np.ones((2, 180), bool))
    with pytest.raises(ValueError, match="batch"):
        estimate_batch(R, 10, 10, L, batch=0)
    # with a `previous` every snapshot is batched and none passes `estimate`'s checks: the
    # noise was taken as it came (-1 % g on every estimate)
    with pytest.raises(ValueError, match=r"Invalid noise_pct_g: -1\.0"):
        estimate_batch(R, 10, 10, L, previous=estimate(R[0], 10, 10, L), noise_pct_g=-1.0)
    with pytest.raises(ValueError, match="Invalid bad_readings"):
        estimate_batch(R, 10, 10, L, bad_readings="drop")
    assert estimate_batch(R[:0], 10, 10, L) == []


def test_roll_gradient_without_the_jacobian_equals_jt_r():
    """`YawProblem._roll_grad` (reverse mode) against ``Jᵀ r`` from the Jacobian rows."""
    n = 9
    _, R = snapshots(n, 2, seed=2)
    g = rng(4)
    for mask in (None, np.arange(R.shape[1]) % 7 != 3):
        st = E.structure.structure_of(n, n, mask)
        a, b = E.roll_pitch(R[0])
        prob = E.yawproblem.YawProblem(st, a, b, st.rest_yaw, np.full(st.n_var, 1e-10),
                                       np.full(st.pairs.shape[0], 1e-4))
        gamma = st.rest_yaw + 0.3 * g.standard_normal(st.n_links)
        c1, g1, blocks = prob.evaluate(gamma, jac=True)
        c2, g2, none = prob.evaluate(gamma, jac=False)
        assert none is None and blocks is not None
        assert abs(c1 - c2) <= 1e-12 * abs(c1)
        np.testing.assert_allclose(g2, g1, rtol=0, atol=1e-12 * np.abs(g1).max())


@pytest.mark.parametrize("n_valid", [1, 2, 3, 6])
def test_a_few_valid_links_and_no_model_cell_estimate_alike_batched_and_alone(n_valid, monkeypatch):
    # no cell with all four links: no roll term at all (numpy's bincount of nothing is int64, and
    # the batched gradient sums raised a casting error on it)
    from host.analysis import estimator as E
    from virtual_sheet.geometry import ideal_readings
    from virtual_sheet.shapes import make_sheet

    r = ideal_readings(make_sheet("gaussian", 5, 5, 0.01))
    v = np.zeros(len(r), bool)
    v[:n_valid] = True
    batch = E.estimate_batch(np.stack([r, r]), 5, 5, 0.01, valid=np.stack([v, v]))
    monkeypatch.setattr(E.kernel, "USE_KERNEL", False)  # the numpy path of one snapshot too
    alone = E.estimate(r, 5, 5, 0.01, valid=v)
    for b in batch:
        assert np.isfinite(b.joints).all()
        np.testing.assert_allclose(b.joints, alone.joints, atol=1e-9)
