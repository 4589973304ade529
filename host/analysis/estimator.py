"""Shape estimator: from one snapshot of link readings to the 3D shape of the whole sheet.

Conventions are docs/design.md's and are not restated differently here: joints ``P[i, j]`` of shape
``(rows, cols, 3)`` in metres, world frame z up; link order and the 4-link units come from
`protocol.lattice.Lattice` only (``endpoints``, ``units``: ``d0 + d1 = d3 + d2``,
``n0 + n2 = n1 + n3``); sensor frame x along the link, z the sheet normal (top face); readings are
specific force (flat, top face up, reads ``(0, 0, +G0)``); ``R = Rz(γ) Ry(β) Rx(α)``; radians.

Two methods, same input, same output (`ShapeEstimate`):

``method="paper"`` (Hoshi & Shinoda, sections 2-3; the reference to beat)
    Roll and pitch from eq. (2) in closed form; per 4-link unit, eq. (8) by steepest descent
    from several starts; the units combined into the sheet. It lives in
    `host.analysis.paper_method`, which names every choice the paper leaves open
    (``paper_options=PaperOptions(...)``); this module only checks the input and dispatches.
    Missing links are not supported (the paper has none).

``method="global"`` (default)
    Roll and pitch as above. All yaws at once, one sparse nonlinear least-squares problem
    (Gauss-Newton with Levenberg-Marquardt damping, one yaw fixed as gauge), warm-started from
    ``previous`` (its yaws and its factorisation, reused while it still contracts well). Terms,
    all in ``z_k = exp(iγ_k)`` (docs/estimator.md has the derivation and the measurements):

    * loop closure, eq. (4), xy part, per unit: ``Σ_m s_m cos β_m z_m = 0`` (exact);
    * the normal model (``model="cells"``, default): per link, its sensor y (known up to yaw)
      is perpendicular to the mean normal of its (one or two) cells, each cell's normal being
      ``A × C`` with ``A``, ``C`` the sums of its two i- and two j-link directions. This is the
      sheet normal a chip on the cloth sees, and it is exact on a Chebyshev net, where eq. (6)
      is not (``model="eq6"`` keeps the paper's assumption, weighted `NORMAL_WEIGHT`);
    * the prior (``prior="adaptive"``, default): what the data cannot determine is held by
      pairs of yaw differences, never by absolute yaws — the bending of the lattice (parallel
      neighbours) and the corner angle of cells that are level within the noise (the paper's
      Case 1) — towards the rest shape's (``rest=``; default square cells). Their weights scale
      with the readings' noise, estimated per snapshot from the spread of ``|s|`` about g, so
      that noise-free readings meet only a floor and the prior never pulls where the data
      decide; the target is never the previous estimate, so long runs do not drift.

    The normal matrix has a fixed sparsity pattern per lattice, mask and model; pattern,
    fill-reducing ordering and index maps are computed once and cached. Then joints by least
    squares over all valid links, ``min Σ ‖p_b − p_a − L d‖²`` (heights follow from the pitches
    alone), with the graph Laplacian factorised once per lattice and mask. A link marked
    invalid contributes no constraint: its two units are dropped from the yaw problem and the
    link from the joint problem; its reported direction is the chord between its estimated
    joints. `ShapeEstimate.yaw_std` and ``joint_std`` state the data's uncertainty (computed on
    first access).

In both, joint ``(0, 0)`` is placed at the origin. The estimate is defined up to a rotation about
world z (yaw gauge); `overlay_error` and `error_percent_of_side` compare shapes as the paper does,
after a least-squares rigid overlay.

This module needs numpy and scipy only; it does not import `virtual_sheet`. One snapshot's
arithmetic (the yaw problem's coefficients, the chord steps' cost and gradient, SuperLU's
triangular sweeps, the flatness, directions, eq. (8) and solvability) runs in a small C kernel
when it is built (host/analysis/_kernel/, cffi, at install; `USE_KERNEL`), else in the numpy code
beside it, which gives the same numbers to rounding; `estimate_batch` always runs the numpy code.
"""

from __future__ import annotations

import copy
import os
import time
from dataclasses import dataclass, field
from functools import cached_property, lru_cache

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from protocol.lattice import Lattice

from .metrics import error_percent_of_side, overlay, overlay_error

try:  # the compiled cost-and-gradient kernel (host/analysis/_kernel/); optional
    if os.environ.get("CAPSHEET_NO_KERNEL"):
        raise ImportError("CAPSHEET_NO_KERNEL is set")
    from ._yaw_kernel import ffi as _kffi, lib as _klib
except ImportError:  # not built (no C compiler at install): the numpy code, same numbers
    _kffi = _klib = None

__all__ = ["ShapeEstimate", "estimate", "estimate_batch", "roll_pitch", "solvability", "overlay",
           "joints_from_directions",
           "overlay_error", "error_percent_of_side", "METHODS", "MODELS", "PRIORS"]

METHODS = ("global", "paper")
#: Standard gravity, m/s² (protocol.constants.G0; host/analysis imports only protocol.lattice).
G0 = 9.80665
MODELS = ("cells", "eq6")
#: Plausible |reading| range, in g: outside it a link is a dead, stuck or saturated chip.
READING_NORM_RANGE = (0.5, 1.5)

#: The priors `estimate` offers (docs/estimator.md compares them): "adaptive" (default) —
#: bending + flat-cell shear, both scaled by the readings' noise; "level" — the same with the
#: bending held only where the region is level: unbiased on a sheet
#: whose lattice lines turn in plan (a drape), noisier on nets whose lines run straight; "off" —
#: only the floors that keep the problem regular (the data alone); "fixed" — the former prior,
#: ``FIXED_PRIOR_WEIGHT`` on every yaw towards the rest; "local" — that yaw prior weighted by
#: the cell's flatness.
PRIORS = ("adaptive", "level", "off", "fixed", "local")
#: Weight of the "fixed"/"local" priors on ``wrap(γ − γ_rest)²`` (the estimator's former prior).
FIXED_PRIOR_WEIGHT = 1e-2
#: Least weight of the yaw prior towards the rest yaws (keeps a link without constraints defined).
ABS_PRIOR_FLOOR = 1e-10
#: Weight of the normal-assumption residuals (eq. 6) relative to the loop closure (eq. 4).
NORMAL_WEIGHT = 0.2
#: Weight of the roll residuals (model "cells") relative to the loop closure (eq. 4); measured
#: best at 5 % g among 0.03-3 (docs/estimator.md).
ROLL_WEIGHT = 0.3
#: Prior std of the bending (yaw difference of parallel neighbours beyond the rest's), rad: the
#: bending prior's weight is ``(σ/BEND_STD_RAD)²`` for readings of noise σ (fraction of g).
BEND_STD_RAD = 0.1
#: Weight of the shear prior (a cell's corner angle towards the rest's) on a flat cell; a cell
#: of tilt θ gets ``SHEAR_WEIGHT · exp(−(θ / (FLAT_TILT_NOISE · σ))²)``.
SHEAR_WEIGHT = 1e-3
#: ... when the rest shape is given (``rest=``): then it is known, not guessed, and holds harder.
SHEAR_WEIGHT_REST = 1e-2
#: A cell counts as flat (locally unobservable, Case 1) while its tilt is below ~this many σ.
FLAT_TILT_NOISE = 3.0
#: ... averaged over (2 FLAT_RADIUS + 1)² cells around it.
FLAT_RADIUS = 3
#: Every prior pair's least weight (noise-free readings): keeps Case 1 regions defined.
PRIOR_WEIGHT_MIN = 1e-8
#: Sparse factorisation of the yaw problem: "splu" (scipy's SuperLU, always there; the default:
#: benchmarks/bench_estimator.py found no consistent gain from CHOLMOD on warm runs, -17 % to
#: +29 % snapshots/s by size), "cholmod" (scikit-sparse, optional: ``pip install
#: 'capture-sheet[fast]'``, needs libsuitesparse-dev) or "auto" (CHOLMOD when installed).
LINEAR_SOLVER = "splu"
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
_REFACTOR_RATIO = 0.7
#: Evaluate a single snapshot's yaw cost and gradient (model "cells", the chord steps) with the
#: compiled kernel when it is built; False: the numpy code (same numbers to ~1e-15 relative;
#: tests/host/analysis/test_estimator_kernel.py). `estimate_batch` always uses numpy.
USE_KERNEL = _klib is not None
#: Weight of the joints' prior (keeps components cut off by missing links defined), per m².
JOINT_PRIOR_WEIGHT = 1e-9

# eq. (4): d0 + d1 - d2 - d3 = 0;  eq. (6): n0 - n1 + n2 - n3 = 0  (Lattice.units numbering)
_S_D = np.array([1.0, 1.0, -1.0, -1.0])
_S_N = np.array([1.0, -1.0, 1.0, -1.0])


@dataclass(frozen=True, eq=False)
class ShapeEstimate:
    """One estimated shape of the sheet.

    Attributes
    ----------
    joints : ndarray, shape (rows, cols, 3)
        Joint positions, metres, world frame (z up), joint ``(0, 0)`` at the origin.
    directions : ndarray, shape (n_links, 3)
        Unit direction of every link (sensor x in world), lattice order. For an invalid link, the
        normalised chord between its estimated joints.
    residual : float
        Sum over all units with four valid links of eq. (8) (loop closure and normal assumption,
        x, y and z), at the final yaws: the same measure for both methods (dimensionless).
    solvability : ndarray, shape (rows-1, cols-1)
        Per unit, ``λ3/λ1`` of eq. (7)'s 4x6 matrix (singular values, largest first); below 0.1 the
        unit's yaws are poorly determined (paper section 2.3). NaN for units with a missing link.
    normals : ndarray, shape (n_links, 3)
        Sensor z of every link in world coordinates (unit); NaN for invalid links.
    yaws : ndarray, shape (n_links,)
        Yaw γ of every link, radians (what ``previous`` warm-starts from); prior value if invalid.
    alpha, beta : ndarray, shape (n_links,)
        Roll and pitch from eq. (2), radians; NaN for invalid links.
    valid : ndarray of bool, shape (n_links,)
        The mask used.
    link_length : float
        ``L``, metres.
    method : str
        ``"global"`` or ``"paper"``.
    iterations : int
        Gauss-Newton iterations (global) or steepest-descent steps (paper,
        `host.analysis.paper_method`).
    factorisations : int
        Sparse factorisations of the Gauss-Newton matrix made for this snapshot (global; 0 when
        the previous snapshot's factorisation sufficed).
    timings : dict
        Wall time of the stages, seconds: ``"angles"``, ``"yaw"``, ``"joints"``, ``"total"``.
    """

    joints: np.ndarray
    directions: np.ndarray
    residual: float
    solvability: np.ndarray
    normals: np.ndarray
    yaws: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray
    valid: np.ndarray
    link_length: float
    method: str
    iterations: int
    factorisations: int
    timings: dict = field(default_factory=dict)
    #: the reading noise (per axis, % of g) `yaw_std` and `joint_std` are stated for
    noise_pct_g: float = 1.0
    #: solver state a later snapshot may warm-start from (structure, factorisation); private
    _state: tuple | None = field(default=None, repr=False)

    @cached_property
    def yaw_std(self) -> np.ndarray:
        """Per link, the standard deviation of its yaw, radians, shape (n_links,), for readings of
        `noise_pct_g` per axis: from the global problem's normal matrix at the estimate
        (docs/estimator.md), relative to the sheet's mean yaw. Where the data do not determine a
        yaw (Case 1, a squashed unit) it is large (the prior's floor: ≫ 1 rad). NaN for
        ``method="paper"`` and for missing links."""
        return _uncertainty(self)[0]

    @cached_property
    def joint_std(self) -> np.ndarray:
        """Per joint, the standard deviation of its position (3-D RMS), metres, shape
        (rows, cols), for readings of `noise_pct_g` per axis, from the yaws' uncertainty
        (`yaw_std`) carried through the joint least squares, after removing the mean
        translation. NaN for ``method="paper"``."""
        return _uncertainty(self)[1]

    @property
    def rows(self) -> int:
        return self.joints.shape[0]

    @property
    def cols(self) -> int:
        return self.joints.shape[1]


# ---------------------------------------------------------------------------------------------
# Angles (eq. 2) and solvability (eq. 7)
# ---------------------------------------------------------------------------------------------

