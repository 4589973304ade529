"""`host.workers.estimate_worker.EstimatorProcess`: the estimates a child process makes are the ones this
process makes, in order, and a snapshot it cannot estimate is said, not fatal."""

from __future__ import annotations

import numpy as np
import pytest

from host.snapshots.snapshot import LatticeSnapshot
from host.analysis.estimator import estimate
from host.workers.estimate_worker import EstimatorProcess
from virtual_sheet.sheet import VirtualSheet


def _snap(counter: int, readings: np.ndarray, valid: np.ndarray) -> LatticeSnapshot:
    n = readings.shape[0]
    return LatticeSnapshot(counter, float(counter), 0.0, readings, valid, np.zeros(n, np.uint8), bool(valid.all()), 0.0)


@pytest.fixture
def worker():
    w = EstimatorProcess(5, 6, 0.01, max_in_flight=3)
    yield w
    w.close()


def test_estimates_match_this_process_in_order(worker):
    sheet = VirtualSheet("gaussian", "5x6", seed=3, noise=1.0)
    n = sheet.lattice.n_links
    rng = np.random.default_rng(7)
    g = sheet.joints()  # (rows, cols, 3): only the shape's size is used
    assert g.shape == (5, 6, 3)
    base, _ = sheet.counts_at(0.0)
    readings = 9.80665 * base / np.linalg.norm(base.astype(float), axis=1, keepdims=True)
    snaps, got = [], []
    for k in range(7):
        valid = np.ones(n, bool)
        if k == 3:
            valid[[2, 11]] = False  # a mask that changes
        snaps.append(_snap(100 + k, readings + rng.normal(0, 0.02, readings.shape), valid))
    for s in snaps:
        while not worker.free:
            got += worker.results(5.0)
        worker.submit(s, uncertainty=(s.counter == 101))
    got += worker.close()
    assert [e.counter for e in got] == [s.counter for s in snaps]
    previous = None
    for k, (s, e) in enumerate(zip(snaps, got)):
        r, v = s.readings, s.valid
        if k == 3:  # links 2 and 11 missing for one snapshot: estimated from their last readings (held)
            r = r.copy()
            r[[2, 11]] = snaps[2].readings[[2, 11]]
            v = np.ones(n, bool)
        mine = estimate(r, 5, 6, 0.01, valid=v, previous=previous, bad_readings="mask")
        previous = mine
        np.testing.assert_array_equal(e.joints, mine.joints)  # the same arithmetic, raw float64 over the pipe
        np.testing.assert_array_equal(e.valid, mine.valid)
        assert e.iterations == mine.iterations and e.method == mine.method
        assert e.held == (2 if k == 3 else 0)
    assert worker.held_links == 2 and worker.held_estimates == 1
    with_std = [e for e in got if "joint_std" in e.__dict__]
    assert [e.counter for e in with_std] == [101]
    np.testing.assert_allclose(with_std[0].joint_std, estimate(snaps[1].readings, 5, 6, 0.01, valid=snaps[1].valid,
                                                               previous=estimate(snaps[0].readings, 5, 6, 0.01)).joint_std,
                               rtol=1e-9)
    assert got[0].yaw_std is None  # not asked: absent, as an uncomputed cached property


def test_a_snapshot_that_cannot_be_estimated_is_said_and_the_next_is_made(worker):
    n = 5 * 5 + 6 * 4
    bad = np.full((n, 3), 100.0)  # |s| ~ 17.7 g on every link: nothing left to estimate
    good = np.tile([0.0, 0.0, 9.80665], (n, 1))
    worker.submit(_snap(1, bad, np.ones(n, bool)))
    worker.submit(_snap(2, good, np.ones(n, bool)))
    got = worker.close()
    assert [e.counter for e in got] == [1, 2]
    assert got[0].error and "Implausible" in got[0].error or "valid" in got[0].error, got[0].error
    assert not got[1].error and got[1].joints.shape == (5, 6, 3)
    assert worker.failed == 1 and worker.made == 1


def test_a_snapshot_of_another_lattice_is_refused(worker):
    with pytest.raises(ValueError, match="lattice of 49 links"):
        worker.submit(_snap(1, np.zeros((10, 3)), np.ones(10, bool)))


