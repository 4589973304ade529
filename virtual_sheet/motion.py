"""Sheets that move, with exact kinematics: every link's true orientation, angular velocity and
specific force at any instant (issue 29, the simulator that moves).

Every scene is an exact net at every instant (all links ``L``: a Chebyshev net, docs/design.md
"Exact ground truth") carried by a rigid motion::

    joints(t) = c(t) + Q(t) · N(t)

``N(t)`` is either a fixed net (a rigid scene: the sheet carried and turned) or the compass
construction of `geometry.chebyshev_net` on a height field that changes with time,
``z = h(x, y, t)`` (a wave, a bending elbow, a dent). The construction is differentiated exactly:
each joint of the net is fixed by two equations (its distances ``L`` to two placed neighbours, or
one distance and the vertical plane of a seed line) on the surface, so by the implicit-function
theorem its velocity and acceleration solve the same 2 × 2 linear system as its position's Newton
step, with the height field's analytic derivatives (`HeightJet`) on the right-hand side. The rigid
motion's derivatives are analytic too (`RigidJet`: rotations about fixed axes with angle profiles
of known first and second derivatives, composed). So for every joint the position, velocity and
acceleration are known to rounding, and `sample` derives per link (docs/design.md conventions):

* ``frames`` — the sensor frame (`geometry.link_frames`), sensor -> world;
* ``angular_velocity`` — its body-frame rate ``Rᵀ Ṙ = [ω]×`` (`geometry.link_frames_jet`): what
  a gyroscope on the link measures, rad/s;
* ``acceleration`` — the link midpoint's (where the chip sits) own acceleration, world frame;
* ``specific_force`` — ``Rᵀ (a + (0, 0, +G0))``, what an accelerometer on the link measures.

Tests check all of it against finite differences of the independent construction
(`joints`, which calls `geometry.chebyshev_net` at one instant).

Built-in scenes (`MOTION_SCENES`, `make_motion_scene`); defaults scale with the sheet's side
``S = (max(rows, cols) − 1) L`` (13 cm for 14 × 14 at 1 cm). Every moving scene starts at rest
and reaches link accelerations of at least 2 m/s² with its defaults (a test checks it on 14 × 14):

========== =====================================================================================
carry      a curved sheet (a cylinder of radius S) carried and turned: 3-D translation of 5-8 cm
           at 0.7-1.1 Hz, heading ±57°, roll ±29°, pitch ±23° (rigid motion)
wave       a travelling bend: ``A sin(k s − 2πft)`` along a direction 0.3 rad from x, amplitude
           S/5, wavelength 2S, frequency set by the surface's peak vertical acceleration 4 m/s²
elbow      a sheet worn over an elbow that bends 0 → 120° in 1 s, holds, straightens in 1 s (the
           upper arm fixed, the forearm turning), while the arm sweeps ±0.35 rad about a shoulder
           0.3 m away
tap        a press on the foam that arrives and leaves fast: a Gaussian dent S/8 deep and S/8
           wide, reached in 0.15 s, held 0.3 s, released in 0.15 s, every 1.2 s
flat_turn  a flat horizontal sheet turning in heading (±69° at 0.2 Hz) and sliding (6 / 4 cm at
           1.0 / 0.8 Hz): the paper's Case 1 in motion
rest       any static shape (``shape=``, default gaussian): a sheet at rest
tumble     a flat sheet turned every way over ~20 s (magnetometer calibration)
board      the calibration board (`board.BoardPoseScene`) with its turns
========== =====================================================================================

>>> s = make_motion_scene("wave", 6, 6, 0.01)
>>> tr = s.sample([0.0, 1.5])
>>> tr.angular_velocity.shape, tr.specific_force.shape
((2, 60, 3), (2, 60, 3))
>>> np.round(tr.specific_force[0, 0], 6).tolist()   # at rest at t = 0: gravity only
[0.0, 0.0, 9.80665]
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, NamedTuple

import numpy as np

from protocol.constants import G0
from protocol.lattice import Lattice
from .geometry import _cross, chebyshev_net, compass_diagonals, link_frames_jet, link_midpoints
from .shapes import flat_net, make_sheet

__all__ = ["Profile", "Constant", "Sine", "Pulse", "RigidJet", "HeightJet", "TravellingWave",
           "Bend", "Dent", "chebyshev_net_jet", "Truth", "truth_from_joints", "MotionScene",
           "RigidScene", "FieldScene", "carry_scene", "wave_scene", "elbow_scene", "tap_scene",
           "flat_turn_scene", "rest_scene", "tumble_scene", "board_scene", "MOTION_SCENES",
           "make_motion_scene", "sample_times"]

_NEWTON_MAX_ITER = 60
_TOL = 1e-13  # |F| <= _TOL L² (as geometry.chebyshev_net): lengths to ~5e-14 relative


def _times(t) -> np.ndarray:
    t = np.atleast_1d(np.asarray(t, dtype=float))
    if t.ndim != 1 or not np.all(np.isfinite(t)):
        raise ValueError(f"Expected `t` to be finite seconds, a scalar or shape (T,), got shape {t.shape}.")
    return t


def _side(rows: int, cols: int, link_length: float) -> float:
    return max(max(rows, cols) - 1, 2) * float(link_length)


# ---------------------------------------------------------------------------------------------
# Time profiles: value, first and second derivative
# ---------------------------------------------------------------------------------------------

class Profile:
    """A scalar function of time with its first two derivatives: ``p(t) -> (f, ḟ, f̈)``, arrays
    shaped like ``t``."""

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raise NotImplementedError


@dataclass(frozen=True)
class Constant(Profile):
    value: float = 0.0

    def __call__(self, t):
        t = np.asarray(t, dtype=float)
        return np.full(t.shape, float(self.value)), np.zeros(t.shape), np.zeros(t.shape)


def _smootherstep(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``6τ⁵ − 15τ⁴ + 10τ³`` clipped to [0, 1], and its derivatives in τ: 0 → 1 with zero first and
    second derivatives at both ends (so a motion built from it has continuous acceleration)."""
    x = np.clip(tau, 0.0, 1.0)
    inside = (tau > 0.0) & (tau < 1.0)
    s = x * x * x * (x * (6 * x - 15) + 10)
    sd = np.where(inside, 30 * x * x * (x - 1) ** 2, 0.0)
    sdd = np.where(inside, 60 * x * (2 * x - 1) * (x - 1), 0.0)
    return s, sd, sdd


