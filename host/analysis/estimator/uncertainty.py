"""The data's uncertainty of an estimate: `ShapeEstimate.yaw_std` and ``joint_std``."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .angles import G0
from .linalg import factorise, solve
from .priors import ABS_PRIOR_FLOOR
from .structure import Structure
from .yawproblem import YawProblem

__all__ = ["UNCERTAINTY_SAMPLES", "yaw_joint_std"]

#: Samples drawn to estimate `ShapeEstimate.yaw_std` / ``joint_std`` (seeded, deterministic).
UNCERTAINTY_SAMPLES = 200


def yaw_joint_std(est) -> tuple[np.ndarray, np.ndarray]:
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
    state = est.solution
    if state is None:
        return np.full(n, np.nan), nanj
    st, prob, gamma = state.structure, state.problem, state.yaws
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
    lu = factorise(st, A, sweeps=False)
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
    dg[:, st.var_links] = solve(lu, np.ascontiguousarray(b[st.perm_inv]))[st.perm_of_var].T
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


def _data_rows_batch(st: Structure, alpha: np.ndarray, beta: np.ndarray,
                     gamma: np.ndarray) -> np.ndarray:
    """`YawProblem.rows` at ``gamma`` (n_links,) for a batch of readings' angles ``alpha``,
    ``beta`` (B, n_links) at once: (B, rows) (the prior does not enter the rows)."""
    return YawProblem(st, alpha, beta, st.rest_yaw, np.full(st.n_var, ABS_PRIOR_FLOOR),
                      np.zeros(st.pairs.shape[0])).rows(gamma)
