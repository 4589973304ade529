"""`estimate`: one snapshot of readings, checked (`checks`), to its shape (global or the paper's
method); the stages (angles -> structure -> prior weights -> solve -> joints and mask) that
`estimate_batch` and `ShapeEstimator` run too."""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

import host.analysis.estimator.kernel as kernel  # the switch, read at call time
import host.analysis.estimator.solver as solver  # YAW_TOL_*, read at call time
from .angles import (angle_trig, angles_of, roll_pitch_trig, solvability,
                     solvability_from_trig)
from .checks import (Options, Snapshot, check_int, check_link_length, check_noise_pct_g,
                     check_options, check_previous, check_readings, rest_yaws)
from .joints import joints_and_mask
from .kernel import ffi as _kffi, lib as _klib
from .linalg import lap_solve, laplacian_kernel
from .priors import DEFAULT_PRIOR, prior_weights
from .result import ShapeEstimate, Solution
from .solver import solve_global
from .structure import JOINT_PRIOR_WEIGHT, structure_of

__all__ = ["estimate", "WarmStart", "link_angles", "closed_pitches", "CLOSE_PITCHES",
           "WEIGHTED_HEIGHTS", "HEIGHT_VAR_FLOOR", "HEIGHT_CG_STEPS",
           "height_weights", "weighted_heights",
           "noise_and_priors", "solve_snapshot", "link_solvability", "paper_snapshot"]

#: Whether the global method first makes the links' pitches consistent with one height per joint
#: (`closed_pitches`: the z part of loop closure, eq. 4), before the yaws are solved with them.
#: False gives the estimator as it was before (docs/estimator.md §3 measures both).
CLOSE_PITCHES = True


