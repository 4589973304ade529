"""Shape estimator: from one snapshot of link readings to the 3D shape of the whole sheet.

Conventions are DESIGN.md's and are not restated differently here: joints ``P[i, j]`` of shape
``(rows, cols, 3)`` in metres, world frame z up; link order and the 4-link units come from
`protocol.lattice.Lattice` only (``endpoints``, ``units``: ``d0 + d1 = d3 + d2``,
``n0 + n2 = n1 + n3``); sensor frame x along the link, z the sheet normal (top face); readings are
specific force (flat, top face up, reads ``(0, 0, +G0)``); ``R = Rz(γ) Ry(β) Rx(α)``; radians.

Two methods, same input, same output (`ShapeEstimate`):

``method="paper"`` (Hoshi & Shinoda, sections 2-3; the reference to beat)
    Roll and pitch from eq. (2) in closed form. Yaw per 4-link unit: with ``γ0`` fixed, minimise
    eq. (8) over ``(γ1, γ2, γ3)`` by steepest descent from several starts (all units and starts at
    once, vectorised). The units are chained from a root link (unit ``(0, 0)``'s link 0, yaw π/2 as
    at rest): along row 0 through the shared i-links, then down every column through the shared
    j-links; each link takes its yaw from the unit it is link 0 or 3 of (the last row's j-links and
    the last column's i-links from the unit they are link 2 or 1 of). Joints are then placed by
    walking along links from joint ``(0, 0)``: along row 0, then down every column ("combining the
    estimated unit shapes"). Missing links are not supported (the paper has none).

``method="global"`` (default)
    Roll and pitch as above. All yaws at once: every unit's eq. (4) and (6), xy parts, are linear in
    ``z_k = exp(iγ_k)`` (DESIGN.md), ``Σ_m s_m c_{u,m} z_{u,m} = 0`` with ``c = cos β`` for (4) and
    ``c = sin β cos α − i sin α`` for (6). One sparse nonlinear least-squares problem in the yaws
    (Gauss-Newton with Levenberg-Marquardt damping): one yaw fixed as gauge; a weak prior
    ``λ Σ wrap(γ − γ_prior)²`` keeps flat regions (the paper's Case 1) defined; its target is the
    rest layout (i-links yaw 0, j-links yaw π/2), or with ``previous`` a blend of mostly the
    previous yaws and a little of the rest layout (`PRIOR_MEMORY`: pure memory would let the
    unobservable modes random-walk over a long run); warm start from ``previous``, whose
    factorisation of the Gauss-Newton matrix is reused while it still contracts well.
    The normal matrix has a fixed sparsity pattern per lattice and mask; pattern, fill-reducing
    ordering and index maps are computed once and cached. Then joints by least squares over all
    valid links, ``min Σ ‖p_b − p_a − L d‖²`` (heights follow from the pitches alone), with the
    graph Laplacian factorised once per lattice and mask. A link marked invalid contributes no
    constraint: its two units are dropped from the yaw problem and the link from the joint problem;
    its reported direction is the chord between its estimated joints.

In both, joint ``(0, 0)`` is placed at the origin. The estimate is defined up to a rotation about
world z (yaw gauge); `overlay_error` and `error_percent_of_side` compare shapes as the paper does,
after a least-squares rigid overlay.

This module needs numpy and scipy only; it does not import `virtual_sheet`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from protocol.lattice import Lattice

from .metrics import error_percent_of_side, overlay, overlay_error

__all__ = ["ShapeEstimate", "estimate", "roll_pitch", "solvability", "overlay",
           "overlay_error", "error_percent_of_side", "METHODS"]

METHODS = ("global", "paper")

#: Prior weight λ on ``wrap(γ − γ_prior)²`` relative to the unit-scale eq. (4)/(6) residuals.
PRIOR_WEIGHT = 1e-2
#: Share of the previous estimate in the prior's target (the rest is the rest layout): 1 would let
#: unobservable (Case 1) modes random-walk over a long run of snapshots, 0 forgets the past.
PRIOR_MEMORY = 0.5
#: Weight of the normal-assumption residuals (eq. 6) relative to the loop closure (eq. 4).
NORMAL_WEIGHT = 0.2
#: Gauss-Newton stops when the largest yaw step is below this, radians.
YAW_TOL_RAD = 1e-4
#: Gauss-Newton iteration cap (warm starts need 2-3; cold starts from the rest layout ~10).
MAX_ITER = 50
#: A chord step (reused factorisation) that shrinks by less than this factor triggers a new one.
_REFACTOR_RATIO = 0.3
#: Weight of the joints' prior (keeps components cut off by missing links defined), per m².
JOINT_PRIOR_WEIGHT = 1e-9

# eq. (4): d0 + d1 - d2 - d3 = 0;  eq. (6): n0 - n1 + n2 - n3 = 0  (Lattice.units numbering)
_S_D = np.array([1.0, 1.0, -1.0, -1.0])
_S_N = np.array([1.0, -1.0, 1.0, -1.0])

# paper method: steepest descent settings
_SD_STARTS_CORNER = np.array([np.pi / 2, np.pi / 4, 3 * np.pi / 4, -np.pi / 2, -np.pi / 4,
                              -3 * np.pi / 4])
_SD_MAX_ITER = 300
_SD_TOL = 1e-14


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
        Gauss-Newton iterations (global) or steepest-descent iterations, summed over the chain
        (paper).
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
    #: solver state a later snapshot may warm-start from (structure, factorisation); private
    _state: tuple | None = field(default=None, repr=False)

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
    alpha = np.arctan2(r[:, 1], r[:, 2])
    beta = np.arctan2(-r[:, 0], np.hypot(r[:, 1], r[:, 2]))
    return alpha, beta


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


def _solvability_units(alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
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
    a, b = np.asarray(alpha, float)[units], np.asarray(beta, float)[units]
    ratio = _solvability_units(a, b)
    bad = ~np.all(np.isfinite(a) & np.isfinite(b), axis=-1)
    if bad.any():
        ratio[bad] = np.nan
    return ratio


# ---------------------------------------------------------------------------------------------
# Overlay and error, as the paper measures it (section 3.3)
# ---------------------------------------------------------------------------------------------

# ---------------------------------------------------------------------------------------------
# Per-lattice structure (cached by rows, cols, mask)
# ---------------------------------------------------------------------------------------------

class _Structure:
    """Everything about a lattice and mask that does not depend on the readings."""

    def __init__(self, rows: int, cols: int, valid: np.ndarray):
        lat = Lattice(rows, cols)
        self.lattice = lat
        self.rows, self.cols = rows, cols
        n = lat.n_links
        self.valid = valid
        self.all_valid = bool(valid.all())
        units = lat.units.reshape(-1, 4)
        self.unit_ok = valid[units].all(axis=1)  # (n_units,)
        self.units = units[self.unit_ok]  # active units (U, 4)
        U = self.units.shape[0]

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
        cand = np.flatnonzero(in_unit) if U else np.flatnonzero(valid)
        self.gauge = int(cand[np.argmin(mid_i[cand] ** 2 + mid_j[cand] ** 2 + 1e-3 * cand)])

        # variables: valid links except the gauge
        var = np.full(n, -1)
        var_links = np.flatnonzero(valid & (np.arange(n) != self.gauge))
        var[var_links] = np.arange(var_links.size)
        self.var_links = var_links
        nv = var_links.size
        self.n_var = nv

        # pattern of the normal matrix: unit 4x4 blocks + diagonal (prior)
        uv = var[self.units]  # (U, 4), -1 for the gauge
        bi = np.repeat(uv, 4, axis=1).ravel()  # row var of block entry (U*16)
        bj = np.tile(uv, (1, 4)).ravel()
        keep = (bi >= 0) & (bj >= 0)
        rr = np.concatenate([bi[keep], np.arange(nv)])
        cc = np.concatenate([bj[keep], np.arange(nv)])

        # fill-reducing ordering, computed once: SuperLU's MMD on A^T + A
        if nv:
            pat = sp.csc_matrix((np.ones(rr.size), (rr, cc)), shape=(nv, nv))
            pat.sum_duplicates()
            pat = pat + sp.identity(nv, format="csc") * (4.0 * pat.max() + 1.0)
            perm = splu(pat.tocsc(), permc_spec="MMD_AT_PLUS_A").perm_c
        else:
            perm = np.arange(0)
        # the matrix is factorised as A[q][:, q] with q = argsort(perm): variable v sits at perm[v]
        pos = np.asarray(perm, dtype=np.int64)
        pr, pc = pos[rr], pos[cc]
        # CSC slots of the permuted matrix, one per (row, col) pair
        key = pc.astype(np.int64) * max(nv, 1) + pr
        ukey, slot = np.unique(key, return_inverse=True)
        self.nnz = ukey.size
        self.csc_indices = (ukey % max(nv, 1)).astype(np.int32)
        col = ukey // max(nv, 1)
        self.csc_indptr = np.searchsorted(col, np.arange(nv + 1)).astype(np.int32)
        n_blk = int(keep.sum())
        # block entry -> slot (dropped gauge entries go to a dummy slot nnz)
        self.blk_slot = np.full(bi.size, self.nnz, dtype=np.int64)
        self.blk_slot[np.flatnonzero(keep)] = slot[:n_blk]
        self.diag_slot = slot[n_blk:]  # for variable v (original order) its diagonal slot
        self.perm_of_var = pos  # permuted position of every variable
        self.perm_inv = np.argsort(pos)  # variable at every permuted position
        # gradient scatter: unit entry -> variable (dummy nv for the gauge)
        self.ent_var = np.where(uv >= 0, uv, nv).ravel()

        # joints: Laplacian of the valid links + a weak prior, factorised once
        vl = np.flatnonzero(valid)
        self.valid_links = vl
        a, b = ep[vl, 0], ep[vl, 1]
        nj = rows * cols
        B = sp.csr_matrix((np.concatenate([-np.ones(vl.size), np.ones(vl.size)]),
                           (np.concatenate([np.arange(vl.size)] * 2), np.concatenate([a, b]))),
                          shape=(vl.size, nj))
        self.incidence_T = B.T.tocsr()
        lap = (B.T @ B + JOINT_PRIOR_WEIGHT * sp.identity(nj)).tocsc()
        self.lap_lu = splu(lap, permc_spec="MMD_AT_PLUS_A")

        # rest layout of the joints (prior for isolated parts), L = 1
        self.rest_joints_unit = np.stack([ji.astype(float), jj.astype(float),
                                          np.zeros(nj)], axis=1)


@lru_cache(maxsize=64)
def _lattice(rows: int, cols: int) -> Lattice:
    """One `Lattice` per size, so its cached ``endpoints``/``units`` are computed once."""
    return Lattice(rows, cols)


@lru_cache(maxsize=16)
def _structure_cached(rows: int, cols: int, mask_bytes: bytes | None) -> _Structure:
    n = Lattice(rows, cols).n_links
    valid = np.ones(n, bool) if mask_bytes is None else np.frombuffer(mask_bytes, dtype=bool).copy()
    return _Structure(rows, cols, valid)


def _structure(rows: int, cols: int, valid: np.ndarray | None) -> _Structure:
    if valid is None or valid.all():
        return _structure_cached(rows, cols, None)
    return _structure_cached(rows, cols, valid.tobytes())


# ---------------------------------------------------------------------------------------------
# Global yaw solve
# ---------------------------------------------------------------------------------------------

def _wrap(x: np.ndarray) -> np.ndarray:
    return (x + np.pi) % (2 * np.pi) - np.pi


def _unit_coeffs(st: _Structure, alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """Complex coefficients of eq. (4) and (6), xy parts, per active unit: shape (U, 2, 4);
    ``[:, 0]`` is eq. (4) (``± cos β``), ``[:, 1]`` eq. (6) (``± (sin β cos α − i sin α)``) times
    `NORMAL_WEIGHT`."""
    a = alpha[st.units]
    b = beta[st.units]
    c = np.empty((a.shape[0], 2, 4), complex)
    c[:, 0] = np.cos(b) * _S_D
    c[:, 1] = (np.sin(b) * np.cos(a) - 1j * np.sin(a)) * (_S_N * NORMAL_WEIGHT)
    return c


class _YawProblem:
    """The global yaw least-squares problem for one snapshot (see the module docstring)."""

    def __init__(self, st: _Structure, alpha, beta, gamma_prior):
        self.st = st
        self.c = _unit_coeffs(st, alpha, beta)
        self.prior = gamma_prior[st.var_links]
        self.lam = PRIOR_WEIGHT

    def evaluate(self, gamma):
        """Cost (½ Σ r² + ½ λ Σ wrap(γ − γ_prior)²), gradient over the variables, and the terms
        ``t = c e^{iγ}`` (U, 2, 4) whose sums are the residuals (``∂r/∂γ_m = i t_m``)."""
        st = self.st
        t = self.c * np.exp(1j * gamma)[st.units][:, None, :]
        r = t.sum(axis=2)
        e = _wrap(gamma[st.var_links] - self.prior)
        cost = 0.5 * (np.vdot(r, r).real + self.lam * np.dot(e, e))
        # gradient Re(conj(i t_m) r) = Im(conj(t_m) r), summed over the two equations
        gu = (t.conj() * r[:, :, None]).imag.sum(axis=1)
        # float64 even when no unit is active (bincount of nothing is int64)
        grad = np.bincount(st.ent_var, weights=gu.ravel(), minlength=st.n_var + 1)[:st.n_var].astype(float)
        grad += self.lam * e
        return cost, grad, t

    def factor(self, t, mu):
        """Factorise the Gauss-Newton matrix ``JᵀJ + (λ + μ) I`` (permuted, fixed pattern)."""
        st = self.st
        # H_mn = Re(conj(i t_m) i t_n) = Re(conj(t_m) t_n), per unit a 4x4 block
        Hd = np.einsum("uem,uen->umn", t.conj(), t).real
        data = np.bincount(st.blk_slot, weights=Hd.ravel(), minlength=st.nnz + 1)[:st.nnz].astype(float)
        data[st.diag_slot] += self.lam + mu
        A = sp.csc_matrix((data, st.csc_indices, st.csc_indptr), shape=(st.n_var, st.n_var))
        return splu(A, permc_spec="NATURAL", diag_pivot_thresh=0.0,
                    options=dict(SymmetricMode=True))

    def step(self, lu, grad):
        st = self.st
        return lu.solve(-grad[st.perm_inv])[st.perm_of_var]


def _solve_global(st: _Structure, alpha, beta, gamma0, gamma_prior, lu=None):
    """Gauss-Newton on all yaws, reusing a factorisation while it contracts well (chord steps),
    Levenberg-Marquardt damping when a step fails. Returns (gamma, iterations, factorisations, lu).

    ``lu`` may be the factorisation left by the previous snapshot (same structure): the normal
    matrix changes little between snapshots, so its chord iterations usually converge without a
    new factorisation. A new one is made when a step raises the cost or contracts by less than
    `_REFACTOR_RATIO`.
    """
    gamma = gamma0.copy()
    prob = _YawProblem(st, alpha, beta, gamma_prior)
    if st.n_var == 0:
        _, _, t = prob.evaluate(gamma)
        return gamma, 0, 0, None, _xy_residual(t), prob
    vl = st.var_links
    cost, grad, t = prob.evaluate(gamma)
    mu = 0.0
    fresh = False
    n_fact = 0
    prev_smax = np.inf
    it = 0
    while it < MAX_ITER:
        it += 1
        if lu is None:
            lu = prob.factor(t, mu)
            fresh = True
            n_fact += 1
        step = prob.step(lu, grad)
        g_new = gamma.copy()
        g_new[vl] += step
        cost_new, grad_new, t_new = prob.evaluate(g_new)
        if not cost_new <= cost * (1.0 + 1e-12) + 1e-300:
            lu = None  # refactorise here; damp if even a fresh Gauss-Newton step failed
            if fresh:
                mu = max(10.0 * mu, 1e-3)
                if mu > 1e8:
                    break
            fresh = False
            continue
        gamma, cost, grad, t = g_new, cost_new, grad_new, t_new
        smax = float(np.max(np.abs(step)))
        # converged: this step, or the next one predicted from the contraction so far, is tiny
        if smax < YAW_TOL_RAD or (mu == 0.0 and smax < prev_smax < np.inf
                                  and smax * smax < YAW_TOL_RAD * prev_smax):
            break
        if mu > 0.0:
            mu = mu / 10.0 if mu > 1e-6 else 0.0
            lu = None
        elif smax > _REFACTOR_RATIO * prev_smax:
            lu = None
        prev_smax = smax
        fresh = False
    return gamma, it, n_fact, lu, _xy_residual(t), prob


def _xy_residual(t) -> float:
    """Eq. (8)'s x and y terms summed over the units, from the solver's terms (U, 2, 4)."""
    rd = t[:, 0].sum(axis=1)
    rn = t[:, 1].sum(axis=1) / NORMAL_WEIGHT
    return float(np.vdot(rd, rd).real + np.vdot(rn, rn).real)


def _z_residual(units, alpha, beta) -> float:
    """Eq. (8)'s z terms (independent of yaw) summed over the units (U, 4)."""
    a, b = alpha[units], beta[units]
    rz = np.sin(b) @ -_S_D
    nz = (np.cos(b) * np.cos(a)) @ _S_N
    return float(np.dot(rz, rz) + np.dot(nz, nz))