@dataclass(frozen=True)
class Sine(Profile):
    """``offset + amplitude · sin(2π f t + phase)``, its swing faded in over ``ramp_s`` seconds
    (multiplied by a smootherstep from 0 at t = 0 to 1 at ``ramp_s``: the motion starts at rest)."""

    amplitude: float
    frequency_hz: float
    phase: float = 0.0
    offset: float = 0.0
    ramp_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("amplitude", "frequency_hz", "phase", "offset", "ramp_s"):
            if not np.isfinite(getattr(self, name)):
                raise ValueError(f"Invalid {name}: {getattr(self, name)!r} (need a finite number)")
        if self.frequency_hz < 0 or self.ramp_s < 0:
            raise ValueError(f"Invalid sine: frequency_hz={self.frequency_hz!r}, ramp_s={self.ramp_s!r} "
                             "(need >= 0)")

    def __call__(self, t):
        t = np.asarray(t, dtype=float)
        w = 2 * np.pi * self.frequency_hz
        a = self.amplitude
        s, c = np.sin(w * t + self.phase), np.cos(w * t + self.phase)
        f, fd, fdd = a * s, a * w * c, -a * w * w * s
        if self.ramp_s > 0:
            r, rd, rdd = _smootherstep(t / self.ramp_s)
            rd, rdd = rd / self.ramp_s, rdd / self.ramp_s ** 2
            f, fd, fdd = r * f, rd * f + r * fd, rdd * f + 2 * rd * fd + r * fdd
        return f + self.offset, fd, fdd


@dataclass(frozen=True)
class Pulse(Profile):
    """A periodic pulse from 0 to ``level``: after ``delay_s``, rise in ``rise_s``, hold
    ``hold_s``, fall in ``fall_s``, rest ``rest_s``, repeat. Rise and fall are smootherstep
    (continuous acceleration)."""

    rise_s: float
    hold_s: float
    fall_s: float
    rest_s: float
    level: float = 1.0
    delay_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("rise_s", "fall_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"Invalid {name}: {v!r} (need > 0 s)")
        for name in ("hold_s", "rest_s", "delay_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"Invalid {name}: {v!r} (need >= 0 s)")
        if not np.isfinite(self.level):
            raise ValueError(f"Invalid level: {self.level!r}")

    @property
    def period_s(self) -> float:
        return self.rise_s + self.hold_s + self.fall_s + self.rest_s

    def __call__(self, t):
        t = np.asarray(t, dtype=float)
        tau = np.where(t < self.delay_s, -1.0, np.mod(t - self.delay_s, self.period_s))
        up, upd, updd = _smootherstep(tau / self.rise_s)
        t_down = self.rise_s + self.hold_s
        dn, dnd, dndd = _smootherstep((tau - t_down) / self.fall_s)
        lv = self.level
        f = lv * (up - dn)
        fd = lv * (upd / self.rise_s - dnd / self.fall_s)
        fdd = lv * (updd / self.rise_s ** 2 - dndd / self.fall_s ** 2)
        return f, fd, fdd


# ---------------------------------------------------------------------------------------------
# Rigid motions with exact derivatives
# ---------------------------------------------------------------------------------------------



def _rodrigues(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotations by ``angle (T,)`` about the unit ``axis (3,)``: ``(T, 3, 3)``."""
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


@dataclass(frozen=True)
class RigidJet:
    """A rigid motion ``p = offset + rotation · n`` at ``T`` instants, with its exact derivatives.

    Attributes
    ----------
    rotation : ndarray, shape (T, 3, 3)
        ``Q``, body -> world.
    omega, omega_dot : ndarray, shape (T, 3)
        Angular velocity of ``Q`` and its derivative, rad/s and rad/s², world frame
        (``Q̇ = [ω]× Q``).
    offset, velocity, acceleration : ndarray, shape (T, 3)
        ``c`` and its first two derivatives, world frame, m, m/s, m/s².
    """

    rotation: np.ndarray
    omega: np.ndarray
    omega_dot: np.ndarray
    offset: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray

    @classmethod
    def identity(cls, n: int) -> "RigidJet":
        z = np.zeros((n, 3))
        return cls(np.tile(np.eye(3), (n, 1, 1)), z, z, z, z, z)

    @classmethod
    def about_axis(cls, axis, angle: tuple[np.ndarray, np.ndarray, np.ndarray],
                   point=(0.0, 0.0, 0.0)) -> "RigidJet":
        """Rotation by ``angle = (φ, φ̇, φ̈)`` (arrays (T,)) about the fixed ``axis`` through ``point``."""
        u = np.asarray(axis, dtype=float)
        if u.shape != (3,) or not np.all(np.isfinite(u)) or np.linalg.norm(u) == 0:
            raise ValueError(f"Invalid axis: {axis!r} (need 3 finite numbers, not all 0)")
        u = u / np.linalg.norm(u)
        p = np.asarray(point, dtype=float)
        phi, phid, phidd = (np.asarray(a, dtype=float) for a in angle)
        Q = _rodrigues(u, phi)
        w = phid[:, None] * u
        wd = phidd[:, None] * u
        Qp = Q @ p
        c = p - Qp
        cd = -_cross(w, Qp)
        cdd = -(_cross(wd, Qp) + _cross(w, _cross(w, Qp)))
        return cls(Q, w, wd, c, cd, cdd)

    @classmethod
    def translation(cls, position: tuple[np.ndarray, np.ndarray, np.ndarray]) -> "RigidJet":
        """Translation by ``(c, ċ, c̈)`` (arrays (T, 3))."""
        c, cd, cdd = (np.asarray(a, dtype=float) for a in position)
        z = np.zeros_like(c)
        return cls(np.tile(np.eye(3), (c.shape[0], 1, 1)), z, z, c, cd, cdd)

    def then(self, outer: "RigidJet") -> "RigidJet":
        """``outer ∘ self``: this motion first, then ``outer`` (``p = c_o + Q_o (c + Q n)``)."""
        Qo = outer.rotation
        Qc = np.einsum("tij,tj->ti", Qo, self.offset)
        Qcd = np.einsum("tij,tj->ti", Qo, self.velocity)
        Qw = np.einsum("tij,tj->ti", Qo, self.omega)
        wo, wdo = outer.omega, outer.omega_dot
        return RigidJet(
            rotation=Qo @ self.rotation,
            omega=wo + Qw,
            omega_dot=wdo + np.einsum("tij,tj->ti", Qo, self.omega_dot) + _cross(wo, Qw),
            offset=outer.offset + Qc,
            velocity=outer.velocity + _cross(wo, Qc) + Qcd,
            acceleration=(outer.acceleration + _cross(wdo, Qc) + _cross(wo, _cross(wo, Qc))
                          + 2 * _cross(wo, Qcd) + np.einsum("tij,tj->ti", Qo, self.acceleration)))

    def apply(self, n: np.ndarray, nd: np.ndarray | None = None,
              ndd: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World positions, velocities, accelerations of body points ``n (T, ..., 3)`` that move in
        the body frame with ``nd``, ``ndd`` (zero if omitted)."""
        n = np.asarray(n, dtype=float)
        T = self.rotation.shape[0]
        if n.shape[0] != T:
            n = np.broadcast_to(n, (T,) + n.shape)
        shape = n.shape
        nf = n.reshape(T, -1, 3)
        Qn = np.einsum("tij,tkj->tki", self.rotation, nf)
        w = self.omega[:, None, :]
        wd = self.omega_dot[:, None, :]
        p = self.offset[:, None, :] + Qn
        v = self.velocity[:, None, :] + _cross(w, Qn)
        a = self.acceleration[:, None, :] + _cross(wd, Qn) + _cross(w, _cross(w, Qn))
        if nd is not None:
            Qnd = np.einsum("tij,tkj->tki", self.rotation, np.asarray(nd, dtype=float).reshape(T, -1, 3))
            v = v + Qnd
            a = a + 2 * _cross(w, Qnd)
        if ndd is not None:
            a = a + np.einsum("tij,tkj->tki", self.rotation, np.asarray(ndd, dtype=float).reshape(T, -1, 3))
        return p.reshape(shape), v.reshape(shape), a.reshape(shape)


# ---------------------------------------------------------------------------------------------
# Height fields that change with time, with exact derivatives
# ---------------------------------------------------------------------------------------------

class HeightJet(NamedTuple):
    """A height field and its derivatives up to second order in x, y, t (arrays of one shape;
    the second-order ones None when only the gradient was asked for)."""

    h: np.ndarray
    hx: np.ndarray
    hy: np.ndarray
    ht: np.ndarray | None = None
    hxx: np.ndarray | None = None
    hxy: np.ndarray | None = None
    hyy: np.ndarray | None = None
    hxt: np.ndarray | None = None
    hyt: np.ndarray | None = None
    htt: np.ndarray | None = None


class MovingField:
    """``z = h(x, y, t)``: ``field(x, y, t)`` is the height, ``field.jet(x, y, t, order)`` adds the
    gradient (order 1) or every derivative to second order (order 2, the default)."""

    def jet(self, x, y, t, order: int = 2) -> HeightJet:
        raise NotImplementedError

    def __call__(self, x, y, t):
        return self.jet(x, y, t, order=0).h


@dataclass(frozen=True)
class TravellingWave(MovingField):
    """``a(t) · sin(k s − 2π f t)`` with ``s = x cos φ + y sin φ``, ``k = 2π / wavelength``;
    ``amplitude`` a `Profile` (metres) so the wave can fade in."""

    amplitude: Profile
    wavelength: float
    frequency_hz: float
    direction: float = 0.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.wavelength) and self.wavelength > 0):
            raise ValueError(f"Invalid wavelength: {self.wavelength!r} m (need > 0)")
        if not (np.isfinite(self.frequency_hz) and self.frequency_hz >= 0):
            raise ValueError(f"Invalid frequency_hz: {self.frequency_hz!r} (need >= 0)")

    def jet(self, x, y, t, order=2):
        a, ad, add = self.amplitude(np.asarray(t, dtype=float))  # on t's own shape, then broadcast
        x, y, t, a, ad, add = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (x, y, t, a, ad, add)))
        k = 2 * np.pi / self.wavelength
        w = 2 * np.pi * self.frequency_hz
        cphi, sphi = np.cos(self.direction), np.sin(self.direction)
        th = k * (x * cphi + y * sphi) - w * t
        S, C = np.sin(th), np.cos(th)
        h = a * S
        if order == 0:
            return HeightJet(h, None, None)
        hs = a * k * C
        if order == 1:
            return HeightJet(h, hs * cphi, hs * sphi)
        hss = -a * k * k * S
        ht = ad * S - a * w * C
        hst = ad * k * C + a * k * w * S
        htt = add * S - 2 * ad * w * C - a * w * w * S
        return HeightJet(h, hs * cphi, hs * sphi, ht, hss * cphi * cphi, hss * cphi * sphi,
                         hss * sphi * sphi, hst * cphi, hst * sphi, htt)


