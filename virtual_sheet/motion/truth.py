"""Ground truth of a moving sheet (`Truth`, `truth_from_joints`) and the scene protocol every moving
scene follows (`MotionScene`): see `virtual_sheet.motion`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocol.constants import G0
from protocol.lattice import Lattice
from ..geometry import link_frames_jet, link_midpoints
from ._jets import RigidJet, times

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
    t = times(t)
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
        t = times(t)
        n, nd, ndd = self._body(t)
        P, V, A = self.motion(t).apply(n, nd, ndd)
        return truth_from_joints(t, P, V, A)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, {self.rows}x{self.cols}, L={self.link_length})"