# ---------------------------------------------------------------------------------------------
# Paper method: per-unit steepest descent on eq. (8), chained
# ---------------------------------------------------------------------------------------------

def _steepest_descent(cd, cn, g, free):
    """Minimise eq. (8) per unit and start by steepest descent (adaptive step, per element).

    cd, cn : complex (U, 1, 4) coefficients; g : (U, S, 4) yaws, updated where ``free`` (U, 1, 4).
    Returns the yaws, eq. (8)'s γ-dependent part per (U, S), and the iterations used.
    """
    def value_grad(g):
        z = np.exp(1j * g)
        td, tn = cd * z, cn * z
        rd, rn = td.sum(-1), tn.sum(-1)
        P = rd.real ** 2 + rd.imag ** 2 + rn.real ** 2 + rn.imag ** 2
        grad = 2 * ((np.conj(td) * rd[..., None]).imag + (np.conj(tn) * rn[..., None]).imag)
        return P, grad * free

    P, grad = value_grad(g)
    step = np.full(P.shape, 0.1)
    it = 0
    for it in range(1, _SD_MAX_ITER + 1):
        g_new = g - step[..., None] * grad
        P_new, grad_new = value_grad(g_new)
        better = P_new <= P
        g = np.where(better[..., None], g_new, g)
        P = np.where(better, P_new, P)
        grad = np.where(better[..., None], grad_new, grad)
        step = np.where(better, step * 1.5, step * 0.5)
        if np.all((np.sum(grad * grad, -1) < _SD_TOL) | (step < 1e-10)):
            break
    return g, P, it


