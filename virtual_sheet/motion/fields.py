"""Field scenes: the exact net on a height field that changes with time (`chebyshev_net_jet`,
`FieldScene`), and the built-in scenes of that kind (wave, elbow, tap, grow): see
`virtual_sheet.motion`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

import numpy as np

from protocol.lattice import Lattice
from ..geometry import cross3, chebyshev_net, compass_diagonals
from ._jets import Profile, Pulse, RigidJet, Sine, check_size, times
from .truth import MotionScene

_NEWTON_MAX_ITER = 60
_TOL = 1e-13  # |F| <= _TOL L² (as geometry.chebyshev_net): lengths to ~5e-14 relative

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
    t = times(t)
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
        n_old = cross3(Pa - Pc, Pb - Pc)
        n_new = cross3(Pn - Pb, Pn - Pa)
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

def wave_scene(rows: int, cols: int, link_length: float = 0.01, *, amplitude_m: float | None = None,
               wavelength_m: float | None = None, peak_accel_mps2: float = 4.0,
               frequency_hz: float | None = None, direction: float = 0.3, ramp_s: float = 1.0,
               **net: Any) -> FieldScene:
    """A travelling bend (`TravellingWave`): amplitude S/5, wavelength 2S, and the frequency at
    which the surface's vertical acceleration peaks at ``peak_accel_mps2`` (``A (2πf)²``), unless
    ``frequency_hz`` is given. Faded in over ``ramp_s``."""
    S = check_size(rows, cols, link_length)
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
    S = check_size(rows, cols, link_length)
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
    S = check_size(rows, cols, link_length)
    d = S / 8 if depth_m is None else float(depth_m)
    sig = S / 8 if sigma_m is None else float(sigma_m)
    c = (0.15 * S, -0.1 * S) if centre is None else (float(centre[0]), float(centre[1]))
    pulse = Pulse(rise_s, hold_s, fall_s, rest_s, level=d, delay_s=delay_s)
    return FieldScene(Dent(pulse, sig, c), rows, cols, link_length, name="tap", **net)


def grow_scene(rows: int, cols: int, link_length: float = 0.01, *, amplitude: float | None = None,
               sigma: float | None = None, period_s: float = 4.0, **net: Any) -> FieldScene:
    """`shapes.GrowScene` with exact kinematics (for 6/9-axis chips): a Gaussian bump of height
    ``amplitude · (1 − cos 2πt/T)/2`` (default S/4, width S/4, T = 4 s) — a `Dent` of negative depth."""
    S = check_size(rows, cols, link_length)
    a = S / 4 if amplitude is None else float(amplitude)
    sig = S / 4 if sigma is None else float(sigma)
    if not (np.isfinite(period_s) and period_s > 0):
        raise ValueError(f"Invalid period_s: {period_s!r} (need > 0 s)")
    depth = Sine(a / 2, 1.0 / period_s, np.pi / 2, offset=-a / 2)  # -a (1 - cos)/2: the dent is a bump
    return FieldScene(Dent(depth, sig), rows, cols, link_length, name="grow", period_s=float(period_s),
                      periodic_from_s=0.0, **net)
