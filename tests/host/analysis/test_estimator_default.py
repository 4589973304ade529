"""The default estimator on the paper's own experiment, and the parts that make it.

Truth: the paper's Fig. 9 drape (`host.cli.paper.build_target`: a 14x14 spring-mass sheet laid
flat over a Gaussian, its lattice lines turning in plan) and the same sheet tilted by 0.8 rad (no
level unit), with the noise draws `capsheet paper noise` makes (MT19937 seeded by seed and level),
and exact Chebyshev nets (`virtual_sheet.shapes.make_sheet`). Metric: the paper's, mean joint
distance after a least-squares rigid overlay, % of the side. The paper's method runs on the same
draws; the bound is the one set for the default (at most 0.8 times the paper's method), not a
measured value. Three trials per level keep the suite short: `capsheet paper noise` runs ten at
every level from 0 to 10 % g (docs/estimator.md section 7).
"""

from __future__ import annotations

import numpy as np
import pytest

from host.analysis import estimator as E
from host.cli.paper import build_target, noise_draws
from host.estimator import error_percent_of_side, estimate, estimate_batch
from protocol.lattice import Lattice
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import noisy_readings
from virtual_sheet.shapes import make_sheet

L = 0.01
N = 14


def _errors(target: str, level: float, trials: int = 3, **kw) -> np.ndarray:
    t = build_target(target)
    return np.array([error_percent_of_side(estimate(r, N, N, L, **kw).joints, t.joints, L).mean()
                     for r in noise_draws(t.readings, level, trials, 2008)])


@pytest.mark.parametrize("target, level", [("fig9", 1.0), ("fig9", 3.0), ("fig9-tilted", 1.0),
                                           ("fig9-tilted", 3.0)])
def test_the_default_is_a_fifth_better_than_the_papers_method_on_its_own_experiment(target, level):
    default = _errors(target, level).mean()
    paper = _errors(target, level, method="paper").mean()
    assert default <= 0.8 * paper, (default, paper)


def test_the_tilted_drape_at_4_pct_g_is_a_fifth_better_over_the_commands_ten_trials():
    """The level where the default came closest to the bound (0.78 of the paper's method; the
    default before the weighted height fit and the smaller tilted share: 0.85), on the draws
    `capsheet paper noise` makes: its ten trials, as the bound is stated over them (three
    trials of it say 0.81)."""
    default = _errors("fig9-tilted", 4.0, trials=10).mean()
    paper = _errors("fig9-tilted", 4.0, trials=10, method="paper").mean()
    assert default <= 0.8 * paper, (default, paper)


def test_the_former_adaptive_prior_is_biased_on_a_drape_and_the_default_is_not():
    """The drape's lattice lines zigzag in plan (parallel neighbours along a line differ by up to
    0.6 rad): a prior that holds every bending pulls where the data decide; the default holds it
    only where the region is level."""
    default, adaptive = _errors("fig9", 1.0).mean(), _errors("fig9", 1.0, prior="adaptive").mean()
    assert default <= 0.5 * adaptive, (default, adaptive)