def estimate(readings: np.ndarray, rows: int, cols: int, link_length: float,
             valid: np.ndarray | None = None, previous: ShapeEstimate | None = None,
             method: str = "global", *, rest=None, model: str = "cells",
             prior: str = DEFAULT_PRIOR, noise_pct_g: float = 1.0,
             bad_readings: str = "raise", paper_options=None) -> ShapeEstimate:
    """Estimate the sheet's shape from one snapshot of readings.

    Parameters
    ----------
    readings : ndarray, shape (n_links, 3)
        Specific force of every link, m/s², sensor frame, links in docs/design.md order
        (``n_links = (rows-1)*cols + rows*(cols-1)``). Entries of invalid links are ignored.
    rows, cols : int
        Joints along i and j, each >= 2.
    link_length : float
        ``L``, metres, > 0.
    valid : ndarray of bool, shape (n_links,), optional
        False marks a missing link (no constraint from it). Default: all valid.
    previous : ShapeEstimate, optional
        An earlier estimate of the same lattice: ``method="global"`` starts from its yaws, its
        joints (the joint problem's weak prior) and its factorisation (`ShapeEstimate.solution`).
        It is not the prior's target (that would let what the data cannot see random-walk over a
        long run). ``method="paper"`` ignores it. Kept for compatibility: a stream of snapshots
        is `ShapeEstimator`'s job, which holds this warm start itself and gives the same
        numbers as a ``previous=`` chain.
    method : {"global", "paper"}
        See the module docstring.
    rest : ShapeEstimate or ndarray, shape (n_links,), optional
        The sheet's rest shape (an estimate, or its link yaws in radians): the prior's target,
        i.e. what fills in what the data cannot determine (a level sheet's layout, a sheet whose
        cells are not square at rest, a tactile sensor's learned rest shape). Default: square
        cells, i-links along +x.
    model : {"cells", "eq6"}
        The normal model (global method): ``"cells"`` (default) — every link's sensor z is the
        mean normal of its cells, each ``A × C`` of the cell's mean i- and j-link (exact on a
        Chebyshev net, docs/estimator.md); ``"eq6"`` — the paper's normal assumption (eq. 6).
    prior : {"level", "adaptive", "off", "fixed", "local"}
        What fills in what the data cannot determine (`PRIORS`; docs/estimator.md §3 measures
        them): "level" (default) holds the bending of the lattice only where the region is
        level, and the shear of level cells, with weights that scale with the readings' noise
        (noise-free readings: only a floor), so that it does not pull where the data decide
        (unbiased on a drape, whose lattice lines zigzag in plan); "adaptive" (the default
        before) holds the bending everywhere (less noisy on nets whose lines run straight,
        biased on a drape); "off" keeps only the floors (the data alone); "fixed" and "local"
        are older alternatives.
    noise_pct_g : float
        The reading noise (per axis, % of g) that `ShapeEstimate.yaw_std` and ``joint_std`` are
        stated for. Does not change the estimate.
    bad_readings : {"raise", "mask"}
        What to do with a valid link whose reading is far from one g (``|s|`` outside
        `READING_NORM_RANGE` · g: a dead, stuck or saturated chip): raise a ValueError naming
        the links (default), or mask them out as missing.
    paper_options : host.analysis.paper_method.PaperOptions, optional
        ``method="paper"`` only: the choices the paper leaves open (default
        ``PaperOptions()``; docs/estimator.md section 7 measures them).

    Returns
    -------
    ShapeEstimate

    Raises
    ------
    ValueError
        Wrong shapes or dtypes (the message names the shape expected and got), non-finite or
        implausible readings on valid links (naming them), a non-boolean mask, no valid link, a
        non-numeric or non-positive ``link_length``, a ``previous`` that is not a finite
        ShapeEstimate of this lattice, an unknown method or model, or missing links with
        ``method="paper"``.
    """
    t0 = time.perf_counter()
    opts = check_options(method, model, prior, noise_pct_g, bad_readings, paper_options)
    rows = check_int("rows", rows, 2)
    cols = check_int("cols", cols, 2)
    L = check_link_length(link_length)
    opts = opts._replace(noise_pct_g=check_noise_pct_g(noise_pct_g))
    snap = check_readings(readings, rows, cols, valid, bad_readings)
    n = snap.valid.size
    if previous is not None:
        check_previous(previous, n, rows, cols)
    rest_yaw = None if rest is None else rest_yaws(rest, n, rows, cols)
    if method == "paper" and snap.mask is not None:
        raise ValueError("method='paper' does not support missing links (the paper has none); "
                         "use method='global'.")
    warm = WarmStart.of(previous)
    if method == "global":
        st = structure_of(rows, cols, snap.mask, model)
        return solve_snapshot(snap, st, L, opts, warm, rest, rest_yaw, t0)
    return paper_snapshot(snap, rows, cols, L, opts, t0)


# ---------------------------------------------------------------------------------------------
# The stages, for one snapshot (arrays (n_links, ...)) or a batch of one structure (B, n_links, ...)
# ---------------------------------------------------------------------------------------------

