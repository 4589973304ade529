"""Sheets that move, with exact kinematics: every link's true orientation, angular velocity and
specific force at any instant (the simulator that moves).

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
level      a level sheet whose cells are sheared by 0.2 rad, lying still (``heading_rad`` 0);
level_turn the same turning about the vertical (±69° at 0.2 Hz): the paper's Case 1 as a sheet
           laid on a table is — its shear seen by magnetometers only
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

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ._jets import Constant, Profile, Pulse, RigidJet, Sine
from .fields import (Bend, Dent, FieldScene, HeightJet, TravellingWave, chebyshev_net_jet,
                     elbow_scene, grow_scene, tap_scene, wave_scene)
from .fields import MovingField  # noqa: F401 (the base of the height fields, importable as before)
from .rigid import (RigidScene, board_scene, carry_scene, flat_turn_scene, level_scene, level_turn_scene,
                    rest_scene, tumble_scene)
from .truth import MotionScene, Truth, truth_from_joints

__all__ = ["Profile", "Constant", "Sine", "Pulse", "RigidJet", "HeightJet", "TravellingWave",
           "Bend", "Dent", "chebyshev_net_jet", "Truth", "truth_from_joints", "MotionScene",
           "RigidScene", "FieldScene", "carry_scene", "wave_scene", "elbow_scene", "tap_scene",
           "flat_turn_scene", "level_scene", "level_turn_scene", "rest_scene", "tumble_scene",
           "board_scene", "MOTION_SCENES", "make_motion_scene", "sample_times"]


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
    #: True for the scenes of the accelerometer-and-gyroscope targets (every moving scene; the
    #: level sheets are magnetometers' scenes: their shear is unobservable without them)
    moving: bool = True


MOTION_SCENES: dict[str, MotionSceneSpec] = {s.name: s for s in [
    MotionSceneSpec("carry", "a curved sheet carried and turned (rigid motion)", carry_scene),
    MotionSceneSpec("wave", "a travelling bend (the sheet waved)", wave_scene),
    MotionSceneSpec("elbow", "a sheet over an elbow bending 0 -> 120 deg in 1 s, the arm sweeping",
                    elbow_scene),
    MotionSceneSpec("tap", "a press on the foam arriving and leaving in 0.15 s", tap_scene),
    MotionSceneSpec("flat_turn", "a flat horizontal sheet turning in heading and sliding",
                    flat_turn_scene),
    MotionSceneSpec("level_turn", "a level sheet with sheared cells (0.2 rad) turning about the vertical",
                    level_turn_scene, moving=False),
    MotionSceneSpec("level", "a level sheet with sheared cells (0.2 rad) lying still", level_scene,
                    moving=False),
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