def test_the_child_warms_up_first_and_its_uncertainty_cost_starts_the_rule():
    """Before its first request the child estimates a flat sheet and its uncertainty (a host makes
    the process before bring-up: the structure and the first uncertainty, 1-2 s at 64x64, are not
    made in the first seconds of streaming). The warm-up is not an estimate (not returned, not
    counted); its uncertainty's cost starts the rule, so the next uncertainty is due only once
    that cost is under `UNCERTAINTY_SHARE` of the time since."""
    import time

    from host.workers.estimate_worker import UNCERTAINTY_SHARE

    w = EstimatorProcess(5, 6, 0.01, max_in_flight=3)
    try:
        assert not w.uncertainty_due(time.monotonic() + 1e6, 0.0)  # not before the warm-up's
        got = []
        t_end = time.monotonic() + 60.0
        while not w.warm and time.monotonic() < t_end:
            got += w.results(1.0)
        assert w.warm and w.warmup_error == "" and got == []
        assert w.made == 0 and w.busy_s == 0.0 and w.uncertainties == 0 and w.free
        cost, t = w.uncertainty_cost_s, w.last_uncertainty_t
        assert 0.0 < cost < 60.0 and t > 0.0
        assert not w.uncertainty_due(t + 0.99 * cost / UNCERTAINTY_SHARE, 0.0)
        assert w.uncertainty_due(t + 1.01 * cost / UNCERTAINTY_SHARE, 0.0)
        n = 5 * 5 + 6 * 4
        w.submit(_snap(7, np.tile([0.0, 0.0, 9.80665], (n, 1)), np.ones(n, bool)))
        [e] = w.close()
        assert e.counter == 7 and not e.error and w.made == 1
    finally:
        w.close()


def test_a_link_missing_longer_than_the_hold_leaves_the_mask():
    """Link 4 missing from snapshot 1 on: held (estimated from its last reading) for HOLD_SNAPSHOTS
    snapshots, then estimated without (its own mask); the other links always present."""
    from host.workers.estimate_worker import HOLD_SNAPSHOTS
    sheet = VirtualSheet("gaussian", "5x6", seed=4, noise=1.0)
    n = sheet.lattice.n_links
    base, _ = sheet.counts_at(0.0)
    readings = 9.80665 * base / np.linalg.norm(base.astype(float), axis=1, keepdims=True)
    w = EstimatorProcess(5, 6, 0.01, max_in_flight=4)
    got = []
    try:
        for k in range(HOLD_SNAPSHOTS + 3):
            valid = np.ones(n, bool)
            r = readings.copy()
            if k >= 1:
                valid[4] = False
                r[4] = np.nan  # as the aggregator sends a missing link
            while not w.free:
                got += w.results(5.0)
            w.submit(_snap(k, r, valid))
    finally:
        got += w.close(30.0)
    assert [e.counter for e in got] == list(range(HOLD_SNAPSHOTS + 3)) and not any(e.error for e in got)
    assert [e.held for e in got] == [0] + [1] * HOLD_SNAPSHOTS + [0, 0]
    assert [bool(e.valid[4]) for e in got] == [True] * (HOLD_SNAPSHOTS + 1) + [False, False]
    assert all(e.valid[np.arange(n) != 4].all() for e in got)


def test_the_hold_treats_a_reading_with_any_axis_not_finite_as_missing_and_keeps_the_latest():
    """`LinkHold.fill` alone (no process): a link whose reading has one axis NaN or inf is held
    at its last full reading, every axis alike; with every link present the held readings are
    the newest (the all-present path keeps them as the per-link one does)."""
    from host.workers.estimate_worker import LinkHold
    n = 6
    hold = LinkHold(n, hold=3)
    first = np.arange(3.0 * n).reshape(n, 3)
    out, used, held = hold.fill(first, np.ones(n, bool))
    assert out is first and used.all() and held == 0
    second = first + 100.0  # every link present again: these are the ones to hold from now on
    hold.fill(second, np.ones(n, bool))
    third = first + 200.0
    for axis, bad in ((0, np.nan), (1, np.inf), (2, -np.inf)):
        third[axis + 1, axis] = bad  # links 1, 2, 3: one axis each
    out, used, held = hold.fill(third, np.ones(n, bool))
    assert held == 3 and used.all()
    assert np.array_equal(out[1:4], second[1:4])  # the newest full readings, not the first
    assert np.array_equal(out[[0, 4, 5]], third[[0, 4, 5]])
    valid = np.ones(n, bool)
    valid[5] = False  # masked: held too, whatever its reading says
    out, used, held = hold.fill(first + 300.0, valid)
    assert held == 1 and np.array_equal(out[5], third[5])