class WarmStart(NamedTuple):
    """Where a global solve starts: the yaws (None: the prior's target), the joints the joint
    problem's weak prior holds isolated parts at (None: the rest layout or ``rest``'s joints),
    the solution whose factorisation it may reuse (when its structure is this one), and the
    links the estimate it came from had (None: all)."""

    yaws: np.ndarray | None = None
    joints: np.ndarray | None = None
    solution: Solution | None = None
    valid: np.ndarray | None = None
    #: the chain's fallback (`ShapeEstimate.warm_fallback`), used when this one does not cover
    fallback: "WarmStart | None" = None

    @classmethod
    def of(cls, previous: ShapeEstimate | None) -> "WarmStart":
        """The warm start an earlier estimate gives (``previous=``); none for None."""
        if previous is None:
            return cls()
        return cls(np.asarray(previous.yaws, dtype=float), np.asarray(previous.joints, float),
                   previous.solution, np.asarray(previous.valid, dtype=bool),
                   getattr(previous, "warm_fallback", None))

    def covers(self, valid: np.ndarray) -> bool:
        """Whether the estimate this came from had every link ``valid`` has."""
        return self.yaws is not None and (self.valid is None or bool(np.all(self.valid[valid])))

    def covering(self, valid: np.ndarray) -> "WarmStart":
        """Where a snapshot of links ``valid`` starts: this warm start if the estimate it came
        from had every one of them, else the chain's fallback if that had, else a cold start.

        A link the estimate lacked holds no yaw of this sheet, and parts it had apart (islands
        between missing links) hold yaws that agree only up to a rotation each. Starting a solve
        where they join ended in a wrong minimum that the warm chain then kept: a 64x64 sheet whose
        chips started over ~0.5 s had residual 2,410 instead of 0.03 on every later snapshot, and
        estimates of up to 3 s (tests/host/analysis/test_estimator_warm.py). The fallback keeps
        a snapshot after a short gap (a gateway late once) warm: it starts where the last
        snapshot before the gap ended."""
        if self.yaws is None or self.covers(valid):
            return self
        fb = self.fallback
        return fb if fb is not None and fb.covers(valid) else WarmStart()

    def next_fallback(self, valid: np.ndarray, own: "WarmStart") -> "WarmStart":
        """The fallback of the estimate of links ``valid`` made from this (chain's) warm start,
        whose own warm start is ``own``: ``own`` when it has every link the chain's fallback
        had (or there was none), else that fallback, kept."""
        fb = self.fallback if self.fallback is not None else (self if self.yaws is not None else None)
        if fb is None or own.covers(np.ones_like(valid) if fb.valid is None else fb.valid):
            return own
        return fb

    def start(self, st, target: np.ndarray):
        """(start yaws, the factorisation to reuse or None) on structure ``st``."""
        start = target if self.yaws is None else self.yaws
        sol = self.solution
        return start, (sol.factorisation if sol is not None and sol.structure is st else None)

    def link_cs(self, start):
        """The cosines and sines of the yaws ``start`` as the last solve kept them (the kernel's
        `YawProblem.link_cs` of its end point), or None when it kept none for these yaws."""
        sol = self.solution
        kept = None if sol is None else sol.problem.__dict__.get("_cs")
        return kept if kept is not None and np.array_equal(kept[0], start) else None

    def chain(self, lu):
        """The `solver.Contraction` a solve reusing factorisation ``lu`` may stop by: the one
        measured on it, for `solver.CHAIN_REMEASURE` snapshots (None: measure again)."""
        sol = self.solution
        c = None if sol is None or lu is None or sol.factorisation is not lu else sol.contraction
        return c if c is not None and c.age < solver.CHAIN_REMEASURE else None

    def joint_prior(self, st, L: float, rest=None) -> np.ndarray:
        """(n_joints, 3): the joints the joint problem's weak prior holds."""
        if self.joints is not None:
            return self.joints.reshape(-1, 3)
        if isinstance(rest, ShapeEstimate):
            return np.asarray(rest.joints, float).reshape(-1, 3)
        return L * st.rest_joints_unit


def link_angles(r: np.ndarray, valid: np.ndarray, mask):
    """Roll and pitch of every link (eq. 2), the invalid links read as level: (readings used,
    alpha, beta, trig) — ``trig`` the kernel's sines and cosines for one snapshot when the kernel
    is used (every later stage reuses them), else None."""
    rr = r if mask is None else np.where(valid[:, None], r, (0.0, 0.0, 1.0))
    if kernel.USE_KERNEL and rr.ndim == 2:
        return (rr, *roll_pitch_trig(rr))
    alpha, beta = angles_of(rr)
    return rr, alpha, beta, None


