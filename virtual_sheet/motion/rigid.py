"""Rigid scenes: a fixed net carried and turned by an exact rigid motion (`RigidScene`), and the
built-in scenes of that kind (carry, flat_turn, rest, tumble, board): see `virtual_sheet.motion`."""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from protocol.constants import G0
from ..shapes import flat_net, make_sheet
from ._jets import RigidJet, Sine, check_size, times
from .truth import MotionScene, Truth, truth_from_joints

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
        t = times(t)
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

def carry_scene(rows: int, cols: int, link_length: float = 0.01, *, shape: str = "cylinder",
                translation_m=(0.08, 0.06, 0.05), translation_hz=(0.9, 0.7, 1.1),
                heading_rad: float = 1.0, heading_hz: float = 0.2, roll_rad: float = 0.5,
                roll_hz: float = 0.4, pitch_rad: float = 0.4, pitch_hz: float = 0.3,
                ramp_s: float = 1.0, **shape_params: Any) -> RigidScene:
    """A curved sheet (`shapes.make_sheet` ``shape``, default a cylinder of radius S) carried and
    turned: its centre moves on a 3-D Lissajous curve, and it turns about its centre by
    ``Rz(heading) Ry(pitch) Rx(roll)``, each a sine (amplitudes in m and rad, frequencies in Hz),
    all faded in over ``ramp_s``."""
    check_size(rows, cols, link_length)
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

def flat_turn_scene(rows: int, cols: int, link_length: float = 0.01, *, heading_rad: float = 1.2,
                    heading_hz: float = 0.2, slide_m=(0.06, 0.04), slide_hz=(1.0, 0.8),
                    ramp_s: float = 1.0, **net: Any) -> RigidScene:
    """A flat horizontal sheet (the paper's Case 1) turning in heading about its centre and sliding
    horizontally on a Lissajous curve; faded in over ``ramp_s``."""
    check_size(rows, cols, link_length)
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


def level_scene(rows: int, cols: int, link_length: float = 0.01, *, shear: float = 0.2,
                heading_rad: float = 0.0, heading_hz: float = 0.2, ramp_s: float = 1.0,
                **net: Any) -> RigidScene:
    """A level sheet whose cells are sheared by ``shear`` rad (0.2: the paper's Case 1 as a sheet
    laid on a table is), still (``heading_rad`` 0) or turning about the vertical through its
    centre by ``heading_rad`` at ``heading_hz``, faded in over ``ramp_s``. Accelerometers alone
    see a level sheet's tilt only, not its shear; magnetometers see each link's heading."""
    if not abs(shear) < np.pi / 2:
        raise ValueError(f"Invalid shear: {shear!r} rad (need |shear| < pi/2)")
    scene = flat_turn_scene(rows, cols, link_length, heading_rad=heading_rad, heading_hz=heading_hz,
                            slide_m=(0.0, 0.0), ramp_s=ramp_s, shear=shear, **net)
    scene.name = "level" if heading_rad == 0 else "level_turn"
    return scene


def level_turn_scene(rows: int, cols: int, link_length: float = 0.01, *, heading_rad: float = 1.2,
                     **params: Any) -> RigidScene:
    """`level_scene` turning: ±69° about the vertical at 0.2 Hz."""
    return level_scene(rows, cols, link_length, heading_rad=heading_rad, **params)


def rest_scene(rows: int, cols: int, link_length: float = 0.01, *, shape: str = "gaussian",
               **shape_params: Any) -> RigidScene:
    """A static `shapes.make_sheet` shape that never moves (gravity only on every chip)."""
    check_size(rows, cols, link_length)
    return RigidScene(make_sheet(shape, rows, cols, link_length, **shape_params), None, link_length,
                      name="rest")


def tumble_scene(rows: int, cols: int, link_length: float = 0.01, *, rates_hz=(0.05, 0.07, 0.11),
                 ramp_s: float = 3.0) -> RigidScene:
    """A flat sheet (on a board) turned every way: ``Rz(π sin) Ry(0.45π sin) Rx(π sin)`` at the
    slow ``rates_hz``, about its centre — every direction of a fixed field is seen in a few tens of
    seconds (magnetometer calibration)."""
    check_size(rows, cols, link_length)
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
    from ..board import BoardPoseScene  # board builds on shapes; imported late like shapes does

    board = BoardPoseScene(rows, cols, link_length, **params)

    def motion(t):
        R, w, wd = board.rotation_jet(t)
        z = np.zeros((t.size, 3))
        return RigidJet(R, w, wd, z, z, z)

    scene = RigidScene(flat_net(rows, cols, link_length), motion, link_length, name="board",
                       period_s=board.period_s)
    scene.board = board
    return scene
