"""`estimate`: one snapshot of readings, checked, to its shape (global or the paper's method)."""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

import host.analysis.estimator.kernel as kernel  # the switch, read at call time
import host.analysis.estimator.solver as solver  # YAW_TOL_*, read at call time
from .angles import G0, angles_of, roll_pitch_trig, solvability_from_trig, solvability
from .joints import joints_and_mask
from .priors import PRIORS, prior_weights
from .result import ShapeEstimate, Solution
from .solver import solve_global
from .structure import lattice_of, structure_of

__all__ = ["METHODS", "MODELS", "READING_NORM_RANGE", "check_int", "rest_yaws", "check_previous",
           "estimate", "Options", "check_options", "check_noise_pct_g", "check_link_length",
           "Snapshot", "check_readings", "WarmStart", "link_angles", "noise_and_priors",
           "solve_snapshot", "link_solvability", "paper_snapshot"]

#: `estimate`'s methods (module docstring)
METHODS = ("global", "paper")
#: `estimate`'s normal models (module docstring)
MODELS = ("cells", "eq6")
#: Plausible |reading| range, in g: outside it a link is a dead, stuck or saturated chip.
READING_NORM_RANGE = (0.5, 1.5)


def check_int(name: str, v, lo: int) -> int:
    """``v`` as an int >= ``lo`` (ValueError naming ``name`` otherwise; a bool is no integer)."""
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v < lo:
        raise ValueError(f"Invalid {name}: {v!r} (need an integer >= {lo})")
    return int(v)


def _as_real(name: str, x, shape: tuple) -> np.ndarray:
    """``x`` as a float array of ``shape``; complex, string, object or bool input is an error."""
    a = np.asarray(x)
    if a.dtype.kind not in "iuf":
        raise ValueError(f"Invalid {name}: dtype {a.dtype} (need real numbers, m/s²)")
    a = a.astype(float, copy=False)
    if a.shape != shape:
        raise ValueError(f"Expected `{name}` to have shape {shape}, got {a.shape}.")
    return a


def rest_yaws(rest, n: int, rows: int, cols: int) -> np.ndarray:
    """The rest yaws (n,) of ``rest`` (a `ShapeEstimate` of this lattice, or its yaws), checked."""
    if isinstance(rest, ShapeEstimate):
        if rest.joints.shape != (rows, cols, 3):
            raise ValueError(f"Expected `rest` of a {rows}x{cols} lattice, joints shape "
                             f"({rows}, {cols}, 3), got {rest.joints.shape}.")
        y = np.asarray(rest.yaws, float)
    else:
        y = np.asarray(rest)
        if y.dtype.kind not in "iuf":
            raise ValueError(f"Invalid rest: {type(rest).__name__} of dtype {y.dtype} (need a "
                             f"ShapeEstimate or rest yaws, shape ({n},), radians)")
        y = y.astype(float)
        if y.shape != (n,):
            raise ValueError(f"Expected `rest` yaws to have shape ({n},) for a {rows}x{cols} "
                             f"lattice, got {y.shape}.")
    if not np.all(np.isfinite(y)):
        raise ValueError("Invalid rest: its yaws contain NaN or inf.")
    return y


def check_previous(previous, n: int, rows: int, cols: int) -> None:
    """ValueError unless ``previous`` is a finite `ShapeEstimate` of this lattice."""
    if not isinstance(previous, ShapeEstimate):
        raise ValueError(f"Invalid previous: {type(previous).__name__} (need a ShapeEstimate from "
                         "an earlier estimate() of the same lattice, or None)")
    pj = np.shape(previous.joints)
    if pj != (rows, cols, 3):
        raise ValueError(f"Expected `previous` of a {rows}x{cols} lattice, joints shape "
                         f"({rows}, {cols}, 3), got {pj}.")
    if np.shape(previous.yaws) != (n,):
        raise ValueError(f"Expected `previous.yaws` to have shape ({n},), got "
                         f"{np.shape(previous.yaws)}.")
    if not (np.all(np.isfinite(previous.yaws)) and np.all(np.isfinite(previous.joints))):
        raise ValueError("Invalid previous: its yaws or joints contain NaN or inf (a failed "
                         "estimate cannot seed the next one; pass previous=None)")


