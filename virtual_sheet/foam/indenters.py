"""Indenters (tip profiles, Winkler's closed forms), presses over time, true contacts."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from .material import require_positive

__all__ = ["Indenter", "SphereIndenter", "FlatPunch", "CapsuleIndenter", "RectPunch", "Press",
           "TrueContact"]


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
        require_positive(self.radius_m, "sphere radius_m", "m")

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
        require_positive(self.radius_m, "punch radius_m", "m")

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
        require_positive(self.radius_m, "capsule radius_m", "m")
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
        require_positive(self.half_length_m, "rect half_length_m", "m")
        require_positive(self.half_width_m, "rect half_width_m", "m")

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