@dataclass(frozen=True)
class Bend(MovingField):
    """A limb bent by ``θ(t)`` under the sheet: ``m(ℓ − √(x² + ℓ²)) − y² / (2 r)`` with
    ``m = tan(θ/2)``. Along x a hyperbola — flat for θ = 0, asymptotic slopes ±θ/2 (so the two
    sides meet at θ), apex radius ``ℓ / m``; across it a parabola of radius ``r`` (the limb's
    round top). ``angle`` is a `Profile` in radians, ``|θ| < π``."""

    angle: Profile
    knee_m: float
    limb_radius_m: float

    def __post_init__(self) -> None:
        for name in ("knee_m", "limb_radius_m"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"Invalid {name}: {v!r} (need > 0 m)")

    def slope(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``m = tan(θ/2)`` and its derivatives."""
        th, thd, thdd = self.angle(np.asarray(t, dtype=float))
        if np.any(np.abs(th) >= np.pi):
            raise ValueError(f"Invalid bend angle: {float(np.max(np.abs(th)))!r} rad (need |θ| < π)")
        tn = np.tan(th / 2)
        sec2 = 1.0 + tn * tn
        return tn, 0.5 * sec2 * thd, 0.5 * sec2 * (thdd + tn * thd * thd)

    def jet(self, x, y, t, order=2):
        m, md, mdd = self.slope(np.asarray(t, dtype=float))
        x, y, m, md, mdd = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (x, y, m, md, mdd)))
        ell, r = self.knee_m, self.limb_radius_m
        q = np.sqrt(x * x + ell * ell)
        h = m * (ell - q) - y * y / (2 * r)
        if order == 0:
            return HeightJet(h, None, None)
        hx, hy = -m * x / q, -y / r
        if order == 1:
            return HeightJet(h, hx, hy)
        zero = np.zeros_like(x)
        return HeightJet(h, hx, hy, md * (ell - q), -m * ell * ell / q ** 3, zero,
                         np.full_like(x, -1.0 / r), -md * x / q, zero, mdd * (ell - q))


@dataclass(frozen=True)
class Dent(MovingField):
    """A Gaussian dent ``−d(t) · exp(−|p − centre|² / 2σ²)`` (``depth`` a `Profile`, metres)."""

    depth: Profile
    sigma_m: float
    centre: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.sigma_m) and self.sigma_m > 0):
            raise ValueError(f"Invalid sigma_m: {self.sigma_m!r} (need > 0 m)")

    def jet(self, x, y, t, order=2):
        d, dd, ddd = self.depth(np.asarray(t, dtype=float))
        x, y, d, dd, ddd = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (x, y, d, dd, ddd)))
        s2 = self.sigma_m ** 2
        u, v = x - self.centre[0], y - self.centre[1]
        E = np.exp(-(u * u + v * v) / (2 * s2))
        h = -d * E
        if order == 0:
            return HeightJet(h, None, None)
        hx, hy = d * E * u / s2, d * E * v / s2
        if order == 1:
            return HeightJet(h, hx, hy)
        return HeightJet(h, hx, hy, -dd * E, d * E * (1 / s2 - u * u / s2 ** 2), -d * E * u * v / s2 ** 2,
                         d * E * (1 / s2 - v * v / s2 ** 2), dd * E * u / s2, dd * E * v / s2, -ddd * E)


# ---------------------------------------------------------------------------------------------
# The compass construction, batched over time, with exact velocities and accelerations
# ---------------------------------------------------------------------------------------------

def _rates(P, J: HeightJet, cons):
    """Velocity and acceleration of new joints ``P (T, m, 3) = (q, h(q, t))`` held by two
    constraints each (module docstring). ``cons``: two of ``("dist", Q, Qd, Qdd)`` (``|P − Q| = L``
    with ``Q`` a moving placed joint) or ``("line", nrm (2,), Qd, Qdd)`` (``nrm · (q − Q_xy)`` fixed)."""
    hx, hy = J.hx, J.hy
    rows, rhs1 = [], []
    for kind, a, Qd, _Qdd in cons:
        if kind == "dist":
            D = P - a
            rows.append((D[..., 0] + D[..., 2] * hx, D[..., 1] + D[..., 2] * hy))
            rhs1.append(np.sum(D * Qd, axis=-1) - D[..., 2] * J.ht)
        else:
            rows.append((np.full(hx.shape, a[0]), np.full(hx.shape, a[1])))
            rhs1.append(a[0] * Qd[..., 0] + a[1] * Qd[..., 1])
    (a11, a12), (a21, a22) = rows
    det = a11 * a22 - a12 * a21

    def solve(r1, r2):
        return (a22 * r1 - a12 * r2) / det, (a11 * r2 - a21 * r1) / det

    qdx, qdy = solve(*rhs1)
    Pd = np.stack([qdx, qdy, hx * qdx + hy * qdy + J.ht], axis=-1)
    kz = (J.hxx * qdx * qdx + 2 * J.hxy * qdx * qdy + J.hyy * qdy * qdy
          + 2 * (J.hxt * qdx + J.hyt * qdy) + J.htt)
    rhs2 = []
    for kind, a, Qd, Qdd in cons:
        if kind == "dist":
            D = P - a
            rel = Pd - Qd
            rhs2.append(-np.sum(rel * rel, axis=-1) - (D[..., 2] * kz - np.sum(D * Qdd, axis=-1)))
        else:
            rhs2.append(a[0] * Qdd[..., 0] + a[1] * Qdd[..., 1])
    qddx, qddy = solve(*rhs2)
    Pdd = np.stack([qddx, qddy, hx * qddx + hy * qddy + kz], axis=-1)
    return Pd, Pdd


def _seed(field: MovingField, S, Sd, Sdd, u, L, t):
    """The next joint of a seed line after ``S (T, 3)`` along the horizontal unit ``u``: on the
    surface, at 3-D distance ``L``, over the line (Newton in the horizontal step, bracketed)."""
    g = field.jet(S[:, 0], S[:, 1], t, order=1)
    slope = g.hx * u[0] + g.hy * u[1]
    s = L / np.sqrt(1.0 + slope * slope)
    lo, hi = np.zeros_like(s), np.full_like(s, L)  # F(0) = −L² < 0 <= F(L)
    for _ in range(_NEWTON_MAX_ITER):
        q0, q1 = S[:, 0] + s * u[0], S[:, 1] + s * u[1]
        J = field.jet(q0, q1, t, order=1)
        dz = J.h - S[:, 2]
        F = s * s + dz * dz - L * L
        if not np.all(np.isfinite(F)):
            raise ValueError("Moving Chebyshev net: the height field is undefined along a seed line.")
        if np.max(np.abs(F)) <= _TOL * L * L:
            break
        lo = np.where(F < 0, s, lo)
        hi = np.where(F > 0, s, hi)
        step = s - F / (2 * s + 2 * dz * (J.hx * u[0] + J.hy * u[1]))
        s = np.where((step >= lo) & (step <= hi), step, 0.5 * (lo + hi))
    else:
        raise ValueError("Moving Chebyshev net: a seed line did not converge (shape too steep?).")
    P = np.stack([q0, q1, J.h], axis=-1)[:, None]
    J = field.jet(q0[:, None], q1[:, None], t[:, None])
    nrm = np.array([-u[1], u[0]])
    Pd, Pdd = _rates(P, J, [("dist", S[:, None], Sd[:, None], Sdd[:, None]),
                            ("line", nrm, Sd[:, None], Sdd[:, None])])
    return P[:, 0], Pd[:, 0], Pdd[:, 0]


def chebyshev_net_jet(field: MovingField, rows: int, cols: int, link_length: float, t, *,
                      origin: tuple[float, float] = (0.0, 0.0), angle: float = 0.0,
                      shear: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`geometry.chebyshev_net` (centre anchor) on ``z = field(x, y, t)`` at every instant of ``t``,
    with the joints' exact velocities and accelerations.

    The same construction — the anchor joint at ``origin``, seed lines over straight horizontal
    lines (direction ``angle``, and ``angle + π/2 + shear``), then anti-diagonal by anti-diagonal each
    joint at distance ``L`` from its two placed neighbours — solved for all instants at once
    (Newton with the field's analytic gradient), then differentiated in time (module docstring).

    Parameters
    ----------
    field : MovingField
    rows, cols : int
    link_length : float
        ``L``, metres.
    t : float or ndarray, shape (T,)
        Seconds.

    Returns
    -------
    joints, velocities, accelerations : ndarray, shape (T, rows, cols, 3)
        Metres, m/s, m/s², world frame of the field.

    Raises
    ------
    ValueError
        The net cannot be placed at some instant (folds, leaves the field, Newton fails).
    """
    Lattice(rows, cols)
    L = float(link_length)
    if not (np.isfinite(L) and L > 0):
        raise ValueError(f"Invalid link_length: {link_length!r} (need a finite value > 0 m)")
    if not abs(shear) < np.pi / 2:
        raise ValueError(f"Invalid shear: {shear!r} rad (need |shear| < pi/2)")
    t = _times(t)
    T = t.size
    u = np.array([np.cos(angle), np.sin(angle)])
    v = np.array([np.cos(angle + np.pi / 2 + shear), np.sin(angle + np.pi / 2 + shear)])
    ic, jc = rows // 2, cols // 2
    P = np.full((T, rows, cols, 3), np.nan)
    V = np.full_like(P, np.nan)
    A = np.full_like(P, np.nan)
    x0, y0 = np.full(T, float(origin[0])), np.full(T, float(origin[1]))
    J0 = field.jet(x0, y0, t)
    if not np.all(np.isfinite(J0.h)):
        raise ValueError(f"Moving Chebyshev net: height field undefined at the origin {tuple(origin)}.")
    zero = np.zeros(T)
    P[:, ic, jc] = np.stack([x0, y0, J0.h], axis=-1)
    V[:, ic, jc] = np.stack([zero, zero, J0.ht], axis=-1)
    A[:, ic, jc] = np.stack([zero, zero, J0.htt], axis=-1)

    def line(di: int, dj: int, n: int, direction: np.ndarray) -> None:
        i, j = ic, jc
        for _ in range(n):
            ni, nj = i + di, j + dj
            P[:, ni, nj], V[:, ni, nj], A[:, ni, nj] = _seed(field, P[:, i, j], V[:, i, j], A[:, i, j],
                                                             direction, L, t)
            i, j = ni, nj

    line(1, 0, rows - 1 - ic, u)
    line(-1, 0, ic, -u)
    line(0, 1, cols - 1 - jc, v)
    line(0, -1, jc, -v)

    tt = t[:, None]
    L2 = L * L
    for ii, jj, si, sj in compass_diagonals(rows, cols, ic, jc):
        Pa, Pb, Pc = P[:, ii - si, jj], P[:, ii, jj - sj], P[:, ii - si, jj - sj]
        q = (Pa + Pb - Pc)[..., :2].copy()
        for _ in range(_NEWTON_MAX_ITER):
            J = field.jet(q[..., 0], q[..., 1], tt, order=1)
            Pn = np.concatenate([q, J.h[..., None]], axis=-1)
            dA, dB = Pn - Pa, Pn - Pb
            F1 = np.sum(dA * dA, axis=-1) - L2
            F2 = np.sum(dB * dB, axis=-1) - L2
            if not (np.all(np.isfinite(F1)) and np.all(np.isfinite(F2))):
                raise ValueError("Moving Chebyshev net: the sheet leaves the height field's domain.")
            if max(np.max(np.abs(F1)), np.max(np.abs(F2))) <= _TOL * L2:
                break
            a11, a12 = 2 * (dA[..., 0] + dA[..., 2] * J.hx), 2 * (dA[..., 1] + dA[..., 2] * J.hy)
            a21, a22 = 2 * (dB[..., 0] + dB[..., 2] * J.hx), 2 * (dB[..., 1] + dB[..., 2] * J.hy)
            det = a11 * a22 - a12 * a21
            if np.any(np.abs(det) <= 1e-12 * L2):
                raise ValueError("Moving Chebyshev net: two links nearly collinear (the net folds or "
                                 "squashes; shape too steep?).")
            dx = (a22 * F1 - a12 * F2) / det
            dy = (-a21 * F1 + a11 * F2) / det
            scale = np.minimum(1.0, 0.5 * L / np.maximum(np.hypot(dx, dy), 1e-300))
            q[..., 0] -= scale * dx
            q[..., 1] -= scale * dy
        else:
            raise ValueError("Moving Chebyshev net: Newton did not converge (shape too steep?).")
        n_old = _cross(Pa - Pc, Pb - Pc)
        n_new = _cross(Pn - Pb, Pn - Pa)
        bad = (np.sum(n_old * n_new, axis=-1) <= 0.0) | (np.linalg.norm(Pn - Pc, axis=-1) < 0.2 * L)
        if np.any(bad):
            at = float(t[np.nonzero(bad)[0][0]])
            raise ValueError(f"Moving Chebyshev net: the lattice folds at t = {at:.6g} s (shape too "
                             "steep or too curved for this sheet).")
        J = field.jet(q[..., 0], q[..., 1], tt)
        Pd, Pdd = _rates(Pn, J, [("dist", Pa, V[:, ii - si, jj], A[:, ii - si, jj]),
                                 ("dist", Pb, V[:, ii, jj - sj], A[:, ii, jj - sj])])
        P[:, ii, jj], V[:, ii, jj], A[:, ii, jj] = Pn, Pd, Pdd
    return P, V, A


# ---------------------------------------------------------------------------------------------
# Ground truth
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Truth:
    """What every link really does at ``T`` instants (docs/design.md frames and link order).

    Attributes
    ----------
    t_s : ndarray, shape (T,)
        Seconds.
    joints, joint_velocity, joint_acceleration : ndarray, shape (T, rows, cols, 3)
        m, m/s, m/s², world frame.
    frames : ndarray, shape (T, n_links, 3, 3)
        Sensor -> world rotation of every link (`geometry.link_frames`).
    angular_velocity : ndarray, shape (T, n_links, 3)
        rad/s, each link's sensor frame (what a gyroscope reads).
    position : ndarray, shape (T, n_links, 3)
        The chip: the link's midpoint, m, world frame.
    acceleration : ndarray, shape (T, n_links, 3)
        The chip's own acceleration, m/s², world frame (zero at rest).
    specific_force : ndarray, shape (T, n_links, 3)
        ``Rᵀ (a + (0, 0, +G0))``, m/s², sensor frame (what an accelerometer reads).
    """

    t_s: np.ndarray
    joints: np.ndarray
    joint_velocity: np.ndarray
    joint_acceleration: np.ndarray
    frames: np.ndarray
    angular_velocity: np.ndarray
    position: np.ndarray
    acceleration: np.ndarray
    specific_force: np.ndarray

    @property
    def n_times(self) -> int:
        return self.t_s.shape[0]

    @property
    def n_links(self) -> int:
        return self.frames.shape[1]

    @property
    def lattice(self) -> Lattice:
        return Lattice(self.joints.shape[1], self.joints.shape[2])

    def __getitem__(self, index) -> "Truth":
        """The instants ``index`` (an int keeps a time axis of length 1; a slice or index array)."""
        if isinstance(index, (int, np.integer)):
            index = slice(int(index), int(index) + 1 if int(index) != -1 else None)
        return Truth(**{f: getattr(self, f)[index] for f in self.__dataclass_fields__})

    @classmethod
    def concatenate(cls, parts: list["Truth"]) -> "Truth":
        return cls(**{f: np.concatenate([getattr(p, f) for p in parts]) for f in cls.__dataclass_fields__})


def truth_from_joints(t, joints: np.ndarray, velocities: np.ndarray, accelerations: np.ndarray) -> Truth:
    """Every link's truth from the joints' exact motion (module docstring).

    Parameters
    ----------
    t : ndarray, shape (T,)
    joints, velocities, accelerations : ndarray, shape (T, rows, cols, 3)
    """
    t = _times(t)
    P, V, A = (np.asarray(a, dtype=float) for a in (joints, velocities, accelerations))
    if P.ndim != 4 or P.shape[0] != t.size or P.shape[-1] != 3 or V.shape != P.shape or A.shape != P.shape:
        raise ValueError(f"Expected joints, velocities, accelerations of shape ({t.size}, rows, cols, 3), "
                         f"got {P.shape}, {V.shape}, {A.shape}.")
    R, omega = link_frames_jet(P, V)
    acc = link_midpoints(A)
    f = np.einsum("tkji,tkj->tki", R, acc + np.array([0.0, 0.0, G0]))
    return Truth(t_s=t, joints=P, joint_velocity=V, joint_acceleration=A, frames=R,
                 angular_velocity=omega, position=link_midpoints(P), acceleration=acc, specific_force=f)


# ---------------------------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------------------------

class MotionScene:
    """A moving sheet: ``joints(t_s)`` (the `shapes.Scene` protocol, one instant, built by
    `geometry.chebyshev_net` independently of the derivatives) and ``sample(t) -> Truth`` (any
    number of instants at once, with exact derivatives). Subclasses give ``_body(t)`` (the net in
    the body frame, with velocities and accelerations) and ``motion(t)`` (a `RigidJet`)."""

    rows: int
    cols: int
    link_length: float
    name: str = "scene"
    #: the scene repeats after this many seconds (None: it does not)
    period_s: float | None = None

    def motion(self, t: np.ndarray) -> RigidJet:
        return RigidJet.identity(np.size(t))

    def _body(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        raise NotImplementedError

    def _body_at(self, t_s: float) -> np.ndarray:
        raise NotImplementedError

    def joints(self, t_s: float) -> np.ndarray:
        """Joints ``(rows, cols, 3)`` at ``t_s``, metres, world frame."""
        n = self._body_at(float(t_s))
        m = self.motion(np.array([float(t_s)]))
        return m.offset[0] + n @ m.rotation[0].T

    def sample(self, t) -> Truth:
        """The truth at every instant of ``t`` (seconds, scalar or (T,))."""
        t = _times(t)
        n, nd, ndd = self._body(t)
        P, V, A = self.motion(t).apply(n, nd, ndd)
        return truth_from_joints(t, P, V, A)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, {self.rows}x{self.cols}, L={self.link_length})"


class RigidScene(MotionScene):
    """A fixed net ``base (rows, cols, 3)`` carried by ``motion(t) -> RigidJet`` (None: at rest)."""

    def __init__(self, base: np.ndarray, motion: Callable[[np.ndarray], RigidJet] | None, link_length: float,
                 name: str = "rigid", period_s: float | None = None) -> None:
        base = np.array(base, dtype=float)
        if base.ndim != 3 or base.shape[2] != 3 or min(base.shape[:2]) < 2:
            raise ValueError(f"Expected `base` to have shape (rows, cols, 3), got {base.shape}.")
        base.setflags(write=False)
        self.base = base
        self.rows, self.cols = base.shape[:2]
        self.link_length = float(link_length)
        self._motion = motion
        self.static = motion is None  #: no motion: the sheet at rest
        self.name = name
        self.period_s = period_s
        self._base_truth: Truth | None = None

    def motion(self, t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return RigidJet.identity(t.size) if self._motion is None else self._motion(t)

    def _body(self, t):
        return np.broadcast_to(self.base, (t.size,) + self.base.shape), None, None

    def _body_at(self, t_s):
        return self.base.copy()

    def sample(self, t) -> Truth:
        """As `MotionScene.sample`, from the fixed net's frames: a rigid motion ``(Q, c)`` turns
        every link's frame to ``Q R₀``, its body rate is ``R₀ᵀ Qᵀ ω``, and the chips move as the
        motion's points (the same truth as differentiating the joints, a test checks, ~10x faster)."""
        t = _times(t)
        if self._base_truth is None:
            z = np.zeros((1,) + self.base.shape)
            self._base_truth = truth_from_joints([0.0], self.base[None], z, z)
            for f in Truth.__dataclass_fields__:
                getattr(self._base_truth, f).setflags(write=False)
        b = self._base_truth
        if self.static:  # read-only views of the one instant: a sheet at rest costs nothing per sample
            return Truth(t_s=t, **{f: np.broadcast_to(getattr(b, f), (t.size,) + getattr(b, f).shape[1:])
                                   for f in Truth.__dataclass_fields__ if f != "t_s"})
        m = self.motion(t)
        P, V, A = m.apply(self.base)
        pos, _v, acc = m.apply(b.position[0])
        R = m.rotation[:, None] @ b.frames[0][None]
        w_body = np.einsum("tji,tj->ti", m.rotation, m.omega)  # Qᵀ ω
        omega = np.einsum("kji,tj->tki", b.frames[0], w_body)
        f = np.einsum("tkji,tkj->tki", R, acc + np.array([0.0, 0.0, G0]))
        return Truth(t_s=t, joints=P, joint_velocity=V, joint_acceleration=A, frames=R,
                     angular_velocity=omega, position=pos, acceleration=acc, specific_force=f)


class FieldScene(MotionScene):
    """The exact net on a moving height field (`chebyshev_net_jet`), optionally carried by a rigid
    ``motion``. ``net`` holds the net options ``origin``, ``angle``, ``shear``.

    ``periodic_from_s``: the field is exactly periodic with ``period_s`` from this time on (a wave
    once faded in), and there is no rigid motion: the net is solved at the equivalent time in the
    first period, ``t0 + (t − t0) mod period``. The truth is the same (to rounding: a test checks)
    and a long run stays where the solver converges (the wave's net solved at t > 20 s failed to
    converge, though its shape is the one of the first period)."""

    def __init__(self, field: MovingField, rows: int, cols: int, link_length: float, *,
                 motion: Callable[[np.ndarray], RigidJet] | None = None, name: str = "field",
                 period_s: float | None = None, periodic_from_s: float | None = None, **net: Any) -> None:
        if periodic_from_s is not None and (motion is not None or not (period_s and np.isfinite(period_s) and period_s > 0)):
            raise ValueError("Invalid periodic_from_s: needs a period_s > 0 and no rigid motion")
        self.periodic_from_s = periodic_from_s
        Lattice(rows, cols)
        unknown = set(net) - {"origin", "angle", "shear"}
        if unknown:
            raise ValueError(f"Invalid parameters: {', '.join(sorted(unknown))} (a moving field's net "
                             "options are origin, angle, shear)")
        self.field = field
        self.rows, self.cols, self.link_length = int(rows), int(cols), float(link_length)
        self._motion = motion
        self.net = dict(net)
        self.name = name
        self.period_s = period_s

    def motion(self, t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return RigidJet.identity(t.size) if self._motion is None else self._motion(t)

    def _wrap(self, t):
        t0 = self.periodic_from_s
        if t0 is None:
            return t
        return np.where(t > t0, t0 + np.mod(t - t0, self.period_s), t)

    def _body(self, t):
        return chebyshev_net_jet(self.field, self.rows, self.cols, self.link_length, self._wrap(t), **self.net)

    def _body_at(self, t_s):
        t_s = float(self._wrap(np.array([float(t_s)]))[0])
        return chebyshev_net(lambda x, y: self.field(x, y, t_s), self.rows, self.cols, self.link_length,
                             **self.net)


def _check_size(rows: int, cols: int, link_length: float) -> float:
    Lattice(rows, cols)
    L = float(link_length)
    if not (np.isfinite(L) and L > 0):
        raise ValueError(f"Invalid link_length: {link_length!r} (need a finite value > 0 m)")
    return _side(rows, cols, L)


def carry_scene(rows: int, cols: int, link_length: float = 0.01, *, shape: str = "cylinder",
                translation_m=(0.08, 0.06, 0.05), translation_hz=(0.9, 0.7, 1.1),
                heading_rad: float = 1.0, heading_hz: float = 0.2, roll_rad: float = 0.5,
                roll_hz: float = 0.4, pitch_rad: float = 0.4, pitch_hz: float = 0.3,
                ramp_s: float = 1.0, **shape_params: Any) -> RigidScene:
    """A curved sheet (`shapes.make_sheet` ``shape``, default a cylinder of radius S) carried and
    turned: its centre moves on a 3-D Lissajous curve, and it turns about its centre by
    ``Rz(heading) Ry(pitch) Rx(roll)``, each a sine (amplitudes in m and rad, frequencies in Hz),
    all faded in over ``ramp_s``."""
    _check_size(rows, cols, link_length)
    base = make_sheet(shape, rows, cols, link_length, **shape_params)
    tr = [Sine(a, f, ramp_s=ramp_s) for a, f in zip(translation_m, translation_hz)]
    ang = [(np.array([1.0, 0, 0]), Sine(roll_rad, roll_hz, ramp_s=ramp_s)),
           (np.array([0, 1.0, 0]), Sine(pitch_rad, pitch_hz, 0.7, ramp_s=ramp_s)),
           (np.array([0, 0, 1.0]), Sine(heading_rad, heading_hz, ramp_s=ramp_s))]

    def motion(t):
        m = RigidJet.identity(t.size)
        for axis, prof in ang:  # Rx first, then Ry, then Rz (Q = Rz Ry Rx)
            m = m.then(RigidJet.about_axis(axis, prof(t)))
        c = [p(t) for p in tr]
        return m.then(RigidJet.translation(tuple(np.stack([ci[k] for ci in c], axis=-1) for k in range(3))))

    return RigidScene(base, motion, link_length, name="carry")


def wave_scene(rows: int, cols: int, link_length: float = 0.01, *, amplitude_m: float | None = None,
               wavelength_m: float | None = None, peak_accel_mps2: float = 4.0,
               frequency_hz: float | None = None, direction: float = 0.3, ramp_s: float = 1.0,
               **net: Any) -> FieldScene:
    """A travelling bend (`TravellingWave`): amplitude S/5, wavelength 2S, and the frequency at
    which the surface's vertical acceleration peaks at ``peak_accel_mps2`` (``A (2πf)²``), unless
    ``frequency_hz`` is given. Faded in over ``ramp_s``."""
    S = _check_size(rows, cols, link_length)
    A = S / 5 if amplitude_m is None else float(amplitude_m)
    lam = 2 * S if wavelength_m is None else float(wavelength_m)
    if not (np.isfinite(A) and A > 0 and np.isfinite(peak_accel_mps2) and peak_accel_mps2 > 0):
        raise ValueError(f"Invalid wave: amplitude_m={amplitude_m!r}, peak_accel_mps2={peak_accel_mps2!r} "
                         "(need > 0)")
    f = np.sqrt(peak_accel_mps2 / A) / (2 * np.pi) if frequency_hz is None else float(frequency_hz)
    field = TravellingWave(Sine(A, 0.0, np.pi / 2, ramp_s=ramp_s), lam, f, direction)
    # faded in, the wave repeats every 1/f exactly: solved in its first period, it runs for ever
    periodic = dict(period_s=1.0 / f, periodic_from_s=float(ramp_s)) if f > 0 else {}
    return FieldScene(field, rows, cols, link_length, name="wave", **periodic, **net)


def elbow_scene(rows: int, cols: int, link_length: float = 0.01, *, bend_rad: float = 2 * np.pi / 3,
                bend_s: float = 1.0, hold_s: float = 0.5, knee_m: float | None = None,
                limb_radius_m: float | None = None, swing_rad: float = 0.35, swing_hz: float = 0.8, shoulder_m: float = 0.3,
                ramp_s: float = 1.0, **net: Any) -> FieldScene:
    """A sheet worn over an elbow (or knee) along x (`Bend`): the joint bends from 0 to
    ``bend_rad`` in ``bend_s``, holds ``hold_s``, straightens in ``bend_s``, rests ``hold_s``. The
    upper arm's side (x < 0) stays where it is: the body frame turns by θ/2 about the y axis
    through the point where the bend's two asymptotes meet (the hinge of the surface's two straight
    sides), so the upper arm's asymptote is the fixed line ``y = z = 0, x < 0`` and the forearm
    turns by θ. Meanwhile the whole arm sweeps by ``swing_rad`` at ``swing_hz`` about a vertical
    axis through the shoulder, ``shoulder_m`` behind the elbow. Defaults: knee (apex) scale
    ``knee_m`` S/4, limb radius 0.6 S."""
    S = _check_size(rows, cols, link_length)
    ell = S / 4 if knee_m is None else float(knee_m)
    r = 0.6 * S if limb_radius_m is None else float(limb_radius_m)
    if not abs(bend_rad) < np.pi:
        raise ValueError(f"Invalid bend_rad: {bend_rad!r} (need |bend| < pi)")
    pulse = Pulse(bend_s, hold_s, bend_s, hold_s, level=bend_rad, delay_s=0.0)
    field = Bend(pulse, ell, r)
    swing = Sine(swing_rad, swing_hz, ramp_s=ramp_s)

    def motion(t):
        m, md, mdd = field.slope(t)
        # body frame: shift the asymptotes' meeting point (0, 0, ℓ m) to the origin ...
        lift = np.zeros((t.size, 3))
        lift_d, lift_dd = np.zeros_like(lift), np.zeros_like(lift)
        lift[:, 2], lift_d[:, 2], lift_dd[:, 2] = -ell * m, -ell * md, -ell * mdd
        th, thd, thdd = pulse(t)
        # ... turn by θ/2 about y (the upper arm's side level again), then sweep about the shoulder
        bend = RigidJet.translation((lift, lift_d, lift_dd)).then(
            RigidJet.about_axis((0.0, 1.0, 0.0), (th / 2, thd / 2, thdd / 2)))
        return bend.then(RigidJet.about_axis((0.0, 0.0, 1.0), swing(t), point=(-shoulder_m, 0.0, 0.0)))

    return FieldScene(field, rows, cols, link_length, motion=motion, name="elbow", **net)


def tap_scene(rows: int, cols: int, link_length: float = 0.01, *, depth_m: float | None = None,
              sigma_m: float | None = None, centre=None, rise_s: float = 0.15, hold_s: float = 0.3,
              fall_s: float = 0.15, rest_s: float = 0.6, delay_s: float = 0.2, **net: Any) -> FieldScene:
    """A press on the foam that arrives and leaves fast (`Dent` on a level sheet): depth S/8 and
    width S/8 by default, centred at (0.15 S, −0.1 S), reached in ``rise_s``, held, released in
    ``fall_s``, then ``rest_s`` at rest; first after ``delay_s``."""
    S = _check_size(rows, cols, link_length)
    d = S / 8 if depth_m is None else float(depth_m)
    sig = S / 8 if sigma_m is None else float(sigma_m)
    c = (0.15 * S, -0.1 * S) if centre is None else (float(centre[0]), float(centre[1]))
    pulse = Pulse(rise_s, hold_s, fall_s, rest_s, level=d, delay_s=delay_s)
    return FieldScene(Dent(pulse, sig, c), rows, cols, link_length, name="tap", **net)


def grow_scene(rows: int, cols: int, link_length: float = 0.01, *, amplitude: float | None = None,
               sigma: float | None = None, period_s: float = 4.0, **net: Any) -> FieldScene:
    """`shapes.GrowScene` with exact kinematics (for 6/9-axis chips): a Gaussian bump of height
    ``amplitude · (1 − cos 2πt/T)/2`` (default S/4, width S/4, T = 4 s) — a `Dent` of negative depth."""
    S = _check_size(rows, cols, link_length)
    a = S / 4 if amplitude is None else float(amplitude)
    sig = S / 4 if sigma is None else float(sigma)
    if not (np.isfinite(period_s) and period_s > 0):
        raise ValueError(f"Invalid period_s: {period_s!r} (need > 0 s)")
    depth = Sine(a / 2, 1.0 / period_s, np.pi / 2, offset=-a / 2)  # -a (1 - cos)/2: the dent is a bump
    return FieldScene(Dent(depth, sig), rows, cols, link_length, name="grow", period_s=float(period_s),
                      periodic_from_s=0.0, **net)


def flat_turn_scene(rows: int, cols: int, link_length: float = 0.01, *, heading_rad: float = 1.2,
                    heading_hz: float = 0.2, slide_m=(0.06, 0.04), slide_hz=(1.0, 0.8),
                    ramp_s: float = 1.0, **net: Any) -> RigidScene:
    """A flat horizontal sheet (the paper's Case 1) turning in heading about its centre and sliding
    horizontally on a Lissajous curve; faded in over ``ramp_s``."""
    _check_size(rows, cols, link_length)
    base = flat_net(rows, cols, link_length, **net)
    head = Sine(heading_rad, heading_hz, ramp_s=ramp_s)
    sx = Sine(slide_m[0], slide_hz[0], ramp_s=ramp_s)
    sy = Sine(slide_m[1], slide_hz[1], 0.5, ramp_s=ramp_s)

    def motion(t):
        x, y = sx(t), sy(t)
        z = np.zeros(t.size)
        c = tuple(np.stack([x[k], y[k], z], axis=-1) for k in range(3))
        return RigidJet.about_axis((0.0, 0.0, 1.0), head(t)).then(RigidJet.translation(c))

    return RigidScene(base, motion, link_length, name="flat_turn")


def rest_scene(rows: int, cols: int, link_length: float = 0.01, *, shape: str = "gaussian",
               **shape_params: Any) -> RigidScene:
    """A static `shapes.make_sheet` shape that never moves (gravity only on every chip)."""
    _check_size(rows, cols, link_length)
    return RigidScene(make_sheet(shape, rows, cols, link_length, **shape_params), None, link_length,
                      name="rest")


def tumble_scene(rows: int, cols: int, link_length: float = 0.01, *, rates_hz=(0.05, 0.07, 0.11),
                 ramp_s: float = 3.0) -> RigidScene:
    """A flat sheet (on a board) turned every way: ``Rz(π sin) Ry(0.45π sin) Rx(π sin)`` at the
    slow ``rates_hz``, about its centre — every direction of a fixed field is seen in a few tens of
    seconds (magnetometer calibration)."""
    _check_size(rows, cols, link_length)
    base = flat_net(rows, cols, link_length)
    profs = [((1.0, 0, 0), Sine(np.pi, rates_hz[0], ramp_s=ramp_s)),
             ((0, 1.0, 0), Sine(0.45 * np.pi, rates_hz[2], ramp_s=ramp_s)),
             ((0, 0, 1.0), Sine(np.pi, rates_hz[1], ramp_s=ramp_s))]

    def motion(t):
        m = RigidJet.identity(t.size)
        for axis, p in profs:
            m = m.then(RigidJet.about_axis(axis, p(t)))
        return m

    return RigidScene(base, motion, link_length, name="tumble")


def board_scene(rows: int, cols: int, link_length: float = 0.01, **params: Any) -> RigidScene:
    """The calibration board (`board.BoardPoseScene`, its parameters) with the exact motion of its
    turns (`board.BoardPoseScene.rotation_jet`)."""
    from .board import BoardPoseScene  # board builds on shapes; imported late like shapes does

    board = BoardPoseScene(rows, cols, link_length, **params)

    def motion(t):
        R, w, wd = board.rotation_jet(t)
        z = np.zeros((t.size, 3))
        return RigidJet(R, w, wd, z, z, z)

    scene = RigidScene(flat_net(rows, cols, link_length), motion, link_length, name="board",
                       period_s=board.period_s)
    scene.board = board
    return scene


def _tap_period(params: dict) -> float:
    return sum(params.get(k, d) for k, d in (("rise_s", 0.15), ("hold_s", 0.3), ("fall_s", 0.15),
                                             ("rest_s", 0.6)))


@dataclass(frozen=True)
class MotionSceneSpec:
    """A built-in moving scene: its one-line description and factory
    ``factory(rows, cols, link_length, **params)``."""

    name: str
    description: str
    factory: Callable[..., MotionScene]
    moving: bool = True  #: True for the scenes of issue 30's targets (every moving scene)


MOTION_SCENES: dict[str, MotionSceneSpec] = {s.name: s for s in [
    MotionSceneSpec("carry", "a curved sheet carried and turned (rigid motion)", carry_scene),
    MotionSceneSpec("wave", "a travelling bend (the sheet waved)", wave_scene),
    MotionSceneSpec("elbow", "a sheet over an elbow bending 0 -> 120 deg in 1 s, the arm sweeping",
                    elbow_scene),
    MotionSceneSpec("tap", "a press on the foam arriving and leaving in 0.15 s", tap_scene),
    MotionSceneSpec("flat_turn", "a flat horizontal sheet turning in heading and sliding",
                    flat_turn_scene),
    MotionSceneSpec("rest", "a static shape (shape=...) at rest", rest_scene, moving=False),
    MotionSceneSpec("grow", "a Gaussian bump rising and falling (shapes.GrowScene, exact kinematics)", grow_scene,
                    moving=False),
    MotionSceneSpec("tumble", "a flat sheet turned every way (magnetometer calibration)",
                    tumble_scene, moving=False),
    MotionSceneSpec("board", "the calibration board turned through held poses", board_scene,
                    moving=False),
]}


def make_motion_scene(name: str, rows: int, cols: int, link_length: float = 0.01,
                      **params: Any) -> MotionScene:
    """A moving scene by name (`MOTION_SCENES`), ``params`` passed to its factory."""
    spec = MOTION_SCENES.get(name)
    if spec is None:
        raise ValueError(f"Unknown motion scene {name!r}; known: {', '.join(MOTION_SCENES)}")
    try:
        return spec.factory(rows, cols, link_length, **params)
    except TypeError as exc:
        raise ValueError(f"Invalid parameters for motion scene {name!r}: {exc}") from exc


def sample_times(duration_s: float, rate_hz: float = 145.0, *, start_s: float = 0.0,
                 jitter_s: float = 0.0, rng: np.random.Generator | None = None) -> np.ndarray:
    """SYNC instants: ``start_s + k / rate_hz`` for ``k = 0 .. ⌊duration · rate⌋ − 1``, each moved
    by uniform jitter in ``±jitter_s`` (a host's timer; needs ``rng``), kept increasing."""
    if not (np.isfinite(duration_s) and duration_s > 0 and np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"Invalid duration_s={duration_s!r} / rate_hz={rate_hz!r} (need > 0)")
    n = int(np.floor(duration_s * rate_hz + 1e-9))
    t = start_s + np.arange(n) / rate_hz
    if jitter_s:
        if not (0 <= jitter_s < 0.5 / rate_hz):
            raise ValueError(f"Invalid jitter_s: {jitter_s!r} (need 0 <= jitter < half a period)")
        if rng is None:
            raise ValueError("jitter_s > 0 needs a seeded `rng`")
        t = t + rng.uniform(-jitter_s, jitter_s, n)
    return t