def estimate(readings: np.ndarray, rows: int, cols: int, link_length: float,
             valid: np.ndarray | None = None, previous: ShapeEstimate | None = None,
             method: str = "global", *, rest=None, model: str = "cells",
             prior: str = "adaptive", noise_pct_g: float = 1.0,
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
    prior : {"adaptive", "level", "off", "fixed", "local"}
        What fills in what the data cannot determine (`PRIORS`; docs/estimator.md measures
        them): "adaptive" (default) holds the bending of the lattice and the shear of level
        cells, with weights that scale with the readings' noise (noise-free readings: only a
        floor), so that it does not pull where the data decide; "level" holds the bending
        only where the region is level (unbiased on a drape, whose lattice lines turn in
        plan; noisier on nets whose lines run straight); "off" keeps only the floors (the data
        alone); "fixed" and "local" are the alternatives it was measured against.
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
# The checks (`estimate`, `estimate_batch` and `ShapeEstimator` make the same)
# ---------------------------------------------------------------------------------------------

class Options(NamedTuple):
    """The checked options of `estimate` that do not depend on the lattice."""

    method: str
    model: str
    prior: str
    noise_pct_g: float
    bad_readings: str
    paper_options: object


def check_options(method="global", model="cells", prior="adaptive", noise_pct_g=1.0,
                  bad_readings="raise", paper_options=None) -> Options:
    """`estimate`'s options checked (ValueError naming what is wrong), as an `Options`
    (``noise_pct_g`` is checked by `check_noise_pct_g`)."""
    if method not in METHODS:
        raise ValueError(f"Invalid method: {method!r} (expected one of {METHODS})")
    if model not in MODELS:
        raise ValueError(f"Invalid model: {model!r} (expected one of {MODELS})")
    if prior not in PRIORS:
        raise ValueError(f"Invalid prior: {prior!r} (expected one of {PRIORS})")
    if bad_readings not in ("raise", "mask"):
        raise ValueError(f"Invalid bad_readings: {bad_readings!r} (expected 'raise' or 'mask')")
    if paper_options is not None:  # method="paper" only (host.analysis.paper_method)
        from ..paper_method import PaperOptions
        if method != "paper" or not isinstance(paper_options, PaperOptions):
            raise ValueError(f"Invalid paper_options: {paper_options!r} (a PaperOptions, with "
                             "method='paper' only)")
    return Options(method, model, prior, noise_pct_g, bad_readings, paper_options)


def check_noise_pct_g(noise_pct_g) -> float:
    """``noise_pct_g`` as a finite float >= 0 (ValueError otherwise)."""
    if isinstance(noise_pct_g, (bool, np.bool_)) or not isinstance(noise_pct_g,
                                                                    (int, float, np.number)) \
            or not (np.isfinite(noise_pct_g) and noise_pct_g >= 0):
        raise ValueError(f"Invalid noise_pct_g: {noise_pct_g!r} (need a finite value >= 0)")
    return float(noise_pct_g)


def check_link_length(link_length) -> float:
    """``link_length`` as a finite float > 0, metres (ValueError otherwise)."""
    if isinstance(link_length, (bool, np.bool_)) or not isinstance(link_length,
                                                                    (int, float, np.number)):
        raise ValueError(f"Invalid link_length: {link_length!r} (need a number of metres > 0)")
    L = float(link_length)
    if not (np.isfinite(L) and L > 0):
        raise ValueError(f"Invalid link_length: {link_length!r} (need a finite value > 0 m)")
    return L


class Snapshot(NamedTuple):
    """One snapshot's readings, checked (`check_readings`)."""

    #: readings, (n_links, 3), m/s², float
    readings: np.ndarray
    #: the links used, (n_links,) bool: ``valid`` less the implausible readings masked out
    valid: np.ndarray
    #: ``valid``, or None when every link is used
    mask: np.ndarray | None
    #: ``|s| / G0`` per link, (n_links,)
    norm_g: np.ndarray


