"""After the yaws: every link's direction and normal in the world, the joints by least squares,
eq. (8)'s residual, and what a missing link reports (`joints_and_mask`)."""

from __future__ import annotations

import numpy as np

import host.analysis.estimator.kernel as kernel  # the switch, read at call time
from .kernel import ffi as _kffi, lib as _klib
from .angles import angle_trig
from .linalg import lap_solve
from .checks import check_int
from .structure import JOINT_PRIOR_WEIGHT, lattice_of, structure_of

__all__ = ["directions_normals", "eq8_residual", "joints_and_mask", "joints_from_directions"]


def directions_normals(alpha, beta, gamma, trig=None, cs=None):
    """Per link its direction (sensor x) and normal (sensor z) in the world, (..., n_links, 3)
    each (docs/design.md's ``R = Rz(γ) Ry(β) Rx(α)``); ``trig``: the links' `angle_trig`, if
    already made (one snapshot); ``cs``: the yaws' cosines and sines, interleaved, if already made
    (`YawProblem.link_cs`)."""
    if kernel.USE_KERNEL and np.ndim(alpha) == 1:  # one snapshot: the kernel
        if trig is None:
            trig = angle_trig(alpha, beta)
        g = np.ascontiguousarray(gamma, dtype=np.float64)
        d, n = np.empty((g.size, 3)), np.empty((g.size, 3))
        fb = _kffi.from_buffer
        if cs is not None:
            _klib.capsheet_directions_cs(g.size, fb("double[]", trig), fb("double[]", cs),
                                         fb("double[]", d), fb("double[]", n))
        else:
            _klib.capsheet_directions(g.size, fb("double[]", trig), fb("double[]", g),
                                      fb("double[]", d), fb("double[]", n))
        return d, n
    ca, sa, cb, sb, cg, sg = (np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta),
                              np.cos(gamma), np.sin(gamma))
    d = np.stack([cg * cb, sg * cb, -sb], axis=-1)
    n = np.stack([cg * sb * ca + sg * sa, sg * sb * ca - cg * sa, cb * ca], axis=-1)
    return d, n


def eq8_residual(units: np.ndarray, d: np.ndarray, n: np.ndarray):
    """Σ over the given units (U, 4) of eq. (8): a float, or one per snapshot for ``d``, ``n``
    with a leading batch axis (B, n_links, 3)."""
    if kernel.USE_KERNEL and d.ndim == 2:  # one snapshot: the kernel
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


def joints_and_mask(st, L: float, alpha, beta, gamma, target, joint_prior, trig=None, cs=None):
    """The shape from the yaws, for one snapshot (``gamma`` (n_links,)) or a batch of one
    structure (B, n_links): every link's direction and normal, the joints by least squares over
    the valid links, ``min Σ ‖p_b − p_a − L d‖²`` plus ``JOINT_PRIOR_WEIGHT`` towards
    ``joint_prior`` (n_joints, 3), with joint (0, 0) at the origin (one multi-right-hand-side
    solve for a batch), eq. (8)'s residual over the active units, and for a missing link: the
    chord between its estimated joints as its direction, NaN normal, roll and pitch, its yaw the
    ``target``'s. Returns (joints (..., n_joints, 3), directions, normals, yaws, alpha, beta,
    residual); ``trig`` (one snapshot) is updated in place (NaN for missing links); ``cs``: the
    yaws' cosines and sines, if made (`directions_normals`)."""
    d, nrm = directions_normals(alpha, beta, gamma, trig, cs)
    single = gamma.ndim == 1
    vl = st.valid_links
    dl = L * (d if st.all_valid else d[..., vl, :])  # (..., n_valid, 3)
    if single:
        rhs = st.incidence_T @ dl + JOINT_PRIOR_WEIGHT * joint_prior
        P = lap_solve(st, rhs)
        P -= P[0]
    else:  # the snapshots side by side: (n_valid, 3 B), one solve
        B = gamma.shape[0]
        rhs = st.incidence_T @ dl.transpose(1, 0, 2).reshape(vl.size, 3 * B)
        rhs += JOINT_PRIOR_WEIGHT * np.tile(joint_prior, (1, B))
        P = st.lap_lu.solve(rhs).reshape(-1, B, 3).transpose(1, 0, 2)
        P = P - P[:, :1]
    residual = eq8_residual(st.units, d, nrm)
    if not st.all_valid:
        ep = st.lattice.endpoints
        miss = ~st.valid
        chord = P[..., ep[miss, 1], :] - P[..., ep[miss, 0], :]
        nc = np.linalg.norm(chord, axis=-1, keepdims=True)
        d[..., miss, :] = chord / np.where(nc > 0, nc, 1.0)
        nrm[..., miss, :] = np.nan
        gamma[..., miss] = target[miss]
        alpha = np.where(st.valid, alpha, np.nan)
        beta = np.where(st.valid, beta, np.nan)
        if trig is not None:
            trig[miss] = np.nan
    return P, d, nrm, gamma, alpha, beta, residual


# ---------------------------------------------------------------------------------------------
# The joints-from-directions step alone (the per-link filters and the fused estimator of
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
    rows, cols = check_int("rows", rows, 2), check_int("cols", cols, 2)
    n = lattice_of(rows, cols).n_links
    d = np.asarray(directions, dtype=float)
    if d.ndim < 2 or d.shape[-2:] != (n, 3):
        raise ValueError(f"Expected `directions` to have shape (..., {n}, 3) for a {rows}x{cols} "
                         f"lattice, got {d.shape}.")
    vm = np.ones(n, bool) if valid is None else np.asarray(valid, dtype=bool)
    st = structure_of(rows, cols, None if vm.all() else vm)
    batch = d.shape[:-2]
    dl = np.moveaxis(d.reshape((-1, n, 3))[:, st.valid_links], 0, -1)  # (links, 3, B)
    P = st.lap_lu.solve(st.incidence_T @ (float(link_length) * dl.reshape(dl.shape[0], -1)))
    P = P.reshape(rows * cols, 3, -1)
    P -= P[:1]
    return np.moveaxis(P, -1, 0).reshape(batch + (rows, cols, 3))