def _unit_height_sums(beta: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Per unit, the height step around its loop, ``Σ ±sin β`` (eq. 4's z part, `Lattice.units`
    numbering: d0 + d1 = d3 + d2), written here from the lattice alone."""
    u = Lattice(rows, cols).units.reshape(-1, 4)
    s = np.sin(beta)
    return s[u[:, 0]] + s[u[:, 1]] - s[u[:, 2]] - s[u[:, 3]]


def test_closed_pitches_close_every_cell_in_height_and_move_a_pitch_by_about_the_noise():
    P = make_sheet("sphere", N, N, L, shear=0.2)
    r = noisy_readings(ideal_readings(P), 3.0, np.random.Generator(np.random.MT19937(11)))
    alpha, beta = E.roll_pitch(r)
    st = E.structure.structure_of(N, N, None, "cells")
    closed, _ = E.pipeline.closed_pitches(st, alpha, beta)
    assert np.abs(_unit_height_sums(beta, N, N)).max() > 0.02  # the noisy pitches do not close
    assert np.abs(_unit_height_sums(closed, N, N)).max() < 1e-9
    moved = np.abs(closed - beta)
    assert 0.005 < np.sqrt(np.mean(moved ** 2)) < 0.03  # about σ = 0.03 rad, never more


def test_a_link_in_no_closed_loop_keeps_its_pitch():
    n = 4
    lat = Lattice(n, n)
    valid = np.ones(lat.n_links, bool)
    u = lat.units.reshape(-1, 4)
    corner = u[0]  # drop three links of the corner cell: its fourth closes no loop any more
    valid[corner[1:]] = False
    free = corner[0]
    assert not np.isin(free, u[np.all(valid[u], axis=1)])
    r = noisy_readings(ideal_readings(make_sheet("gaussian", n, n, L)), 2.0,
                       np.random.Generator(np.random.MT19937(3)))
    alpha, beta = E.roll_pitch(r)
    st = E.structure.structure_of(n, n, valid, "cells")
    closed, _ = E.pipeline.closed_pitches(st, alpha, beta)
    assert abs(closed[free] - beta[free]) < 1e-9
    assert np.abs(closed[valid] - beta[valid]).max() > 1e-4  # the others did move


def test_closing_the_pitches_lowers_the_error_on_the_tilted_drape(monkeypatch):
    closed = _errors("fig9-tilted", 3.0).mean()
    monkeypatch.setattr(E.pipeline, "CLOSE_PITCHES", False)
    raw = _errors("fig9-tilted", 3.0).mean()
    assert closed <= 0.9 * raw, (closed, raw)


def test_roll_weights_are_the_inverse_of_the_rolls_noise():
    # a reading's roll atan2(s_y, s_z) has the standard deviation σ / cos β
    n = 5
    lat = Lattice(n, n)
    st = E.structure.structure_of(n, n, None, "cells")
    beta = np.random.Generator(np.random.MT19937(2)).uniform(-1.4, 1.4, lat.n_links)
    cells = np.bincount(lat.units.ravel(), minlength=lat.n_links)  # 1 on the edge, else 2
    k = st.roll_links
    want = E.ROLL_WEIGHT * np.abs(np.cos(beta[k])) / cells[k]
    np.testing.assert_allclose(E.yawproblem.roll_weights(st, beta), want, rtol=1e-12)


def _island_mask(n: int) -> np.ndarray:
    """Every link of the cells around cell (4, 4) missing except the ring's outer links: the
    cell (4, 4) keeps its four links, which no active unit joins to the rest."""
    lat = Lattice(n, n)
    u = lat.units.reshape(n - 1, n - 1, 4)
    valid = np.ones(lat.n_links, bool)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di or dj:
                ring = u[4 + di, 4 + dj]
                valid[ring[~np.isin(ring, u[4, 4])]] = False
    return valid


def test_the_level_prior_holds_the_pairs_that_join_what_the_data_do_not():
    n = 10
    st = E.structure.structure_of(n, n, None, "cells")
    assert not E.priors.bridging_pairs(st).any()  # one island without missing links
    valid = _island_mask(n)
    st = E.structure.structure_of(n, n, valid, "cells")
    bridge = E.priors.bridging_pairs(st)
    pb = st.pairs[:st.n_bend]
    cell = Lattice(n, n).units.reshape(n - 1, n - 1, 4)[4, 4]
    inside = np.isin(pb, cell)
    assert bridge[inside[:, 0] ^ inside[:, 1]].all()  # every pair from the cell outwards
    # far from the hole (both links in the first two rows of joints) the data join everything
    ep = Lattice(n, n).endpoints
    far = (ep[pb, 1] // n <= 1).all(axis=1)
    assert far.sum() > 10 and not bridge[far].any()


def test_a_sheet_with_missing_links_is_solved_in_a_few_steps(monkeypatch):
    """A 32x32 saddle with 5 % of its links missing (the kernel tests' mask): without the pairs
    that join its islands, the level prior leaves each island's rotation at the floor weight
    (1e-8), and every warm snapshot needed new factorisations (3-11, and 8-17 steps; before the
    roll weights, 50 steps of damping) where the kept one serves."""
    n = 32
    m = 2 * n * (n - 1)
    valid = np.ones(m, bool)
    valid[np.random.Generator(np.random.MT19937(5)).choice(m, size=m // 20, replace=False)] = False
    P = make_sheet("saddle", n, n, L, shear=0.2)
    g = np.random.Generator(np.random.MT19937(1))
    snaps = [noisy_readings(ideal_readings(P), 1.0, g) for _ in range(3)]

    def run():
        E.structure.cached_structure.cache_clear()
        prev, out = None, []
        for r in snaps:
            prev = estimate(r, n, n, L, valid=valid, previous=prev)
            out.append((prev.iterations, prev.factorisations))
        return out

    # the islands alone: without the small share every tilted pair keeps (which would hold
    # them weakly too, `test_a_compass_stream_stays_on_its_factorisation_under_the_default`)
    monkeypatch.setattr(E.priors, "LEVEL_TILTED_SHARE", 0.0)
    warm = run()[1:]
    assert all(f == 0 and i <= 10 for i, f in warm), warm
    monkeypatch.setattr(E.priors, "bridging_pairs", lambda st: np.zeros(st.n_bend))
    broken = run()[1:]
    assert all(f >= 3 for _, f in broken), broken  # the broken prior: the check above can fail
    E.structure.cached_structure.cache_clear()


def test_the_stopping_rule_trusts_a_prediction_only_near_the_tolerance():
    tol = 1e-4
    conv = E.solver.step_converged
    assert conv(5e-5, np.inf, False, tol)  # first step below the tolerance
    assert not conv(2e-4, np.inf, False, tol)
    assert conv(1.5e-4, 3e-3, False, tol)  # fast contraction: the next step 7.5e-6
    # a large step whose ratio looks fast says nothing of the slow modes: one more step
    assert not conv(2.4e-3, 6.1e-2, False, tol)
    # a slow contraction: each step under the tolerance, the rest of the series is not
    assert not conv(9e-5, 1e-4, False, tol)
    assert conv(9e-6, 1e-5, False, tol)
    assert conv(9e-5, 1e-4, True, tol)  # after an accelerated move the ratio means nothing


def test_after_a_slow_step_was_passed_the_stop_sums_the_series_at_its_contraction():
    """The drape at 3 % g (tolerance 3e-4): a solve passed a step of ratio 0.97 far above the
    tolerance (6.3e-3, no new factorisation) and the next one, 4.9e-4, contracted by 0.08. Taken
    at its own ratio it stops (the slow mode under it left the estimate 0.057 % of the side from
    the minimiser); at the slow step's it does not, nor at the cap for any slower one."""
    conv, tol = E.solver.step_converged, 3e-4
    assert conv(4.9e-4, 6.3e-3, False, tol)  # its own ratio: the stop that was short
    assert not conv(4.9e-4, 6.3e-3, False, tol, slow=0.97)
    cap = E.solver.SLOW_CAP
    edge = tol * (1 - cap) / cap  # at the cap: stops just below this
    assert conv(0.99 * edge, 1e-3, False, tol, slow=0.97)
    assert not conv(1.01 * edge, 1e-3, False, tol, slow=0.97)
    assert conv(0.99 * edge, 1e-3, True, tol, slow=0.8) == conv(0.99 * edge, 1e-3, False, tol, slow=0.8)


def test_a_slow_step_far_above_the_tolerance_costs_no_factorisation_and_no_accuracy(monkeypatch):
    """bench_estimator's 64x64 stream (a still Gaussian, fresh 1 % g noise per snapshot): its
    third chord step is often 0.3-1.0 of the second, the first step's curvature, and the fourth
    converges. Refactorising on such a step (`REFACTOR_PATIENCE` = 1, the rule before) made two
    factorisations in its first twelve snapshots, each ~60 chord steps' time; passing it makes none, and
    every estimate still stops within 0.03 % of the side of the minimiser (the bound every path
    is held to, test_estimate_batch.py)."""
    n = 64
    P = make_sheet("gaussian", n, n, L)
    g = np.random.Generator(np.random.MT19937(1))
    snaps = [noisy_readings(ideal_readings(P), 1.0, g) for _ in range(30)]  # the benchmark's draws

    def run(tight=False):
        if tight:
            monkeypatch.setattr(E.solver, "YAW_TOL_RAD", 1e-12)
            monkeypatch.setattr(E.solver, "YAW_TOL_NOISE", 0.0)
        prev, out = estimate(snaps[-1], n, n, L), []
        for r in snaps[:12]:
            prev = estimate(r, n, n, L, previous=prev)
            out.append(prev)
        return out
    got = run()
    assert sum(e.factorisations for e in got) == 0
    monkeypatch.setattr(E.solver, "REFACTOR_PATIENCE", 1)
    assert sum(e.factorisations for e in run()) >= 2  # the rule before: the check can fail
    monkeypatch.undo()
    ref = run(tight=True)
    far = max(np.abs(a.joints - b.joints).max() for a, b in zip(got, ref)) / ((n - 1) * L) * 100
    assert far <= 0.03


def test_a_growing_step_refactorises_and_the_warm_drape_stops_near_the_minimiser(monkeypatch):
    """The drape at 5 % g: a warm solve's third step was 1.6 times its second, far above the
    tolerance (5e-4). Let pass as a slow step, the solve stopped 0.048 % of the side from the
    minimiser; refactorised there (`REFACTOR_GROWTH`), every warm estimate stops within the 0.03 %
    every path is held to. (The chain's cold start is not held to it here.)"""
    t = build_target("fig9")
    R = np.stack(noise_draws(t.readings, 5.0, 4, 2008))

    def chain():
        prev, out = None, []
        for r in R:
            prev = estimate(r, N, N, L, previous=prev)
            out.append(prev)
        return out
    got = chain()
    with monkeypatch.context() as m:
        m.setattr(E.solver, "YAW_TOL_RAD", 1e-12)
        m.setattr(E.solver, "YAW_TOL_NOISE", 0.0)
        ref = chain()

    def far(out):
        return max(np.abs(a.joints - b.joints).max() for a, b in zip(out[1:], ref[1:])) / (13 * L) * 100
    assert far(got) <= 0.03
    monkeypatch.setattr(E.solver, "REFACTOR_GROWTH", np.inf)  # a growing step let pass
    assert far(chain()) > 0.03


def test_the_batch_and_one_at_a_time_agree_under_the_default_on_the_drape():
    t = build_target("fig9")
    R = np.stack(noise_draws(t.readings, 3.0, 6, 2008))
    out = estimate_batch(R, N, N, L, batch=6)
    prev, one = None, []
    for r in R:
        prev = estimate(r, N, N, L, previous=prev)
        one.append(prev)
    gap = max(np.abs(a.joints - b.joints).max() for a, b in zip(out, one)) / (13 * L) * 100
    assert gap <= 0.03  # % of side: the bound test_estimate_batch.py holds both paths to


def test_capsheet_estimate_prior_selects_an_older_prior_by_name(tmp_path, capsys):
    from host.cli import main
    from host.record.recording import Recorder
    from host.snapshots.aggregator import LatticeSnapshot

    n = 6
    lat = Lattice(n, n)
    P = make_sheet("cylinder", n, n, L, shear=0.2)
    g = np.random.Generator(np.random.MT19937(8))
    R = [noisy_readings(ideal_readings(P), 3.0, g) for _ in range(4)]
    src = tmp_path / "run.mcap"
    rec = Recorder(src, lat, L, session={"mode": "test"})
    try:
        for k, r in enumerate(R):
            rec.snapshot(LatticeSnapshot(k, 0.01 * k, 1e9 + 0.01 * k, r, np.ones(lat.n_links, bool),
                                         np.zeros(lat.n_links, np.uint8), True, 0.0))
    finally:
        rec.close()
    got = {}
    for prior in ("adaptive", None):
        out = tmp_path / f"{prior}.npz"
        argv = ["estimate", str(src), "--out", str(out), "--jobs", "1", "-q", "--method", "global"]
        assert main(argv + (["--prior", prior] if prior else [])) == 0
        got[prior] = np.load(out)["joints"]
    for prior, kw in (("adaptive", {"prior": "adaptive"}), (None, {})):
        prev, want = None, []
        for r in R:  # what the library gives, each snapshot warm-started from the one before
            prev = estimate(r, n, n, L, previous=prev, **kw)
            want.append(prev.joints)
        np.testing.assert_allclose(got[prior], np.stack(want), atol=1e-6 * L)
    assert np.abs(got["adaptive"] - got[None]).max() > 1e-3 * L  # the option does change them
    with pytest.raises(SystemExit) as bad:  # argparse: a one-line error, exit status 2
        main(["estimate", str(src), "--prior", "bogus"])
    assert bad.value.code == 2


def test_a_compass_stream_stays_on_its_factorisation_under_the_default(monkeypatch):
    """A 64x64 compass Gaussian streamed at 1 % g: the "level" prior keeps a small share of the
    bending on tilted regions (`tilted_share`) so that the smooth modes the data hold weakly do
    not stall the chord steps; without it the stream refactorised every 4-5 snapshots (a count,
    not a rate: the time is bench_estimator's), and now takes more steps."""
    n = 64
    P = make_sheet("gaussian", n, n, L)
    g = np.random.Generator(np.random.MT19937(1))
    snaps = [noisy_readings(ideal_readings(P), 1.0, g) for _ in range(13)]

    def run():
        prev = estimate(snaps[0], n, n, L)
        count = steps = 0
        for r in snaps[1:]:
            prev = estimate(r, n, n, L, previous=prev)
            count += prev.factorisations
            steps += prev.iterations
        return count, steps

    count, steps = run()
    assert count == 0
    # without the share: more chord steps, or factorisations (the check can fail) ...
    monkeypatch.setattr(E.priors, "LEVEL_TILTED_SHARE", 0.0)
    count0, steps0 = run()
    assert count0 > 0 or steps0 > steps
    # ... and under the refactorisation rule before a slow step far above the tolerance was let
    # pass (`solver.REFACTOR_PATIENCE` = 1), factorisations; the share alone avoided them there
    monkeypatch.setattr(E.solver, "REFACTOR_PATIENCE", 1)
    assert run()[0] >= 1


def test_the_tilted_share_falls_with_the_noise_above_one_pct_g_and_the_tilted_drape_gains(
        monkeypatch):
    """Up to 1 % g a tilted pair keeps the share 0.003 of the bending weight, above it the share
    falls as 1/σ (the pair's weight grows as σ, not σ²): at 3-5 % g the constant share cost the
    tilted drape 7-9 % of its error (docs/estimator.md §3)."""
    share = E.priors.tilted_share
    k = E.priors.LEVEL_TILTED_SHARE
    assert share(0.0) == share(0.005) == share(0.01) == k
    assert share(0.04) == pytest.approx(k / 4, rel=1e-12)
    np.testing.assert_allclose(share(np.array([0.002, 0.02])), [[k], [k / 2]], rtol=1e-12)
    falling = _errors("fig9-tilted", 4.0).mean()
    monkeypatch.setattr(E.priors, "LEVEL_SHARE_NOISE", 1.0)  # the share constant at every noise
    assert falling <= 0.95 * _errors("fig9-tilted", 4.0).mean()


def test_a_links_height_step_is_as_noisy_as_the_cosine_of_its_pitch():
    """`height_weights`' noise model: white noise of σ per axis moves ``sin β`` of a reading by
    σ cos β (a steep link's height step is better known), here by drawing readings of links at
    two pitches, not from the estimator's formula."""
    g = np.random.Generator(np.random.MT19937(21))
    sigma, k = 0.02, 20000
    var = {}
    for beta in (0.0, 1.1):
        s = np.array([-np.sin(beta), np.cos(beta) * np.sin(0.3), np.cos(beta) * np.cos(0.3)])
        r = E.G0 * (s + sigma * g.standard_normal((k, 3)))
        var[beta] = np.var(-r[:, 0] / np.linalg.norm(r, axis=1))
    w0, w1 = E.pipeline.height_weights(np.sin(np.array([0.0, 1.1])))
    floor = E.pipeline.HEIGHT_VAR_FLOOR
    model = (1.0 / w1 - floor) / (1.0 / w0 - floor)  # the weights' variance ratio, floor removed
    assert abs(var[1.1] / var[0.0] / model - 1.0) < 0.05, (var, model)
    assert w1 > 2.5 * w0  # the steep link counts more


def test_the_weighted_height_fit_comes_close_to_the_weighted_least_squares():
    """`weighted_heights` against the weighted normal equations written here from the lattice's
    endpoints and solved directly: a few conjugate-gradient steps from the unweighted fit."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    n = 14
    P = make_sheet("sphere", n, n, L, shear=0.2)
    r = noisy_readings(ideal_readings(P), 3.0, np.random.Generator(np.random.MT19937(11)))
    _, beta = E.roll_pitch(r)
    st = E.structure.structure_of(n, n, None, "cells")
    ep = Lattice(n, n).endpoints
    m = ep.shape[0]
    D = sp.csr_matrix((np.r_[-np.ones(m), np.ones(m)], (np.r_[np.arange(m), np.arange(m)],
                                                       np.r_[ep[:, 0], ep[:, 1]])), (m, n * n))
    dz = -np.sin(beta)
    w = 1.0 / (np.cos(beta) ** 2 + E.pipeline.HEIGHT_VAR_FLOOR)
    A = (D.T @ sp.diags(w) @ D + E.structure.JOINT_PRIOR_WEIGHT * sp.identity(n * n)).tocsc()
    exact = D @ spsolve(A, D.T @ (w * dz))  # the steps of the exact weighted fit

    def off(z):
        return np.abs(D @ z - exact).max()

    plain = off(E.pipeline.weighted_heights(st, dz))
    assert plain > 1e-3  # the unweighted fit's steps differ: the check below can fail
    assert off(E.pipeline.weighted_heights(st, dz, w, steps=12)) < 1e-9
    assert off(E.pipeline.weighted_heights(st, dz, w)) < 0.05 * plain  # the default two steps
    # a batch of two snapshots gives each the steps it gets alone (the heights' common offset,
    # which the joints' weak prior alone fixes, is left to rounding)
    both = E.pipeline.weighted_heights(st, np.stack([dz, dz[::-1]]), np.stack([w, w[::-1]]))
    np.testing.assert_allclose(D @ both[:, 1], D @ E.pipeline.weighted_heights(st, dz[::-1], w[::-1]),
                               rtol=0, atol=1e-12)


def test_weighting_the_heights_lowers_the_error_on_the_tilted_drape(monkeypatch):
    weighted = _errors("fig9-tilted", 4.0).mean()
    monkeypatch.setattr(E.pipeline, "WEIGHTED_HEIGHTS", False)
    assert weighted <= 0.97 * _errors("fig9-tilted", 4.0).mean()


def test_the_command_lines_prior_choices_are_the_estimators():
    # written out in host.cli.estimate so that building the parser imports no estimator
    from host.cli import estimate as cli

    assert cli.PRIOR_CHOICES == E.PRIORS and cli.DEFAULT_PRIOR == E.DEFAULT_PRIOR
