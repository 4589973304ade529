"""Foam bodies wrapped in the sheet, indenters pressing them with known forces (docs/tactile.md).

The tactile sensor of the paper is "a compressible material, such as urethane foam, wrapped by the
sheet"; forces follow "from the surface deformation and Young's modulus of the material". This
module is the virtual version: a foam layer of thickness ``h``, Young's modulus ``E`` and Poisson's
ratio ``ν`` on a rigid core (a block's top face, a cylinder, a sphere), indenters (sphere, flat
punch, capsule "finger", rectangular "edge") pressed into it with a known normal force, and the
sheet laid over the indented surface with every link keeping its length ``L``.

Foam model: a thin layer as a Vlasov two-parameter foundation
-----------------------------------------------------------------
A layer bonded to a rigid base, with the vertical displacement decaying linearly through the
thickness (Vlasov & Leontiev 1966; Kerr 1964), reacts to a surface deflection ``w`` (positive into
the foam, metres) with the pressure

    p = k w − G_p ∇²w,   k = E_oed / h,   G_p = G h / 3,

``E_oed = E (1 − ν) / ((1 + ν)(1 − 2ν))`` the oedometric (constrained) modulus, ``G = E / 2(1 + ν)``.
``k`` alone is Winkler's foundation (each point a spring, ``p = k w``); ``G_p`` couples neighbours
through the layer's shear, so the deflection spreads beyond the indenter over the length

    λ = sqrt(G_p / k) = h sqrt((1 − 2ν) / (6 (1 − ν)))      (h/√6 ≈ 0.41 h for ν = 0).

Two properties make the force readable from the shape: the shear term integrates to zero over the
surface (the deflection dies out), so the **total force is exactly** ``F = k ∫ w dA`` — Winkler's
integral — whatever the spreading; and the model is linear, so several indenters superpose.

Contact: each indenter is rigid; its tip profile ``g(u, v)`` (height above its lowest point,
paraboloidal for curved tips, ``+inf`` off a flat punch's face) is pressed to a depth ``δ`` such
that the foam surface touches it where the pressure is positive and stays below it elsewhere
(``w ≥ δ − g``, equality where ``p > 0``, ``p ≥ 0``), with ``∫ p dA = F``. The layer's response
``ŵ = p̂ / (k (1 + λ² q²))`` is exact on a periodic FFT grid; the complementarity problem is solved
by the constrained conjugate-gradient method of Polonsky & Keer (Wear 231, 1999) — the standard
FFT contact solver — one indenter at a time with the others' deflection as background (a few
Gauss-Seidel sweeps when several press at once). With ``λ = 0`` (``FoamLayer(spreading=False)``)
it reduces to Winkler's closed forms (``k`` in Pa/m), which give the depths as a check and the
solver its first guess:

========= ======================================= ==========================================
sphere    radius R, ``g = r² / 2R``               ``F = π k R δ²``
punch     flat circle, radius a                   ``F = π k a² δ``
capsule   radius R, segment half-length ℓ, angle  ``F = k (8/3 ℓ sqrt(2R) δ^{3/2} + π R δ²)``
rect      flat, half-sides a × b, angle           ``F = 4 k a b δ``
========= ======================================= ==========================================

With spreading, the same force gives a shallower, wider dent (the punch's pressure concentrates
at its rim), but ``F = k ∫ w dA`` still holds exactly.
Given a target force, `Indenter.depth_from_force` inverts ``F(δ)`` (closed form or bracketed root).
The linear model holds for strains ``δ / h`` up to ~20 % (foam's linear-elastic range before its
plateau); the scenes below stay there by default.

The sheet on the surface: the surface of the indented body is sampled on a fine grid (``L/6``),
interpolated by bicubic splines, and the sheet is laid on it with every link exactly ``L``: on the
block by the compass construction (`geometry.chebyshev_net`, centre-anchored, exact), on the
cylinder and sphere by the paper's spring-mass relaxation (`drape.drape`, warm-started from the
rest drape). The sheet's own bending stiffness is neglected against the foam's.

>>> layer = FoamLayer(thickness_m=0.02, youngs_modulus_pa=30e3, poisson=0.25)
>>> round(layer.k_pa_per_m), round(float(layer.shear_length_m) * 1000, 2)
(1800000, 6.67)
>>> ind = SphereIndenter(0.015)
>>> d = ind.depth_from_force(layer.k_pa_per_m, 1.0)
>>> round(float(d) * 1000, 3), round(float(ind.force_from_depth(layer.k_pa_per_m, d)), 9)
(3.434, 1.0)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Protocol, Sequence, runtime_checkable

import numpy as np

from protocol.lattice import Lattice
from .drape import drape
from .geometry import chebyshev_net
from .shapes import flat_net

__all__ = ["FoamLayer", "oedometric_modulus", "Indenter", "SphereIndenter", "FlatPunch",
           "CapsuleIndenter", "RectPunch", "Press", "TrueContact", "FoamBody", "FoamBlock",
           "FoamCylinder", "FoamSphere", "FoamScene", "Deflection", "solve_contact"]


def _positive(value: float, name: str, unit: str) -> float:
    v = float(value)
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"Invalid {name}: {value!r} {unit} (need a finite value > 0)")
    return v


def oedometric_modulus(youngs_modulus_pa: float, poisson: float) -> float:
    """Constrained (oedometric) modulus ``E (1 − ν) / ((1 + ν)(1 − 2ν))``, Pa; ``E`` at ``ν = 0``."""
    E, nu = float(youngs_modulus_pa), float(poisson)
    return E * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu))


@dataclass(frozen=True)
class FoamLayer:
    """The foam: thickness ``h``, Young's modulus ``E``, Poisson's ratio ``ν`` (module docstring).

    Attributes
    ----------
    thickness_m : float
        ``h``, metres (default 20 mm).
    youngs_modulus_pa : float
        ``E``, Pa (default 20 kPa: soft polyurethane foam is 5-100 kPa).
    poisson : float
        ``ν``, in [0, 0.45] (default 0.25; open-cell foam is 0-0.3).
    """

    thickness_m: float = 0.02
    youngs_modulus_pa: float = 20e3
    poisson: float = 0.25
    spreading: bool = True  #: False: plain Winkler (λ = 0), for checks against the closed forms

    def __post_init__(self) -> None:
        _positive(self.thickness_m, "thickness_m", "m")
        _positive(self.youngs_modulus_pa, "youngs_modulus_pa", "Pa")
        if not (0.0 <= float(self.poisson) <= 0.45):
            raise ValueError(f"Invalid poisson: {self.poisson!r} (need 0 <= nu <= 0.45)")

    @property
    def k_pa_per_m(self) -> float:
        """Foundation modulus ``k = E_oed / h``, Pa/m (pressure per metre of deflection)."""
        return oedometric_modulus(self.youngs_modulus_pa, self.poisson) / self.thickness_m

    @property
    def shear_length_m(self) -> float:
        """Spreading length ``λ = h sqrt((1 − 2ν) / (6 (1 − ν)))``, metres."""
        if not self.spreading:
            return 0.0
        nu = float(self.poisson)
        return self.thickness_m * np.sqrt((1.0 - 2.0 * nu) / (6.0 * (1.0 - nu)))


# ---------------------------------------------------------------------------------------------
# Indenters
# ---------------------------------------------------------------------------------------------

def _rotate(dx: np.ndarray, dy: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates in the indenter's frame (its long axis at ``angle`` from surface +u)."""
    c, s = np.cos(angle), np.sin(angle)
    return c * dx + s * dy, -s * dx + c * dy


