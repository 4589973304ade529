"""The calibration scene: the sheet clamped flat on a rigid board that a person turns through a
sequence of poses, holding each still (docs/calibration.md).

`BoardPoseScene` holds pose ``i`` for ``hold_s`` seconds, then turns the board to pose ``i + 1``
over ``move_s`` seconds (spherical interpolation of the board's orientation), and starts again
after the last pose. Pose ``i`` is the board orientation ``R_i`` (board -> world) whose gravity
direction in the board's frame, ``R_iᵀ (0, 0, 1)``, is ``directions[i]`` turned by a small seeded
random rotation (``jitter_rad`` standard deviation per axis: nobody sets a board down exactly).
The board's frame is the flat sheet's: i-links along its x, j-links along its y, top face +z.

The default directions are the twelve poses of `protocol.frames.BOARD_POSES` (six faces, then six
45° tilts), in its order.

The rotations are numpy's (`protocol.rotations`): scipy.spatial
(`Slerp`, `Rotation.from_matrix`), which they replace to ~1e-15, cost ~0.7 s of CPU at the start of
every process that makes a board sheet (`capsheet virtual --shape board`, the calibration's tests).

>>> s = BoardPoseScene(3, 3, hold_s=2.0, move_s=1.0, jitter_rad=0.0)
>>> s.pose_at(0.5), s.pose_at(2.5), s.pose_at(3.1)
(0, None, 1)
>>> from virtual_sheet.geometry import ideal_readings
>>> np.round(ideal_readings(s.joints(3.5))[0], 6).tolist()  # top down: z reads -g
[0.0, 0.0, -9.80665]
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from protocol.constants import G0
from protocol.frames import BOARD_POSES
from protocol.lattice import Lattice
from .geometry import flat_net
from protocol.rotations import matrix_rotvecs, rotvec_matrices

__all__ = ["BoardPoseScene", "DEFAULT_DIRECTIONS", "board_rotation"]

#: gravity directions in the board's frame, in `protocol.frames.BOARD_POSES` order
DEFAULT_DIRECTIONS: tuple[tuple[float, float, float], ...] = tuple(p[2] for p in BOARD_POSES)


def board_rotation(direction) -> np.ndarray:
    """The smallest rotation ``R`` (board -> world) with ``Rᵀ (0, 0, 1) = direction`` (unit-normalised);
    a half turn about x for ``direction = (0, 0, -1)``."""
    u = np.asarray(direction, dtype=float)
    if u.shape != (3,) or not np.all(np.isfinite(u)) or np.linalg.norm(u) == 0:
        raise ValueError(f"Invalid direction: {direction!r} (need 3 finite numbers, not all 0)")
    u = u / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(u, z)
    s, c = np.linalg.norm(axis), float(u @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return rotvec_matrices((axis / s * np.arctan2(s, c))[None])[0]


@dataclass(frozen=True)
class BoardPoseScene:
    """A flat sheet on a board turned through static poses (module docstring).

    Parameters
    ----------
    rows, cols : int
        Joints.
    link_length : float
        Metres.
    directions : sequence of 3-vectors, optional
        Gravity direction in the board's frame for each pose (default `DEFAULT_DIRECTIONS`).
    hold_s, move_s : float
        Seconds each pose is held still, and spent turning to the next.
    jitter_rad : float
        Standard deviation of the random error of each pose's orientation, radians per axis.
    seed : int
        Seed of that error (``Generator(MT19937(seed))``).
    """

    rows: int
    cols: int
    link_length: float = 0.01
    directions: tuple = DEFAULT_DIRECTIONS
    hold_s: float = 6.0
    move_s: float = 1.0
    jitter_rad: float = 0.03
    seed: int = 0
    _R: np.ndarray = field(init=False, repr=False)
    _flat: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        Lattice(self.rows, self.cols)
        for name in ("hold_s", "move_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"Invalid {name}: {v!r} (need > 0 s)")
        if not (np.isfinite(self.jitter_rad) and 0 <= self.jitter_rad < 0.5):
            raise ValueError(f"Invalid jitter_rad: {self.jitter_rad!r} (need 0 <= jitter < 0.5 rad)")
        d = np.asarray(self.directions, dtype=float)
        if d.ndim != 2 or d.shape[1] != 3 or d.shape[0] < 1:
            raise ValueError(f"Invalid directions: expected shape (n_poses, 3), got {d.shape}")
        g = np.random.Generator(np.random.MT19937(int(self.seed)))
        jit = rotvec_matrices(g.normal(0.0, self.jitter_rad, d.shape))
        R = np.array([board_rotation(u) for u in d]) @ jit  # board -> world
        object.__setattr__(self, "directions", tuple(tuple(float(x) for x in u) for u in d))
        object.__setattr__(self, "_R", R)
        object.__setattr__(self, "_flat", flat_net(self.rows, self.cols, self.link_length))

    @property
    def n_poses(self) -> int:
        return len(self.directions)

    @property
    def period_s(self) -> float:
        """One pass through every pose, seconds."""
        return self.n_poses * (self.hold_s + self.move_s)

    def pose_at(self, t_s: float) -> int | None:
        """Index of the pose held at ``t_s``, or None while the board is turning."""
        i, tau = divmod(float(t_s) % self.period_s, self.hold_s + self.move_s)
        return int(i) if tau < self.hold_s else None

    def orientation(self, t_s: float) -> np.ndarray:
        """Board -> world rotation at ``t_s``, (3, 3): held, or on the way from pose ``i`` to ``j``
        ``R_i Exp(w v)``, ``v`` the rotation vector of ``R_iᵀ R_j`` (a spherical interpolation)."""
        i, tau = divmod(float(t_s) % self.period_s, self.hold_s + self.move_s)
        i = int(i)
        if tau < self.hold_s:
            return self._R[i].copy()
        w = (tau - self.hold_s) / self.move_s
        w = 0.5 - 0.5 * np.cos(np.pi * w)  # start and stop smoothly
        j = (i + 1) % self.n_poses
        v = matrix_rotvecs(self._R[i].T @ self._R[j])
        return self._R[i] @ rotvec_matrices(w * v)

    def rotation_jet(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`orientation` at every instant of ``t`` (seconds, (T,)) with its exact rates.

        During a turn from pose ``i`` to ``j`` the board is ``R_i Exp(w(τ) v)``, ``v`` the rotation
        vector of ``R_iᵀ R_j`` and ``w = (1 − cos πτ)/2`` (what `Slerp` computes), so its angular
        velocity is ``ẇ v`` in the board's frame and its angular acceleration ``ẅ v``. (`orientation`
        computes the same.)

        Returns
        -------
        rotation : ndarray, shape (T, 3, 3)
            Board -> world.
        omega, omega_dot : ndarray, shape (T, 3)
            rad/s and rad/s², world frame.
        """
        t = np.atleast_1d(np.asarray(t, dtype=float))
        step = self.hold_s + self.move_s
        i, tau = np.divmod(np.mod(t, self.period_s), step)
        i = i.astype(int) % self.n_poses
        j = (i + 1) % self.n_poses
        v = matrix_rotvecs(np.transpose(self._R[i], (0, 2, 1)) @ self._R[j])
        moving = tau >= self.hold_s
        x = np.where(moving, (tau - self.hold_s) / self.move_s, 0.0)
        w = np.where(moving, 0.5 - 0.5 * np.cos(np.pi * x), 0.0)
        wd = np.where(moving, 0.5 * np.pi * np.sin(np.pi * x) / self.move_s, 0.0)
        wdd = np.where(moving, 0.5 * np.pi ** 2 * np.cos(np.pi * x) / self.move_s ** 2, 0.0)
        R = self._R[i] @ rotvec_matrices(w[:, None] * v)
        return R, np.einsum("tij,tj->ti", R, wd[:, None] * v), np.einsum("tij,tj->ti", R, wdd[:, None] * v)

    def gravity_in_board(self, pose: int) -> np.ndarray:
        """Specific force of gravity in the board's frame in pose ``pose`` (truth), m/s², (3,)."""
        return self._R[pose].T @ np.array([0.0, 0.0, G0])

    def joints(self, t_s: float) -> np.ndarray:
        """Joints ``(rows, cols, 3)``, metres, world frame: the flat net turned by the board."""
        return self._flat @ self.orientation(t_s).T