def _solve_paper(rows: int, cols: int, alpha, beta):
    """Paper's yaw estimation: units chained from a root link, each by steepest descent on eq. (8).

    Unit ``(0, 0)`` has its link 0 fixed (root, yaw π/2 as at rest) and solves for its other three
    yaws. Every further unit has one or two links already fixed by the units solved before it
    (link 3 = left neighbour's link 1, link 0 = upper neighbour's link 2) and solves for the rest,
    by steepest descent from several starts (parallelogram shapes of several corner angles); the
    start ending with the smallest eq. (8) wins. Units on one anti-diagonal ``i + j = k`` do not
    depend on each other and are solved together (vectorised). Returns (gamma, iterations).
    """
    lat = Lattice(rows, cols)
    units = lat.units  # (R-1, C-1, 4)
    a, b = alpha[units], beta[units]
    cb, sb, ca, sa = np.cos(b), np.sin(b), np.cos(a), np.sin(a)
    cd_all = cb * _S_D
    cn_all = (sb * ca - 1j * sa) * _S_N
    gamma = np.full(lat.n_links, np.nan)
    gamma[units[0, 0, 0]] = np.pi / 2  # the root link
    c = _SD_STARTS_CORNER  # (S,)
    R1, C1 = units.shape[:2]
    total_it = 0
    for k in range(R1 + C1 - 1):
        ii = np.arange(max(0, k - C1 + 1), min(R1 - 1, k) + 1)
        jj = k - ii
        lk = units[ii, jj]  # (U, 4)
        known = np.isfinite(gamma[lk])  # (U, 4)
        g_known = np.where(known, gamma[lk], 0.0)
        g0, g3 = g_known[:, 0:1], g_known[:, 3:4]
        # starts (U, S, 4): parallelogram with corner angle c between link 3 and link 0
        k0 = known[:, 0:1]
        k3 = known[:, 3:4]
        base0 = np.where(k0, g0, g3 + c)  # link 0
        base3 = np.where(k3, g3, g0 - c)  # link 3
        both = k0 & k3
        shift = np.where(both, c - np.pi / 2, 0.0)  # both known: perturb links 1 and 2 instead
        g = np.stack([base0, base3 + shift, base0 + shift, base3], axis=-1)
        g = np.where(known[:, None, :], g_known[:, None, :], g)
        g, P, it = _steepest_descent(cd_all[ii, jj][:, None, :], cn_all[ii, jj][:, None, :], g,
                                     (~known)[:, None, :].astype(float))
        total_it += it
        best = np.argmin(P, axis=1)
        gb = g[np.arange(lk.shape[0]), best]  # (U, 4)
        gamma[lk] = np.where(known, gamma[lk], gb)
    return _wrap(gamma), total_it


