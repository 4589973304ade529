"""Roll and pitch from a reading (paper eq. 2: `protocol.frames.roll_pitch`, re-exported) and the
solvability of a unit (eq. 7)."""

from __future__ import annotations

import numpy as np

from protocol.constants import G0
from protocol.frames import angles_of, roll_pitch

import host.analysis.estimator.kernel as kernel  # the switch, read at call time
from .kernel import ffi as _kffi, lib as _klib
from .structure import lattice_of, units_int64

__all__ = ["G0", "roll_pitch", "angles_of", "eq7_matrices", "solvability_units", "solvability",
           "angle_trig", "roll_pitch_trig", "solvability_from_trig"]


def eq7_matrices(alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
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
    eigenvalues of the 2x2 Hermitian ``K Kᴴ`` in closed form. `eq7_matrices` + SVD agrees.
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
    units = lattice_of(rows, cols).units
    if kernel.USE_KERNEL and np.ndim(alpha) == 1 and np.ndim(beta) == 1:  # one snapshot: the kernel
        al = np.ascontiguousarray(alpha, dtype=np.float64)
        be = np.ascontiguousarray(beta, dtype=np.float64)
        if al.shape == be.shape == (lattice_of(rows, cols).n_links,):
            return solvability_from_trig(angle_trig(al, be), rows, cols)
    a, b = np.asarray(alpha, float)[..., units], np.asarray(beta, float)[..., units]
    ratio = solvability_units(a, b)
    bad = ~np.all(np.isfinite(a) & np.isfinite(b), axis=-1)
    if bad.any():
        ratio[bad] = np.nan
    return ratio


def angle_trig(alpha, beta) -> np.ndarray:
    """(n, 4): cos α, sin α, cos β, sin β per link (the kernel's ``trig``)."""
    a = np.ascontiguousarray(alpha, dtype=np.float64)
    b = np.ascontiguousarray(beta, dtype=np.float64)
    trig = np.empty((a.size, 4))
    fb = _kffi.from_buffer
    _klib.capsheet_angle_trig(a.size, fb("double[]", a), fb("double[]", b), fb("double[]", trig))
    return trig


def roll_pitch_trig(r: np.ndarray):
    """`roll_pitch` of one snapshot's readings (n, 3), and their `angle_trig` from the
    readings' ratios in the kernel (a trigonometric call would cost more than the rest of a
    stage): (alpha, beta, trig)."""
    r = np.ascontiguousarray(r, dtype=np.float64)
    alpha, beta = angles_of(r)
    trig = np.empty((r.shape[0], 4))
    fb = _kffi.from_buffer
    _klib.capsheet_reading_trig(r.shape[0], fb("double[]", r), fb("double[]", alpha),
                                fb("double[]", beta), fb("double[]", trig))
    return alpha, beta, trig


def solvability_from_trig(trig: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """`solvability` of one snapshot from its links' trig (NaN rows: missing links)."""
    u = units_int64(rows, cols)
    out = np.empty((rows - 1, cols - 1))
    _klib.capsheet_solvability(u.shape[0], _kffi.from_buffer("int64_t[]", u),
                               _kffi.from_buffer("double[]", trig),
                               _kffi.from_buffer("double[]", out))
    return out
