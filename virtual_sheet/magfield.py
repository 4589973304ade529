"""The magnetic field the chips sit in: Earth's, plus local disturbances.

World frame as docs/design.md (z up). Earth's field is uniform: magnitude ``F`` (25–65 µT on
Earth), inclination (dip) ``I`` (positive downwards, 0° at the magnetic equator, 90° at the
poles) and declination ``D`` (the horizontal component's direction, radians from world +x towards
+y — the yaw of magnetic north)::

    B_earth = F (cos I cos D, cos I sin D, −sin I)

Disturbances add to it:

* `Dipole` — a magnet or a magnetised steel part: ``B = μ0/4π (3 r̂ (m·r̂) − m) / |r|³``, moment
  ``m`` in A·m², fixed in the world;
* `SteelPart` — soft steel magnetised by Earth's field: a dipole whose moment is induced along the
  ambient field, ``m = k · B_earth / μ0`` (``k``: the part's effective volume susceptibility times
  its volume, m³; a 1 cm steel bolt is of the order of 1e-6 m³ · a few tens).

`quarter_disturbance` places a magnet under one quarter of a sheet (the fused estimator's "local
disturbance over a quarter of the sheet") and `disturbance_angle` says how far it turns the field
at each chip.

>>> env = MagneticField(EarthField(50e-6, np.radians(60)))
>>> np.round(env.at(np.zeros((1, 3)))[0] * 1e6, 3).tolist()
[25.0, 0.0, -43.301]
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["MU0", "EarthField", "Dipole", "SteelPart", "MagneticField", "field_in_sensor_frames",
           "quarter_disturbance", "disturbance_angle"]

#: Vacuum permeability, T·m/A (CODATA 2018, 1.00000000055 × 4π × 1e-7).
MU0 = 1.25663706212e-6


def _points(points) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim < 1 or p.shape[-1] != 3:
        raise ValueError(f"Expected `points` to have shape (..., 3), got {p.shape}.")
    return p


def _vec3(value, name: str) -> tuple[float, float, float]:
    v = np.asarray(value, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"Invalid {name}: {value!r} (expected 3 finite numbers)")
    return tuple(float(x) for x in v)


@dataclass(frozen=True)
class EarthField:
    """Earth's field (module docstring): ``magnitude_t`` tesla, ``dip_rad``, ``declination_rad``."""

    magnitude_t: float = 50e-6
    dip_rad: float = float(np.radians(60.0))
    declination_rad: float = 0.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.magnitude_t) and 0 <= self.magnitude_t < 1e-3):
            raise ValueError(f"Invalid magnitude_t: {self.magnitude_t!r} (Earth: 25e-6 .. 65e-6 T)")
        if not (np.isfinite(self.dip_rad) and abs(self.dip_rad) <= np.pi / 2):
            raise ValueError(f"Invalid dip_rad: {self.dip_rad!r} (need |dip| <= pi/2)")
        if not np.isfinite(self.declination_rad):
            raise ValueError(f"Invalid declination_rad: {self.declination_rad!r}")

    @property
    def vector(self) -> np.ndarray:
        """``B_earth``, tesla, world frame, shape (3,)."""
        ci, si = np.cos(self.dip_rad), np.sin(self.dip_rad)
        return self.magnitude_t * np.array([ci * np.cos(self.declination_rad),
                                            ci * np.sin(self.declination_rad), -si])


def _dipole(points: np.ndarray, position, moment: np.ndarray) -> np.ndarray:
    r = points - np.asarray(position, dtype=float)
    d = np.linalg.norm(r, axis=-1, keepdims=True)
    if np.any(d <= 0):
        raise ValueError("A field point sits exactly on a dipole.")
    rh = r / d
    return MU0 / (4 * np.pi) * (3 * rh * np.sum(rh * moment, axis=-1, keepdims=True) - moment) / d ** 3


@dataclass(frozen=True)
class Dipole:
    """A point dipole of ``moment_am2`` (A·m², world frame) at ``position_m`` (world)."""

    position_m: tuple[float, float, float]
    moment_am2: tuple[float, float, float]

    def __post_init__(self) -> None:
        object.__setattr__(self, "position_m", _vec3(self.position_m, "position_m"))
        object.__setattr__(self, "moment_am2", _vec3(self.moment_am2, "moment_am2"))

    def at(self, points: np.ndarray, ambient_t: np.ndarray) -> np.ndarray:
        return _dipole(points, self.position_m, np.asarray(self.moment_am2))


