"""The sensor frame's conventions, defined once (docs/design.md §4): roll and pitch from a
reading (paper eq. 2) and the calibration board's poses.

Pure computation on arrays (numpy, no I/O), so the simulator, the host and the science
(host/analysis) all import it; gravity's value is `protocol.constants.G0`.

>>> import numpy as np
>>> a, b = roll_pitch(np.array([[0.0, 0.0, 9.80665], [-9.80665, 0.0, 0.0]]))
>>> a.tolist(), (b.round(6) + 0.0).tolist()
([0.0, 0.0], [0.0, 1.570796])
>>> BOARD_POSES[1][:2], BOARD_POSES[1][2]
(('top down', 'board flat, top face down'), (0.0, 0.0, -1.0))
"""

from __future__ import annotations

import numpy as np

__all__ = ["roll_pitch", "angles_of", "BOARD_POSES"]


def roll_pitch(readings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Roll α and pitch β of every link from its reading, closed form (paper eq. 2).

    With ``R = Rz(γ) Ry(β) Rx(α)`` (sensor -> world) the reading is the specific force
    ``Rᵀ (0, 0, +g) = g (−sin β, cos β sin α, cos β cos α)`` — the paper's ``s`` with the sign of
    docs/design.md (reading = −s). Hence ``α = atan2(r_y, r_z)`` and ``β = atan2(−r_x, hypot(r_y, r_z))``.
    The magnitude of the reading does not matter (scale errors common to the three axes cancel).

    Parameters
    ----------
    readings : ndarray, shape (n_links, 3)
        Specific force in m/s² (or any common unit, e.g. counts minus offset), sensor frame.

    Returns
    -------
    alpha : ndarray, shape (n_links,)
        Roll about the link (sensor x), radians, in (−π, π].
    beta : ndarray, shape (n_links,)
        Pitch, radians, in [−π/2, π/2]; positive when the link points downwards.
    """
    r = np.asarray(readings, dtype=float)
    if r.ndim != 2 or r.shape[1] != 3:
        raise ValueError(f"Expected `readings` to have shape (n_links, 3), got {r.shape}.")
    return angles_of(r)


def angles_of(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`roll_pitch` without the checks, over the last axis of ``r`` (..., 3)."""
    return np.arctan2(r[..., 1], r[..., 2]), np.arctan2(-r[..., 0], np.hypot(r[..., 1], r[..., 2]))


#: The calibration board's suggested poses, in order (docs/calibration.md): (name, instruction,
#: gravity's specific force direction in the board's frame: what a chip with x along the board's
#: x reads, normalised). The six faces then six tilts of 45° towards the edges; the twelve give
#: every parameter with the accuracy docs/calibration.md states at 200 averaged samples per pose.
#: The board's frame is the flat sheet's: i-links along its x, j-links along its y, top face +z.
_S = float(np.sqrt(0.5))
BOARD_POSES: tuple[tuple[str, str, tuple[float, float, float]], ...] = (
    ("top up", "board flat, top face up", (0.0, 0.0, 1.0)),
    ("top down", "board flat, top face down", (0.0, 0.0, -1.0)),
    ("+x edge up", "board on its -x edge (the edge at low i down)", (1.0, 0.0, 0.0)),
    ("-x edge up", "board on its +x edge (the edge at high i down)", (-1.0, 0.0, 0.0)),
    ("+y edge up", "board on its -y edge (the edge at low j down)", (0.0, 1.0, 0.0)),
    ("-y edge up", "board on its +y edge (the edge at high j down)", (0.0, -1.0, 0.0)),
    ("top up, +x raised 45°", "top up, tilted 45° with the +x edge raised", (_S, 0.0, _S)),
    ("top up, +y raised 45°", "top up, tilted 45° with the +y edge raised", (0.0, _S, _S)),
    ("top down, -x raised 45°", "top down, tilted 45° with the -x edge raised", (-_S, 0.0, -_S)),
    ("top down, -y raised 45°", "top down, tilted 45° with the -y edge raised", (0.0, -_S, -_S)),
    ("+x and +y edges up 45°", "on the (-x,-y) corner edge, 45° between the two", (_S, _S, 0.0)),
    ("-x and +y edges up 45°", "on the (+x,-y) corner edge, 45° between the two", (-_S, _S, 0.0)),
)
