"""What 6/9-axis chips read at a SYNC on a moving sheet: the phase-1 models fed by a scene.

`ImuSource` answers a chip's read at ``now_s`` with the instant of a fixed time grid (``grid_hz``,
about 2 × the paper's 145 Hz) at or before it: it takes a `motion.MotionScene`'s exact truth there
and reads it through an `imu.ImuArray` (accelerometer, gyroscope, magnetometer, seeded, bias
processes continued from read to read): every chip's counts, and ``time_us`` = that instant minus
``now_s`` — the per-sample chip timestamp of docs/protocol.md §16.1, what a host integrating the
gyroscope needs. A chip that reads the same instant twice (two SYNCs within one grid step) gets the
same values flagged STALE (§5.3: no new conversion); a read behind the newest instant takes that one
(the sample is then after its SYNC: ``time_us`` > 0).

The truth costs: a moving 14 × 14 net is solved in ~30 ms a call plus ~0.5 ms an instant. So the
instants are solved in chunks (``chunk_s`` ahead), and a scene that repeats exactly
(``periodic_from_s``, `motion.FieldScene`: grow, wave) is solved over one period once
(`precompute`; the grid is then a whole number of steps a period) and looked up after.

**When the scene starts** (`hold`, `start_at`): by default at the source's time 0 (the device's
start). A moving scene starts at rest, as the fused estimator's first snapshot assumes; a demo whose
bring-up took 1-5 s (longer on a busy machine) began streaming wherever the motion then was, and
its error against the truth depended on that instant (a 14x14 carried sheet: 0.11-0.90 % of side
for streams begun 0-5 s in). `hold` keeps the sheet at its start (every read takes instant 0,
``time_us`` 0) until `start_at` sets the scene's time 0 at the device's time given.

Sans-I/O and time as an argument, as the chips.
"""

from __future__ import annotations

import math
import threading
from types import SimpleNamespace

import numpy as np

from protocol.constants import SampleStatus
from protocol.imu_units import GyroRange, MagRange, gyro_nominal_sensitivity, mag_nominal_sensitivity

__all__ = ["ImuSource", "MOTION_SHAPES"]

#: the moving scenes of `motion.MOTION_SCENES` a virtual sheet takes as ``--shape``
MOTION_SHAPES = ("carry", "wave", "elbow", "tap", "flat_turn", "tumble")
_FIELDS = ("specific_force", "angular_velocity", "position", "frames", "joints")
_STALE = int(SampleStatus.STALE)


