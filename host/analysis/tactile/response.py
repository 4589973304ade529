"""The foam layer's response to pressure, per newton: the templates the contact fit is made of.

The host's foam model is the virtual foam's (docs/tactile.md, "Foam model"): a thin layer as a
Vlasov two-parameter foundation, ``k (w − λ² ∇²w) = p``. It is linear, so a contact's dent is its
force times the layer's response to the contact's pressure *shape*, and that response is known in
closed form for the shapes used here:

* a **uniform disc** of radius ``a`` (`disc_response`): ``w = [1 − α K1(α) I0(r/λ)] / (π a² k)``
  inside, ``α I1(α) K0(r/λ) / (π a² k)`` outside, ``α = a / λ`` (continuous with its slope at
  the rim; a point load's ``K0(r/λ) / (2π λ² k)`` as ``a → 0``);
* a **line of discs** (`line_response`): the disc swept along a segment of half-length ``ℓ`` at
  angle ``θ`` — a finger, a gripper's jaw, an edge — by Gauss-Legendre quadrature over the
  segment.

Every template integrates to ``k ∫ w dA = 1`` (the shear term integrates out), so the amplitude a
fit finds for it *is* the force in newtons, whatever the shape: no integral of a fitted surface,
no tail lost beyond the sheet's edge. Derivatives with respect to the geometry are returned
with the values (the fit is Gauss-Newton).

Pressure moments: a uniform disc of radius ``a`` has the second central moment ``a² / 4`` in
every direction, a line of discs ``ℓ² / 3 + a² / 4`` along and ``a² / 4`` across it; half-axes
are reported as ``2 sqrt(moment)`` (a uniform disc of radius ``a`` gives ``a``).
"""

from __future__ import annotations

import os

import numpy as np
from scipy.special import i0e, i1e, k0e, k1e

try:  # the compiled response (host/analysis/tactile/_kernel); optional, numpy without it
    if os.environ.get("CAPSHEET_NO_KERNEL"):
        raise ImportError("CAPSHEET_NO_KERNEL is set")
    from ._response_kernel import ffi as _kffi, lib as _klib
except ImportError:
    _kffi = _klib = None

#: Whether `line_response` runs the compiled kernel (same formulas, Bessel functions by
#: Abramowitz & Stegun 9.8 to 3e-7; the tests compare it with the numpy code).
USE_KERNEL = _klib is not None

__all__ = ["disc_response", "line_response", "pressure_half_axes", "LINE_NODES"]

#: Gauss-Legendre nodes along a line of discs: 12 keep the swept response smooth along a 3 cm
#: line of 4 mm discs (with 6 the depth between nodes dipped 30 % below that at them, and the
#: half-depth footprint came out 15 % narrow).
LINE_NODES = 12
_XI, _WQ = np.polynomial.legendre.leggauss(LINE_NODES)
_WQ = _WQ / 2.0


def disc_response(r: np.ndarray, a: float, lam: float, k: float, derivatives: bool = False):
    """Deflection per newton of a uniform-pressure disc (module docstring), metres per N.

    Parameters
    ----------
    r : ndarray
        Distances from the disc's centre, metres (any shape).
    a : float
        Disc radius, metres, > 0.
    lam : float
        The layer's spreading length ``λ``, metres, > 0.
    k : float
        The layer's stiffness, Pa/m.
    derivatives : bool
        Also return ``∂w/∂r`` and ``∂w/∂a`` (same shape as ``r``, per metre).

    >>> from scipy.integrate import quad
    >>> a, lam, k = 0.006, 0.0067, 1.2e6
    >>> f = lambda r: 2 * np.pi * r * float(disc_response(np.array(r), a, lam, k))
    >>> round(k * (quad(f, 0, a)[0] + quad(f, a, 0.3)[0]), 6)   # unit force
    1.0
    """
    rho = np.asarray(r, float) / lam
    al = a / lam
    c = 1.0 / (k * np.pi * lam * lam)
    inside = rho < al
    ins = np.flatnonzero(inside)   # few: the joints under the contact
    out = np.flatnonzero(~inside)
    rf = rho.ravel()
    ri, ro = rf[ins], rf[out]
    k1a, i1a = k1e(al), i1e(al)
    ein = np.exp(ri - al)          # I0(ρ) K1(α) = i0e(ρ) k1e(α) e^(ρ − α)
    eout = np.exp(al - ro)         # I1(α) K0(ρ) = i1e(α) k0e(ρ) e^(α − ρ)
    i0r = i0e(ri) * ein
    k0r = k0e(ro) * eout
    w = np.empty(rf.shape)
    w[ins] = c * (1.0 / (al * al) - k1a * i0r / al)
    w[out] = c * i1a * k0r / al
    w = w.reshape(rho.shape)
    if not derivatives:
        return w
    k0a, i0a = k0e(al), i0e(al)
    dr = np.empty(rf.shape)
    da = np.empty(rf.shape)
    dr[ins] = -c * k1a * i1e(ri) * ein / (al * lam)
    dr[out] = -c * i1a * k1e(ro) * eout / (al * lam)
    da[ins] = c * (-2.0 / al ** 3 + (al * k0a + 2.0 * k1a) * i0r / al ** 2) / lam
    da[out] = c * (al * i0a - 2.0 * i1a) * k0r / (al * al * lam)
    return w, dr.reshape(rho.shape), da.reshape(rho.shape)


