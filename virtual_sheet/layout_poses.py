"""The layout-learning scene: the sheet taken through the poses of ``capsheet layout learn`` on a timer.

`LayoutPoseScene` holds each pose of `POSES` for ``hold_s`` seconds, moves to the next over
``move_s`` seconds and starts again after the last, so a host that joins at any moment meets the
whole procedure within one pass (docs/host.md, "Learning the layout"). Every instant is an exact
net (all links of length L): a level flat net, turned rigidly and bent into a cylinder.

* ``flat``: lying level, top face up.
* ``tilt``: a ramp, the row-(rows-1) edge raised by ``tilt_rad``.
* ``hump_i``: the row-0 and row-(rows-1) edges pushed towards each other, the sheet rising in one
  hump whose ridge runs along j: the slope along i falls from ``hump_rad`` at row 0 to
  ``-hump_rad`` at the last row (an arc).
* ``hump_j``: the same across the columns.

Each pose is turned by a small seeded random rotation (``jitter_rad`` per axis: nobody lays a sheet
down exactly level), and during a move the parameters slide from one pose to the next, those that
fall first, then those that rise (so a hump never meets the other hump: every instant is one
cylinder, turned).

>>> s = LayoutPoseScene(3, 4, hold_s=2.0, move_s=1.0, jitter_rad=0.0)
>>> s.pose_at(0.5), s.pose_at(2.5), s.pose_at(3.5), s.period_s
('flat', None, 'tilt', 12.0)
>>> from virtual_sheet.geometry import ideal_readings
>>> r = ideal_readings(s.joints(3.5)) / 9.80665   # the ramp: i-links pitch up, j-links roll
>>> np.round(r[0], 3).tolist(), np.round(r[8], 3).tolist()
([0.479, 0.0, 0.878], [0.0, -0.479, 0.878])
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from protocol.lattice import Lattice
from protocol.rotations import rotvec_matrices
from .geometry import flat_net

__all__ = ["LayoutPoseScene", "POSES"]

#: the poses of the procedure, in order (host.analysis.layout.learn.PROCEDURE names the same)
POSES = ("flat", "tilt", "hump_i", "hump_j")


def _profile(n_joints: int, amp: float, L: float) -> tuple[np.ndarray, np.ndarray]:
    """Arc length positions of ``n_joints`` joints along a curve whose slope angle falls linearly
    from ``amp`` to ``-amp`` (link k at angle ``amp (1 - 2 (k + 1/2) / (n-1))``): (horizontal, height)."""
    k = np.arange(n_joints - 1)
    theta = amp * (1.0 - 2.0 * (k + 0.5) / (n_joints - 1))
    x = np.concatenate([[0.0], np.cumsum(L * np.cos(theta))])
    z = np.concatenate([[0.0], np.cumsum(L * np.sin(theta))])
    return x - x.mean(), z


def _rot_y(a: float) -> np.ndarray:
    """Rotation that raises +x towards +z by ``a``."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