def check_readings(readings, rows: int, cols: int, valid=None, bad_readings: str = "raise"
                   ) -> Snapshot:
    """One snapshot's readings and mask checked as `estimate` checks them (ValueError naming the
    shape expected and got, the non-finite or implausible links), as a `Snapshot`."""
    n = lattice_of(rows, cols).n_links
    r = np.asarray(readings)
    if r.dtype.kind not in "iuf":
        raise ValueError(f"Invalid readings: dtype {r.dtype} (need real numbers, m/s²)")
    r = r.astype(float, copy=False)
    if r.shape != (n, 3):
        raise ValueError(f"Expected `readings` to have shape ({n}, 3) for a {rows}x{cols} "
                         f"lattice, got {r.shape}.")
    if valid is None:
        vmask = np.ones(n, bool)
    else:
        vmask = np.asarray(valid)
        if vmask.dtype != bool:
            raise ValueError(f"Invalid valid: dtype {vmask.dtype} (need a boolean mask, True = "
                             "link present)")
        if vmask.shape != (n,):
            raise ValueError(f"Expected `valid` to have shape ({n},) for a {rows}x{cols} lattice, "
                             f"got {vmask.shape}.")
        if not vmask.any():
            raise ValueError(f"No valid link: all {n} links are masked out by `valid`; "
                             "cannot estimate a shape.")
    bad = ~np.all(np.isfinite(r), axis=1) & vmask
    if bad.any():
        raise ValueError(f"Non-finite readings on valid links {_few(np.flatnonzero(bad))}; mask "
                         "them out with `valid`.")
    norm = np.sqrt(np.einsum("ij,ij->i", r, r)) / G0
    lo, hi = READING_NORM_RANGE
    far = vmask & ~((norm >= lo) & (norm <= hi))
    if far.any():
        if bad_readings == "raise":
            k = np.flatnonzero(far)
            raise ValueError(f"Implausible readings on links {_few(k)}: |s| = "
                             f"{_few(np.round(norm[k], 3))} g, outside [{lo}, {hi}] g (dead or "
                             "stuck chips?); mask them with `valid` or bad_readings='mask'.")
        vmask = vmask & ~far
        if not vmask.any():
            raise ValueError("No valid link left after masking the implausible readings.")
    return Snapshot(r, vmask, None if vmask.all() else vmask, norm)


# ---------------------------------------------------------------------------------------------
# The stages, for one snapshot (arrays (n_links, ...)) or a batch of one structure (B, n_links, ...)
# ---------------------------------------------------------------------------------------------

class WarmStart(NamedTuple):
    """Where a global solve starts: the yaws (None: the prior's target), the joints the joint
    problem's weak prior holds isolated parts at (None: the rest layout or ``rest``'s joints),
    and the solution whose factorisation it may reuse (when its structure is this one)."""

    yaws: np.ndarray | None = None
    joints: np.ndarray | None = None
    solution: Solution | None = None

    @classmethod
    def of(cls, previous: ShapeEstimate | None) -> "WarmStart":
        """The warm start an earlier estimate gives (``previous=``); none for None."""
        if previous is None:
            return cls()
        return cls(np.asarray(previous.yaws, dtype=float), np.asarray(previous.joints, float),
                   previous.solution)

    def start(self, st, target: np.ndarray):
        """(start yaws, the factorisation to reuse or None) on structure ``st``."""
        start = target if self.yaws is None else self.yaws
        sol = self.solution
        return start, (sol.factorisation if sol is not None and sol.structure is st else None)

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
    t1 = time.perf_counter()
    target = st.rest_yaw if rest_yaw is None else rest_yaw
    start, lu = warm.start(st, target)
    _, prior_w, bend_w, tol = noise_and_priors(opts.prior, st, rr, snap.norm_g, snap.valid,
                                               rest_yaw is not None)
    gamma, iters, n_fact, lu, prob = solve_global(st, alpha, beta, start.copy(), target,
                                                  prior_w, bend_w, lu, tol, trig)
    solution = Solution(st, lu, prob, gamma)
    t2 = time.perf_counter()
    P, d, nrm, gamma, alpha, beta, residual = joints_and_mask(
        st, L, alpha, beta, gamma, target, warm.joint_prior(st, L, rest), trig)
    t3 = time.perf_counter()
    solv = link_solvability(alpha, beta, trig, rows, cols)
    t4 = time.perf_counter()
    return ShapeEstimate(joints=P.reshape(rows, cols, 3), directions=d, residual=residual,
                         solvability=solv, normals=nrm, yaws=gamma, alpha=alpha, beta=beta,
                         valid=snap.valid, link_length=L, method="global",
                         iterations=int(iters), factorisations=int(n_fact),
                         timings={"angles": t1 - t0, "yaw": t2 - t1, "joints": t3 - t2,
                                  "total": t4 - t0}, noise_pct_g=opts.noise_pct_g,
                         solution=solution)


def link_solvability(alpha, beta, trig, rows: int, cols: int) -> np.ndarray:
    """`solvability` (from the kernel's ``trig`` when there is one)."""
    if trig is None:
        return solvability(alpha, beta, rows, cols)
    return solvability_from_trig(trig, rows, cols)


def paper_snapshot(snap: Snapshot, rows: int, cols: int, L: float, opts: Options, t0: float
           ) -> ShapeEstimate:
    """``method="paper"``: host.analysis.paper_method (issue 33) on the checked snapshot."""
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


def _few(idx, limit: int = 8) -> str:
    """A short list for error messages: the first ``limit`` items and how many more."""
    items = [str(v) for v in np.asarray(idx).tolist()[:limit]]
    more = len(idx) - len(items)
    return "[" + ", ".join(items) + (f", … {more} more" if more > 0 else "") + "]"