def _paper_joints(rows: int, cols: int, vec: np.ndarray) -> np.ndarray:
    """Walk along links from joint (0, 0): row 0 by its j-links, then down every column."""
    lat = Lattice(rows, cols)
    vi = vec[:lat.n_i_links].reshape(rows - 1, cols, 3)
    vj = vec[lat.n_i_links:].reshape(rows, cols - 1, 3)
    P = np.zeros((rows, cols, 3))
    P[0, 1:] = np.cumsum(vj[0], axis=0)
    P[1:] = P[0][None] + np.cumsum(vi, axis=0)
    return P


# ---------------------------------------------------------------------------------------------
# estimate()
# ---------------------------------------------------------------------------------------------

def _directions_normals(alpha, beta, gamma):
    ca, sa, cb, sb, cg, sg = (np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta),
                              np.cos(gamma), np.sin(gamma))
    d = np.stack([cg * cb, sg * cb, -sb], axis=1)
    n = np.stack([cg * sb * ca + sg * sa, sg * sb * ca - cg * sa, cb * ca], axis=1)
    return d, n


def _eq8_residual(units: np.ndarray, d: np.ndarray, n: np.ndarray) -> float:
    """Σ over the given units (U, 4) of eq. (8)."""
    du, nu = d[units], n[units]
    rd = du[:, 0] + du[:, 1] - du[:, 2] - du[:, 3]
    rn = nu[:, 0] - nu[:, 1] + nu[:, 2] - nu[:, 3]
    return float(np.sum(rd * rd) + np.sum(rn * rn))