@runtime_checkable
class Indenter(Protocol):
    """An indenter: its tip profile and Winkler's closed-form ``F(δ)``.

    ``profile(du, dv)`` is the tip's height above its lowest point, metres (``+inf`` where it
    cannot touch, off a flat face), at offsets ``du, dv`` (metres, surface coordinates) from its
    centre; ``force_from_depth(k, δ)`` the Winkler force ``k ∫ (δ − g)₊ dA``, N;
    ``depth_from_force(k, F)`` the inverse, metres; ``footprint(δ)`` the Winkler contact
    half-axes. ``kind`` names the shape.
    """

    kind: str

    def profile(self, du: np.ndarray, dv: np.ndarray) -> np.ndarray: ...

    def force_from_depth(self, k: float, depth: float) -> float: ...

    def depth_from_force(self, k: float, force: float) -> float: ...


@dataclass(frozen=True)
class SphereIndenter:
    """Sphere of ``radius_m``; tip profile ``g = r² / 2R``; ``F = π k R δ²``."""

    radius_m: float
    kind: str = field(default="sphere", init=False)

    def __post_init__(self) -> None:
        _positive(self.radius_m, "sphere radius_m", "m")

    def profile(self, du, dv):
        return (du * du + dv * dv) / (2.0 * self.radius_m)

    def force_from_depth(self, k, depth):
        return float(np.pi * k * self.radius_m * depth * depth)

    def depth_from_force(self, k, force):
        return float(np.sqrt(max(force, 0.0) / (np.pi * k * self.radius_m)))

    def footprint(self, depth: float) -> tuple[float, float]:
        """Contact half-axes (a, b), metres: the circle ``a = b = sqrt(2 R δ)``."""
        a = float(np.sqrt(2.0 * self.radius_m * max(depth, 0.0)))
        return a, a