def closed_pitches(st, alpha, beta, trig=None):
    """The pitches made consistent with one height per joint: (beta, trig).

    A link's height step is ``−L sin β`` whatever its yaw, and around every cell the steps sum
    to zero (the z part of eq. 4). Noisy pitches break that; the heights that fit them best by
    least squares (``min Σ w (z_b − z_a + L sin β)²``, the joints' Laplacian weighted by
    `height_weights`, `weighted_heights`) satisfy it, and each valid link's pitch becomes
    ``asin`` of its fitted step. This removes the part of the pitch noise that no sheet can have
    (about half of it) before the yaws are solved with those pitches: the yaw problem's
    coefficients (``cos β``, the cells' normals) are then less noisy. A link in no closed loop
    keeps its pitch. One snapshot (``beta`` (n_links,)) or a batch of one structure
    (B, n_links); ``trig`` (one snapshot, the kernel's table) is rebuilt from the new pitches."""
    if trig is not None and kernel.USE_KERNEL:  # one snapshot: the kernel, the same arithmetic
        lk = laplacian_kernel(st)
        if lk is not None:
            return _closed_pitches_kernel(st, lk, trig, beta)
    vl = st.valid_links
    sb = np.sin(beta[..., vl])
    w = height_weights(sb) if WEIGHTED_HEIGHTS else None
    z = weighted_heights(st, -sb, w)
    step = (st.incidence @ z).T  # (..., n_valid): z_b - z_a of every valid link
    out = beta.copy()
    out[..., vl] = np.arcsin(np.clip(-step, -1.0, 1.0))
    if trig is not None:
        trig = angle_trig(alpha, out)
    return out, trig


def _closed_pitches_kernel(st, lk, trig_in, beta):
    """`closed_pitches` of one snapshot in the kernel (``capsheet_closed_pitches``: the same
    fit, `weighted_heights`' steps, with the Laplacian's solves in C), from the readings' trig
    (``trig_in``: the pitches' sines; the new pitches' cosines and sines are ``sqrt(1 − s²)``
    and ``s`` of the fitted step, no trigonometric call): (beta, trig)."""
    ep = st.derived.get("valid_endpoints")
    if ep is None:
        e = st.lattice.endpoints[st.valid_links]
        ep = st.derived["valid_endpoints"] = (
            np.ascontiguousarray(st.valid_links, np.int64), np.ascontiguousarray(e[:, 0], np.int64),
            np.ascontiguousarray(e[:, 1], np.int64))
    n, nv, nj = beta.size, ep[0].size, st.rows * st.cols
    a = np.ascontiguousarray(trig_in, np.float64)
    b = np.ascontiguousarray(beta, np.float64)
    out, trig = np.empty(n), np.empty((n, 4))
    work = np.empty(7 * nj + 2 * nv + lk[1][3]["work_size"])
    fb = _kffi.from_buffer
    _klib.capsheet_closed_pitches(lk[0], n, nv, fb("int64_t[]", ep[0]), fb("int64_t[]", ep[1]),
                                  fb("int64_t[]", ep[2]), fb("double[]", a), fb("double[]", b),
                                  1 if WEIGHTED_HEIGHTS else 0, HEIGHT_VAR_FLOOR,
                                  JOINT_PRIOR_WEIGHT, HEIGHT_CG_STEPS, fb("double[]", out),
                                  fb("double[]", trig), fb("double[]", work))
    return out, trig


#: Whether `closed_pitches` weights every link's height step by the inverse of its noise's
#: variance (`height_weights`); False: all alike (the estimator before; docs/estimator.md §2
#: measures both).
WEIGHTED_HEIGHTS = True
#: `height_weights`: the variance of a step's noise is taken as ``cos² β + HEIGHT_VAR_FLOOR``
#: (per σ², in L²), so that a link near the vertical, whose step the first-order noise leaves
#: alone, does not outweigh every other (its step still errs by the chip's misalignment, and
#: by σ² to second order)
HEIGHT_VAR_FLOOR = 0.05
#: `weighted_heights` takes this many conjugate-gradient steps from the unweighted fit towards
#: the weighted one (each costs one solve with the joints' Laplacian). On `capsheet paper
#: noise`'s tilted drape (seeds 1 and 2, 10 trials, 1-10 % g) 1 step gave 85 % of the exact fit's
#: gain, 2 steps 95 % (docs/estimator.md §2).
HEIGHT_CG_STEPS = 2


