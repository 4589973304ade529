"""What 6/9-axis chips read at a SYNC on a moving sheet (issue 29): the phase-1 models fed by a scene.

`ImuSource` samples a `motion.MotionScene`'s exact truth on a fixed time grid (``grid_hz``, 4 × the
paper's 145 Hz by default) in chunks, reads it through an `imu.ImuArray` (accelerometer, gyroscope,
magnetometer, seeded, bias processes continued from chunk to chunk), and answers a chip's read at
``now_s`` with the grid instant at or before it: every chip's counts, and ``time_us`` = that instant
minus ``now_s`` — the per-sample chip timestamp of docs/protocol.md §16.1, what a host integrating the
gyroscope needs. Gyroscope and magnetometer counts are rescaled from the model's range to the range a
chip was configured with (CONFIG_IMU), clipped to 16 bits.

Sans-I/O and time as an argument, as the chips; reads must not go back further than one chunk.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from protocol.imu_units import gyro_nominal_sensitivity, mag_nominal_sensitivity

__all__ = ["ImuSource", "MOTION_SHAPES"]

#: the moving scenes of `motion.MOTION_SCENES` a virtual sheet takes as ``--shape`` (issue 29)
MOTION_SHAPES = ("carry", "wave", "elbow", "tap", "flat_turn", "tumble")


class ImuSource:
    """Every chip's IMU reading at any ``now_s`` (module docstring).

    Parameters
    ----------
    scene : motion.MotionScene
    imu : imu.ImuArray
    grid_hz : float
    chunk_s : float
    """

    def __init__(self, scene, imu, *, grid_hz: float = 580.0, chunk_s: float = 0.25) -> None:
        if not (math.isfinite(grid_hz) and grid_hz > 0 and math.isfinite(chunk_s) and chunk_s > 0):
            raise ValueError(f"Invalid grid_hz={grid_hz!r} / chunk_s={chunk_s!r} (need > 0)")
        self.scene, self.imu = scene, imu
        self.grid_hz = float(grid_hz)
        self.per = max(1, int(round(chunk_s * grid_hz)))
        self._k0: int | None = None  # grid index of the chunk's first instant
        self._chunk = None  # (ImuReading, Truth)
        self._lock = threading.Lock()
        self.truth_cache: dict[int, np.ndarray] = {}

    def _load(self, k: int) -> None:
        t = (k + np.arange(self.per)) / self.grid_hz
        truth = self.scene.sample(t)
        self._chunk = (self.imu.read(truth), truth)
        self._k0 = k

    def index(self, now_s: float) -> tuple[int, int]:
        """``(chunk row, grid index)`` of the grid instant at or before ``now_s`` (loads as needed)."""
        k = int(math.floor(now_s * self.grid_hz + 1e-9))
        with self._lock:
            if self._k0 is None:
                self._load(max(0, k))
            elif k >= self._k0 + self.per:
                self._load(max(self._k0 + self.per, k))  # ahead: the next chunk (or skip to now)
            k = min(max(k, self._k0), self._k0 + self.per - 1)  # behind the chunk: its first instant
            return k - self._k0, k

    def read(self, now_s: float, idx: np.ndarray, gyro_range=None, mag_range=None):
        """Chips ``idx``: ``(accel counts (m, 3) int64, accel status (m,) int64, gyro counts (m, 3)
        or None, mag counts (m, 3) or None, time_us (m,) int64)`` at the grid instant at or before
        ``now_s``; gyro/mag counts at range codes ``gyro_range`` / ``mag_range`` (scalars or (m,)),
        default the model's."""
        row, k = self.index(now_s)
        r = self._chunk[0]
        t_us = int(round((k / self.grid_hz - now_s) * 1e6))
        t_us = np.full(idx.shape[0], max(-32767, min(32767, t_us)), dtype=np.int64)
        g = m = None
        if r.gyro_counts is not None:
            g = _rescale(r.gyro_counts[row][idx], self.imu.gyro.sensitivity, gyro_range, gyro_nominal_sensitivity)
        if r.mag_counts is not None:
            m = _rescale(r.mag_counts[row][idx], self.imu.mag.sensitivity, mag_range, mag_nominal_sensitivity)
        return (r.accel_counts[row][idx].astype(np.int64), r.accel_status[row][idx].astype(np.int64), g, m, t_us)

    def joints(self, now_s: float) -> np.ndarray:
        """The exact joints at the grid instant a read at ``now_s`` takes."""
        row, _k = self.index(now_s)
        return self._chunk[1].joints[row].copy()


def _rescale(counts, model_sens: float, range_code, nominal) -> np.ndarray:
    c = counts.astype(np.int64)
    if range_code is None:
        return c
    rc = np.asarray(range_code)
    sens = np.vectorize(nominal, otypes=[float])(rc) if rc.ndim else nominal(int(rc))
    scale = np.asarray(sens, dtype=float) / model_sens
    if np.all(scale == 1.0):
        return c
    out = np.rint(c * (scale[:, None] if np.ndim(scale) else scale))
    return np.clip(out, -32768, 32767).astype(np.int64)