@dataclass(frozen=True)
class FlatPunch:
    """Flat-ended cylinder of ``radius_m``; uniform deflection ``δ``; ``F = π k a² δ``."""

    radius_m: float
    kind: str = field(default="punch", init=False)

    def __post_init__(self) -> None:
        _positive(self.radius_m, "punch radius_m", "m")

    def profile(self, du, dv):
        return np.where(du * du + dv * dv <= self.radius_m ** 2, 0.0, np.inf)

    def force_from_depth(self, k, depth):
        return float(np.pi * k * self.radius_m ** 2 * depth)

    def depth_from_force(self, k, force):
        return float(max(force, 0.0) / (np.pi * k * self.radius_m ** 2))

    def footprint(self, depth: float) -> tuple[float, float]:
        return float(self.radius_m), float(self.radius_m)


@dataclass(frozen=True)
class CapsuleIndenter:
    """A finger: a capsule of ``radius_m`` around a segment of half-length ``half_length_m``,
    lying in the surface at ``angle_rad`` from surface +u; ``g = d² / 2R`` with ``d`` the distance
    to the segment; ``F = k (8/3 ℓ sqrt(2R) δ^{3/2} + π R δ²)``."""

    radius_m: float
    half_length_m: float
    angle_rad: float = 0.0
    kind: str = field(default="capsule", init=False)

    def __post_init__(self) -> None:
        _positive(self.radius_m, "capsule radius_m", "m")
        if not (np.isfinite(self.half_length_m) and self.half_length_m >= 0):
            raise ValueError(f"Invalid capsule half_length_m: {self.half_length_m!r} m (need >= 0)")

    def profile(self, du, dv):
        a, b = _rotate(du, dv, self.angle_rad)
        along = np.maximum(np.abs(a) - self.half_length_m, 0.0)
        return (along * along + b * b) / (2.0 * self.radius_m)

    def force_from_depth(self, k, depth):
        d = max(depth, 0.0)
        return float(k * (8.0 / 3.0 * self.half_length_m * np.sqrt(2.0 * self.radius_m) * d ** 1.5
                          + np.pi * self.radius_m * d * d))

    def depth_from_force(self, k, force):
        from scipy.optimize import brentq
        if force <= 0:
            return 0.0
        hi = SphereIndenter(self.radius_m).depth_from_force(k, force)  # F(δ) >= sphere's
        return float(brentq(lambda d: self.force_from_depth(k, d) - force, 0.0, hi,
                            xtol=1e-15, rtol=1e-13))

    def footprint(self, depth: float) -> tuple[float, float]:
        b = float(np.sqrt(2.0 * self.radius_m * max(depth, 0.0)))
        return self.half_length_m + b, b


@dataclass(frozen=True)
class RectPunch:
    """An edge: a flat rectangle of half-sides ``half_length_m`` (along ``angle_rad``) ×
    ``half_width_m``; ``F = 4 k a b δ``."""

    half_length_m: float
    half_width_m: float
    angle_rad: float = 0.0
    kind: str = field(default="rect", init=False)

    def __post_init__(self) -> None:
        _positive(self.half_length_m, "rect half_length_m", "m")
        _positive(self.half_width_m, "rect half_width_m", "m")

    def profile(self, du, dv):
        a, b = _rotate(du, dv, self.angle_rad)
        inside = (np.abs(a) <= self.half_length_m) & (np.abs(b) <= self.half_width_m)
        return np.where(inside, 0.0, np.inf)

    def force_from_depth(self, k, depth):
        return float(4.0 * k * self.half_length_m * self.half_width_m * max(depth, 0.0))

    def depth_from_force(self, k, force):
        return float(max(force, 0.0) / (4.0 * k * self.half_length_m * self.half_width_m))

    def footprint(self, depth: float) -> tuple[float, float]:
        return float(self.half_length_m), float(self.half_width_m)