@dataclass(frozen=True)
class LayoutPoseScene:
    """The poses of layout learning on a timer (module docstring).

    Parameters
    ----------
    rows, cols : int
        Joints.
    link_length : float
        Metres.
    hold_s, move_s : float
        Seconds each pose is held, and spent moving to the next.
    tilt_rad : float
        The ramp's slope, radians.
    hump_rad : float
        The humps' slope at their edges, radians.
    jitter_rad : float
        Standard deviation of each pose's small random turn, radians per axis.
    seed : int
        Seed of those turns (``Generator(MT19937(seed))``).
    """

    rows: int
    cols: int
    link_length: float = 0.01
    hold_s: float = 3.0
    move_s: float = 1.0
    tilt_rad: float = 0.5
    hump_rad: float = 1.0
    jitter_rad: float = 0.02
    seed: int = 0
    _params: np.ndarray = field(init=False, repr=False)
    _jitter: np.ndarray = field(init=False, repr=False)
    _flat: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        Lattice(self.rows, self.cols)
        for name in ("hold_s", "move_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"Invalid {name}: {v!r} (need > 0 s)")
        for name in ("tilt_rad", "hump_rad"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0 < v < np.pi / 2):
                raise ValueError(f"Invalid {name}: {v!r} (need 0 < {name} < pi/2)")
        if not (np.isfinite(self.jitter_rad) and 0 <= self.jitter_rad < 0.2):
            raise ValueError(f"Invalid jitter_rad: {self.jitter_rad!r} (need 0 <= jitter < 0.2 rad)")
        # (tilt, hump along i, hump along j) of each pose
        params = np.array([[0, 0, 0], [self.tilt_rad, 0, 0], [0, self.hump_rad, 0], [0, 0, self.hump_rad]], float)
        g = np.random.Generator(np.random.MT19937(int(self.seed)))
        jitter = g.normal(0.0, self.jitter_rad, (len(POSES), 3))
        object.__setattr__(self, "_params", params)
        object.__setattr__(self, "_jitter", jitter)
        object.__setattr__(self, "_flat", flat_net(self.rows, self.cols, self.link_length))

    @property
    def period_s(self) -> float:
        """One pass through every pose, seconds."""
        return len(POSES) * (self.hold_s + self.move_s)

    def pose_at(self, t_s: float) -> str | None:
        """The pose held at ``t_s``, or None while moving."""
        i, tau = divmod(float(t_s) % self.period_s, self.hold_s + self.move_s)
        return POSES[int(i)] if tau < self.hold_s else None

    def _state(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        i, tau = divmod(float(t_s) % self.period_s, self.hold_s + self.move_s)
        i = int(i) % len(POSES)
        if tau < self.hold_s:
            return self._params[i], self._jitter[i]
        j = (i + 1) % len(POSES)
        w = (tau - self.hold_s) / self.move_s
        a, b = self._params[i], self._params[j]
        # what falls moves in the first half, what rises in the second
        fall = np.clip(2 * w, 0, 1)
        rise = np.clip(2 * w - 1, 0, 1)
        p = np.where(b < a, a + (b - a) * fall, a + (b - a) * rise)
        jit = self._jitter[i] + (self._jitter[j] - self._jitter[i]) * w
        return p, jit

    def joints(self, t_s: float) -> np.ndarray:
        """Joints ``(rows, cols, 3)``, metres, world frame, at ``t_s``."""
        (tilt, hi, hj), jit = self._state(t_s)
        P = self._flat.copy()
        L = self.link_length
        if hi > 0:
            x, z = _profile(self.rows, hi, L)
            P[:, :, 0] = x[:, None]
            P[:, :, 2] = z[:, None]
        elif hj > 0:
            y, z = _profile(self.cols, hj, L)
            P[:, :, 1] = y[None, :]
            P[:, :, 2] = z[None, :]
        R = rotvec_matrices(jit) @ _rot_y(tilt)
        return P @ R.T


class PosesThenScene:
    """The layout poses until a switch, then another scene: what ``capsheet demo --learn-layout``
    runs (the poses while the host learns the layout, then the demo's own shape, whose estimate is
    scored). ``joints(t)`` is ``poses.joints(t)`` before `switch_at_s` and ``then.joints(t)`` from it;
    the switch is set once, in the sheet's process and in the demo's copy alike, at a time still to
    come, so every instant keeps one answer. No ``period_s``: the sheet solves each step once, in
    time order."""

    def __init__(self, poses: LayoutPoseScene, then) -> None:
        self.poses, self.then = poses, then
        self.rows, self.cols, self.link_length = poses.rows, poses.cols, poses.link_length
        self.switch_at_s = float("inf")
        self._memo: list[dict] = [{}, {}]  # per scene: step -> joints, one period of a periodic scene
        self._rate: float | None = None

    def precompute(self, rate_hz: float) -> int:
        """Solve one period of each periodic scene at ``rate_hz`` steps now (a scene such as a growing
        bump costs milliseconds a step, which a sheet answering SYNC at 145 Hz should not spend
        live); returns how many steps."""
        self._rate = float(rate_hz)
        n_all = 0
        for scene, memo in zip((self.poses, self.then), self._memo):
            period = getattr(scene, "period_s", None)
            if period is None or abs(period * rate_hz - round(period * rate_hz)) > 1e-9:
                continue
            for k in range(int(round(period * rate_hz))):
                memo[k] = scene.joints(k / rate_hz)
            n_all += len(memo)
        return n_all

    def switch(self, at_s: float) -> None:
        """From ``at_s`` on (the sheet's clock, seconds), the other scene."""
        if self.switch_at_s != float("inf"):
            raise ValueError(f"already switched at {self.switch_at_s:g} s")
        self.switch_at_s = float(at_s)

    def joints(self, t_s: float) -> np.ndarray:
        k = 0 if t_s < self.switch_at_s else 1
        memo = self._memo[k]
        if memo and self._rate is not None:
            x = t_s * self._rate
            if abs(x - round(x)) < 1e-6:
                return memo[int(round(x)) % len(memo)].copy()
        return (self.poses, self.then)[k].joints(t_s)
