"""Gauss-Newton on all yaws at once: chord steps on a kept factorisation, Anderson acceleration,
Levenberg-Marquardt damping; one snapshot, or a batch of one structure sharing a factorisation."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

import host.analysis.estimator.kernel as kernel  # the switch, read at call time
from .structure import Structure
from .yawproblem import YawProblem

__all__ = ["YAW_TOL_RAD", "YAW_TOL_NOISE", "MAX_ITER", "REFACTOR_RATIO", "REFACTOR_PATIENCE",
           "REFACTOR_FAR", "REFACTOR_GROWTH", "CHAIN_SAFETY", "CHAIN_REMEASURE", "STALE_STEPS",
           "STALE_RUN", "Contraction", "solve_global", "step_converged", "SLOW_CAP",
           "chord_in_kernel", "ANDERSON_COS", "anderson", "BATCH_MAX_ITER", "BATCH_REFACTOR",
           "solve_global_batch"]

#: Gauss-Newton stops when the largest yaw step is below this, radians.
YAW_TOL_RAD = 1e-4
#: ... or below this fraction of the readings' noise σ (rad ≈ fraction of g): noise moves yaws by ~σ.
YAW_TOL_NOISE = 0.01
#: Gauss-Newton iteration cap (warm starts need 2-3; cold starts from the rest layout ~10).
MAX_ITER = 50
#: A chord step (reused factorisation) that shrinks by less than this factor triggers a new one.
#: A factorisation costs 30-60 solves at every size (benchmarks/bench_estimator.py,
#: ``linear_algebra``), a chord iteration one solve and one evaluation: a contraction of 0.7
#: still reaches the tolerance in a few chord steps, far cheaper than refactorising (0.3 made
#: 128x128 refactorise every snapshot, 2.4 s of its 2.5 s).
REFACTOR_RATIO = 0.7
#: ... in this many steps in a row (each accepted). One slow step on a kept factorisation is
#: common and passes: on a static 64x64 sheet at 1 % g (bench_estimator's stream) the third step
#: is often 0.3-1.0 of the second and the fourth converges, and a factorisation (~60 chord steps'
#: time) made on one such step was a third of the stream's time; a sheet whose shape has moved
#: away from the factorisation contracts slowly step after step (docs/estimator.md §6).
REFACTOR_PATIENCE = 2
#: ... but a slow step below this many tolerances triggers one at once: far above the tolerance a
#: slow step is the curvature's (a first step of ~0.05 rad, the next ones its second-order
#: remainder), which a new factorisation does not remove; near it, the steps are linear and a
#: slow one says the factorisation is stale (a moving sheet's), whose slowest modes the step's
#: largest entry then hides (with this at 0 the drape at 3 % g stopped 0.093 % of the side from
#: the minimiser, where every path is held to 0.03 %).
REFACTOR_FAR = 10.0
#: ... and so does a step this much larger than the last, wherever it is: the iteration is
#: moving away, not contracting slowly (the drape at 5 % g passed a step 1.6 times its
#: predecessor and stopped 0.048 % of the side from the minimiser, against 0.018 % refactorising)
REFACTOR_GROWTH = 1.25
#: A warm solve also stops after its first chord step when the contraction its chain measured on
#: the same factorisation (`Contraction`) predicts the next step below the tolerance by this
#: factor. On a 64x64 sheet streaming at 145 Hz the first step is ~3e-3 rad and the second
#: ~7e-6, 15x below the 1e-4 tolerance: a solve and an evaluation (a quarter of an estimate)
#: spent to learn that the first step had converged (docs/estimator.md §6).
CHAIN_SAFETY = 4.0
#: ... and the chain measures the contraction afresh (two steps) after this many snapshots on it
CHAIN_REMEASURE = 4
#: A stream's factorisation is stale when `STALE_RUN` snapshots in a row on it each took at least
#: this many chord steps more than the first snapshot solved wholly on it
#: (`result.Solution.base_steps`); the next snapshot then factorises before its first step
#: (`pipeline.solve_snapshot`). A moving sheet's Gauss-Newton matrix moves away from a kept
#: factorisation snapshot by snapshot: on the rising bump at 145 Hz (64x64) the warm solves
#: took 2, then 3, then 5 chord steps over ~40 snapshots until a slow step refactorised in the
#: middle of a solve; refactorised at the start, the snapshots after it stop after one step
#: (the chain's contraction, `CHAIN_SAFETY`). Relative to the factorisation's own first solve,
#: not a count of steps: a noisy sheet's solves take 4-5 steps on a fresh factorisation (its
#: curvature's, which no factorisation removes) and a fixed count refactorised every snapshot.
STALE_STEPS = 2
#: ... in this many snapshots in a row (one slow snapshot is a burst of noise)
STALE_RUN = 2


class Contraction(NamedTuple):
    """How a kept factorisation's chord steps contracted, measured on a solve's first two steps
    ``s1``, ``s2`` (their largest entries): linearly ``rho = s2 / s1``, or quadratically (the
    curvature Gauss-Newton neglects, which dominates a warm start's small first step)
    ``kappa = s2 / s1²``; ``age``: the snapshots since, on the same factorisation."""

    rho: float
    kappa: float
    age: int = 0

    @classmethod
    def measured(cls, s1: float, s2: float) -> "Contraction | None":
        if not (s1 > 0.0 and np.isfinite(s1) and np.isfinite(s2)):
            return None
        return cls(s2 / s1, s2 / (s1 * s1), 0)

    def predicts_converged(self, smax: float, tol: float) -> bool:
        """Whether a first step of largest entry ``smax`` is predicted to leave a next step below
        ``tol`` (by `CHAIN_SAFETY`). The larger of the linear and the quadratic prediction: each
        is the cautious one on its side of the measured step."""
        return CHAIN_SAFETY * max(self.rho * smax, self.kappa * smax * smax) < tol


def solve_global(st: Structure, alpha, beta, gamma0, target, prior_w, bend_w, lu=None,
                 tol=YAW_TOL_RAD, trig=None, chain: Contraction | None = None, cs=None):
    """Gauss-Newton on all yaws, reusing a factorisation while it contracts well (chord steps),
    Levenberg-Marquardt damping when a step fails. Returns (gamma, iterations, factorisations,
    lu, problem, contraction): the `Contraction` of the returned ``lu`` measured by this solve's
    first two steps on it, or ``chain`` one snapshot older when the solve stopped after one step
    by it (None otherwise).

    ``cs``: (yaws, their cosines and sines) the previous solve kept (`YawProblem.link_cs`), for
    the kernel's evaluations at ``gamma0`` when they are its yaws.

    ``chain``: the contraction the previous snapshot's solve measured on ``lu``. With it the
    first chord step also ends the solve when `Contraction.predicts_converged`; the caller
    passes it for `CHAIN_REMEASURE` snapshots at most, then lets a solve measure again.

    ``lu`` may be the factorisation left by the previous snapshot (same structure): the normal
    matrix changes little between snapshots, so its chord iterations usually converge without a
    new factorisation. A new one is made when a step raises the cost or contracts by less than
    `REFACTOR_RATIO`.

    The chord steps are accelerated (Anderson, one step of history, `anderson`): on noisy
    readings Gauss-Newton's neglected curvature makes a smooth mode overshoot, each step about
    −0.5 times the last (the 128x128 sheet took 5-7 steps, each reversing the one before); the
    extrapolation sums that series. An accelerated step that raises the cost is replaced by the
    plain one before anything else is tried.
    """
    gamma = gamma0.copy()
    prob = YawProblem(st, alpha, beta, target, prior_w, bend_w, trig)
    if cs is not None:  # (γ, its cosines and sines) kept by the solve before: not made again
        prob.keep_cs(*cs)
    if st.n_var == 0:
        return gamma, 0, 0, None, prob, None
    lu_in = lu
    vl = st.var_links
    cost, grad, blocks = prob.evaluate(gamma, jac=lu is None)
    mu = 0.0
    fresh = False
    n_fact = 0
    prev_smax = np.inf
    hist = None  # (last raw step, last move) of the current chord map, for the acceleration
    accelerated = False  # the last move accepted was an extrapolated one
    it = 0
    poor = 0  # steps in a row on the current factorisation that contracted by less than REFACTOR_RATIO
    slow = 0.0  # the slowest contraction of such a step passed without a new factorisation
    seen: list[float] = []  # the largest entries of the first undamped steps on the current lu
    if lu is not None and chord_in_kernel(st, lu, gamma):
        # the warm start's chord steps in the kernel: this loop's iterations, one C call
        status, it, cost, grad, prev_smax, seen = prob.chord_kernel(
            gamma, cost, grad, lu, tol, MAX_ITER, REFACTOR_RATIO, ANDERSON_COS, chain, CHAIN_SAFETY,
            PREDICT_WITHIN, REFACTOR_PATIENCE, REFACTOR_FAR, REFACTOR_GROWTH)
        if status in (0, 3):  # converged, or out of iterations
            return gamma, it, 0, lu, prob, _contraction(seen, chain, lu is lu_in and it == 1)
        lu, blocks, seen = None, None, []  # 1: the cost rose; 2: a step contracted too little
    while it < MAX_ITER:
        it += 1
        if lu is None:
            if blocks is None:  # the Jacobian of this point, for its first factorisation
                blocks = prob.evaluate(gamma)[2]
            lu = prob.factor(blocks, mu)
            fresh = True
            hist, accelerated, poor, slow = None, False, 0, 0.0
            n_fact += 1
            seen = []
        step = prob.step(lu, grad)
        move = anderson(step, hist) if mu == 0.0 else step
        g_new = gamma.copy()
        g_new[vl] += move
        smax = float(np.max(np.abs(step)))
        if mu == 0.0 and len(seen) < 2:
            seen.append(smax)
        if mu == 0.0 and (step_converged(smax, prev_smax, accelerated, tol, slow)
                          or it == 1 and chain is not None and not fresh
                          and chain.predicts_converged(smax, tol)):
            # converged: the step (or the next one, predicted from the contraction so far) is
            # below the tolerance. A Gauss-Newton/chord step on an SPD matrix is a descent
            # direction and this one is tiny, so it is taken without evaluating the cost again
            # (an evaluation is a third of an iteration); the returned state is at ``g_new``.
            # Right after an accelerated move the steps' ratio says nothing of the contraction
            # of the other modes: then only a step below the tolerance ends it.
            gamma = g_new
            break
        cost_new, grad_new, blocks_new = prob.evaluate(g_new, jac=False)
        if move is not step and not cost_new <= cost * (1.0 + 1e-12) + 1e-300:
            move = step  # the extrapolation overshot: the plain chord step instead
            g_new = gamma.copy()
            g_new[vl] += move
            cost_new, grad_new, blocks_new = prob.evaluate(g_new, jac=False)
        if not cost_new <= cost * (1.0 + 1e-12) + 1e-300:
            lu = None  # refactorise here; damp if even a fresh Gauss-Newton step failed
            if fresh:
                mu = max(10.0 * mu, 1e-3)
                if mu > 1e8:
                    break
            fresh = False
            continue
        gamma, cost, grad, blocks = g_new, cost_new, grad_new, blocks_new
        hist = (step, move)
        accelerated = move is not step
        if mu > 0.0 and smax < tol:  # a damped step this small: converged as well
            break
        if mu > 0.0:
            mu = mu / 10.0 if mu > 1e-6 else 0.0
            lu = None
        elif smax > REFACTOR_RATIO * prev_smax:
            poor += 1
            if (smax < REFACTOR_FAR * tol or poor >= REFACTOR_PATIENCE
                    or smax > REFACTOR_GROWTH * prev_smax):
                lu, poor = None, 0
            else:
                slow = max(slow, smax / prev_smax)
        else:
            poor = 0
        prev_smax = smax
        fresh = False
    return gamma, it, n_fact, lu, prob, _contraction(seen, chain, lu is lu_in and it == 1)


#: `step_converged` trusts a predicted next step only for a step within this many tolerances (on
#: test_estimate_batch.py's cases: 3 ends within 0.017 % of side of the minimiser; 10 too, in 3.1
#: steps per 14x14 snapshot against 3.6, but a batch on a stale factorisation then stopped 0.031 %
#: short; 30 and more let the 0.10-0.14 % stops through)
PREDICT_WITHIN = 3.0


#: `step_converged` after a slow step was passed: the contraction it assumes, at most this
SLOW_CAP = 0.9


def step_converged(smax: float, prev: float, accelerated: bool, tol: float,
                   slow: float = 0.0) -> bool:
    """Whether a chord step of largest entry ``smax`` ends the iteration (``prev``: the last
    step's, inf when none; ``accelerated``: the last move was an Anderson one).

    While the steps contract (ratio ``rho = smax / prev`` < 1, known after a plain step), what
    is left after this step is about the rest of a geometric series, ``smax · rho / (1 − rho)``:
    the iteration stops when that is below ``tol``, or, for ``rho`` up to 0.5, when the next
    step alone is (``smax · rho``, which the series at most doubles). A slow contraction (rho
    0.5-0.9, a mode the data hold weakly, as where the "level" prior holds nothing) thus
    iterates on although each step is below ``tol``: stopping at ``smax < tol`` there left the
    estimate up to 0.13 % of the side from the minimiser (docs/estimator.md §6). Without a
    known ratio (the first step, after an accelerated move, a growing step), ``smax < tol``.

    ``slow``: the slowest contraction of a slow step that this factorisation's iteration passed
    without refactorising (`REFACTOR_PATIENCE`; 0: none). Its mode may be left under faster
    ones, so the series is then summed at the larger of it and this step's ratio, at most
    `SLOW_CAP`: on the drape at 3 % g a solve that passed a step of ratio 0.97 and stopped on the
    next one's 0.08 stopped 0.057 % of the side from the minimiser."""
    if slow > 0.0:
        rho = min(max(slow, smax / prev if 0.0 < prev < np.inf else 0.0), SLOW_CAP)
        return smax * rho < tol * (1.0 - rho)
    if prev < np.inf and not accelerated and smax < prev and smax < PREDICT_WITHIN * tol:
        rho = smax / prev
        return smax * rho < tol * (1.0 - rho if rho > 0.5 else 1.0)
    return smax < tol


def _contraction(seen, chain, one_step_on_chain: bool) -> Contraction | None:
    """A solve's `Contraction`: measured when it took two undamped steps on its last
    factorisation, else ``chain`` a snapshot older when it took one on the chain's."""
    if len(seen) >= 2:
        return Contraction.measured(seen[0], seen[1])
    if chain is not None and one_step_on_chain:
        return chain._replace(age=chain.age + 1)
    return None


def chord_in_kernel(st, lu, gamma) -> bool:
    """Whether `YawProblem.chord_kernel` can run this snapshot's chord steps: the kernel is
    built, model "cells", one snapshot, a SuperLU factorisation with its supernodal form."""
    return (kernel.USE_KERNEL and st.model == "cells" and gamma.ndim == 1 and lu[0] == "splu"
            and len(lu) > 2 and lu[2] is not None)


#: `anderson` extrapolates only a step that reverses the last one: cos(s, s_prev) below this.
ANDERSON_COS = -0.9


def anderson(step: np.ndarray, hist) -> np.ndarray:
    """Anderson acceleration with one step of history of the fixed-point map ``x -> x + s(x)``:
    ``x + s − θ (Δx + Δs)``, θ minimising the linearised next step. For a mode that the steps
    overshoot, each −ρ times the last (0 < ρ < 1), it moves ``s / (1 + ρ)``, the whole rest of the
    series. Used only for such a step — nearly opposite to the last (`ANDERSON_COS`), so
    0 < θ < 1 and the move is shorter than the step — else the plain step is returned. ``hist``:
    (previous raw step, previous move) of the same map, or None."""
    if hist is None:
        return step
    s_prev, dx = hist
    nn = float(step @ step) * float(s_prev @ s_prev)
    if not (nn > 0.0 and float(step @ s_prev) < ANDERSON_COS * np.sqrt(nn)):
        return step
    ds = step - s_prev
    theta = float(ds @ step) / float(ds @ ds)
    if not 0.0 < theta < 1.0:
        return step
    return step - theta * (dx + ds)


#: `estimate_batch`: chord iterations per snapshot before it is handed to `estimate` instead.
BATCH_MAX_ITER = 8
#: ... and factorisations per group at most (a slow contraction or a rising cost makes one).
BATCH_REFACTOR = 3


def solve_global_batch(st: Structure, alpha, beta, gamma0, target, prior_w, bend_w, lu, tol):
    """`solve_global` for a batch (B, n_links) of snapshots of one structure, all started at
    ``gamma0`` (n_links,): chord Gauss-Newton steps on one shared factorisation (the previous
    snapshot's, or one made at the batch's first), with the same stopping rule per snapshot.
    As in `solve_global`, a new factorisation is made (at the first snapshot still iterating,
    at most `BATCH_REFACTOR` times) when the steps contract by less than `REFACTOR_RATIO`
    (median over the batch) or raise some snapshot's cost. A snapshot whose step raised its cost,
    or that has not converged in `BATCH_MAX_ITER` steps, is reported failed (the caller
    re-estimates it with `estimate`). Returns (gamma (B, n), iterations (B,), failed (B,),
    factorisations, lu, the problem's ``take``)."""
    B = alpha.shape[0]
    gamma = np.repeat(gamma0[None, :], B, axis=0)
    iters = np.zeros(B, int)
    failed = np.zeros(B, bool)
    prob = YawProblem(st, alpha, beta, target, prior_w, bend_w)
    if st.n_var == 0:
        return gamma, iters, failed, 0, lu, prob.take
    vl = st.var_links
    c_act, gr_act, _ = prob.evaluate(gamma, jac=False)
    n_fact = 0
    if lu is None:
        p0 = prob.take(0)
        lu = p0.factor(p0.evaluate(gamma[0])[2], 0.0)
        n_fact = 1
    act, sub, g_act = np.arange(B), prob, gamma.copy()  # the snapshots still iterating
    prev_smax = np.full(B, np.inf)
    rate = np.zeros(B)  # per snapshot, the slowest contraction since the factorisation
    for _ in range(BATCH_MAX_ITER):
        iters[act] += 1
        step = sub.step(lu, gr_act)
        smax = np.max(np.abs(step), axis=1)
        g_new = g_act.copy()
        g_new[:, vl] += step
        ps, tl = prev_smax[act], tol[act]
        # converged: the step, or the next one predicted at the slowest contraction seen (a
        # shared factorisation contracts a snapshot's modes at different rates, so one fast
        # step says little), is below the tolerance; taken without evaluating (`solve_global`)
        rt = np.maximum(rate[act], smax / ps)
        known = (smax < ps) & (ps < np.inf) & (rt < 1.0) & (smax < PREDICT_WITHIN * tl)
        # `step_converged` at the slowest contraction seen
        conv = np.where(known, smax * rt < tl * np.where(rt > 0.5, 1.0 - rt, 1.0), smax < tl)
        gamma[act[conv]] = g_new[conv]
        keep = ~conv
        act, g_new, smax = act[keep], g_new[keep], smax[keep]
        if not act.size:
            break
        sub = prob.take(act)
        c_new, gr_new, _ = sub.evaluate(g_new, jac=False)
        worse = ~(c_new <= c_act[keep] * (1.0 + 1e-12) + 1e-300)
        failed[act[worse]] = True
        ok = ~worse
        ratio = smax[ok] / prev_smax[act[ok]]
        act, g_act, c_act, gr_act = act[ok], g_new[ok], c_new[ok], gr_new[ok]
        gamma[act] = g_act
        prev_smax[act] = smax[ok]
        rate[act] = np.maximum(rate[act], ratio)
        if not act.size:
            break
        if not ok.all():
            sub = prob.take(act)
        if n_fact < BATCH_REFACTOR and (worse.any() or np.median(ratio) > REFACTOR_RATIO):
            pf = prob.take(int(act[0]))
            lu = pf.factor(pf.evaluate(g_act[0])[2], 0.0)
            n_fact += 1
            prev_smax[act] = np.inf  # a new matrix: its contraction is measured afresh
            rate[act] = 0.0
    failed[act] = True  # out of steps
    return gamma, iters, failed, n_fact, lu, prob.take