class ImuSource:
    """Every chip's IMU reading at any ``now_s`` (module docstring).

    Parameters
    ----------
    scene : motion.MotionScene
    imu : imu.ImuArray
    grid_hz : float
        At least this rate (a periodic scene's grid is rounded up to a whole number of steps a period).
    chunk_s : float
        How far ahead a non-periodic scene is solved at once.
    """

    def __init__(self, scene, imu, *, grid_hz: float = 290.0, chunk_s: float = 0.1) -> None:
        if not (math.isfinite(grid_hz) and grid_hz > 0 and math.isfinite(chunk_s) and chunk_s > 0):
            raise ValueError(f"Invalid grid_hz={grid_hz!r} / chunk_s={chunk_s!r} (need > 0)")
        self.scene, self.imu = scene, imu
        t0, period = getattr(scene, "periodic_from_s", None), getattr(scene, "period_s", None)
        self.periodic = t0 is not None and period
        if self.periodic:
            steps = math.ceil(period * grid_hz)
            grid_hz = steps / period
            self._steps = steps
            self._k0 = math.ceil(t0 * grid_hz - 1e-9)  # the first grid instant of the periodic part
            self._cache: dict[int, SimpleNamespace] = {}
        self._ramp: dict[int, SimpleNamespace] = {}  # a periodic scene's fade-in, when precomputed
        self.grid_hz = float(grid_hz)
        self.chunk = max(1, int(round(chunk_s * self.grid_hz)))
        self._ahead: tuple[int, object] | None = None  # (first grid index, Truth) of the chunk solved
        self._k: int | None = None  # grid index of the instant read last
        self._reading = None  # (ImuReading, truth) of that instant
        self._chip_k = np.full(imu.n_links, -1, dtype=np.int64)  # per chip: the instant it read last
        self._lock = threading.Lock()
        self.origin_s = 0.0  #: the device's time of the scene's time 0 (`hold`, `start_at`)

    # ---- when the scene starts
    def hold(self) -> None:
        """Keep the sheet at the scene's start until `start_at` (module docstring)."""
        with self._lock:
            self.origin_s = math.inf

    def start_at(self, t_s: float) -> None:
        """The scene's time 0 at the device's ``t_s`` (after `hold`; reads before it stay at the start)."""
        if not math.isfinite(t_s):
            raise ValueError(f"Invalid t_s: {t_s!r} (need a finite time, s)")
        with self._lock:
            if self._k is not None and self._k > 0:
                raise ValueError("the scene has already moved on: start_at is for a source held at its start")
            self.origin_s = float(t_s)

    def _grid(self, now_s: float) -> int:
        """The grid index of the scene's instant at the device's ``now_s`` (0 before the start)."""
        if now_s < self.origin_s:
            return 0
        return max(0, int(math.floor((now_s - self.origin_s) * self.grid_hz + 1e-9)))

    # ---- the truth at grid instants
    def _solve(self, ks: np.ndarray) -> dict:
        tr = self.scene.sample(ks / self.grid_hz)
        return {f: np.asarray(getattr(tr, f)) for f in _FIELDS}

    def precompute(self) -> int:
        """Solve a periodic scene now (before streaming): its fade-in (the instants before
        ``periodic_from_s``) and one period; returns how many instants. A live stream then solves
        nothing: a chunk of a net scene solved between two SYNCs held the sheet ~36 ms (14 × 14),
        and a stream that starts within the fade-in (a demo's bring-up is shorter than a wave's 1 s
        fade-in) met one every 0.1 s."""
        if not self.periodic:
            return 0
        for a in range(0, self._steps, 64):
            key = np.arange(a, min(a + 64, self._steps))
            sol = self._solve(self._k0 + key)
            for j, kk in enumerate(key.tolist()):
                self._cache[kk] = SimpleNamespace(**{f: sol[f][j] for f in _FIELDS})
        for a in range(0, self._k0, 64):
            ks = np.arange(a, min(a + 64, self._k0))
            sol = self._solve(ks)
            for j, kk in enumerate(ks.tolist()):
                self._ramp[kk] = SimpleNamespace(**{f: sol[f][j] for f in _FIELDS})
        return self._steps + self._k0

    def truth_at(self, k: int) -> SimpleNamespace:
        """The exact truth at grid instant ``k`` (``k / grid_hz`` s): positions, frames, specific
        force, rates, from the source's own cache under its lock — what a part's register emulator
        is fed (`virtual_sheet.parts.truth.SheetTruth`)."""
        with self._lock:
            return self._truth(k)

    def _truth(self, k: int) -> SimpleNamespace:
        if self.periodic and k >= self._k0:
            key = (k - self._k0) % self._steps
            e = self._cache.get(key)
            if e is None:  # not precomputed: this instant and the chunk after it, at once
                keys = (key + np.arange(self.chunk)) % self._steps
                sol = self._solve(self._k0 + keys)
                for j, kk in enumerate(keys.tolist()):
                    self._cache[kk] = SimpleNamespace(**{f: sol[f][j] for f in _FIELDS})
                e = self._cache[key]
            return e
        e = self._ramp.get(k)
        if e is not None:
            return e
        ah = self._ahead
        if ah is None or not (ah[0] <= k < ah[0] + self.chunk):
            ah = self._ahead = (k, self._solve(k + np.arange(self.chunk)))
        j = k - ah[0]
        return SimpleNamespace(**{f: ah[1][f][j] for f in _FIELDS})

    def index(self, now_s: float) -> int:
        """The grid index of the instant a read at ``now_s`` takes (read through the IMU models once)."""
        with self._lock:
            k = self._grid(now_s)
            if self._k is None or k > self._k:
                e = self._truth(k)
                one = SimpleNamespace(t_s=np.array([k / self.grid_hz]),
                                      **{f: getattr(e, f)[None] for f in _FIELDS})
                self._reading = (self.imu.read(one), e)
                self._k = k
            return self._k

    def read(self, now_s: float, idx: np.ndarray, gyro_range=None, mag_range=None):
        """Chips ``idx``: ``(accel counts (m, 3) int64, accel status (m,) int64, gyro counts (m, 3)
        or None, mag counts (m, 3) or None, time_us (m,) int64)`` at the instant a read at ``now_s``
        takes; gyro/mag counts at range codes ``gyro_range`` / ``mag_range`` (scalars or (m,)),
        default the model's."""
        k = self.index(now_s)
        r = self._reading[0]
        held = now_s < self.origin_s  # at rest at the start: the read's own instant
        t_us = 0 if held else int(round((self.origin_s + k / self.grid_hz - now_s) * 1e6))
        t_us = np.full(idx.shape[0], max(-32767, min(32767, t_us)), dtype=np.int64)
        g = m = None
        if r.gyro_counts is not None:
            g = _rescale(r.gyro_counts[0][idx], self.imu.gyro.sensitivity, gyro_range, gyro_nominal_sensitivity)
        if r.mag_counts is not None:
            m = _rescale(r.mag_counts[0][idx], self.imu.mag.sensitivity, mag_range, mag_nominal_sensitivity)
        status = r.accel_status[0][idx].astype(np.int64)
        return r.accel_counts[0][idx].astype(np.int64), status, g, m, t_us

    def mark_read(self, now_s: float, idx: np.ndarray) -> np.ndarray:
        """Chips ``idx`` take the instant of ``now_s`` as their conversion: True where it is the one they
        took last time (their sample is then STALE, §5.3)."""
        k = self.index(now_s)
        stale = self._chip_k[idx] == k
        self._chip_k[idx] = k
        return stale

    def joints(self, now_s: float) -> np.ndarray:
        """The exact joints at the instant a read at ``now_s`` takes."""
        self.index(now_s)
        return np.array(self._reading[1].joints, dtype=float)

    def joints_at(self, t_s: float) -> np.ndarray:
        """The exact joints at grid instant ``t_s`` (a time a read took: `ImuSource.time_of`)."""
        with self._lock:
            return np.array(self._truth(int(round(t_s * self.grid_hz))).joints, dtype=float)

    def time_of(self, now_s: float) -> float:
        """The grid instant a read at ``now_s`` takes (without reading)."""
        return self._grid(now_s) / self.grid_hz


def _rescale(counts, model_sens: float, range_code, nominal) -> np.ndarray:
    c = counts.astype(np.int64)
    if range_code is None:
        return c
    rc = np.asarray(range_code)
    if rc.ndim:  # per chip: the codes' sensitivities by table (a call per chip cost ~0.5 ms a SYNC)
        sens = _sensitivity_table(nominal)[rc]
    else:
        sens = nominal(int(rc))
    scale = np.asarray(sens, dtype=float) / model_sens
    if np.all(scale == 1.0):
        return c
    out = np.rint(c * (scale[:, None] if np.ndim(scale) else scale))
    return np.clip(out, -32768, 32767).astype(np.int64)


_TABLES: dict = {}


def _sensitivity_table(nominal) -> np.ndarray:
    """``nominal(code)`` for every range code of its sensor (the codes CONFIG_IMU takes)."""
    t = _TABLES.get(nominal)
    if t is None:
        codes = GyroRange if nominal is gyro_nominal_sensitivity else MagRange
        t = _TABLES[nominal] = np.array([nominal(int(c)) for c in sorted(codes)], dtype=float)
        assert [int(c) for c in sorted(codes)] == list(range(t.size))
    return t
