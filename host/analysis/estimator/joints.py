"""After the yaws: every link's direction and normal in the world, and eq. (8)'s residual."""

from __future__ import annotations

import numpy as np

import host.analysis.estimator.kernel as kernel  # the switch, read at call time
from .kernel import ffi as _kffi, lib as _klib
from .angles import _angle_trig


def _directions_normals(alpha, beta, gamma, trig=None):
    """Per link its direction (sensor x) and normal (sensor z) in the world, (..., n_links, 3)
    each (docs/design.md's ``R = Rz(γ) Ry(β) Rx(α)``); ``trig``: the links' `_angle_trig`, if
    already made (one snapshot)."""
    if kernel.USE_KERNEL and np.ndim(alpha) == 1:  # one snapshot: the kernel
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