@dataclass(frozen=True)
class SteelPart:
    """Soft steel at ``position_m`` magnetised by the ambient (Earth's) field:
    ``m = susceptibility_volume_m3 · B_earth / μ0`` (module docstring)."""

    position_m: tuple[float, float, float]
    susceptibility_volume_m3: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "position_m", _vec3(self.position_m, "position_m"))
        if not (np.isfinite(self.susceptibility_volume_m3) and self.susceptibility_volume_m3 >= 0):
            raise ValueError(f"Invalid susceptibility_volume_m3: {self.susceptibility_volume_m3!r} (need >= 0)")

    def at(self, points: np.ndarray, ambient_t: np.ndarray) -> np.ndarray:
        return _dipole(points, self.position_m, self.susceptibility_volume_m3 * ambient_t / MU0)


@dataclass(frozen=True)
class MagneticField:
    """Earth's field plus ``disturbances`` (`Dipole`, `SteelPart`), all fixed in the world."""

    earth: EarthField = field(default_factory=EarthField)
    disturbances: tuple = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "disturbances", tuple(self.disturbances))
        for d in self.disturbances:
            if not hasattr(d, "at"):
                raise ValueError(f"Invalid disturbance: {d!r} (expected a Dipole or SteelPart)")

    def at(self, points) -> np.ndarray:
        """The field at ``points (..., 3)`` (m, world), tesla, world frame, same shape."""
        p = _points(points)
        b0 = self.earth.vector
        out = np.broadcast_to(b0, p.shape).copy()
        for d in self.disturbances:
            out += d.at(p, b0)
        return out


def field_in_sensor_frames(env: MagneticField, positions: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """The field each chip feels, in its sensor frame: ``Rᵀ B(position)``.

    Parameters
    ----------
    positions : ndarray, shape (..., n_links, 3)
        Chip positions, m, world (`motion.Truth.position`).
    frames : ndarray, shape (..., n_links, 3, 3)
        Sensor -> world (`motion.Truth.frames`).

    Returns
    -------
    ndarray, shape (..., n_links, 3)
        Tesla, sensor frames.
    """
    B = env.at(positions)
    return np.einsum("...ji,...j->...i", np.asarray(frames, dtype=float), B)


def quarter_disturbance(rows: int, cols: int, link_length: float = 0.01, *,
                        moment_am2: float = 0.005, depth_m: float | None = None,
                        corner: tuple[int, int] = (1, 1)) -> Dipole:
    """A magnet under one quarter of a level ``rows x cols`` sheet centred on the origin (as the
    shapes lay it): at the centre of the quarter on the side ``corner`` (``(±1, ±1)``: the
    +x/+y quarter by default), ``depth_m`` below the sheet (default S/4), moment ``moment_am2``
    pointing up. 0.005 A·m² (a small magnet) 3.25 cm below a 14 × 14, 1 cm sheet gives ~29 µT
    right above it: it turns the field by 5–32° (median 12°) over its quarter, by a median 1.4° on
    the two neighbouring quarters and at most 3.7° on the opposite one (Earth 50 µT, dip 60°)."""
    S = max(max(rows, cols) - 1, 2) * float(link_length)
    d = S / 4 if depth_m is None else float(depth_m)
    sx, sy = corner
    if sx not in (-1, 1) or sy not in (-1, 1):
        raise ValueError(f"Invalid corner: {corner!r} (expected (±1, ±1))")
    return Dipole((sx * (rows - 1) * link_length / 4, sy * (cols - 1) * link_length / 4, -d),
                  (0.0, 0.0, float(moment_am2)))


def disturbance_angle(env: MagneticField, points: np.ndarray) -> np.ndarray:
    """Angle (radians) between the field at ``points (..., 3)`` and Earth's field alone: how far
    the disturbances turn each chip's compass."""
    B = env.at(points)
    b0 = env.earth.vector
    c = np.sum(B * b0, axis=-1) / (np.linalg.norm(B, axis=-1) * np.linalg.norm(b0))
    return np.arccos(np.clip(c, -1.0, 1.0))