def line_response(xy: np.ndarray, centre: np.ndarray, a: float, half_length: float,
                  angle: float, lam: float, k: float, jacobian: bool = False):
    """Deflection per newton of a line of uniform discs (module docstring), metres per N.

    Parameters
    ----------
    xy : ndarray, shape (n, 2)
        Points in the contact's tangent plane, metres.
    centre : ndarray, shape (2,)
        The segment's middle, metres, same frame.
    a : float
        Disc radius (the contact's half-width), metres, > 0.
    half_length : float
        ``ℓ``, metres, >= 0 (0: one disc).
    angle : float
        ``θ``, the segment's direction from the frame's first axis, radians.
    lam, k : float
        As `disc_response`.
    jacobian : bool
        Also return the derivatives, shape (n, 5), with respect to
        ``(centre_x, centre_y, a, q_x, q_y)``, ``q = ℓ (cos θ, sin θ)`` the half-segment as a
        vector: the response is an even, smooth function of it, also at ``ℓ = 0`` (where an
        angle is undefined).
    """
    if USE_KERNEL:
        return _line_kernel(xy, centre, a, half_length, angle, lam, k, jacobian)
    return _line_numpy(xy, centre, a, half_length, angle, lam, k, jacobian)


def _line_kernel(xy, centre, a, half_length, angle, lam, k, jacobian):
    P = np.ascontiguousarray(xy, dtype=float)
    n = P.shape[0]
    w = np.empty(n)
    J = np.empty((n, 5)) if jacobian else None
    fb = _kffi.from_buffer
    st = _klib.capsheet_line_response(
        n, fb("double[]", P), float(centre[0]), float(centre[1]), float(a),
        float(half_length * np.cos(angle)), float(half_length * np.sin(angle)), float(lam),
        float(k), LINE_NODES, fb("double[]", _XI), fb("double[]", _WQ), fb("double[]", w),
        fb("double[]", J) if jacobian else _kffi.NULL)
    if st != 0:
        raise ValueError(f"Invalid line response: a={a!r}, lam={lam!r}, k={k!r} "
                         "(need finite values > 0)")
    return (w, J) if jacobian else w


def _line_numpy(xy, centre, a, half_length, angle, lam, k, jacobian):
    e = np.array([np.cos(angle), np.sin(angle)])
    nodes = np.asarray(centre, float)[None, :] + half_length * _XI[:, None] * e[None, :]
    D = xy[:, None, :] - nodes[None, :, :]              # (n, q, 2)
    r = np.sqrt(np.einsum("nqi,nqi->nq", D, D))
    if not jacobian:
        return disc_response(r, a, lam, k) @ _WQ
    w, dr, da = disc_response(r, a, lam, k, derivatives=True)
    G = (dr / np.maximum(r, 1e-12))[..., None] * D       # ∂w/∂x at the point = −∂w/∂node
    J = np.empty((xy.shape[0], 5))
    J[:, 0:2] = -np.einsum("nqi,q->ni", G, _WQ)
    J[:, 2] = da @ _WQ
    # a node at ξ ℓ e moves by ξ dq: ∂w/∂q = −Σ w_q ξ_q ∂w/∂x
    J[:, 3:5] = -np.einsum("nqi,q->ni", G, _WQ * _XI)
    return w @ _WQ, J


def pressure_half_axes(a: float, half_length: float) -> tuple[float, float]:
    """Principal half-axes ``2 sqrt(moment)`` (major, minor) of a line of uniform discs'
    pressure, metres: ``2 sqrt(ℓ² / 3 + a² / 4)`` and ``a`` (a uniform disc gives ``a``, ``a``).
    (The quadrature's nodes carry the line's moment ``Σ w_q ξ_q² ℓ² = ℓ² / 3`` exactly.)"""
    return float(2.0 * np.sqrt(half_length ** 2 / 3.0 + a * a / 4.0)), float(a)