def roll_pitch(readings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Roll α and pitch β of every link from its reading, closed form (paper eq. 2).

    The reading is ``g (−sin β, cos β sin α, cos β cos α)`` (specific force; the paper's ``s`` with
    the opposite sign), so ``α = atan2(r_y, r_z)``, ``β = atan2(−r_x, hypot(r_y, r_z))``.

    Parameters
    ----------
    readings : ndarray, shape (n_links, 3)
        Specific force, m/s² (any common scale), sensor frame.

    Returns
    -------
    alpha : ndarray, shape (n_links,)
        Roll, radians, in (−π, π].
    beta : ndarray, shape (n_links,)
        Pitch, radians, in [−π/2, π/2]; positive when the link points down.
    """
    r = np.asarray(readings, dtype=float)
    if r.ndim != 2 or r.shape[1] != 3:
        raise ValueError(f"Expected `readings` to have shape (n_links, 3), got {r.shape}.")
    return _angles(r)


def _angles(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`roll_pitch` without the checks, over the last axis of ``r`` (..., 3)."""
    return np.arctan2(r[..., 1], r[..., 2]), np.arctan2(-r[..., 0], np.hypot(r[..., 1], r[..., 2]))


def _eq7_matrices(alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """Eq. (7)'s 4x6 matrices for units given as ``(..., 4)`` angle arrays (paper numbering).

    Used by the solvability figure; `solvability` itself uses the equivalent complex form.
    """
    ca, sa, cb, sb = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)
    M = np.zeros(alpha.shape[:-1] + (4, 6))
    sign = (-1.0, 1.0, 1.0)  # eq. (4) solved for d0: d0 = -d1 + d2 + d3
    nsign = (1.0, -1.0, 1.0)  # eq. (6) solved for n0: n0 = n1 - n2 + n3
    for m in (1, 2, 3):
        c = 2 * (m - 1)
        M[..., 0, c] = sign[m - 1] * cb[..., m]
        M[..., 1, c + 1] = sign[m - 1] * cb[..., m]
        p = sb[..., m] * ca[..., m]
        M[..., 2, c] = nsign[m - 1] * p
        M[..., 2, c + 1] = nsign[m - 1] * sa[..., m]
        M[..., 3, c] = -nsign[m - 1] * sa[..., m]
        M[..., 3, c + 1] = nsign[m - 1] * p
    return M


def solvability_units(alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """``λ3/λ1`` of eq. (7) for units given as ``(..., 4)`` angle arrays.

    Eq. (7)'s 4x6 real matrix is the realification of a complex 2x3 matrix ``K`` acting on
    ``(e^{iγ1}, e^{iγ2}, e^{iγ3})``: row 1 holds ``−cos β1, cos β2, cos β3`` and row 2
    ``±(sin β_m cos α_m − i sin α_m)`` with signs ``+, −, +``. A realification has the singular
    values of ``K``, each twice, so ``λ1 = λ2 = σ1(K)`` and ``λ3 = λ4 = σ2(K)``, and ``σ²`` are the
    eigenvalues of the 2x2 Hermitian ``K Kᴴ`` in closed form. `_eq7_matrices` + SVD agrees.
    """
    ca, sa, cb, sb = (np.cos(alpha[..., 1:]), np.sin(alpha[..., 1:]), np.cos(beta[..., 1:]),
                      np.sin(beta[..., 1:]))
    a = cb * np.array([-1.0, 1.0, 1.0])
    b = (sb * ca - 1j * sa) * np.array([1.0, -1.0, 1.0])
    return _sigma_ratio(a, b)


#: its name before it was public (host/analysis/_kernel/yaw_eval.h cites it)
_solvability_units = solvability_units


def _sigma_ratio(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``σ2/σ1`` of the complex 2x3 matrices with rows ``a`` (real, (..., 3)) and ``b`` (complex)."""
    A = np.sum(a * a, axis=-1)
    B = np.sum(b.real ** 2 + b.imag ** 2, axis=-1)
    C = np.sum(a * b, axis=-1)  # a real: a * conj(b) has the same modulus
    half = 0.5 * (A + B)
    disc = np.sqrt(np.maximum(0.25 * (A - B) ** 2 + (C.real ** 2 + C.imag ** 2), 0.0))
    mu1 = half + disc
    mu2 = np.maximum(half - disc, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(mu1 > 0, np.sqrt(mu2 / np.where(mu1 > 0, mu1, 1.0)), 0.0)


def solvability(alpha: np.ndarray, beta: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Per unit, ``λ3/λ1`` of eq. (7)'s 4x6 coefficient matrix (paper section 2.3).

    Parameters
    ----------
    alpha, beta : ndarray, shape (n_links,)
        Roll and pitch of every link, radians (NaN marks a missing link).
    rows, cols : int
        Lattice size in joints.

    Returns
    -------
    ndarray, shape (rows-1, cols-1)
        Third over first singular value, in [0, 1]; < 0.1 means unsolvable in the paper's sense
        (Case 1: a horizontal unit; Case 2: a squashed one). NaN where a link is missing.
    """
    units = _lattice(rows, cols).units
    if USE_KERNEL and np.ndim(alpha) == 1 and np.ndim(beta) == 1:  # one snapshot: the kernel
        al = np.ascontiguousarray(alpha, dtype=np.float64)
        be = np.ascontiguousarray(beta, dtype=np.float64)
        if al.shape == be.shape == (_lattice(rows, cols).n_links,):
            return _solvability_kernel(_angle_trig(al, be), rows, cols)
    a, b = np.asarray(alpha, float)[..., units], np.asarray(beta, float)[..., units]
    ratio = solvability_units(a, b)
    bad = ~np.all(np.isfinite(a) & np.isfinite(b), axis=-1)
    if bad.any():
        ratio[bad] = np.nan
    return ratio


def _angle_trig(alpha, beta) -> np.ndarray:
    """(n, 4): cos α, sin α, cos β, sin β per link (the kernel's ``trig``)."""
    a = np.ascontiguousarray(alpha, dtype=np.float64)
    b = np.ascontiguousarray(beta, dtype=np.float64)
    trig = np.empty((a.size, 4))
    fb = _kffi.from_buffer
    _klib.capsheet_angle_trig(a.size, fb("double[]", a), fb("double[]", b), fb("double[]", trig))
    return trig


def _roll_pitch_trig(r: np.ndarray):
    """`roll_pitch` of one snapshot's readings (n, 3), and their `_angle_trig` from the
    readings' ratios in the kernel (a trigonometric call would cost more than the rest of a
    stage): (alpha, beta, trig)."""
    r = np.ascontiguousarray(r, dtype=np.float64)
    alpha, beta = _angles(r)
    trig = np.empty((r.shape[0], 4))
    fb = _kffi.from_buffer
    _klib.capsheet_reading_trig(r.shape[0], fb("double[]", r), fb("double[]", alpha),
                                fb("double[]", beta), fb("double[]", trig))
    return alpha, beta, trig


def _solvability_kernel(trig: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """`solvability` of one snapshot from its links' trig (NaN rows: missing links)."""
    u = _units_int64(rows, cols)
    out = np.empty((rows - 1, cols - 1))
    _klib.capsheet_solvability(u.shape[0], _kffi.from_buffer("int64_t[]", u),
                               _kffi.from_buffer("double[]", trig),
                               _kffi.from_buffer("double[]", out))
    return out


# ---------------------------------------------------------------------------------------------
# Per-lattice structure (cached by rows, cols, mask, model)
# ---------------------------------------------------------------------------------------------

def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a × b`` over the last axis (3), without np.cross's overhead."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


class _Structure:
    """Everything about a lattice, mask and model that does not depend on the readings.

    The yaw problem's residuals come in blocks with a fixed set of variables per row: the loop
    closure (eq. 4, and eq. 6 for ``model="eq6"``) per active unit on its 4 links, and for
    ``model="cells"`` one roll residual per link on the link and the other links of its (one or
    two) cells, 7 variables. The Gauss-Newton matrix ``JᵀJ + diag`` therefore has a fixed pattern;
    its fill-reducing ordering and the CSC slot of every block product are computed here once.
    """

    def __init__(self, rows: int, cols: int, valid: np.ndarray, model: str):
        lat = Lattice(rows, cols)
        self.lattice = lat
        self.rows, self.cols = rows, cols
        self.model = model
        n = lat.n_links
        self.n_links = n
        self.valid = valid
        self.all_valid = bool(valid.all())
        units = lat.units.reshape(-1, 4)
        self.unit_ok = valid[units].all(axis=1)  # (n_units,)
        self.units = units[self.unit_ok]  # active units (U, 4)
        U = self.units.shape[0]
        self.n_units = U

        # rest yaws: i-links along +x (0), j-links along +y (pi/2)
        self.rest_yaw = np.zeros(n)
        self.rest_yaw[lat.n_i_links:] = np.pi / 2

        # gauge: the valid link in an active unit nearest the lattice centre (index space)
        ep = lat.endpoints
        jid = np.arange(rows * cols)
        ji, jj = jid // cols, jid % cols
        mid_i = 0.5 * (ji[ep[:, 0]] + ji[ep[:, 1]]) - (rows - 1) / 2
        mid_j = 0.5 * (jj[ep[:, 0]] + jj[ep[:, 1]]) - (cols - 1) / 2
        in_unit = np.zeros(n, bool)
        in_unit[self.units.ravel()] = True
        self.in_unit = in_unit
        cand = np.flatnonzero(in_unit) if U else np.flatnonzero(valid)
        self.gauge = int(cand[np.argmin(mid_i[cand] ** 2 + mid_j[cand] ** 2 + 1e-3 * cand)])

        # variables: valid links except the gauge; nv is the dummy variable (gauge, padding)
        var = np.full(n, -1)
        var_links = np.flatnonzero(valid & (np.arange(n) != self.gauge))
        var[var_links] = np.arange(var_links.size)
        self.var_links = var_links
        nv = var_links.size
        self.n_var = nv
        var_d = np.where(var >= 0, var, nv)
        self.unit_var = var_d[self.units]  # (U, 4)

        blocks = [self.unit_var]
        if model == "cells":
            # every link's active cells (at most 2), and its position in each
            flat = self.units.ravel()
            order = np.argsort(flat, kind="stable")
            fl = flat[order]
            uid, pos = order // 4, order % 4
            first = np.r_[True, fl[1:] != fl[:-1]][:fl.size]  # fl is empty when no cell is whole
            slot = np.zeros(fl.size, int)
            slot[~first] = 1
            cell = np.full((n, 2), U)
            cpos = np.zeros((n, 2), int)
            cell[fl, slot] = uid
            cpos[fl, slot] = pos
            ncell = np.bincount(fl, minlength=n)
            k = np.flatnonzero(ncell > 0)
            self.roll_links = k
            self.roll_cells = cell[k]  # (K, 2), U = no cell
            self.roll_pos = cpos[k]  # (K, 2)
            self.roll_inv_ncell = 1.0 / ncell[k]
            others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
            self.roll_others = others[self.roll_pos]  # (K, 2, 3) positions of the other links
            uv_ext = np.vstack([self.unit_var, np.full((1, 4), nv)])
            cols_o = uv_ext[self.roll_cells[:, :, None], self.roll_others]  # (K, 2, 3)
            self.roll_var = np.concatenate([var_d[k][:, None], cols_o.reshape(-1, 6)], axis=1)
            # fast gathers: a missing second cell points at the first, with weight 0
            K = k.size
            self.roll_c0 = self.roll_cells[:, 0]
            has1 = self.roll_cells[:, 1] < U
            self.roll_c1 = np.where(has1, self.roll_cells[:, 1], self.roll_c0)
            self.roll_ws1 = has1.astype(float)
            base = (np.arange(K) * 8)[:, None]
            self.roll_idx_self = base + np.array([0, 4]) + self.roll_pos  # into (K, 2, 4) flat
            self.roll_idx_oth = (base[:, :, None] + np.array([0, 4])[None, :, None]
                                 + self.roll_others).reshape(K, 6)
            blocks.append(self.roll_var)

        # bending prior: pairs of parallel neighbours (i-links (i,j)-(i+1,j) and (i,j)-(i,j+1),
        # j-links likewise), both valid
        ni = lat.n_i_links
        iid = np.arange(ni).reshape(rows - 1, cols)
        jidx = ni + np.arange(rows * (cols - 1)).reshape(rows, cols - 1)
        pairs = np.concatenate([
            np.stack([iid[:-1].ravel(), iid[1:].ravel()], 1),
            np.stack([iid[:, :-1].ravel(), iid[:, 1:].ravel()], 1),
            np.stack([jidx[:, :-1].ravel(), jidx[:, 1:].ravel()], 1),
            np.stack([jidx[:-1].ravel(), jidx[1:].ravel()], 1)]).reshape(-1, 2)
        pairs = pairs[valid[pairs].all(axis=1)]
        self.n_bend = pairs.shape[0]
        # shear prior: per unit, its j-link 0 against its i-link 3 (the cell's corner angle)
        shear = units[:, [0, 3]]
        ok = valid[shear].all(axis=1)
        self.shear_unit = np.flatnonzero(ok)  # unit (all units' numbering) of every shear pair
        pairs = np.concatenate([pairs, shear[ok]])
        self.pairs = pairs
        self.pair_var = var_d[pairs]
        blocks.append(self.pair_var)

        # pattern of the normal matrix: every block's outer products + the diagonal
        ents = []
        for cols_b in blocks:
            p = cols_b.shape[1]
            bi = np.repeat(cols_b, p, axis=1).ravel()
            bj = np.tile(cols_b, (1, p)).ravel()
            ents.append((bi, bj))
        allr = np.concatenate([e[0] for e in ents] + [np.arange(nv)])
        allc = np.concatenate([e[1] for e in ents] + [np.arange(nv)])
        keep = (allr < nv) & (allc < nv)
        rr, cc = allr[keep], allc[keep]
        if nv:
            pat = sp.csc_matrix((np.ones(rr.size), (rr, cc)), shape=(nv, nv))
            pat.sum_duplicates()
            pat = pat + sp.identity(nv, format="csc") * (4.0 * pat.max() + 1.0)
            if nv >= ND_MIN_VARS:  # large: nested dissection on the links' positions
                mid = np.stack([mid_i[var_links], mid_j[var_links]], axis=1)
                perm = np.argsort(_nested_dissection(pat.tocsr(), mid))
            else:  # small: minimum degree fills less
                perm = splu(pat.tocsc(), permc_spec="MMD_AT_PLUS_A").perm_c
        else:
            perm = np.arange(0)
        pos_v = np.asarray(perm, dtype=np.int64)
        key = pos_v[cc] * max(nv, 1) + pos_v[rr]
        ukey, inv = np.unique(key, return_inverse=True)
        self.nnz = ukey.size
        self.csc_indices = (ukey % max(nv, 1)).astype(np.int32)
        col = ukey // max(nv, 1)
        self.csc_indptr = np.searchsorted(col, np.arange(nv + 1)).astype(np.int32)
        slot_all = np.full(allr.size, self.nnz, dtype=np.int64)
        slot_all[np.flatnonzero(keep)] = inv
        self.block_slots = []
        at = 0
        for bi, _ in ents:
            self.block_slots.append(slot_all[at:at + bi.size])
            at += bi.size
        self.diag_slot = slot_all[at:at + nv]
        self.perm_of_var = pos_v
        self.perm_inv = np.argsort(pos_v)

        # joints: Laplacian of the valid links + a weak prior, factorised once
        vl = np.flatnonzero(valid)
        self.valid_links = vl
        a, b = ep[vl, 0], ep[vl, 1]
        nj = rows * cols
        B = sp.csr_matrix((np.concatenate([-np.ones(vl.size), np.ones(vl.size)]),
                           (np.concatenate([np.arange(vl.size)] * 2), np.concatenate([a, b]))),
                          shape=(vl.size, nj))
        self.incidence = B.tocsr()
        self.incidence_T = B.T.tocsr()
        lap = (B.T @ B + JOINT_PRIOR_WEIGHT * sp.identity(nj)).tocsc()
        self.lap_lu = splu(lap, permc_spec="MMD_AT_PLUS_A")

        # rest layout of the joints (prior for isolated parts), L = 1
        self.rest_joints_unit = np.stack([ji.astype(float), jj.astype(float),
                                          np.zeros(nj)], axis=1)

    def kernel_arrays(self) -> dict:
        return _kernel_arrays(self)


#: `_Structure.kernel_arrays`' index arrays, by their field name in ``capsheet_yaw_t``
#: `_Structure`: from this many yaw variables on (about 28x28 joints), the Gauss-Newton matrix is
#: ordered by nested dissection instead of SuperLU's minimum degree. Fill of L (bench_estimator's
#: Gaussian): 14x14 MMD 11.7k / ND 13.3k, 32x32 130k / 121k, 64x64 909k / 716k.
ND_MIN_VARS = 1500
#: ... and parts of at most this many variables are not split further.
ND_LEAF = 16


def _nested_dissection(adj, xy: np.ndarray, leaf: int = ND_LEAF) -> np.ndarray:
    """An elimination order (position -> variable) by geometric nested dissection: split the
    variables at the median of their longer extent, take as separator the smaller of the two
    sides' boundaries (the variables with a neighbour across), order each side recursively and
    the separator last. ``adj``: the symmetric pattern (CSR, any values); ``xy`` (nv, 2) the
    variables' positions."""
    nv = xy.shape[0]
    out: list[np.ndarray] = []
    side = np.zeros(nv, np.int8)  # scratch: 1 left part, 2 right part of the current split
    stack = [(np.arange(nv), False)]
    while stack:  # explicit stack: (nodes, emit) — emit=True places a separator
        nodes, emit = stack.pop()
        if emit or nodes.size <= leaf:
            out.append(nodes)
            continue
        c = xy[nodes]
        ax = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        order = np.argsort(c[:, ax], kind="stable")
        left = np.zeros(nodes.size, bool)
        left[order[:nodes.size // 2]] = True
        side[nodes[left]] = 1
        side[nodes[~left]] = 2
        sub = adj[nodes]
        nb_side = side[sub.indices]
        row = np.repeat(np.arange(nodes.size), np.diff(sub.indptr))
        touch_r = np.bincount(row[nb_side == 2], minlength=nodes.size) > 0
        touch_l = np.bincount(row[nb_side == 1], minlength=nodes.size) > 0
        side[nodes] = 0
        sep_l, sep_r = left & touch_r, ~left & touch_l
        sep = sep_l if sep_l.sum() <= sep_r.sum() else sep_r
        # popped last-in first: left part, then right part, then the separator
        stack.append((nodes[sep], True))
        stack.append((nodes[~left & ~sep], False))
        stack.append((nodes[left & ~sep], False))
    return np.concatenate(out) if out else np.arange(0)


_KERNEL_INDEX_FIELDS = ("units", "unit_var", "roll_links", "roll_c0", "roll_c1", "roll_var0",
                        "pairs", "pair_var", "var_links")


def _kernel_arrays(st: "_Structure") -> dict:
    """The structure's arrays as the kernel reads them (int64/float64, contiguous) with their
    cffi pointers, and a work buffer (one snapshot at a time uses it): made once, kept on ``st``."""
    ka = st.__dict__.get("_kernel")
    if ka is not None:
        return ka
    src = {"units": st.units, "unit_var": st.unit_var, "roll_links": st.roll_links,
           "roll_c0": st.roll_c0, "roll_c1": st.roll_c1, "roll_var0": st.roll_var[:, 0],
           "pairs": st.pairs, "pair_var": st.pair_var, "var_links": st.var_links}
    ka = {}
    for name, a in src.items():
        a = np.ascontiguousarray(a, dtype=np.int64)
        ka[name] = (a, _kffi.from_buffer("int64_t[]", a))
    a = np.ascontiguousarray(st.roll_ws1, dtype=np.float64)
    ka["roll_ws1"] = (a, _kffi.from_buffer("double[]", a))
    ka["sizes"] = (st.n_units, st.roll_links.size, st.pairs.shape[0], st.n_var)
    ka["work"] = np.empty(19 * max(st.n_units, 1) + 2 * st.n_links)
    st._kernel = ka
    return ka


@lru_cache(maxsize=64)
def _lattice(rows: int, cols: int) -> Lattice:
    """One `Lattice` per size, so its cached ``endpoints``/``units`` are computed once."""
    return Lattice(rows, cols)


@lru_cache(maxsize=64)
def _units_int64(rows: int, cols: int) -> np.ndarray:
    """All units' links (n_units, 4), int64, contiguous: what the kernel's `solvability` reads."""
    return np.ascontiguousarray(_lattice(rows, cols).units.reshape(-1, 4), dtype=np.int64)


@lru_cache(maxsize=16)
def _structure_cached(rows: int, cols: int, mask_bytes: bytes | None, model: str) -> _Structure:
    n = Lattice(rows, cols).n_links
    valid = np.ones(n, bool) if mask_bytes is None else np.frombuffer(mask_bytes, dtype=bool).copy()
    return _Structure(rows, cols, valid, model)


def _structure(rows: int, cols: int, valid: np.ndarray | None, model: str = "cells") -> _Structure:
    if valid is None or valid.all():
        return _structure_cached(rows, cols, None, model)
    return _structure_cached(rows, cols, valid.tobytes(), model)


# ---------------------------------------------------------------------------------------------
# Global yaw solve
# ---------------------------------------------------------------------------------------------

def _wrap(x: np.ndarray) -> np.ndarray:
    return (x + np.pi) % (2 * np.pi) - np.pi


def _sumsq(x: np.ndarray) -> float:
    """``Σ |x|²`` without BLAS (a threaded BLAS dot on a busy machine costs milliseconds)."""
    if np.iscomplexobj(x):
        return float(np.add.reduce(x.real * x.real) + np.add.reduce(x.imag * x.imag))
    return float(np.add.reduce(x * x))


def _cell_normals(D, Az, Cz):
    """Per cell (last axis of ``D``: its 4 links' xy directions), ``A``, ``C`` the sums of its
    i- and j-link directions (xy complex; ``Az``, ``Cz`` their z), and the unit normal of
    ``m = A × C``: ``(Axy, Cxy, nxy, nz, 1/|m|)``. A squashed cell (A ∥ C) has no normal:
    ``1/|m|`` is 0 there, so its roll terms drop out."""
    Axy = D[..., 1] + D[..., 3]
    Cxy = D[..., 0] + D[..., 2]
    mxy = 1j * (Az * Cxy - Cz * Axy)
    mz = (Axy.conj() * Cxy).imag
    mm = np.sqrt(mxy.real ** 2 + mxy.imag ** 2 + mz * mz)
    inv = np.where(mm > 1e-9, 1.0 / np.maximum(mm, 1e-300), 0.0)
    return Axy, Cxy, mxy * inv, mz * inv, inv


def _wrap_fast(x: np.ndarray) -> np.ndarray:
    """``x`` wrapped to [−π, π] (rounding, cheaper than a float modulo)."""
    return x - _TWO_PI * np.rint(x * (1.0 / _TWO_PI))


_TWO_PI = 2.0 * np.pi
#: eq. (4) signs turn the loop terms t = ±cos β e^{iγ} back into the links' xy directions
_SIGN_D = _S_D


def _scatter(idx: np.ndarray, w: np.ndarray, size: int) -> np.ndarray:
    """``Σ w`` into ``size`` bins by ``idx`` (m,) over ``w``'s last axis (..., m): a bincount,
    one per leading row (at most one leading axis, the batch)."""
    # astype: numpy's bincount of no entries is int64 even with float weights (a snapshot with no
    # model cell: the in-place gradient sums then raised a casting error)
    if w.ndim == 1:
        return np.bincount(idx, weights=w, minlength=size).astype(float, copy=False)
    B = w.shape[0]
    off = (idx[None, :] + size * np.arange(B)[:, None]).ravel()
    return np.bincount(off, weights=w.reshape(-1), minlength=B * size).astype(float, copy=False).reshape(B, size)


def _sumsq_last(x: np.ndarray):
    """``Σ |x|²`` over the last axis (a 0-d value for a 1-d ``x``), without BLAS."""
    if np.iscomplexobj(x):
        return np.add.reduce(x.real * x.real, axis=-1) + np.add.reduce(x.imag * x.imag, axis=-1)
    return np.add.reduce(x * x, axis=-1)


class _YawProblem:
    """The global yaw least-squares problem for one snapshot (see the module docstring), or for
    a batch of snapshots of one structure at once: ``alpha``, ``beta`` (B, n_links), and
    ``prior_w``/``bend_w`` per snapshot or shared; every method then works row-wise on a
    leading batch axis (`estimate_batch`), with the same arithmetic.

    Cost ``½ Σ |loop|² (+ ½ Σ |eq6|²) + ½ Σ roll² + ½ Σ_pairs λ_p (wrap(γ_k − γ_l) − δ_kl)²
    (+ ½ Σ λ wrap(γ − τ)²)``; the complex form of every term is in docs/estimator.md.
    """

    #: per-snapshot attributes and their number of axes without the batch axis (`take`)
    _PER_SNAPSHOT = {"c_loop": 2, "c_n": 2, "Az": 1, "Cz": 1, "y_c": 1, "y_z": 1, "lam": 1,
                     "lam_b": 1}

    def __init__(self, st: _Structure, alpha, beta, target, prior_w, bend_w, trig=None):
        self.st = st
        self.target = target[st.var_links]
        self.lam = prior_w  # (nv,) prior weight per variable
        self.abs_prior = bool(np.any(prior_w > ABS_PRIOR_FLOOR))
        if target is st.rest_yaw:  # the default target: its pair differences once per structure
            pt = st.__dict__.get("_rest_pair_t")
            if pt is None:
                pt = st._rest_pair_t = _wrap(target[st.pairs[:, 0]] - target[st.pairs[:, 1]])
            self.pair_t = pt
        else:
            self.pair_t = _wrap(target[st.pairs[:, 0]] - target[st.pairs[:, 1]])
        self.lam_b = bend_w  # (n_pairs,)
        if USE_KERNEL and st.model == "cells" and np.ndim(alpha) == 1:  # one snapshot: the kernel
            self._coeffs_kernel(alpha, beta, trig)
            return
        ca, sa, cb, sb = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)
        u = st.units
        cbu = cb[..., u]
        self.c_loop = cbu * _S_D  # (U, 4) real
        if st.model == "eq6":
            self.c_n = (sb[..., u] * ca[..., u] - 1j * sa[..., u]) * (_S_N * NORMAL_WEIGHT)
        else:
            k = st.roll_links
            sbu = sb[..., u]
            self.Az = -(sbu[..., 1] + sbu[..., 3])  # z of the cell's i-link sum A (yaw-free)
            self.Cz = -(sbu[..., 0] + sbu[..., 2])  # z of its j-link sum C
            self.y_c = (sb[..., k] * sa[..., k] + 1j * ca[..., k])  # sensor y, xy before the yaw
            self.y_z = cb[..., k] * sa[..., k]
            self.w = ROLL_WEIGHT * st.roll_inv_ncell

    def _coeffs_kernel(self, alpha, beta, trig=None):
        """`__init__`'s yaw-free coefficients (model "cells", one snapshot) in the kernel;
        ``trig``: the links' `_angle_trig`, if already made."""
        st = self.st
        sk = st.kernel_arrays()
        U, K = st.n_units, st.roll_links.size
        if trig is None:
            trig = _angle_trig(alpha, beta)
        self.c_loop, self.Az, self.Cz = np.empty((U, 4)), np.empty(U), np.empty(U)
        self.y_c, self.y_z = np.empty(K, dtype=complex), np.empty(K)
        fb = _kffi.from_buffer
        _klib.capsheet_yaw_coeffs(U, sk["units"][1], K, sk["roll_links"][1],
                                  fb("double[]", trig), fb("double[]", self.c_loop),
                                  fb("double[]", self.Az), fb("double[]", self.Cz),
                                  fb("double[]", self.y_c.view(np.float64)),
                                  fb("double[]", self.y_z))
        self.w = ROLL_WEIGHT * st.roll_inv_ncell

    def take(self, idx):
        """The problem of the snapshots ``idx`` of a batch (an int: one snapshot, no batch axis)."""
        sub = copy.copy(self)
        sub.__dict__.pop("_kp", None)  # the kernel's view of one snapshot's arrays
        for name, nd in self._PER_SNAPSHOT.items():
            v = getattr(self, name, None)
            if v is not None and np.ndim(v) == nd + 1:
                setattr(sub, name, v[idx])
        return sub

    def evaluate(self, gamma, jac: bool = True):
        """Cost, gradient over the variables, and the Jacobian blocks (for `factor`; None when
        ``jac`` is False: the roll terms' gradient then comes from `_roll_grad`, without
        forming their Jacobian)."""
        st = self.st
        if not jac and st.model == "cells" and USE_KERNEL and gamma.ndim == 1:
            return self._evaluate_kernel(gamma)
        nv1 = st.n_var + 1
        z = np.exp(1j * gamma)
        zu = z[..., st.units]
        t = self.c_loop * zu  # (U, 4) complex; ∂r/∂γ_m = i t_m
        r = t.sum(axis=-1)
        cost2 = _sumsq_last(r)
        gu = (t.conj() * r[..., None]).imag  # (U, 4)
        blocks = [t]
        if st.model == "eq6":
            tn = self.c_n * zu
            rn = tn.sum(axis=-1)
            cost2 = cost2 + _sumsq_last(rn)
            gu += (tn.conj() * rn[..., None]).imag
            blocks = [np.stack([t, tn], axis=-2)]
        lead = gamma.shape[:-1]
        if st.model == "cells" and not jac:
            rr, gn, gd = self._roll_grad(z, t)
            cost2 = cost2 + _sumsq_last(rr)
            grad = _scatter(st.unit_var.ravel(), (gu + gn).reshape(lead + (-1,)), nv1)
            grad += _scatter(st.roll_var[:, 0], gd, nv1)
            blocks = None
        else:
            grad = _scatter(st.unit_var.ravel(), gu.reshape(lead + (-1,)), nv1).astype(float)
        if st.model == "cells" and jac:
            Jr, rr = self._roll(z, t)
            cost2 = cost2 + _sumsq_last(rr)
            grad += _scatter(st.roll_var.ravel(), (Jr * rr[..., None]).reshape(lead + (-1,)),
                             nv1)
            blocks.append(Jr)
        pr = st.pairs
        eb = _wrap_fast(gamma[..., pr[:, 0]] - gamma[..., pr[:, 1]] - self.pair_t)
        wb = self.lam_b * eb
        cost2 = cost2 + np.add.reduce(wb * eb, axis=-1)
        grad += _scatter(st.pair_var[:, 0], wb, nv1)
        grad -= _scatter(st.pair_var[:, 1], wb, nv1)
        grad = grad[..., :st.n_var]
        if self.abs_prior:  # otherwise the floor only sits on the diagonal (`factor`)
            e = _wrap_fast(gamma[..., st.var_links] - self.target)
            cost2 = cost2 + np.add.reduce(self.lam * e * e, axis=-1)
            grad += self.lam * e
        return 0.5 * cost2, grad, blocks

    def _evaluate_kernel(self, gamma):
        """`evaluate` with ``jac=False`` for one snapshot, model "cells", in the compiled kernel
        (host/analysis/_kernel/yaw_eval.c: the same terms as `evaluate` and `_roll_grad`)."""
        kp = self.__dict__.get("_kp")
        if kp is None:
            kp = self._kp = self._kernel_problem()
        st = self.st
        g = np.ascontiguousarray(gamma, dtype=float)
        grad = np.empty(st.n_var + 1)
        cost = _klib.capsheet_yaw_eval(kp[0], _kffi.from_buffer("double[]", g),
                                       _kffi.from_buffer("double[]", grad), kp[1])
        return cost, grad[:st.n_var], None

    def chord_kernel(self, gamma, cost, grad, lu, tol):
        """`_solve_global`'s chord iterations on the kept factorisation ``lu`` in the kernel
        (``capsheet_chord``: the same steps, acceleration, tests and counts as the Python
        loop). ``gamma`` is updated in place. Returns (status, iterations, cost, grad,
        prev_smax); status 0 converged, 1 the cost rose, 2 a poor contraction (refactorise
        for both), 3 out of iterations."""
        kp = self.__dict__.get("_kp")
        if kp is None:
            kp = self._kp = self._kernel_problem()
        st = self.st
        nv = st.n_var
        (val, diag, sym), ptrs = lu[2]
        fb = _kffi.from_buffer
        c = _kffi.new("capsheet_chord_t *")
        c.n_links, c.max_iter, c.tol = gamma.size, MAX_ITER, float(tol)
        c.refactor_ratio, c.anderson_cos = _REFACTOR_RATIO, _ANDERSON_COS
        pi = np.ascontiguousarray(st.perm_inv, np.int64)
        pv = np.ascontiguousarray(st.perm_of_var, np.int64)
        c.perm_inv, c.perm_of_var = fb("int64_t[]", pi), fb("int64_t[]", pv)
        c.n_super = ptrs[0]
        c.sn_col, c.sn_row, c.rows, c.sn_diag, c.sn_below = ptrs[1:6]
        c.val, c.diag = ptrs[6], ptrs[7]
        c.ldl_work_size = sym["work_size"]
        g = np.zeros(nv + 1)
        g[:nv] = grad
        out_cost = _kffi.new("double *", float(cost))
        its = _kffi.new("int64_t *", 0)
        ps = _kffi.new("double *", np.inf)
        work = np.empty(6 * nv + gamma.size + 1 + sym["work_size"] + 19 * max(st.n_units, 1)
                        + 2 * st.n_links)
        assert gamma.dtype == np.float64 and gamma.flags.c_contiguous
        status = _klib.capsheet_chord(kp[0], fb("double[]", gamma), out_cost, fb("double[]", g), c,
                                      its, ps, fb("double[]", work))
        return int(status), int(its[0]), float(out_cost[0]), g[:nv], float(ps[0])

    def _kernel_problem(self):
        """The kernel's ``capsheet_yaw_t`` for this snapshot, its work buffer, and the arrays
        it points into (kept alive with it). The structure's index arrays are shared
        (`_Structure.kernel_arrays`)."""
        st = self.st
        sk = st.kernel_arrays()
        keep = [sk]
        fb = _kffi.from_buffer

        def ptr(a):
            a = np.ascontiguousarray(a, dtype=np.float64)
            keep.append(a)
            return fb("double[]", a)

        p = _kffi.new("capsheet_yaw_t *")
        p.n_units, p.n_roll, p.n_pairs, p.n_var = sk["sizes"]
        p.n_links = st.n_links
        for name in _KERNEL_INDEX_FIELDS:
            setattr(p, name, sk[name][1])
        p.roll_ws1, p.w = sk["roll_ws1"][1], ptr(self.w)
        p.c_loop, p.Az, p.Cz = ptr(self.c_loop), ptr(self.Az), ptr(self.Cz)
        p.y_c = ptr(np.ascontiguousarray(self.y_c, dtype=complex).view(np.float64))
        p.y_z, p.pair_t = ptr(self.y_z), ptr(self.pair_t)
        p.lam_b = ptr(self.lam_b if np.ndim(self.lam_b) else np.full(st.pairs.shape[0], self.lam_b))
        p.target = ptr(self.target)
        p.lam = ptr(self.lam if np.ndim(self.lam) else np.full(st.n_var, self.lam))
        p.abs_prior = 1 if self.abs_prior else 0
        return p, fb("double[]", sk["work"]), keep

    def rows(self, gamma) -> np.ndarray:
        """The data residuals as real rows: loop (and eq. 6) real parts, imaginary parts, then
        the roll residuals (the order `_uncertainty` weights them in)."""
        st = self.st
        z = np.exp(1j * gamma)
        zu = z[..., st.units]
        t = self.c_loop * zu
        r = t.sum(axis=-1)
        if st.model == "eq6":
            r = np.concatenate([r, (self.c_n * zu).sum(axis=-1)], axis=-1)
            return np.concatenate([r.real, r.imag], axis=-1)
        return np.concatenate([r.real, r.imag, self._roll(z, t)[1]], axis=-1)

    def _roll(self, z, t):
        """Roll residuals ``w · y_k · N_k`` and their Jacobian rows (K, 7).

        Per cell: ``A``, ``C`` the sums of its i- and j-link directions (xy complex, z real),
        ``m = A × C``, ``n = m/|m|``; a link's ``N`` is the mean of its cells' ``n``.
        ``∂m/∂γ`` for an i-link ``a``: ``(C_z a, −Re(ā C))``; for a j-link ``c``:
        ``(−A_z c, Re(Ā c))`` (xy, z), with ``a``, ``c`` the links' xy directions.
        """
        st = self.st
        D = t * _SIGN_D  # links' xy directions per unit (U, 4), cos β e^{iγ}
        Az, Cz = self.Az, self.Cz
        Axy, Cxy, nxy, nz, inv = _cell_normals(D, Az, Cz)
        dmxy = D * np.stack([-Az, Cz, -Az, Cz], axis=-1)
        X = np.stack([Axy, Cxy, Axy, Cxy], axis=-1)
        dmz = (X.conj() * D).real * np.array([1.0, -1.0, 1.0, -1.0])
        nd = (nxy.conj()[..., None] * dmxy).real + nz[..., None] * dmz  # n · ∂m  (U, 4)
        c0, c1, ws1 = st.roll_c0, st.roll_c1, self.st.roll_ws1
        yxy = self.y_c * z[..., st.roll_links]
        yz = self.y_z
        Nxy = nxy[..., c0] + ws1 * nxy[..., c1]
        Nz = nz[..., c0] + ws1 * nz[..., c1]
        yc = yxy.conj()
        w = self.w
        res = w * ((yc * Nxy).real + yz * Nz)
        K = c0.size
        lead = yxy.shape[:-1]
        Jraw = np.empty(lead + (K, 2, 4))
        for s_, c, ws in ((0, c0, None), (1, c1, ws1)):
            ynu = (yc * nxy[..., c]).real + yz * nz[..., c]  # y · n_c  (K,)
            ydm = (yc[..., None] * dmxy[..., c, :]).real + yz[..., None] * dmz[..., c, :]
            sc = inv[..., c] if ws is None else inv[..., c] * ws
            Jraw[..., s_, :] = (ydm - ynu[..., None] * nd[..., c, :]) * sc[..., None]
        flat = Jraw.reshape(lead + (-1,))
        J = np.empty(lead + (K, 7))
        sidx = st.roll_idx_self
        J[..., 0] = w * ((yc * Nxy).imag + flat[..., sidx[:, 0]] + flat[..., sidx[:, 1]])
        J[..., 1:] = w[:, None] * flat[..., st.roll_idx_oth]
        return J, res

    def _roll_grad(self, z, t):
        """Roll residuals and their gradient ``Jᵀ res`` without the Jacobian (reverse mode):
        (res (K,), per unit and position the part through the cell normals (U, 4), per roll
        link the part through its own sensor y (K,)).

        With ``ρ_k = w_k res_k``, cell ``c`` collects ``Y_c = Σ_k ρ_k y_k`` over its links (both
        cells of a link: the mean's weights), and ``Y · ∂n = Q · ∂m`` with
        ``Q = (Y − (Y·n) n)/|m|`` (``∂n = (∂m − n (n·∂m))/|m|``): the same terms as `_roll`'s rows
        summed, in a few passes over the cells instead of one per Jacobian entry.
        """
        st = self.st
        D = t * _SIGN_D
        Az, Cz = self.Az, self.Cz
        Axy, Cxy, nxy, nz, inv = _cell_normals(D, Az, Cz)
        c0, c1, ws1 = st.roll_c0, st.roll_c1, st.roll_ws1
        yxy = self.y_c * z[..., st.roll_links]
        yz = self.y_z
        Nxy = nxy[..., c0] + ws1 * nxy[..., c1]
        Nz = nz[..., c0] + ws1 * nz[..., c1]
        yc = yxy.conj()
        w = self.w
        res = w * ((yc * Nxy).real + yz * Nz)
        rho = w * res
        gd = rho * (yc * Nxy).imag  # through y_k = y_c e^{iγ_k}: ∂(ȳ N)/∂γ_k = Im(ȳ N)
        U = st.n_units
        cells = np.concatenate([c0, c1])
        ry, rz = rho * yxy, rho * yz
        r1 = ws1 * rho
        wx = np.concatenate([ry.real, (r1 * yxy).real], axis=-1)
        wy = np.concatenate([ry.imag, (r1 * yxy).imag], axis=-1)
        wz = np.concatenate([rz, r1 * yz], axis=-1)
        Yxy = _scatter(cells, wx, U) + 1j * _scatter(cells, wy, U)
        Yz = _scatter(cells, wz, U)
        Yn = (Yxy.conj() * nxy).real + Yz * nz
        Qxy = (Yxy - Yn * nxy) * inv
        Qz = (Yz - Yn * nz) * inv
        dmxy = D * np.stack([-Az, Cz, -Az, Cz], axis=-1)
        X = np.stack([Axy, Cxy, Axy, Cxy], axis=-1)
        dmz = (X.conj() * D).real * np.array([1.0, -1.0, 1.0, -1.0])
        gn = (Qxy.conj()[..., None] * dmxy).real + Qz[..., None] * dmz
        return res, gn, gd

    def factor(self, blocks, mu):
        """Factorise the Gauss-Newton matrix ``JᵀJ + diag(λ) + μ I`` (permuted, fixed pattern)
        of one snapshot (``blocks`` from `evaluate` without a batch axis)."""
        st = self.st
        t = blocks[0]
        if t.ndim == 3:  # eq6: (U, 2, 4)
            Hd = np.einsum("uem,uen->umn", t.conj(), t).real
        else:
            Hd = (t.conj()[:, :, None] * t[:, None, :]).real
        w = [Hd.ravel()]
        if st.model == "cells":
            Jr = blocks[1]
            w.append((Jr[:, :, None] * Jr[:, None, :]).ravel())
        w.append((self.lam_b[:, None] * np.array([1.0, -1.0, -1.0, 1.0])).ravel())
        data = np.zeros(st.nnz + 1)
        for sl, wt in zip(st.block_slots, w):
            data += np.bincount(sl, weights=wt, minlength=st.nnz + 1)
        data = data[:st.nnz]
        data[st.diag_slot] += self.lam + mu
        A = sp.csc_matrix((data, st.csc_indices, st.csc_indptr), shape=(st.n_var, st.n_var))
        return _factorise(st, A)

    def step(self, lu, grad):
        """The (chord) Gauss-Newton step ``−A⁻¹ grad``, row-wise for a batch (B, nv)."""
        st = self.st
        b = -grad[..., st.perm_inv]
        if b.ndim == 1:
            return _solve(lu, b)[st.perm_of_var]
        return _solve(lu, np.ascontiguousarray(b.T)).T[:, st.perm_of_var]


def _cholmod():
    """scikit-sparse's CHOLMOD module, or None when not installed (it is optional)."""
    try:
        from sksparse import cholmod
    except ImportError:  # pragma: no cover - depends on the installation
        return None
    return cholmod


def _backend() -> str:
    if LINEAR_SOLVER == "auto":
        return "cholmod" if _cholmod() is not None else "splu"
    return LINEAR_SOLVER


def _factorise(st: "_Structure", A, sweeps: bool = True):
    """Factorise the (permuted, SPD) Gauss-Newton matrix with the chosen backend: SuperLU on
    the fixed ordering, or CHOLMOD with its symbolic analysis (METIS) cached per structure."""
    if _backend() == "cholmod":
        cm = _cholmod()
        sym = getattr(st, "_cholmod_sym", None)
        if sym is None:
            sym = cm.analyze(A, mode="supernodal", ordering_method="metis")
            st._cholmod_sym = sym
        return ("cholmod", sym.cholesky(A))
    lu = splu(A, permc_spec="NATURAL", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
    # the kernel's sweeps serve one right-hand side at a time (the chord steps); ``sweeps=False``
    # for a factorisation solved only with many at once (the uncertainty's)
    return ("splu", lu, _triangular(lu, st) if USE_KERNEL and sweeps else None)


def _triangular(lu, st=None):
    """SuperLU's factors as the kernel's supernodal ``capsheet_ldl_solve`` takes them: the
    matrix is SPD and factorised without pivoting, so ``U = D Lᵀ`` and L (unit lower) with U's
    diagonal D is the whole factorisation; L's columns are grouped into supernodes (consecutive
    columns sharing their rows below), each stored as a dense block so that a solve runs on
    contiguous memory instead of scattered single entries, its values in float32 (the solve is
    bound by memory; the chord step matrix is approximate anyway and the iteration's fixed point,
    grad = 0, does not depend on it). The supernodes depend only on L's
    pattern, fixed for a structure: built once and cached on ``st``. None when SuperLU permuted
    rows or columns (it was asked not to: the ordering is the structure's)."""
    n = lu.shape[0]
    if not (np.array_equal(lu.perm_r, np.arange(n)) and np.array_equal(lu.perm_c, np.arange(n))):
        return None
    L = lu.L
    ptr = np.ascontiguousarray(L.indptr, np.int32)
    idx = np.ascontiguousarray(L.indices, np.int32)
    sym = getattr(st, "_ldl_symbolic", None)
    if sym is None or not (np.array_equal(sym["l_ptr"], ptr) and np.array_equal(sym["l_idx"], idx)):
        sym = _ldl_symbolic(n, ptr, idx)
        if st is not None:
            st._ldl_symbolic = sym
    fb = _kffi.from_buffer
    val = np.zeros(sym["n_val"], np.float32)
    diag = np.ascontiguousarray(lu.U.diagonal(), np.float64)
    _klib.capsheet_ldl_fill(sym["n_super"], fb("int32_t[]", ptr), fb("int32_t[]", idx),
                            fb("double[]", np.ascontiguousarray(L.data, np.float64)),
                            *sym["c_args"][:5], fb("int32_t[]", np.full(max(n, 1), -1, np.int32)),
                            fb("float[]", val))
    ptrs = (sym["n_super"], *sym["c_args"][:5], fb("float[]", val), fb("double[]", diag))
    return (val, diag, sym), ptrs


def _ldl_symbolic(n: int, l_ptr: np.ndarray, l_idx: np.ndarray) -> dict:
    """L's supernodes (fundamental: column j+1 joins j's when j's first row below the diagonal
    is j+1 and j+1 has exactly j's other rows) and the layout `capsheet_ldl_solve` reads."""
    col = np.repeat(np.arange(n), np.diff(l_ptr))
    keep = l_idx > col
    ci, ri = col[keep], l_idx[keep].astype(np.int64)
    order = np.lexsort((ri, ci))  # rows sorted within each column
    ci, ri = ci[order], ri[order]
    cnt = np.bincount(ci, minlength=n)
    ptr = np.zeros(n + 1, np.int64)
    np.cumsum(cnt, out=ptr[1:])
    first = np.full(n, -1, np.int64)
    nz = cnt > 0
    first[nz] = ri[ptr[:-1][nz]]
    cand = np.flatnonzero((first[:-1] == np.arange(1, n)) & (cnt[1:] == cnt[:-1] - 1))
    m = cnt[cand + 1]
    if m.sum():  # the rows themselves agree (the counts suffice for an exact symbolic pattern)
        rep = np.repeat(np.arange(cand.size), m)
        off = np.arange(int(m.sum())) - np.repeat(np.cumsum(m) - m, m)
        same = ri[ptr[cand][rep] + 1 + off] == ri[ptr[cand + 1][rep] + off]
        cand = cand[np.bincount(rep[~same], minlength=cand.size) == 0]
    cont = np.zeros(n, bool)
    cont[cand + 1] = True
    sn_col = np.append(np.flatnonzero(~cont), n).astype(np.int32)
    ns = sn_col.size - 1
    w = np.diff(sn_col).astype(np.int64)
    last = sn_col[1:].astype(np.int64) - 1
    nb = cnt[last]
    sn_row = np.zeros(ns + 1, np.int64)
    np.cumsum(nb, out=sn_row[1:])
    rep = np.repeat(np.arange(ns), nb)
    rows = np.ascontiguousarray(ri[ptr[last][rep] + np.arange(rep.size) - sn_row[:-1][rep]], np.int32)
    base = np.zeros(ns + 1, np.int64)
    np.cumsum(w * w + w * nb, out=base[1:])
    sn_diag = np.ascontiguousarray(base[:-1])
    sn_below = np.ascontiguousarray(base[:-1] + w * w)
    fb = _kffi.from_buffer
    arrays = (sn_col, sn_row, rows, sn_diag, sn_below)
    work = np.empty(max(int(nb.max()) if ns else 0, 1))
    c_args = (fb("int32_t[]", sn_col), fb("int64_t[]", sn_row), fb("int32_t[]", rows),
              fb("int64_t[]", sn_diag), fb("int64_t[]", sn_below))
    return {"l_ptr": l_ptr.copy(), "l_idx": l_idx.copy(), "n_super": ns, "n_val": int(base[-1]),
            "arrays": arrays, "c_args": c_args, "work_size": work.size}


def _solve(fac, b):
    """``A⁻¹ b`` with a factorisation from `_factorise`; one right-hand side (b (n,)) of a SuperLU
    factorisation goes through the kernel's triangular sweeps when it is built."""
    kind, f = fac[0], fac[1]
    if kind == "cholmod":
        return f(b)
    tri = fac[2] if len(fac) > 2 else None
    if tri is None or b.ndim != 1 or not USE_KERNEL:
        return f.solve(b)
    x = np.array(b, dtype=np.float64)  # a copy: solved in place
    work = np.empty(tri[0][2]["work_size"])  # per call: solves may run in several threads
    _klib.capsheet_ldl_solve(x.size, *tri[1], _kffi.from_buffer("double[]", x),
                             _kffi.from_buffer("double[]", work))
    return x


def _solve_global(st: _Structure, alpha, beta, gamma0, target, prior_w, bend_w, lu=None,
                  tol=YAW_TOL_RAD, trig=None):
    """Gauss-Newton on all yaws, reusing a factorisation while it contracts well (chord steps),
    Levenberg-Marquardt damping when a step fails. Returns (gamma, iterations, factorisations,
    lu, problem).

    ``lu`` may be the factorisation left by the previous snapshot (same structure): the normal
    matrix changes little between snapshots, so its chord iterations usually converge without a
    new factorisation. A new one is made when a step raises the cost or contracts by less than
    `_REFACTOR_RATIO`.

    The chord steps are accelerated (Anderson, one step of history, `_anderson`): on noisy
    readings Gauss-Newton's neglected curvature makes a smooth mode overshoot, each step about
    −0.5 times the last (the 128x128 sheet took 5-7 steps, each reversing the one before); the
    extrapolation sums that series. An accelerated step that raises the cost is replaced by the
    plain one before anything else is tried.
    """
    gamma = gamma0.copy()
    prob = _YawProblem(st, alpha, beta, target, prior_w, bend_w, trig)
    if st.n_var == 0:
        return gamma, 0, 0, None, prob
    vl = st.var_links
    cost, grad, blocks = prob.evaluate(gamma, jac=lu is None)
    mu = 0.0
    fresh = False
    n_fact = 0
    prev_smax = np.inf
    hist = None  # (last raw step, last move) of the current chord map, for the acceleration
    accelerated = False  # the last move accepted was an extrapolated one
    it = 0
    if lu is not None and _chord_in_kernel(st, lu, gamma):
        # the warm start's chord steps in the kernel: this loop's iterations, one C call
        status, it, cost, grad, prev_smax = prob.chord_kernel(gamma, cost, grad, lu, tol)
        if status in (0, 3):  # converged, or out of iterations
            return gamma, it, 0, lu, prob
        lu, blocks = None, None  # 1: the cost rose; 2: a step contracted too little
    while it < MAX_ITER:
        it += 1
        if lu is None:
            if blocks is None:  # the Jacobian of this point, for its first factorisation
                blocks = prob.evaluate(gamma)[2]
            lu = prob.factor(blocks, mu)
            fresh = True
            hist, accelerated = None, False
            n_fact += 1
        step = prob.step(lu, grad)
        move = _anderson(step, hist) if mu == 0.0 else step
        g_new = gamma.copy()
        g_new[vl] += move
        smax = float(np.max(np.abs(step)))
        if mu == 0.0 and (smax < tol or smax < prev_smax < np.inf and not accelerated
                          and smax * smax < tol * prev_smax):
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
        if smax < tol:  # a damped step this small: converged as well
            break
        if mu > 0.0:
            mu = mu / 10.0 if mu > 1e-6 else 0.0
            lu = None
        elif smax > _REFACTOR_RATIO * prev_smax:
            lu = None
        prev_smax = smax
        fresh = False
    return gamma, it, n_fact, lu, prob


def _chord_in_kernel(st, lu, gamma) -> bool:
    """Whether `_YawProblem.chord_kernel` can run this snapshot's chord steps: the kernel is
    built, model "cells", one snapshot, a SuperLU factorisation with its supernodal form."""
    return (USE_KERNEL and st.model == "cells" and gamma.ndim == 1 and lu[0] == "splu"
            and len(lu) > 2 and lu[2] is not None)


#: `_anderson` extrapolates only a step that reverses the last one: cos(s, s_prev) below this.
_ANDERSON_COS = -0.9


def _anderson(step: np.ndarray, hist) -> np.ndarray:
    """Anderson acceleration with one step of history of the fixed-point map ``x -> x + s(x)``:
    ``x + s − θ (Δx + Δs)``, θ minimising the linearised next step. For a mode that the steps
    overshoot, each −ρ times the last (0 < ρ < 1), it moves ``s / (1 + ρ)``, the whole rest of the
    series. Used only for such a step — nearly opposite to the last (`_ANDERSON_COS`), so
    0 < θ < 1 and the move is shorter than the step — else the plain step is returned. ``hist``:
    (previous raw step, previous move) of the same map, or None."""
    if hist is None:
        return step
    s_prev, dx = hist
    nn = float(step @ step) * float(s_prev @ s_prev)
    if not (nn > 0.0 and float(step @ s_prev) < _ANDERSON_COS * np.sqrt(nn)):
        return step
    ds = step - s_prev
    theta = float(ds @ step) / float(ds @ ds)
    if not 0.0 < theta < 1.0:
        return step
    return step - theta * (dx + ds)


# ---------------------------------------------------------------------------------------------
# estimate()
# ---------------------------------------------------------------------------------------------

def _directions_normals(alpha, beta, gamma, trig=None):
    """Per link its direction (sensor x) and normal (sensor z) in the world, (..., n_links, 3)
    each (docs/design.md's ``R = Rz(γ) Ry(β) Rx(α)``); ``trig``: the links' `_angle_trig`, if
    already made (one snapshot)."""
    if USE_KERNEL and np.ndim(alpha) == 1:  # one snapshot: the kernel
        if trig is None:
            trig = _angle_trig(alpha, beta)
        g = np.ascontiguousarray(gamma, dtype=np.float64)
        d, n = np.empty((g.size, 3)), np.empty((g.size, 3))
        fb = _kffi.from_buffer
        _klib.capsheet_directions(g.size, fb("double[]", trig), fb("double[]", g),
                                  fb("double[]", d), fb("double[]", n))
        return d, n
    ca, sa, cb, sb, cg, sg = (np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta),
                              np.cos(gamma), np.sin(gamma))
    d = np.stack([cg * cb, sg * cb, -sb], axis=-1)
    n = np.stack([cg * sb * ca + sg * sa, sg * sb * ca - cg * sa, cb * ca], axis=-1)
    return d, n


def _eq8_residual(units: np.ndarray, d: np.ndarray, n: np.ndarray):
    """Σ over the given units (U, 4) of eq. (8): a float, or one per snapshot for ``d``, ``n``
    with a leading batch axis (B, n_links, 3)."""
    if USE_KERNEL and d.ndim == 2:  # one snapshot: the kernel
        u = np.ascontiguousarray(units, dtype=np.int64)
        d, n = np.ascontiguousarray(d, dtype=np.float64), np.ascontiguousarray(n, dtype=np.float64)
        fb = _kffi.from_buffer
        return float(_klib.capsheet_eq8(u.shape[0], fb("int64_t[]", u), fb("double[]", d),
                                        fb("double[]", n)))
    du, nu = d[..., units, :], n[..., units, :]
    rd = du[..., 0, :] + du[..., 1, :] - du[..., 2, :] - du[..., 3, :]
    rn = nu[..., 0, :] - nu[..., 1, :] + nu[..., 2, :] - nu[..., 3, :]
    tot = np.sum(rd * rd + rn * rn, axis=(-2, -1))
    return float(tot) if d.ndim == 2 else tot


def _check_int(name: str, v, lo: int) -> int:
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


def _rest_yaws(rest, n: int, rows: int, cols: int) -> np.ndarray:
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
    return y


def _check_previous(previous, n: int, rows: int, cols: int) -> None:
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


def _flatness(st, r, norm_g, noise):
    """Per unit (all units, row-major), ``h = exp(−(θ/θ0)²)`` in [0, 1]: 1 where the region
    around the unit is level within the noise (Case 1, unobservable), 0 where it is clearly
    tilted. θ² is twice the mean of ``1 − cos`` of the links' sensor-z tilts (cos from the
    reading: ``s_z/|s|``), averaged over the (2 `FLAT_RADIUS` + 1)² units around;
    θ0 = `FLAT_TILT_NOISE` · σ. Noise-free readings (σ = 0) give 0 everywhere."""
    units = st.lattice.units.reshape(-1, 4)
    noise = np.asarray(noise, float)
    if noise.ndim == 0 and noise <= 0.0:
        return np.zeros(units.shape[0])
    lead = noise.shape  # () or (B,): r (..., n_links, 3), norm_g (..., n_links)
    if USE_KERNEL and not lead and r.ndim == 2 and FLAT_RADIUS >= 0:  # one snapshot: the kernel
        u = _units_int64(st.rows, st.cols)
        rc = np.ascontiguousarray(r, dtype=np.float64)
        ng = np.ascontiguousarray(norm_g, dtype=np.float64)
        work, h = np.empty(2 * u.shape[0]), np.empty(u.shape[0])
        fb = _kffi.from_buffer
        _klib.capsheet_flatness(st.rows - 1, st.cols - 1, fb("int64_t[]", u), fb("double[]", rc),
                                fb("double[]", ng), G0, FLAT_RADIUS,
                                FLAT_TILT_NOISE * max(float(noise), 1e-300),
                                fb("double[]", work[:u.shape[0]]),
                                fb("double[]", work[u.shape[0]:]), fb("double[]", h))
        return h
    cz = r[..., 2] / np.maximum(norm_g * G0, 1e-300)
    th2 = 2.0 * (1.0 - cz[..., units]).mean(axis=-1)
    if FLAT_RADIUS > 0:
        # regional: a level strip between tilted cells (a cylinder's crest) is held by its
        # tilted neighbours through the lattice; only wide level regions need the prior
        from scipy.ndimage import uniform_filter  # here: importing scipy.ndimage costs ~0.2 s

        k = 2 * FLAT_RADIUS + 1
        th2 = uniform_filter(th2.reshape(lead + (st.rows - 1, st.cols - 1)),
                             size=(1,) * len(lead) + (k, k), mode="nearest"
                             ).reshape(lead + (-1,))
    th0 = FLAT_TILT_NOISE * np.maximum(noise, 1e-300)
    with np.errstate(divide="ignore", over="ignore"):  # noise 0: th0² underflows; masked below
        h = np.exp(-np.maximum(th2, 0.0) / (th0[..., None] ** 2 if lead else th0 ** 2))
    return np.where((noise > 0.0)[..., None], h, 0.0) if lead else h


def _link_flatness(st, h):
    """Per link, the mean flatness `h` (..., n_units) of the units it belongs to (one or two)."""
    units = st.lattice.units.reshape(-1, 4)
    acc = np.zeros(np.shape(h)[:-1] + (st.n_links,))
    cnt = np.zeros(st.n_links)
    for k in range(4):  # a link holds one position k in at most one unit: no repeated index
        acc[..., units[:, k]] += h
        cnt[units[:, k]] += 1.0
    return acc / np.maximum(cnt, 1.0)


def _prior_weights(prior, st, r, norm_g, noise, rest_given=False):
    """(per-variable yaw-prior weights (nv,), per-pair weights (n_pairs,)) for ``prior``.

    "adaptive": bending pairs ``(σ/BEND_STD_RAD)²``, shear pairs ``SHEAR_WEIGHT · h`` (h the
    unit's `_flatness`), no yaw prior beyond `ABS_PRIOR_FLOOR`; "level": the same with bending
    pairs at ``(σ/BEND_STD_RAD)² · h``, h the larger of its two links' `_link_flatness`; "off": floors only; "fixed":
    `FIXED_PRIOR_WEIGHT` on every yaw; "local": that times the mean flatness of the link's
    units. Pairs never go below `PRIOR_WEIGHT_MIN`.
    """
    lead = np.shape(noise)  # () or (B,): one snapshot, or a batch ("adaptive" only)
    w = np.full(lead + (st.pairs.shape[0],), PRIOR_WEIGHT_MIN)
    lam = np.full(st.n_var, ABS_PRIOR_FLOOR)
    if prior in ("adaptive", "level"):
        hu = _flatness(st, r, norm_g, noise)
        bend = (np.asarray(noise)[..., None] / BEND_STD_RAD) ** 2
        if prior == "level":  # a pair is held as much as its flatter link's units are level
            bend = bend * _link_flatness(st, hu)[..., st.pairs[:st.n_bend]].max(axis=-1)
        w[..., :st.n_bend] = np.maximum(bend, PRIOR_WEIGHT_MIN)
        sw = SHEAR_WEIGHT_REST if rest_given else SHEAR_WEIGHT
        w[..., st.n_bend:] = np.maximum(sw * hu[..., st.shear_unit], PRIOR_WEIGHT_MIN)
    elif prior == "fixed":
        lam[:] = FIXED_PRIOR_WEIGHT
    elif prior == "local":
        units = st.lattice.units.reshape(-1, 4)
        h = _flatness(st, r, norm_g, noise)
        acc = np.bincount(units.ravel(), weights=np.repeat(h, 4), minlength=st.n_links)
        cnt = np.bincount(units.ravel(), minlength=st.n_links)
        hl = acc / np.maximum(cnt, 1)
        lam = np.maximum(FIXED_PRIOR_WEIGHT * hl[st.var_links], ABS_PRIOR_FLOOR)
    return lam, w


def _noise_from_norms(norm_g: np.ndarray, valid: np.ndarray) -> float:
    """The readings' noise, per axis, as a fraction of g: the RMS of ``|s|/g − 1`` over the valid
    links (white noise of σ per axis moves ``|s|`` by σ; a static sheet reads exactly g)."""
    e = norm_g[valid] - 1.0
    return float(np.sqrt(_sumsq(e) / max(e.size, 1)))


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
        An earlier estimate of the same lattice: ``method="global"`` starts from its yaws (and
        its factorisation). It is not the prior's target (that would let what the data cannot
        see random-walk over a long run). ``method="paper"`` ignores it.
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
    if method not in METHODS:
        raise ValueError(f"Invalid method: {method!r} (expected one of {METHODS})")
    if model not in MODELS:
        raise ValueError(f"Invalid model: {model!r} (expected one of {MODELS})")
    if prior not in PRIORS:
        raise ValueError(f"Invalid prior: {prior!r} (expected one of {PRIORS})")
    if bad_readings not in ("raise", "mask"):
        raise ValueError(f"Invalid bad_readings: {bad_readings!r} (expected 'raise' or 'mask')")
    if paper_options is not None:  # method="paper" only (host.analysis.paper_method)
        from .paper_method import PaperOptions
        if method != "paper" or not isinstance(paper_options, PaperOptions):
            raise ValueError(f"Invalid paper_options: {paper_options!r} (a PaperOptions, with "
                             "method='paper' only)")
    rows = _check_int("rows", rows, 2)
    cols = _check_int("cols", cols, 2)
    lat = _lattice(rows, cols)
    n = lat.n_links
    if isinstance(link_length, (bool, np.bool_)) or not isinstance(link_length,
                                                                    (int, float, np.number)):
        raise ValueError(f"Invalid link_length: {link_length!r} (need a number of metres > 0)")
    L = float(link_length)
    if not (np.isfinite(L) and L > 0):
        raise ValueError(f"Invalid link_length: {link_length!r} (need a finite value > 0 m)")
    if isinstance(noise_pct_g, (bool, np.bool_)) or not isinstance(noise_pct_g,
                                                                    (int, float, np.number)) \
            or not (np.isfinite(noise_pct_g) and noise_pct_g >= 0):
        raise ValueError(f"Invalid noise_pct_g: {noise_pct_g!r} (need a finite value >= 0)")
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
    mask = None if vmask.all() else vmask
    if previous is not None:
        _check_previous(previous, n, rows, cols)
    rest_yaw = None if rest is None else _rest_yaws(rest, n, rows, cols)
    if rest_yaw is not None and not np.all(np.isfinite(rest_yaw)):
        raise ValueError("Invalid rest: its yaws contain NaN or inf.")
    if method == "paper" and mask is not None:
        raise ValueError("method='paper' does not support missing links (the paper has none); "
                         "use method='global'.")

    rr = r if mask is None else np.where(vmask[:, None], r, (0.0, 0.0, 1.0))
    if USE_KERNEL:  # the angles and their sines and cosines, which every stage below uses
        alpha, beta, trig = _roll_pitch_trig(rr)
    else:
        (alpha, beta), trig = _angles(rr), None
    t1 = time.perf_counter()

    state = None
    if method == "global":
        st = _structure(rows, cols, mask, model)
        target = st.rest_yaw if rest_yaw is None else rest_yaw
        if previous is not None:
            start = np.asarray(previous.yaws, dtype=float)
        else:
            start = target
        lu = None
        pstate = getattr(previous, "_state", None)
        if pstate is not None and pstate[0] is st:
            lu = pstate[1]
        noise_est = _noise_from_norms(norm, vmask)
        prior_w, bend_w = _prior_weights(prior, st, rr, np.where(vmask, norm, 1.0), noise_est,
                                         rest_yaw is not None)
        # stop when the step is far below what the noise moves the yaws by (σ rad, roughly)
        tol = max(YAW_TOL_RAD, YAW_TOL_NOISE * noise_est)
        gamma, iters, n_fact, lu, prob = _solve_global(st, alpha, beta, start.copy(), target,
                                                       prior_w, bend_w, lu, tol, trig)
        state = (st, lu, prob, gamma)
        t2 = time.perf_counter()
        d, nrm = _directions_normals(alpha, beta, gamma, trig)
        rhs_links = L * (d if st.all_valid else d[st.valid_links])
        if previous is not None:
            pprior = np.asarray(previous.joints, float).reshape(-1, 3)
        elif isinstance(rest, ShapeEstimate):
            pprior = np.asarray(rest.joints, float).reshape(-1, 3)
        else:
            pprior = L * st.rest_joints_unit
        rhs = st.incidence_T @ rhs_links + JOINT_PRIOR_WEIGHT * pprior
        P = st.lap_lu.solve(rhs)
        P -= P[0]
        joints = P.reshape(rows, cols, 3)
        residual = _eq8_residual(st.units, d, nrm)
        if mask is not None:
            ep = lat.endpoints
            miss = ~vmask
            chord = P[ep[miss, 1]] - P[ep[miss, 0]]
            nc = np.linalg.norm(chord, axis=1, keepdims=True)
            d[miss] = chord / np.where(nc > 0, nc, 1.0)
            nrm[miss] = np.nan
            gamma[miss] = target[miss]
            alpha = np.where(vmask, alpha, np.nan)
            beta = np.where(vmask, beta, np.nan)
            if trig is not None:
                trig[miss] = np.nan
    else:  # --- method="paper": host.analysis.paper_method (issue 33) ---
        from . import paper_method

        res = paper_method.estimate(alpha, beta, rows, cols, L,
                                    paper_options or paper_method.PaperOptions())
        gamma, iters, d, nrm = res["yaws"], res["iterations"], res["directions"], res["normals"]
        joints, residual, n_fact = res["joints"], res["residual"], 0
        t2 = t1 + res["t_yaw"]
    t3 = time.perf_counter()
    solv = (solvability(alpha, beta, rows, cols) if trig is None
            else _solvability_kernel(trig, rows, cols))
    t4 = time.perf_counter()
    return ShapeEstimate(joints=joints, directions=d, residual=residual, solvability=solv,
                         normals=nrm, yaws=gamma, alpha=alpha, beta=beta, valid=vmask,
                         link_length=L, method=method, iterations=int(iters),
                         factorisations=int(n_fact),
                         timings={"angles": t1 - t0, "yaw": t2 - t1, "joints": t3 - t2,
                                  "total": t4 - t0}, noise_pct_g=float(noise_pct_g),
                         _state=state)


#: `estimate_batch`: chord iterations per snapshot before it is handed to `estimate` instead.
BATCH_MAX_ITER = 8
#: ... and factorisations per group at most (a slow contraction or a rising cost makes one).
BATCH_REFACTOR = 3


def _solve_global_batch(st: _Structure, alpha, beta, gamma0, target, prior_w, bend_w, lu, tol):
    """`_solve_global` for a batch (B, n_links) of snapshots of one structure, all started at
    ``gamma0`` (n_links,): chord Gauss-Newton steps on one shared factorisation (the previous
    snapshot's, or one made at the batch's first), with the same stopping rule per snapshot.
    As in `_solve_global`, a new factorisation is made (at the first snapshot still iterating,
    at most `BATCH_REFACTOR` times) when the steps contract by less than `_REFACTOR_RATIO`
    (median over the batch) or raise some snapshot's cost. A snapshot whose step raised its cost,
    or that has not converged in `BATCH_MAX_ITER` steps, is reported failed (the caller
    re-estimates it with `estimate`). Returns (gamma (B, n), iterations (B,), failed (B,),
    factorisations, lu, the problem's ``take``)."""
    B = alpha.shape[0]
    gamma = np.repeat(gamma0[None, :], B, axis=0)
    iters = np.zeros(B, int)
    failed = np.zeros(B, bool)
    prob = _YawProblem(st, alpha, beta, target, prior_w, bend_w)
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
        # step says little), is below the tolerance; taken without evaluating (`_solve_global`)
        rt = np.maximum(rate[act], smax / ps)
        conv = (smax < tl) | ((smax < ps) & (ps < np.inf) & (smax * rt < tl))
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
        if n_fact < BATCH_REFACTOR and (worse.any() or np.median(ratio) > _REFACTOR_RATIO):
            pf = prob.take(int(act[0]))
            lu = pf.factor(pf.evaluate(g_act[0])[2], 0.0)
            n_fact += 1
            prev_smax[act] = np.inf  # a new matrix: its contraction is measured afresh
            rate[act] = 0.0
    failed[act] = True  # out of steps
    return gamma, iters, failed, n_fact, lu, prob.take


def estimate_batch(readings: np.ndarray, rows: int, cols: int, link_length: float,
                   valid: np.ndarray | None = None, previous: ShapeEstimate | None = None, *,
                   noise_pct_g: float = 1.0, bad_readings: str = "raise",
                   batch: int = 32) -> list[ShapeEstimate]:
    """Estimate a sequence of snapshots, many at a time: what an offline run wants.

    The result is what ``estimate(readings[k], ..., previous=result[k - 1])`` in a loop gives
    (``method="global"``, ``model="cells"``, ``prior="adaptive"``), to the solver's tolerance:
    the same cost is minimised with the same stopping rule, but ``batch`` consecutive snapshots
    are solved together — every snapshot of a group starts from the estimate before the group
    (without ``previous``, the first snapshot is estimated alone and the rest start there),
    their chord steps share one factorisation and their arithmetic runs as one numpy pass (one
    multi-right-hand-side solve per step, one joint solve per group), so the per-call overhead
    that dominates a 14x14 snapshot is paid once per group. A snapshot the group cannot finish
    (its mask differs from the group's, its readings need checking, its step fails to descend or
    it needs more than `BATCH_MAX_ITER` steps) is estimated by `estimate` on its own, in order.

    Parameters
    ----------
    readings : ndarray, shape (S, n_links, 3)
        Specific force per snapshot, m/s², as `estimate` takes one.
    valid : ndarray of bool, shape (S, n_links) or (n_links,), optional
        Per snapshot (or for all) the links present. Default: all.
    previous : ShapeEstimate, optional
        The estimate before the first snapshot (warm start), as in `estimate`.
    noise_pct_g, bad_readings
        As in `estimate`.
    batch : int
        Snapshots solved together (>= 1).

    Returns
    -------
    list of ShapeEstimate, one per snapshot. ``iterations`` counts the snapshot's own steps,
    ``factorisations`` is 1 on the snapshot whose group paid a factorisation, and ``timings``
    holds its share of the group's time (``"batched"``: 1.0 when it was solved in a group).

    Raises
    ------
    ValueError
        As `estimate`, prefixed with the snapshot's index; wrong shapes or dtypes of the inputs.
    """
    rows = _check_int("rows", rows, 2)
    cols = _check_int("cols", cols, 2)
    batch = _check_int("batch", batch, 1)
    if bad_readings not in ("raise", "mask"):
        raise ValueError(f"Invalid bad_readings: {bad_readings!r} (expected 'raise' or 'mask')")
    lat = _lattice(rows, cols)
    n = lat.n_links
    R = np.asarray(readings)
    if R.dtype.kind not in "iuf":
        raise ValueError(f"Invalid readings: dtype {R.dtype} (need real numbers, m/s²)")
    if R.ndim != 3 or R.shape[1:] != (n, 3):
        raise ValueError(f"Expected `readings` to have shape (S, {n}, 3) for a {rows}x{cols} "
                         f"lattice, got {R.shape}.")
    S = R.shape[0]
    if valid is None:
        V = np.ones((S, n), bool)
    else:
        V = np.asarray(valid)
        if V.dtype != bool:
            raise ValueError(f"Invalid valid: dtype {V.dtype} (need a boolean mask, True = "
                             "link present)")
        if V.shape == (n,):
            V = np.broadcast_to(V, (S, n))
        if V.shape != (S, n):
            raise ValueError(f"Expected `valid` to have shape ({S}, {n}) or ({n},), got "
                             f"{V.shape}.")
    kw = dict(noise_pct_g=noise_pct_g, bad_readings=bad_readings)
    # the checks `estimate` makes (it raises what is wrong; its messages name the links)
    if previous is not None:
        _check_previous(previous, n, rows, cols)
    L = float(link_length) if isinstance(link_length, (int, float, np.number)) \
        and not isinstance(link_length, (bool, np.bool_)) else link_length
    if S == 0:
        return []
    out: list[ShapeEstimate | None] = [None] * S

    def _one(k, r_k, v_k, before):
        try:
            return estimate(r_k, rows, cols, link_length, valid=v_k, previous=before, **kw)
        except ValueError as exc:
            raise ValueError(f"snapshot {k}: {exc}") from exc

    prev = previous
    lo, hi = READING_NORM_RANGE
    for s0 in range(0, S, batch):
        t0 = time.perf_counter()
        r = R[s0:s0 + batch].astype(float, copy=False)
        v = V[s0:s0 + batch]
        m = r.shape[0]
        norm = np.sqrt(np.einsum("bij,bij->bi", r, r)) / G0
        clean = np.all(np.isfinite(r), axis=2) & (norm >= lo) & (norm <= hi)
        mask0 = v[0]
        fast = np.all(v == mask0, axis=1) & np.all(clean | ~mask0, axis=1) & mask0.any()
        if not (isinstance(L, float) and np.isfinite(L) and L > 0):
            fast[:] = False  # `estimate` says what is wrong with it
        if prev is None and fast[0]:  # a cold start is one snapshot's job; the rest start there
            out[s0] = prev = _one(s0, r[0], v[0], None)
            fast[0] = False
        idx = np.flatnonzero(fast)
        if idx.size:
            mask = None if mask0.all() else mask0
            st = _structure(rows, cols, mask, "cells")
            rr = r[idx] if mask is None else np.where(mask0[None, :, None], r[idx],
                                                      (0.0, 0.0, 1.0))
            alpha, beta = _angles(rr)
            nm = np.where(mask0, norm[idx], 1.0)
            e = nm[:, mask0] - 1.0
            noise = np.sqrt(np.add.reduce(e * e, axis=1) / max(e.shape[1], 1))
            prior_w, bend_w = _prior_weights("adaptive", st, rr, nm, noise, False)
            tol = np.maximum(YAW_TOL_RAD, YAW_TOL_NOISE * noise)
            target = st.rest_yaw
            start = target if prev is None else np.asarray(prev.yaws, dtype=float)
            pstate = getattr(prev, "_state", None)
            lu = pstate[1] if pstate is not None and pstate[0] is st else None
            gamma, iters, failed, n_fact, lu, prob_of = _solve_global_batch(
                st, alpha, beta, start, target, prior_w, bend_w, lu, tol)
            ok = ~failed
            rows_ok = np.flatnonzero(ok)
            t1 = time.perf_counter()
            d, nrm = _directions_normals(alpha[ok], beta[ok], gamma[ok])
            k = int(ok.sum())
            vl = st.valid_links
            rhs_links = L * (d if st.all_valid else d[:, vl])  # (k, n_valid, 3)
            pprior = (L * st.rest_joints_unit if prev is None
                      else np.asarray(prev.joints, float).reshape(-1, 3))
            rhs = st.incidence_T @ rhs_links.transpose(1, 0, 2).reshape(vl.size, 3 * k)
            rhs += JOINT_PRIOR_WEIGHT * np.tile(pprior, (1, k))
            P = st.lap_lu.solve(rhs).reshape(-1, k, 3).transpose(1, 0, 2) if k else \
                np.zeros((0, rows * cols, 3))
            P = P - P[:, :1]
            residual = _eq8_residual(st.units, d, nrm) if k else np.zeros(0)
            a_out, b_out, g_out = alpha[ok], beta[ok], gamma[ok]
            if mask is not None:
                ep = lat.endpoints
                miss = ~mask0
                chord = P[:, ep[miss, 1]] - P[:, ep[miss, 0]]
                nc = np.linalg.norm(chord, axis=2, keepdims=True)
                d[:, miss] = chord / np.where(nc > 0, nc, 1.0)
                nrm[:, miss] = np.nan
                g_out[:, miss] = target[miss]
                a_out = np.where(mask0, a_out, np.nan)
                b_out = np.where(mask0, b_out, np.nan)
            solv = solvability(a_out, b_out, rows, cols)
            dt = (time.perf_counter() - t0) / max(idx.size, 1)
            for j, kk in enumerate(idx[ok]):
                out[s0 + kk] = ShapeEstimate(
                    joints=P[j].reshape(rows, cols, 3), directions=d[j], residual=float(residual[j]),
                    solvability=solv[j], normals=nrm[j], yaws=g_out[j], alpha=a_out[j],
                    beta=b_out[j], valid=mask0.copy(), link_length=L, method="global",
                    iterations=int(iters[rows_ok[j]]), factorisations=n_fact if j == 0 else 0,
                    timings={"angles": 0.0, "yaw": (t1 - t0) / max(idx.size, 1),
                             "joints": 0.0, "total": dt, "batched": 1.0},
                    noise_pct_g=float(noise_pct_g),
                    _state=(st, lu, prob_of(int(rows_ok[j])), g_out[j]))
            fast[idx[failed]] = False
        # the rest, one at a time and in order (what `estimate` says about them is the answer)
        for kk in range(m):
            if out[s0 + kk] is not None:
                continue
            before = next((out[q] for q in range(s0 + kk - 1, -1, -1) if out[q] is not None),
                          previous)
            out[s0 + kk] = _one(s0 + kk, r[kk], v[kk], before)
        prev = out[s0 + m - 1]
    return out  # type: ignore[return-value]


#: Samples drawn to estimate `ShapeEstimate.yaw_std` / ``joint_std`` (seeded, deterministic).
UNCERTAINTY_SAMPLES = 200


def _uncertainty(est: "ShapeEstimate") -> tuple[np.ndarray, np.ndarray]:
    """(yaw_std, joint_std) of an estimate, from the data's Fisher information (no prior).

    Linearised at the estimate: ``F = Jᵀ W J`` with ``W`` the inverse variance of every
    residual row for readings of noise σ = `noise_pct_g` per axis (the variance measured by
    perturbing the readings, `UNCERTAINTY_SAMPLES` // 4 draws, so that second-order terms such as
    cos β near β = 0 count). The yaws' covariance is ``(F + ε I)⁻¹`` with ``ε = 1/π²``: a yaw the
    data do not determine (Case 1, a squashed unit) gets a standard deviation near π rad instead
    of infinity. Its diagonal is sampled as ``δγ = (F + ε)⁻¹ (Jᵀ W^½ ξ + ε^½ η)`` (one solve per
    sample; covariance exactly ``(F + ε)⁻¹`` in expectation), the sheet's mean yaw removed
    (the yaw gauge). Each sample is carried to the joints through the joint least squares.
    """
    n = est.directions.shape[0]
    nanj = np.full(est.joints.shape[:2], np.nan)
    state = est._state
    if state is None:
        return np.full(n, np.nan), nanj
    st, _, prob, gamma = state
    nv = st.n_var
    if nv == 0 or est.noise_pct_g == 0.0:
        return np.where(est.valid, 0.0, np.nan), np.zeros(est.joints.shape[:2])
    g = np.random.Generator(np.random.MT19937(20260))
    sigma = est.noise_pct_g / 100.0 * G0
    # residual variances by perturbing the readings (reconstructed from the angles)
    ca, sa, cb, sb = (np.cos(est.alpha), np.sin(est.alpha), np.cos(est.beta), np.sin(est.beta))
    r0 = G0 * np.stack([-sb, cb * sa, cb * ca], axis=1)
    r0[~st.valid] = (0.0, 0.0, G0)
    base = prob.rows(gamma)
    K = max(UNCERTAINTY_SAMPLES // 4, 8)
    var = np.zeros_like(base)
    chunk = max(1, min(K, 2_000_000 // max(st.n_links, 1)))  # draws per batch (memory)
    done = 0
    while done < K:
        c = min(chunk, K - done)
        rk = r0 + g.normal(0.0, sigma, (c,) + r0.shape)  # the draws in order, as one per loop
        dr = _data_rows_batch(st, np.arctan2(rk[..., 1], rk[..., 2]),
                              np.arctan2(-rk[..., 0], np.hypot(rk[..., 1], rk[..., 2])),
                              gamma) - base
        var += np.einsum("ij,ij->j", dr, dr)
        done += c
    var = np.maximum(var / K, (1e-6 * sigma / G0) ** 2)
    _, _, blocks = prob.evaluate(gamma)
    eps = 1.0 / np.pi ** 2
    U = st.units.shape[0]
    t = blocks[0]
    if t.ndim == 3:  # eq6: (U, 2, 4) complex -> (2U, 4) rows, each complex row = 2 real rows
        t = t.transpose(1, 0, 2).reshape(2 * U, 4)
        uv = np.vstack([st.unit_var, st.unit_var])
    else:
        uv = st.unit_var
    m = t.shape[0]
    w_re = 1.0 / np.sqrt(var[:m])
    w_im = 1.0 / np.sqrt(var[m:2 * m])
    jre, jim = -t.imag * w_re[:, None], t.real * w_im[:, None]
    Hd = jre[:, :, None] * jre[:, None, :] + jim[:, :, None] * jim[:, None, :]
    data = np.zeros(st.nnz + 1)
    if t is blocks[0] or blocks[0].ndim != 3:
        data += np.bincount(st.block_slots[0], weights=Hd.ravel(), minlength=st.nnz + 1)
    else:  # eq6: two rows per unit share the unit's slots
        data += np.bincount(st.block_slots[0], weights=(Hd[:U] + Hd[U:]).ravel(),
                            minlength=st.nnz + 1)
    Jr = None
    if st.model == "cells":
        Jr = blocks[1] / np.sqrt(var[2 * m:])[:, None]
        data += np.bincount(st.block_slots[1], weights=(Jr[:, :, None] * Jr[:, None, :]).ravel(),
                            minlength=st.nnz + 1)
    data = data[:st.nnz]
    data[st.diag_slot] += eps
    A = sp.csc_matrix((data, st.csc_indices, st.csc_indptr), shape=(nv, nv))
    lu = _factorise(st, A, sweeps=False)
    S = UNCERTAINTY_SAMPLES
    # all samples at once: sample s draws ξ_re (m), ξ_im (m), ξ_roll (K) and η (nv), in this
    # order, from one stream (a row of Z); b = Jᵀ W^½ ξ + ε^½ η as one sparse product, and one
    # multi-right-hand-side solve (a solve per sample cost 200 triangular sweeps)
    kr = 0 if Jr is None else Jr.shape[0]
    Z = g.standard_normal((S, 2 * m + kr + nv))
    vals = [jre.ravel(), jim.ravel()]
    rows_ = [uv.ravel(), uv.ravel()]
    cols_ = [np.repeat(np.arange(m), uv.shape[1]), np.repeat(np.arange(m, 2 * m), uv.shape[1])]
    if Jr is not None:
        vals.append(Jr.ravel())
        rows_.append(st.roll_var.ravel())
        cols_.append(np.repeat(np.arange(2 * m, 2 * m + kr), st.roll_var.shape[1]))
    M = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows_), np.concatenate(cols_))),
                      shape=(nv + 1, 2 * m + kr))
    b = M @ Z[:, :2 * m + kr].T  # (nv + 1, S)
    b = b[:nv] + np.sqrt(eps) * Z[:, 2 * m + kr:].T
    dg = np.zeros((S, n))
    dg[:, st.var_links] = _solve(lu, np.ascontiguousarray(b[st.perm_inv]))[st.perm_of_var].T
    dg[:, st.valid] -= dg[:, st.valid].mean(axis=1, keepdims=True)
    ys = np.sqrt(np.mean(dg * dg, axis=0))
    ys[~st.valid] = np.nan
    # joints: δd = (e_z × d) δγ, δP = Lap⁻¹ Bᵀ (L δd), mean translation removed
    d = est.directions
    dp = np.stack([-d[:, 1], d[:, 0], np.zeros(n)], axis=1)
    vl = st.valid_links
    rhs = st.incidence_T @ (est.link_length * (dg[:, vl, None] * dp[None, vl])
                            ).transpose(1, 0, 2).reshape(vl.size, S * 3)
    dP = st.lap_lu.solve(rhs).reshape(-1, S, 3)
    dP -= dP.mean(axis=0, keepdims=True)
    js = np.sqrt(np.mean(np.sum(dP * dP, axis=2), axis=1)).reshape(est.joints.shape[:2])
    return ys, js


def _data_rows_batch(st: _Structure, alpha: np.ndarray, beta: np.ndarray,
                     gamma: np.ndarray) -> np.ndarray:
    """`_YawProblem.rows` at ``gamma`` (n_links,) for a batch of readings' angles ``alpha``,
    ``beta`` (B, n_links) at once: (B, rows) (the prior does not enter the rows)."""
    return _YawProblem(st, alpha, beta, st.rest_yaw, np.full(st.n_var, ABS_PRIOR_FLOOR),
                       np.zeros(st.pairs.shape[0])).rows(gamma)


def _few(idx, limit: int = 8) -> str:
    """A short list for error messages: the first ``limit`` items and how many more."""
    items = [str(v) for v in np.asarray(idx).tolist()[:limit]]
    more = len(idx) - len(items)
    return "[" + ", ".join(items) + (f", … {more} more" if more > 0 else "") + "]"


# ---------------------------------------------------------------------------------------------
# The joints-from-directions step alone (issue 30: the per-link filters and the fused estimator of
# host/analysis/motion/ place their joints with it, as `estimate` does)
# ---------------------------------------------------------------------------------------------

def joints_from_directions(directions: np.ndarray, rows: int, cols: int, link_length: float,
                           valid: np.ndarray | None = None) -> np.ndarray:
    """Joints from link directions by least squares, ``min Σ ‖p_b − p_a − L d‖²`` over the valid
    links (docs/design.md §5.6), joint ``(0, 0)`` at the origin: `estimate`'s last step, with the
    Laplacian factorised once per lattice and mask, without `estimate`'s weak prior.

    Parameters
    ----------
    directions : ndarray, shape (..., n_links, 3)
        Unit link directions (or any per-link vectors: the map is linear), world frame.
    rows, cols : int
    link_length : float
        ``L``, metres.
    valid : ndarray of bool, shape (n_links,), optional

    Returns
    -------
    ndarray, shape (..., rows, cols, 3)
    """
    rows, cols = _check_int("rows", rows, 2), _check_int("cols", cols, 2)
    n = _lattice(rows, cols).n_links
    d = np.asarray(directions, dtype=float)
    if d.ndim < 2 or d.shape[-2:] != (n, 3):
        raise ValueError(f"Expected `directions` to have shape (..., {n}, 3) for a {rows}x{cols} "
                         f"lattice, got {d.shape}.")
    vm = np.ones(n, bool) if valid is None else np.asarray(valid, dtype=bool)
    st = _structure(rows, cols, None if vm.all() else vm)
    batch = d.shape[:-2]
    dl = np.moveaxis(d.reshape((-1, n, 3))[:, st.valid_links], 0, -1)  # (links, 3, B)
    P = st.lap_lu.solve(st.incidence_T @ (float(link_length) * dl.reshape(dl.shape[0], -1)))
    P = P.reshape(rows * cols, 3, -1)
    P -= P[:1]
    return np.moveaxis(P, -1, 0).reshape(batch + (rows, cols, 3))