def _ramp(t: float, t0: float, ramp: float) -> float:
    """Raised-cosine step from 0 at ``t0`` to 1 at ``t0 + ramp``."""
    if ramp <= 0:
        return 1.0 if t >= t0 else 0.0
    x = min(max((t - t0) / ramp, 0.0), 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * x)


@dataclass(frozen=True)
class Press:
    """One indenter pressed into the body over time.

    The force rises from 0 at ``t_on_s`` to ``force_n`` over ``ramp_s`` (raised cosine), holds,
    and falls back to 0 from ``t_off_s`` over ``ramp_s``. The centre is at ``position_m`` (surface
    coordinates ``(u, v)``, metres: on the block world ``(x, y)``; see each body) and moves at
    ``velocity_mps`` from ``t_on_s`` on.

    Attributes
    ----------
    indenter : Indenter
    position_m : tuple of float
        ``(u, v)`` at ``t_on_s``, metres, surface coordinates.
    force_n : float
        Peak normal force, N (>= 0).
    t_on_s, t_off_s, ramp_s : float
        Seconds; ``t_off_s = inf`` presses for ever.
    velocity_mps : tuple of float
        Drift of the centre, m/s, surface coordinates.
    """

    indenter: Indenter
    position_m: tuple[float, float] = (0.0, 0.0)
    force_n: float = 1.0
    t_on_s: float = 0.0
    t_off_s: float = float("inf")
    ramp_s: float = 0.0
    velocity_mps: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.force_n) and self.force_n >= 0):
            raise ValueError(f"Invalid force_n: {self.force_n!r} N (need a finite value >= 0)")
        if not (self.ramp_s >= 0 and self.t_off_s >= self.t_on_s):
            raise ValueError(f"Invalid schedule: t_on_s={self.t_on_s!r}, t_off_s={self.t_off_s!r}, "
                             f"ramp_s={self.ramp_s!r} (need ramp_s >= 0, t_off_s >= t_on_s)")
        if len(self.position_m) != 2 or len(self.velocity_mps) != 2:
            raise ValueError(f"Invalid position_m/velocity_mps: {self.position_m!r}, "
                             f"{self.velocity_mps!r} (expected two numbers each)")

    def force_at(self, t_s: float) -> float:
        """Force at time ``t_s``, N."""
        t = float(t_s)
        return float(self.force_n * (_ramp(t, self.t_on_s, self.ramp_s)
                                     - _ramp(t, self.t_off_s, self.ramp_s)))

    def position_at(self, t_s: float) -> np.ndarray:
        """Centre ``(u, v)`` at ``t_s``, metres, surface coordinates."""
        dt = max(float(t_s) - self.t_on_s, 0.0)
        return np.asarray(self.position_m, float) + dt * np.asarray(self.velocity_mps, float)


@dataclass(frozen=True)
class TrueContact:
    """Ground truth of one active contact.

    Attributes
    ----------
    index : int
        Index of its `Press` in the scene.
    kind : str
        The indenter's kind ("sphere", "punch", "capsule", "rect").
    position_uv : ndarray, shape (2,)
        Centre, metres, surface coordinates.
    position : ndarray, shape (3,)
        Centre on the undeformed surface, metres, world frame.
    force_n : float
        Normal force, N.
    depth_m : float
        Indenter penetration ``δ`` (the tip's depth below the undeformed surface), metres.
    max_deflection_m : float
        Deepest surface deflection within the footprint, metres (``≈ δ``).
    footprint_m : tuple of float
        Contact half-axes ``(a, b)`` of the Winkler contact at this force, metres (major along
        ``angle_rad``; the layer's spreading makes the dent wider).
    angle_rad : float
        Orientation of the major half-axis from surface +u (0 for round indenters).
    """

    index: int
    kind: str
    position_uv: np.ndarray
    position: np.ndarray
    force_n: float
    depth_m: float
    max_deflection_m: float
    footprint_m: tuple[float, float]
    angle_rad: float


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


