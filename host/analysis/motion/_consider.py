"""The gyroscopes' residual scale and cross-axis error as a consider state (Schmidt–Kalman): the
fused estimator's step 1 when `FusedConfig.gyro_scale_fixed_error` > 0 (docs/estimator.md §8).

A calibration leaves every chip a small fixed error ``E`` (3 x 3: scale on the diagonal,
cross-axis off it) in its gyroscope, ``ω_read = (I + E) ω + b``. Taken as white noise per step
(`FusedConfig.gyro_scale_error`, ``∝ |ω| Δt``) its variance grows with the sum of the squared
steps, so a sustained turn (whose error ``R E Δθ`` grows with the angle) is under-told and a
back-and-forth one (whose error averages out) over-told. Here ``E`` is fixed per chip with
every entry independent (`FusedConfig.gyro_scale_fixed_error`): it is not estimated (nine
numbers more per link would be the accelerometers' to find, and they cannot during most
motions), but each link's error state
``δx = (δθ, δb)`` keeps its cross-covariance with it, ``C = cov(δx, vec E)`` (6 x 9), so the
covariance ``P`` the updates use is the marginal one a fixed error gives:

* propagation, ``δθ' = δθ − R δb Δt − R (E ω) Δt``: with ``Γ = −Δt R Ω(ω)`` (``Ω(ω) vec E =
  E ω``, row-major), ``Σ`` the entries' variances and ``F`` the step's transition,
  ``C' = F C + [Γ Σ; 0]`` and ``P'`` gains ``F C Γᵀ + Γ Cᵀ Fᵀ + Γ Σ Γᵀ`` (with every entry's
  ``σ²`` alike ``Γ Σ Γᵀ = σ² |ω|² Δt² I``: the white model's per-step term) beside the
  kernel's ``F P Fᵀ + Q``;
* every update with gain ``K`` on a measurement of ``H δx``: ``C ← C − K H C`` (``E`` itself is
  not updated: that is the consider filter's rule).

Each function takes the covariance *before* the step it accompanies (the gains are made from
it, as the step makes them) except `propagate`, which follows the kernel's propagation (it
needs the new frames, and reads nothing of ``P`` that the propagation changed).
"""

from __future__ import annotations

import numpy as np

from ._linalg import USE_KERNEL, inv_sym3, kernel_args, kernel_lib, skew


def propagate(R, P, C, U, dt, s2) -> None:
    """`np_propagate`, in C when `USE_KERNEL` (link_filter.h: ``capsheet_mf_consider_*``)."""
    if USE_KERNEL:
        kernel_lib.capsheet_mf_consider_propagate(R.shape[0], U.shape[1], *kernel_args(
            "consider_propagate", (R, P, C, U, dt, s2)))
    else:
        np_propagate(R, P, C, U, dt, s2)


def accel(R, P, C, f, vec, r2, gate, valid) -> None:
    """`np_accel`, in C when `USE_KERNEL`."""
    if USE_KERNEL:
        kernel_lib.capsheet_mf_consider_accel(R.shape[0], C.shape[2], *kernel_args(
            "consider_accel", (R, P, C, f, vec, r2, gate, valid)))
    else:
        np_accel(R, P, C, f, vec, r2, gate, valid)


def yaw(P, C, a_diag) -> None:
    """`np_yaw`, in C when `USE_KERNEL`."""
    if USE_KERNEL:
        kernel_lib.capsheet_mf_consider_yaw(P.shape[0], C.shape[2],
                                            *kernel_args("consider_yaw", (P, C, a_diag)))
    else:
        np_yaw(P, C, a_diag)


def np_propagate(R: np.ndarray, P: np.ndarray, C: np.ndarray, U: np.ndarray, dt: np.ndarray,
                 s2: np.ndarray) -> None:
    """After the kernel's propagation (``R`` the new frames, ``P`` its result): ``P`` gains the
    fixed errors' correlated terms, ``C`` its step. ``U`` (n, m, 3) the inputs each block of
    nine multiplies (the step's rates; the specific force's change, g), link frames; ``s2``
    (9 m,) the variances of the entries, row by row, block by block (``Σ = diag(s2)``)."""
    n, m = U.shape[:2]
    G = R * dt[:, None, None]  # δθ' = δθ − G δb
    Cb = C[:, 3:, :]
    Ct = C[:, :3, :] - G @ Cb  # F C, its θ rows (the b rows are unchanged)
    # F C Γᵀ with Γ = −Δt R [Ω(u_1) … Ω(u_m)]: (F C Ωᵀ)[:, a, j] = Σ_b Σ_l (F C)[a, 9 b + 3 j + l]
    # u_b,l, then times Rᵀ
    FC = np.concatenate([Ct, Cb], axis=1)  # (n, 6, 9 m)
    Y = (FC.reshape(n, 6, m, 3, 3) @ U[:, None, :, :, None])[..., 0].sum(axis=2)
    X = -Y @ G.transpose(0, 2, 1)
    P[:, :, :3] += X
    P[:, :3, :] += X.transpose(0, 2, 1)
    # Γ Σ Γᵀ = Δt² R diag(D) Rᵀ, D_j = Σ_b Σ_l s2[9 b + 3 j + l] u_b,l²
    D = np.einsum("kbl,bjl->kj", U * U, s2.reshape(m, 3, 3))
    P[:, :3, :3] += (G * D[:, None, :]) @ G.transpose(0, 2, 1)
    # C' = F C + Γ Σ: Γ[:, i, 9 b + 3 j + l] = −Δt R[i, j] u_b,l
    Ct -= (G[:, :, None, :, None] * U[:, None, :, None, :]).reshape(n, 3, 9 * m) * s2
    C[:, :3, :] = Ct


def np_accel(R: np.ndarray, P: np.ndarray, C: np.ndarray, f: np.ndarray, vec: np.ndarray,
             r2: np.ndarray, gate: float, valid: np.ndarray) -> None:
    """Before the accelerometer update (``P`` its prior): ``C ← C − K H C`` with the update's own
    gain (its gate's inflation included), ``H = Rᵀ [vec]×`` on ``δθ``."""
    Rt = R.transpose(0, 2, 1)
    y = f - np.einsum("kij,kj->ki", Rt, vec)
    H = Rt @ skew(vec)
    HP = H @ P[:, :3, :]  # (n, 3, 6)
    S = HP[:, :, :3] @ H.transpose(0, 2, 1) + r2[:, None, None] * np.eye(3)
    Si = inv_sym3(S)
    m2 = np.einsum("ki,kij,kj->k", y, Si, y)
    Si /= np.maximum(1.0, np.where(valid, m2, 0.0) / gate)[:, None, None]
    K = HP.transpose(0, 2, 1) @ Si  # (n, 6, 3)
    K[~valid] = 0.0
    C -= K @ (H @ C[:, :3, :])


def np_yaw(P: np.ndarray, C: np.ndarray, a_diag: np.ndarray) -> None:
    """Before the yaw update (``P`` its prior): the lattice's solve is, per link, a scalar
    measurement of its yaw whose information is ``a_diag − 1/p`` (the conditional variance
    after it, ``1 / a_diag``), so its gain is ``c / p · (1 − 1 / (a_diag p))`` (``c`` the
    covariance's yaw column) and ``C ← C − gain ⊗ C[yaw]``."""
    c = P[:, :, 2]
    p = c[:, 2]
    gain = c * ((1.0 - 1.0 / (a_diag * p)) / p)[:, None]
    C -= gain[:, :, None] * C[:, 2, None, :]