def estimate(readings: np.ndarray, rows: int, cols: int, link_length: float,
             valid: np.ndarray | None = None, previous: ShapeEstimate | None = None,
             method: str = "global") -> ShapeEstimate:
    """Estimate the sheet's shape from one snapshot of readings.

    Parameters
    ----------
    readings : ndarray, shape (n_links, 3)
        Specific force of every link, m/s², sensor frame, links in DESIGN.md order
        (``n_links = (rows-1)*cols + rows*(cols-1)``). Entries of invalid links are ignored.
    rows, cols : int
        Joints along i and j, each >= 2.
    link_length : float
        ``L``, metres, > 0.
    valid : ndarray of bool, shape (n_links,), optional
        False marks a missing link (no constraint from it). Default: all valid.
    previous : ShapeEstimate, optional
        An earlier estimate of the same lattice: ``method="global"`` starts from its yaws (and
        its factorisation), and blends them into the weak prior's target (`PRIOR_MEMORY`;
        default target: the rest layout). ``method="paper"`` ignores it.
    method : {"global", "paper"}
        See the module docstring.

    Returns
    -------
    ShapeEstimate

    Raises
    ------
    ValueError
        Wrong shapes (the message names the shape expected and got), non-finite readings on valid
        links, no valid link, an unknown method, or missing links with ``method="paper"``.
    """
    t0 = time.perf_counter()
    if method not in METHODS:
        raise ValueError(f"Invalid method: {method!r} (expected one of {METHODS})")
    lat = _lattice(int(rows), int(cols))
    n = lat.n_links
    L = float(link_length)
    if not (np.isfinite(L) and L > 0):
        raise ValueError(f"Invalid link_length: {link_length!r} (need a finite value > 0 m)")
    r = np.asarray(readings, dtype=float)
    if r.shape != (n, 3):
        raise ValueError(f"Expected `readings` to have shape ({n}, 3) for a {rows}x{cols} "
                         f"lattice, got {r.shape}.")
    if valid is None:
        mask = None
        vmask = np.ones(n, bool)
    else:
        vmask = np.asarray(valid)
        if vmask.shape != (n,):
            raise ValueError(f"Expected `valid` to have shape ({n},) for a {rows}x{cols} lattice, "
                             f"got {vmask.shape}.")
        vmask = vmask.astype(bool)
        if not vmask.any():
            raise ValueError(f"No valid link: all {n} links are masked out by `valid`; "
                             "cannot estimate a shape.")
        mask = None if vmask.all() else vmask
    if mask is None:
        if not np.all(np.isfinite(r)):
            raise ValueError("Non-finite readings on valid links; mask them out with `valid`.")
    elif not np.all(np.isfinite(r[vmask])):
        raise ValueError("Non-finite readings on valid links; mask them out with `valid`.")
    if previous is not None:
        pj = np.shape(previous.joints)
        if pj != (rows, cols, 3):
            raise ValueError(f"Expected `previous` of a {rows}x{cols} lattice, joints shape "
                             f"({rows}, {cols}, 3), got {pj}.")
    if method == "paper" and mask is not None:
        raise ValueError("method='paper' does not support missing links (the paper has none); "
                         "use method='global'.")

    rr = r if mask is None else np.where(vmask[:, None], r, (0.0, 0.0, 1.0))
    alpha, beta = roll_pitch(rr)
    t1 = time.perf_counter()

    if method == "global":
        st = _structure(rows, cols, mask)
        if previous is not None:
            start = np.asarray(previous.yaws, dtype=float)
            if start.shape != (n,):
                raise ValueError(f"Expected `previous.yaws` to have shape ({n},), got {start.shape}.")
            # prior target: mostly the previous yaws, partly the rest layout, so that what the
            # data cannot see (flat regions) does not random-walk from snapshot to snapshot
            prior = st.rest_yaw + PRIOR_MEMORY * _wrap(start - st.rest_yaw)
        else:
            start = prior = st.rest_yaw
        lu = None
        pstate = getattr(previous, "_state", None)
        if pstate is not None and pstate[0] is st:
            lu = pstate[1]
        gamma, iters, n_fact, lu, res_xy, prob = _solve_global(st, alpha, beta, start.copy(),
                                                               prior, lu)
        residual = res_xy + _z_residual(st.units, alpha, beta)
        state = (st, lu)
        t2 = time.perf_counter()
        d, nrm = _directions_normals(alpha, beta, gamma)
        rhs_links = L * (d if st.all_valid else d[st.valid_links])
        if previous is not None:
            pprior = np.asarray(previous.joints, float).reshape(-1, 3)
        else:
            pprior = L * st.rest_joints_unit
        rhs = st.incidence_T @ rhs_links + JOINT_PRIOR_WEIGHT * pprior
        P = st.lap_lu.solve(rhs)
        P -= P[0]
        joints = P.reshape(rows, cols, 3)
        if mask is not None:
            ep = lat.endpoints
            bad = ~vmask
            chord = P[ep[bad, 1]] - P[ep[bad, 0]]
            nc = np.linalg.norm(chord, axis=1, keepdims=True)
            d[bad] = chord / np.where(nc > 0, nc, 1.0)
            nrm[bad] = np.nan
            gamma[bad] = prior[bad]
            alpha = np.where(vmask, alpha, np.nan)
            beta = np.where(vmask, beta, np.nan)
    else:
        gamma, iters = _solve_paper(rows, cols, alpha, beta)
        t2 = time.perf_counter()
        d, nrm = _directions_normals(alpha, beta, gamma)
        joints = _paper_joints(rows, cols, L * d)
        residual = _eq8_residual(lat.units.reshape(-1, 4), d, nrm)
        n_fact = 0
        state = None
    t3 = time.perf_counter()
    if method == "global" and mask is None:
        # eq. (7)'s complex rows are the solver's coefficients of links 1..3 (up to a common sign)
        solv = _sigma_ratio(prob.c[:, 0, 1:].real, prob.c[:, 1, 1:] / NORMAL_WEIGHT
                            ).reshape(rows - 1, cols - 1)
    else:
        solv = solvability(alpha, beta, rows, cols)
    t4 = time.perf_counter()
    return ShapeEstimate(joints=joints, directions=d, residual=residual, solvability=solv,
                         normals=nrm, yaws=gamma, alpha=alpha, beta=beta, valid=vmask,
                         link_length=L, method=method, iterations=int(iters),
                         factorisations=int(n_fact),
                         timings={"angles": t1 - t0, "yaw": t2 - t1, "joints": t3 - t2,
                                  "total": t4 - t0}, _state=state)