#: The half-depth footprint table's grid: contact half-width ``α = a / λ`` (geometric) and
#: half-length ``β = ℓ / λ``; rays per quadrant (Gauss-Legendre in the polar angle).
_FP_ALPHA = np.geomspace(0.08, 5.0, 28)
_FP_BETA = np.linspace(0.0, 8.0, 33)
_FP_RAYS = 16
_fp_table: np.ndarray | None = None


def footprint_table() -> np.ndarray:
    """Half-depth footprint of a line of discs in units of ``λ`` (the response scales with
    ``λ``: ``w(x; a, ℓ, λ) = f(x / λ; a / λ, ℓ / λ) / (k λ²)``), shape (alpha, beta, 3): major and
    minor half-axes ``2 sqrt(moment)`` of the region deeper than half the centre's depth (uniform
    weights), and its area. Rays from the centre to the half-depth contour (bisection), moments
    of the star-shaped region by quadrature over the polar angle. Computed once, on first use
    (tenths of a second with the kernel, seconds without; `TactileSensor` asks for it when it
    is made)."""
    global _fp_table
    if _fp_table is not None:
        return _fp_table
    x, wx = np.polynomial.legendre.leggauss(_FP_RAYS)
    phi = (x + 1.0) * np.pi / 4.0
    wphi = wx * np.pi / 4.0
    c, s = np.cos(phi), np.sin(phi)
    out = np.empty((_FP_ALPHA.size, _FP_BETA.size, 3))
    zero = np.zeros(2)
    for ia, al in enumerate(_FP_ALPHA):
        for ib, be in enumerate(_FP_BETA):
            half = 0.5 * float(line_response(np.zeros((1, 2)), zero, al, be, 0.0, 1.0, 1.0)[0])
            lo = np.zeros(_FP_RAYS)
            hi = np.full(_FP_RAYS, be + al + 8.0)
            for _ in range(22):
                mid = 0.5 * (lo + hi)
                deeper = line_response(np.stack([mid * c, mid * s], axis=1), zero, al, be, 0.0,
                                       1.0, 1.0) >= half
                lo = np.where(deeper, mid, lo)
                hi = np.where(deeper, hi, mid)
            R = 0.5 * (lo + hi)
            area = 4.0 * (R * R / 2.0) @ wphi
            out[ia, ib] = (2.0 * np.sqrt(4.0 * (R ** 4 / 4.0 * c * c) @ wphi / area),
                           2.0 * np.sqrt(4.0 * (R ** 4 / 4.0 * s * s) @ wphi / area), area)
    _fp_table = out
    return out


def half_depth_footprint(a, half_length, lam: float):
    """The half-depth footprint of a line of discs' dent (what the sheet sees of a contact:
    the region deeper than half the deepest point, uniform weights; `footprint_table`,
    interpolated bilinearly in ``log a`` and ``ℓ``).

    Parameters
    ----------
    a, half_length : float or ndarray
        Metres (arrays broadcast).
    lam : float
        Spreading length, metres.

    Returns
    -------
    axes : ndarray, shape (..., 2)
        Half-axes ``2 sqrt(moment)`` along and across the line, metres (a uniform disc region
        of radius ``R`` gives ``R``).
    area : float or ndarray
        m².

    >>> ax, area = half_depth_footprint(0.006, 0.0, 0.0067)
    >>> bool(abs(ax[0] - ax[1]) < 1e-9 and abs(area - np.pi * ax[0] ** 2) < 1e-2 * area)
    True
    """
    tab = footprint_table()
    a, b = np.broadcast_arrays(np.asarray(a, float), np.asarray(half_length, float))
    la = np.log(np.clip(a / lam, _FP_ALPHA[0], _FP_ALPHA[-1]))
    be = np.clip(b / lam, _FP_BETA[0], _FP_BETA[-1])
    lg = np.log(_FP_ALPHA)
    i = np.clip(np.searchsorted(lg, la) - 1, 0, lg.size - 2)
    j = np.clip(np.searchsorted(_FP_BETA, be) - 1, 0, _FP_BETA.size - 2)
    fa = ((la - lg[i]) / (lg[i + 1] - lg[i]))[..., None]
    fb = ((be - _FP_BETA[j]) / (_FP_BETA[j + 1] - _FP_BETA[j]))[..., None]
    v = ((1 - fa) * (1 - fb) * tab[i, j] + fa * (1 - fb) * tab[i + 1, j]
         + (1 - fa) * fb * tab[i, j + 1] + fa * fb * tab[i + 1, j + 1])
    area = v[..., 2] * lam * lam
    return v[..., :2] * lam, (float(area) if area.ndim == 0 else area)