def height_weights(sin_beta):
    """Per link (..., n), the weight of its height step ``−L sin β`` in the height fit: the
    inverse of the step's noise variance. A reading's pitch has noise σ (per axis, in g) in
    every direction, and ``sin β = −s_x/|s|`` moves by ``cos β`` times it: a steep link's step is
    better known than a level one's (``1 / (cos² β + HEIGHT_VAR_FLOOR)``)."""
    return 1.0 / (1.0 - sin_beta * sin_beta + HEIGHT_VAR_FLOOR)


def weighted_heights(st, dz, w=None, steps=None):
    """The heights (n_joints,) or (n_joints, B) (in the unit of ``dz``) that fit every valid
    link's height step ``dz`` (..., n_valid) best, ``min Σ w (z_b − z_a − dz)²`` (plus the
    joints' weak prior), ``w`` (..., n_valid) the steps' weights (None: all 1).

    Unweighted it is one solve with the joints' Laplacian, factorised once per structure.
    Weighted, ``steps`` (default `HEIGHT_CG_STEPS`) conjugate-gradient steps on the weighted
    Laplacian, preconditioned by the unweighted one, start from the unweighted fit: the
    condition number is at most the weights' spread, so a few steps come close to the exact
    weighted fit without a factorisation per snapshot. A fixed number of steps, each snapshot's
    column on its own: a snapshot gets the same heights alone or in a batch."""
    B, BT = st.incidence, st.incidence_T
    solve = st.lap_lu.solve
    x = solve(np.ascontiguousarray(BT @ dz.T))
    if w is None:
        return x
    wt, dzt = w.T, dz.T  # (n_valid,) or (n_valid, B)
    eps = JOINT_PRIOR_WEIGHT
    r = BT @ (wt * (dzt - B @ x)) - eps * x  # the weighted normal equations' residual
    p = rz = None
    for _ in range(HEIGHT_CG_STEPS if steps is None else steps):
        zr = solve(np.ascontiguousarray(r))
        rz_new = np.add.reduce(r * zr, axis=0)
        p = zr if p is None else zr + (rz_new / np.where(rz > 0.0, rz, 1.0)) * p
        rz = rz_new
        ap = BT @ (wt * (B @ p)) + eps * p
        pap = np.add.reduce(p * ap, axis=0)
        a = rz / np.where(pap > 0.0, pap, 1.0)
        x = x + a * p
        r = r - a * ap
    return x


def noise_and_priors(prior: str, st, rr, norm_g, valid, rest_given: bool):
    """The readings' noise σ (per axis, fraction of g: the RMS of ``|s|/g − 1`` over the valid
    links — white noise of σ per axis moves ``|s|`` by σ; a static sheet reads exactly g), the
    prior's weights (`priors.prior_weights`) and the solver's tolerance: (σ, prior_w, bend_w,
    tol), each per snapshot for a batch."""
    if norm_g.ndim == 1:  # one snapshot: Python floats (numpy's scalars cost microseconds)
        e = norm_g[valid] - 1.0
        noise = float(np.sqrt(float(np.add.reduce(e * e)) / max(e.size, 1)))
    else:
        e = norm_g[:, valid] - 1.0
        noise = np.sqrt(np.add.reduce(e * e, axis=1) / max(e.shape[1], 1))
    prior_w, bend_w = prior_weights(prior, st, rr, np.where(valid, norm_g, 1.0), noise,
                                    rest_given)
    # stop when the step is far below what the noise moves the yaws by (σ rad, roughly)
    if norm_g.ndim == 1:
        return noise, prior_w, bend_w, max(solver.YAW_TOL_RAD, solver.YAW_TOL_NOISE * noise)
    return noise, prior_w, bend_w, np.maximum(solver.YAW_TOL_RAD, solver.YAW_TOL_NOISE * noise)