# ---------------------------------------------------------------------------------------------
# Contact solver
# ---------------------------------------------------------------------------------------------

def _compliance(layer: FoamLayer, n: int, step: float) -> np.ndarray:
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
    comp = _compliance(layer, n, step_m)
    k = layer.k_pa_per_m
    dA = step_m * step_m

    def apply(p):
        return irfft2(rfft2(p) * comp, s=(n, n))

    ps = []
    for g, F in zip(profiles, forces):  # Winkler's contact as the first guess
        F = _positive(F, "force", "N")
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


# ---------------------------------------------------------------------------------------------
# Bodies
# ---------------------------------------------------------------------------------------------

class FoamBody:
    """Base of the foam bodies: a `FoamLayer` on a rigid core, the sheet on its surface.

    Subclasses define surface coordinates ``(u, v)`` (metres along the surface), ``surface_point``
    (the undeformed surface, world frame), ``normal_at`` and ``sheet(deflection)`` (the sheet's
    joints on the indented surface).
    """

    layer: FoamLayer

    def surface_point(self, uv: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def normal_at(self, uv: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def rest_sheet(self, rows: int, cols: int, link_length: float) -> np.ndarray:
        raise NotImplementedError

    def sheet(self, deflection: Deflection | None, rows: int, cols: int, link_length: float,
              rest: np.ndarray) -> np.ndarray:
        raise NotImplementedError


@dataclass(frozen=True, eq=False)
class FoamBlock(FoamBody):
    """A foam block, top face level at ``z = 0``; surface coordinates are world ``(x, y)``, normal
    +z. The sheet is a centre-anchored Chebyshev net (exact, `geometry.chebyshev_net`)."""

    layer: FoamLayer = FoamLayer()

    def surface_point(self, uv):
        uv = np.asarray(uv, float)
        return np.concatenate([uv, np.zeros(uv.shape[:-1] + (1,))], axis=-1)

    def normal_at(self, uv):
        uv = np.asarray(uv, float)
        return np.broadcast_to(np.array([0.0, 0.0, 1.0]), uv.shape[:-1] + (3,)).copy()

    def rest_sheet(self, rows, cols, link_length):
        return flat_net(rows, cols, link_length)

    def sheet(self, deflection, rows, cols, link_length, rest):
        if deflection is None:
            return rest.copy()
        return chebyshev_net(lambda x, y: -deflection.at(x, y), rows, cols, link_length)


class _RadialSurface:
    """A `drape.Surface`: radius ``R − w(u, v)`` about ``centre`` along the direction of a point
    (projection is radial: exact on the undeformed surface, within O(slope²) when indented)."""

    def __init__(self, body, deflection: Deflection | None):
        self.body, self.deflection = body, deflection

    @property
    def anchor(self) -> np.ndarray:
        return self.body.surface_point(np.zeros(2))

    def project(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, float)
        uv = self.body.uv_of(p)
        r = self.body.radius_m
        if self.deflection is not None:
            r = r - self.deflection.at(uv[..., 0], uv[..., 1])
        c = self.body.centre
        d = p - c
        return c + np.asarray(r)[..., None] * d / np.linalg.norm(d, axis=-1, keepdims=True)


@dataclass(frozen=True, eq=False)
class FoamCylinder(FoamBody):
    """A foam cylinder of outer radius ``radius_m``, axis along world y, top line at ``z = 0``
    (axis at ``z = −R``). Surface coordinates: ``u = R θ`` (arc length from the top line towards
    +x), ``v = y``. The sheet is draped (`drape.drape`), its i lines round the cylinder."""

    radius_m: float = 0.06
    layer: FoamLayer = FoamLayer()

    def __post_init__(self) -> None:
        _positive(self.radius_m, "cylinder radius_m", "m")

    @property
    def centre(self) -> np.ndarray:
        return np.array([0.0, 0.0, -self.radius_m])

    def surface_point(self, uv):
        uv = np.asarray(uv, float)
        th = uv[..., 0] / self.radius_m
        R = self.radius_m
        return np.stack([R * np.sin(th), uv[..., 1], R * np.cos(th) - R], axis=-1)

    def normal_at(self, uv):
        uv = np.asarray(uv, float)
        th = uv[..., 0] / self.radius_m
        return np.stack([np.sin(th), 0.0 * th, np.cos(th)], axis=-1)

    def uv_of(self, p):
        """Surface coordinates of world points (radially projected), shape ``(..., 2)``."""
        d = np.asarray(p, float) - self.centre
        th = np.arctan2(d[..., 0], d[..., 2])
        return np.stack([self.radius_m * th, d[..., 1]], axis=-1)

    def rest_sheet(self, rows, cols, link_length):
        return _drape(_CylSurface(self, None), rows, cols, link_length, None)

    def sheet(self, deflection, rows, cols, link_length, rest):
        if deflection is None:
            return rest.copy()
        return _drape(_CylSurface(self, deflection), rows, cols, link_length, rest)


class _CylSurface(_RadialSurface):
    """Radial projection about the cylinder's axis (y kept)."""

    def project(self, points):
        p = np.asarray(points, float)
        uv = self.body.uv_of(p)
        r = np.full(p.shape[:-1], self.body.radius_m)
        if self.deflection is not None:
            r = r - self.deflection.at(uv[..., 0], uv[..., 1])
        c = self.body.centre
        d = p - c
        d[..., 1] = 0.0
        out = c + r[..., None] * d / np.linalg.norm(d, axis=-1, keepdims=True)
        out[..., 1] = p[..., 1]
        return out


@dataclass(frozen=True, eq=False)
class FoamSphere(FoamBody):
    """A foam ball of outer radius ``radius_m``, top at ``z = 0`` (centre at ``z = −R``). Surface
    coordinates: azimuthal equidistant about the top, ``(u, v) = R θ (cos φ, sin φ)`` with ``θ``
    the polar angle and ``φ`` the azimuth from +x (so ``(u, v) ≈ (x, y)`` near the top; distances
    along meridians are exact). The sheet is draped (`drape.drape`)."""

    radius_m: float = 0.08
    layer: FoamLayer = FoamLayer()

    def __post_init__(self) -> None:
        _positive(self.radius_m, "sphere radius_m", "m")

    @property
    def centre(self) -> np.ndarray:
        return np.array([0.0, 0.0, -self.radius_m])

    def _dir(self, uv):
        uv = np.asarray(uv, float)
        rho = np.hypot(uv[..., 0], uv[..., 1])
        th = rho / self.radius_m
        phi = np.arctan2(uv[..., 1], uv[..., 0])
        return np.stack([np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), np.cos(th)], axis=-1)

    def surface_point(self, uv):
        return self.centre + self.radius_m * self._dir(uv)

    def normal_at(self, uv):
        return self._dir(uv)

    def uv_of(self, p):
        d = np.asarray(p, float) - self.centre
        th = np.arctan2(np.hypot(d[..., 0], d[..., 1]), d[..., 2])
        phi = np.arctan2(d[..., 1], d[..., 0])
        rho = self.radius_m * th
        return np.stack([rho * np.cos(phi), rho * np.sin(phi)], axis=-1)

    def rest_sheet(self, rows, cols, link_length):
        return _drape(_RadialSurface(self, None), rows, cols, link_length, None)

    def sheet(self, deflection, rows, cols, link_length, rest):
        if deflection is None:
            return rest.copy()
        return _drape(_RadialSurface(self, deflection), rows, cols, link_length, rest)


def _drape(surface, rows, cols, L, init) -> np.ndarray:
    P, info = drape(surface, rows, cols, L, init="compass" if init is None else init, tol=1e-9)
    if not info.converged:
        raise ValueError(f"Foam sheet: drape did not converge (link error "
                         f"{info.max_length_error:.3g}); indentation too steep for the links?")
    return P


# ---------------------------------------------------------------------------------------------
# Scene
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class FoamScene:
    """A sheet on a foam body with indenters pressed and released over time.

    Like the scenes of `virtual_sheet.shapes`: ``joints(t_s)`` gives the sheet's joints, shape
    ``(rows, cols, 3)``, metres, world frame, every link ``link_length``; ``contacts(t_s)`` the
    true contacts active at ``t_s`` (force > ``min_force_n``).

    Attributes
    ----------
    body : FoamBody
        `FoamBlock` (default), `FoamCylinder` or `FoamSphere`.
    presses : sequence of Press
    rows, cols : int
    link_length : float
        ``L``, metres.
    grid_step_m : float, optional
        Deflection grid spacing, metres (default ``L / 6``).
    margin_m : float, optional
        Grid extent beyond the sheet, metres (default ``6 λ + 3 L``: the spreading has died out,
        ``e^{-6}``, and the FFT's periodic images do not touch).
    min_force_n : float
        Contacts below this force are not reported as active (default 1 mN).
    """

    body: FoamBody
    presses: Sequence[Press]
    rows: int = 14
    cols: int = 14
    link_length: float = 0.01
    grid_step_m: float | None = None
    margin_m: float | None = None
    min_force_n: float = 1e-3

    def __post_init__(self) -> None:
        Lattice(self.rows, self.cols)
        _positive(self.link_length, "link_length", "m")
        object.__setattr__(self, "presses", tuple(self.presses))
        object.__setattr__(self, "_cache", {})

    @property
    def layer(self) -> FoamLayer:
        return self.body.layer

    @cached_property
    def _grid(self) -> tuple[np.ndarray, float]:
        L = self.link_length
        step = L / 6 if self.grid_step_m is None else _positive(self.grid_step_m, "grid_step_m", "m")
        margin = (6 * self.layer.shear_length_m + 3 * L if self.margin_m is None
                  else float(self.margin_m))
        half = 0.5 * max(self.rows, self.cols) * L + margin
        from scipy.fft import next_fast_len
        n = next_fast_len(int(np.ceil(2 * half / step)), real=True)
        u = (np.arange(n) - n // 2) * step
        return u, step

    @cached_property
    def rest_joints(self) -> np.ndarray:
        """The sheet on the undeformed body, shape ``(rows, cols, 3)``, metres, world frame."""
        P = self.body.rest_sheet(self.rows, self.cols, self.link_length)
        P.setflags(write=False)
        return P

    def deflection(self, t_s: float) -> Deflection | None:
        """The surface deflection at ``t_s`` (None when nothing presses), cached per time."""
        key = ("defl", float(t_s))
        if key in self._cache:
            return self._cache[key]
        active = [(i, p.force_at(t_s), p.position_at(t_s)) for i, p in enumerate(self.presses)]
        active = [a for a in active if a[1] > 0]
        if not active:
            return None
        u, step = self._grid
        U, V = np.meshgrid(u, u, indexing="ij")
        profiles = [self.presses[i].indenter.profile(U - c[0], V - c[1]) for i, _, c in active]
        p, depths, w = solve_contact(self.layer, profiles, [F for _, F, _ in active], step)
        out = Deflection(u=u, v=u.copy(), w=w, pressure=p, step_m=step,
                         depths_m={i: d for (i, _, _), d in zip(active, depths)})
        if len(self._cache) > 256:
            self._cache.clear()
        self._cache[key] = out
        return out

    def joints(self, t_s: float) -> np.ndarray:
        """The sheet's joints at ``t_s``, shape ``(rows, cols, 3)``, metres, world frame."""
        key = ("joints", float(t_s))
        if key not in self._cache:
            d = self.deflection(t_s)
            if len(self._cache) > 256:
                self._cache.clear()
            self._cache[key] = self.body.sheet(d, self.rows, self.cols, self.link_length,
                                               np.array(self.rest_joints))
        return self._cache[key].copy()

    def contacts(self, t_s: float) -> list[TrueContact]:
        """The true contacts active at ``t_s``, in `presses` order."""
        k = self.layer.k_pa_per_m
        out = []
        defl = None
        for idx, press in enumerate(self.presses):
            F = press.force_at(t_s)
            if F <= self.min_force_n:
                continue
            if defl is None:
                defl = self.deflection(t_s)
            c = press.position_at(t_s)
            d = defl.depths_m[idx]
            a, b = press.indenter.footprint(press.indenter.depth_from_force(k, F))
            r = np.linspace(-a, a, 41)
            gu, gv = np.meshgrid(r, r * b / max(a, 1e-300), indexing="ij")
            ang = float(getattr(press.indenter, "angle_rad", 0.0))
            cu, cv = np.cos(ang) * gu - np.sin(ang) * gv, np.sin(ang) * gu + np.cos(ang) * gv
            wmax = float(np.max(defl.at(c[0] + cu, c[1] + cv)))
            out.append(TrueContact(index=idx, kind=press.indenter.kind, position_uv=c,
                                   position=self.body.surface_point(c), force_n=F, depth_m=d,
                                   max_deflection_m=wmax, footprint_m=(a, b), angle_rad=ang))
        return out
