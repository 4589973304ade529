"""The FFT contact solver (Polonsky & Keer) on the Vlasov layer, and the deflection it gives."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Sequence

import numpy as np

from .material import FoamLayer, require_positive

__all__ = ["Deflection", "solve_contact"]


@dataclass(frozen=True, eq=False)
class Deflection:
    """The foam's surface deflection on a grid of surface coordinates.

    Attributes
    ----------
    u, v : ndarray, shape (n,)
        Grid coordinates, metres (ascending, uniform spacing ``step_m``).
    w : ndarray, shape (n, n)
        Deflection into the foam ``w[iu, iv]``, metres (>= 0 up to FFT round-off).
    pressure : ndarray, shape (n, n)
        Contact pressure, Pa (the punch rim's line load shows as a ring of high cells).
    step_m : float
    depths_m : dict
        Penetration ``δ`` of every active press (key: its index in the scene), metres.
    """

    u: np.ndarray
    v: np.ndarray
    w: np.ndarray
    pressure: np.ndarray
    step_m: float
    depths_m: dict = field(default_factory=dict)

    def force_n(self, k: float) -> float:
        """``k ∫ w dA`` over the grid, N (equals the applied total force)."""
        return float(k * self.w.sum() * self.step_m ** 2)

    @cached_property
    def spline(self):
        from scipy.interpolate import RectBivariateSpline
        return RectBivariateSpline(self.u, self.v, self.w, kx=3, ky=3)

    def at(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Deflection at surface coordinates ``(u, v)`` (arrays of equal shape), metres."""
        u, v = np.broadcast_arrays(np.asarray(u, float), np.asarray(v, float))
        return self.spline(u.ravel(), v.ravel(), grid=False).reshape(u.shape)


def compliance(layer: FoamLayer, n: int, step: float) -> np.ndarray:
    """``1 / (k (1 + λ² q²))`` on the ``rfft2`` grid of an ``n × n`` grid of spacing ``step``."""
    q = 2 * np.pi * np.fft.fftfreq(n, d=step)
    qr = 2 * np.pi * np.fft.rfftfreq(n, d=step)
    lam = layer.shear_length_m
    return 1.0 / (layer.k_pa_per_m * (1.0 + lam * lam * (q[:, None] ** 2 + qr[None, :] ** 2)))


def _polonsky_keer(apply, g, force, dA, p, background, tol, max_iter):
    """Polonsky & Keer's constrained CG for one rigid indenter: find ``p >= 0`` with
    ``∑ p dA = force`` and ``w + g − δ = 0`` where ``p > 0``, ``>= 0`` elsewhere
    (``w = apply(p) + background``). Returns ``(p, δ, iterations)``."""
    allowed = np.isfinite(g)
    gg = np.where(allowed, g, 0.0)
    t = np.zeros_like(p)
    g_old, conj = 1.0, False
    delta = 0.0
    for it in range(1, max_iter + 1):
        c = p > 0
        if not c.any():
            raise ValueError("Contact solver: lost contact (no positive pressure left).")
        gap = apply(p) + background + gg
        delta = float(gap[c].mean())
        gap -= delta
        g_norm = float(np.sum(gap[c] ** 2))
        t = np.where(c, gap + (g_norm / g_old) * t if conj else gap, 0.0)
        g_old = g_norm
        r = apply(t)
        r -= r[c].mean()
        denom = float(np.sum(r[c] * t[c]))
        if denom <= 0:
            break
        tau = float(np.sum(gap[c] * t[c])) / denom
        p_old = p
        p = np.maximum(p - tau * t, 0.0)
        overlap = (p == 0) & (gap < 0) & allowed
        conj = not overlap.any()
        p[overlap] -= tau * gap[overlap]
        p *= force / (p.sum() * dA)
        err = float(np.abs(p - p_old).sum() * dA / force)
        if err < tol:
            break
    return p, delta, it


def solve_contact(layer: FoamLayer, profiles: Sequence[np.ndarray], forces: Sequence[float],
                  step_m: float, *, tol: float = 1e-6, max_iter: int = 400,
                  sweeps: int = 4) -> tuple[np.ndarray, list[float], np.ndarray]:
    """Rigid indenters with given forces on the foam layer (module docstring, "Contact").

    Parameters
    ----------
    layer : FoamLayer
    profiles : sequence of ndarray, shape (n, n)
        Every indenter's tip profile ``g`` on the periodic grid, metres (``inf`` where it
        cannot touch), grid index ``[iu, iv]``.
    forces : sequence of float
        Normal force of every indenter, N, > 0.
    step_m : float
        Grid spacing, metres.
    tol, max_iter : float, int
        Polonsky-Keer stop: relative change of the pressure (L1) below ``tol``.
    sweeps : int
        Gauss-Seidel sweeps over the indenters when there are several.

    Returns
    -------
    pressure : ndarray, shape (n, n)
        Pa, the sum over indenters; ``∑ p dA = ∑ forces``.
    depths : list of float
        Every indenter's penetration ``δ``, metres.
    w : ndarray, shape (n, n)
        Surface deflection into the foam, metres; ``k ∑ w dA = ∑ forces`` (FFT zero mode).
    """
    from scipy.fft import irfft2, rfft2

    n = profiles[0].shape[0]
    if any(np.shape(g) != (n, n) for g in profiles) or len(profiles) != len(forces):
        raise ValueError(f"Expected {len(forces)} profiles of shape ({n}, {n}); got "
                         f"{[np.shape(g) for g in profiles]}.")
    comp = compliance(layer, n, step_m)
    k = layer.k_pa_per_m
    dA = step_m * step_m

    def apply(p):
        return irfft2(rfft2(p) * comp, s=(n, n))

    ps = []
    for g, F in zip(profiles, forces):  # Winkler's contact as the first guess
        F = require_positive(F, "force", "N")
        fin = np.isfinite(g)
        d0 = np.sqrt(F / (np.pi * k * max(np.min(g[fin]) + step_m, step_m)))  # any positive
        p0 = np.where(fin, np.maximum(d0 - np.where(fin, g, 0.0), 0.0), 0.0)
        if not p0.any():
            p0 = np.where(fin & (g <= np.min(g[fin]) + 1e-12), 1.0, 0.0)
        ps.append(p0 * F / (p0.sum() * dA))
    depths = [0.0] * len(ps)
    total = sum(ps)
    for _ in range(sweeps if len(ps) > 1 else 1):
        for j, (g, F) in enumerate(zip(profiles, forces)):
            bg = apply(total - ps[j]) if len(ps) > 1 else 0.0
            new, depths[j], _ = _polonsky_keer(apply, g, float(F), dA, ps[j], bg, tol, max_iter)
            total = total - ps[j] + new
            ps[j] = new
    return total, depths, apply(total)