def solve_snapshot(snap: Snapshot, st, L: float, opts: Options, warm: WarmStart, rest=None,
                   rest_yaw=None, t0: float | None = None) -> ShapeEstimate:
    """``method="global"`` on one checked snapshot, on structure ``st`` (its lattice, mask and
    model), from ``warm``: angles -> prior weights -> solve -> joints and mask."""
    t0 = time.perf_counter() if t0 is None else t0
    rows, cols = st.rows, st.cols
    rr, alpha, beta, trig = link_angles(snap.readings, snap.valid, snap.mask)
    if CLOSE_PITCHES:
        beta, trig = closed_pitches(st, alpha, beta, trig)
    t1 = time.perf_counter()
    target = st.rest_yaw if rest_yaw is None else rest_yaw
    chain, warm = warm, warm.covering(snap.valid)
    start, lu = warm.start(st, target)
    _, prior_w, bend_w, tol = noise_and_priors(opts.prior, st, rr, snap.norm_g, snap.valid,
                                               rest_yaw is not None)
    if lu is not None and warm.solution.stale_run >= solver.STALE_RUN:
        lu = None  # a stale factorisation (a moving sheet's): a new one before the first step
    gamma, iters, n_fact, lu, prob, contraction = solve_global(
        st, alpha, beta, start.copy(), target, prior_w, bend_w, lu, tol, trig,
        warm.chain(lu), warm.link_cs(start))
    base, run = None, 0
    if n_fact == 0 and lu is not None:  # solved wholly on the warm start's factorisation
        base = warm.solution.base_steps
        base = int(iters) if base is None else base
        run = warm.solution.stale_run + 1 if iters >= base + solver.STALE_STEPS else 0
    solution = Solution(st, lu, prob, gamma, contraction, base, run)
    t2 = time.perf_counter()
    kept = prob.__dict__.get("_cs") if trig is not None else None  # the end point's cos, sin
    cs = kept[1] if kept is not None and np.array_equal(kept[0], gamma) else None
    P, d, nrm, gamma, alpha, beta, residual = joints_and_mask(
        st, L, alpha, beta, gamma, target, warm.joint_prior(st, L, rest), trig, cs)
    t3 = time.perf_counter()
    solv = link_solvability(alpha, beta, trig, rows, cols)
    t4 = time.perf_counter()
    joints = P.reshape(rows, cols, 3)
    fallback = chain.next_fallback(snap.valid, WarmStart(gamma, joints, solution, snap.valid))
    return ShapeEstimate(joints=joints, directions=d, residual=residual,
                         solvability=solv, normals=nrm, yaws=gamma, alpha=alpha, beta=beta,
                         valid=snap.valid, link_length=L, method="global",
                         iterations=int(iters), factorisations=int(n_fact),
                         timings={"angles": t1 - t0, "yaw": t2 - t1, "joints": t3 - t2,
                                  "total": t4 - t0}, noise_pct_g=opts.noise_pct_g,
                         solution=solution, warm_fallback=fallback)


def link_solvability(alpha, beta, trig, rows: int, cols: int) -> np.ndarray:
    """`solvability` (from the kernel's ``trig`` when there is one)."""
    if trig is None:
        return solvability(alpha, beta, rows, cols)
    return solvability_from_trig(trig, rows, cols)


def paper_snapshot(snap: Snapshot, rows: int, cols: int, L: float, opts: Options, t0: float
           ) -> ShapeEstimate:
    """``method="paper"``: host.analysis.paper_method on the checked snapshot."""
    from .. import paper_method

    _, alpha, beta, trig = link_angles(snap.readings, snap.valid, snap.mask)
    t1 = time.perf_counter()
    res = paper_method.estimate(alpha, beta, rows, cols, L,
                                opts.paper_options or paper_method.PaperOptions())
    t2 = t1 + res["t_yaw"]
    t3 = time.perf_counter()
    solv = link_solvability(alpha, beta, trig, rows, cols)
    t4 = time.perf_counter()
    return ShapeEstimate(joints=res["joints"], directions=res["directions"],
                         residual=res["residual"], solvability=solv, normals=res["normals"],
                         yaws=res["yaws"], alpha=alpha, beta=beta, valid=snap.valid,
                         link_length=L, method="paper", iterations=int(res["iterations"]),
                         factorisations=0,
                         timings={"angles": t1 - t0, "yaw": t2 - t1, "joints": t3 - t2,
                                  "total": t4 - t0}, noise_pct_g=opts.noise_pct_g)
