"""Time profiles and rigid motions with exact first and second derivatives, the building blocks of
every moving scene (`virtual_sheet.motion`), and the checks the scenes share."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocol.lattice import Lattice
from ..geometry import cross3

def times(t) -> np.ndarray:
    t = np.atleast_1d(np.asarray(t, dtype=float))
    if t.ndim != 1 or not np.all(np.isfinite(t)):
        raise ValueError(f"Expected `t` to be finite seconds, a scalar or shape (T,), got shape {t.shape}.")
    return t


def _side(rows: int, cols: int, link_length: float) -> float:
    return max(max(rows, cols) - 1, 2) * float(link_length)

def check_size(rows: int, cols: int, link_length: float) -> float:
    Lattice(rows, cols)
    L = float(link_length)
    if not (np.isfinite(L) and L > 0):
        raise ValueError(f"Invalid link_length: {link_length!r} (need a finite value > 0 m)")
    return _side(rows, cols, L)


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
        cd = -cross3(w, Qp)
        cdd = -(cross3(wd, Qp) + cross3(w, cross3(w, Qp)))
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
            omega_dot=wdo + np.einsum("tij,tj->ti", Qo, self.omega_dot) + cross3(wo, Qw),
            offset=outer.offset + Qc,
            velocity=outer.velocity + cross3(wo, Qc) + Qcd,
            acceleration=(outer.acceleration + cross3(wdo, Qc) + cross3(wo, cross3(wo, Qc))
                          + 2 * cross3(wo, Qcd) + np.einsum("tij,tj->ti", Qo, self.acceleration)))

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
        v = self.velocity[:, None, :] + cross3(w, Qn)
        a = self.acceleration[:, None, :] + cross3(wd, Qn) + cross3(w, cross3(w, Qn))
        if nd is not None:
            Qnd = np.einsum("tij,tkj->tki", self.rotation, np.asarray(nd, dtype=float).reshape(T, -1, 3))
            v = v + Qnd
            a = a + 2 * cross3(w, Qnd)
        if ndd is not None:
            a = a + np.einsum("tij,tkj->tki", self.rotation, np.asarray(ndd, dtype=float).reshape(T, -1, 3))
        return p.reshape(shape), v.reshape(shape), a.reshape(shape)
