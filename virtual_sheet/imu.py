"""6- and 9-axis chips: gyroscope and magnetometer models beside the accelerometer's.

`ImuArray` turns the truth of every link (`motion.Truth`: specific force, angular velocity,
position and frame) into what its chip reports — counts at the configured ranges and the same in SI
— vectorised over all links and any number of SYNCs, seeded. The accelerometer is
`sensor.SensorModel` (12-bit counts, docs/protocol.md §5.2), unchanged. Per chip, fixed for its
life (drawn once from ``chip_seed``, the *hidden truth* `gyro_errors` / `mag_errors` that
calibration is measured against):

Gyroscope (`GyroModel`), in the chip's axes (the accelerometer's: one package, so the mounting
rotation ``M`` of `sensor.ChipErrors.misalignment` is shared)::

    ω_meas = K Mᵀ ω + b₀ + b(t) + Γ f / G0 + n

* ``K = I + S`` — scale errors on the diagonal, cross-axis sensitivity off it;
* ``b₀`` — turn-on bias (zero-rate offset); ``b(t)`` — bias instability, a first-order
  Gauss–Markov process (stationary standard deviation, correlation time) plus an optional rate
  random walk;
* ``Γ`` — g-sensitivity, °/s per g of specific force ``f`` (chip frame);
* ``n`` — white noise of one-sided density ``N`` (°/s/√Hz) over the sample rate's Nyquist band:
  standard deviation ``N √(rate/2)`` per sample, so its Allan deviation is ``N / √(2τ)``.

Magnetometer (`MagModel`), its own part with its own mounting rotation ``M_m``::

    m = W M_mᵀ B + h + n

* ``W`` — soft iron (and the part's scale errors): symmetric, ``I`` plus small terms;
* ``h`` — hard iron: the part's offset and the link's magnetised parts, tesla;
* ``n`` — white noise, RMS per axis per sample (the datasheet's RMS noise at its output rate).

Counts: ``round(value · sensitivity)`` clipped to 16 bits at the range (`protocol.imu_units`:
the one place the counts <-> SI rule lives), flagged when clipped.

Presets (`GYRO_PARTS`, `MAG_PARTS`; figures as the datasheets state them, *assumed* where a
datasheet is silent):

========== ===========================================================================================
icm42688p  TDK ICM-42688-P (DS-000347): noise 2.8 mdps/√Hz; zero-rate offset ±0.5 °/s (taken as
           the standard deviation); scale ±0.5 %; cross-axis ±1.25 %. Assumed: bias instability
           3 °/h (Gauss–Markov, 100 s), g-sensitivity 0.1 °/s/g (BMI270's figure; TDK states none)
icm42605   TDK ICM-42605: noise 3.8 mdps/√Hz, otherwise as icm42688p
ideal      no errors at all (for exactness tests)
lis3mdl    ST LIS3MDL (DocID024204): ±4/8/12/16 gauss, RMS noise 3.2 / 3.2 / 4.1 mgauss (x, y, z;
           ultra-high-performance mode, up to 155 Hz). Assumed: hard iron 30 µT per axis (part offset
           plus the link's parts), soft iron 2 % (symmetric terms), mounting 1.5° per axis
ideal      no errors
========== ===========================================================================================

The accelerometer of an ICM-42688-P (70 µg/√Hz: 0.06 % g over 72.5 Hz; zero-g offset ±20 mg;
scale ±0.5 %) is `accel_model("icm42688p")`; the fused estimator's benchmarks use 1 % g noise instead.

Why `read` takes no generator: each sensor draws from its own stream (``seed`` and the sensor),
kept between calls, so the same scene read with and without a magnetometer gives the same
accelerometer and gyroscope data (an estimator compared with and without magnetometers sees the
same motion data), and a long run read in chunks equals the run read at once.

>>> from virtual_sheet.motion import make_motion_scene
>>> scene = make_motion_scene("rest", 3, 3, 0.01, shape="flat")
>>> imu = ImuArray(12, accel=SensorModel(), gyro=GyroModel.part("ideal"))
>>> r = imu.read(scene.sample([0.0, 0.01]))
>>> r.accel_counts[0, 0].tolist(), r.gyro_counts[1, 0].tolist()
([0, 0, 1024], [0, 0, 0])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocol.constants import G0, SampleStatus, counts_to_si
from protocol.imu_units import (GyroRange, MagRange, RAD_PER_DEG, TESLA_PER_GAUSS, count_limits,
                                gyro_nominal_sensitivity, mag_nominal_sensitivity)
from .magfield import MagneticField, field_in_sensor_frames
from protocol.rotations import rotvec_matrices
from .sensor import SensorModel

__all__ = ["GyroModel", "MagModel", "GyroErrors", "MagErrors", "ImuArray", "ImuReading",
           "GYRO_PARTS", "MAG_PARTS", "accel_model", "SENSOR_SETS", "imu_array", "simulate"]

_DPS = RAD_PER_DEG  # rad/s per °/s


def _nonneg(obj, names) -> None:
    for name in names:
        v = getattr(obj, name)
        if not (isinstance(v, (int, float, np.floating, np.integer)) and np.isfinite(v) and v >= 0):
            raise ValueError(f"Invalid {name}: {v!r} (need a finite number >= 0)")


def _small_rotations(z: np.ndarray, sigma: float) -> np.ndarray:
    if z.shape[0] == 0:
        return np.zeros((0, 3, 3))
    return rotvec_matrices(z * sigma).reshape(-1, 3, 3)


@dataclass(frozen=True)
class GyroErrors:
    """A gyroscope array's fixed errors (`GyroModel.errors`), chip axes.

    Attributes
    ----------
    scale : ndarray, shape (n, 3, 3)
        ``K = I + S`` (dimensionless).
    bias_rps : ndarray, shape (n, 3)
        Turn-on bias ``b₀``, rad/s.
    g_sensitivity : ndarray, shape (n, 3, 3)
        ``Γ``, rad/s per g.
    """

    scale: np.ndarray
    bias_rps: np.ndarray
    g_sensitivity: np.ndarray


@dataclass(frozen=True)
class GyroModel:
    """A gyroscope part (module docstring). Standard deviations; validated when built.

    Parameters
    ----------
    noise_density_dps : float
        One-sided white-noise density, °/s/√Hz.
    bias_dps : float
        Turn-on bias per axis, °/s.
    bias_instability_dps : float
        Stationary standard deviation of the Gauss–Markov bias, °/s.
    bias_time_constant_s : float
        Its correlation time, s.
    rate_random_walk_dps : float
        Rate random walk, °/s/√s (0: none).
    scale_error, cross_axis : float
        Per-axis scale error and each off-diagonal term of ``K`` (0.005 = 0.5 %).
    g_sensitivity_dps : float
        Each entry of ``Γ``, °/s per g.
    range : GyroRange
        Full-scale range (±125 … ±2000 °/s).
    chip_seed : int
        Seed of the fixed errors.
    """

    noise_density_dps: float = 0.0028
    bias_dps: float = 0.5
    bias_instability_dps: float = 3.0 / 3600.0
    bias_time_constant_s: float = 100.0
    rate_random_walk_dps: float = 0.0
    scale_error: float = 0.005
    cross_axis: float = 0.0125
    g_sensitivity_dps: float = 0.1
    range: GyroRange = GyroRange.DPS1000
    chip_seed: int = 0

    def __post_init__(self) -> None:
        _nonneg(self, ("noise_density_dps", "bias_dps", "bias_instability_dps", "rate_random_walk_dps",
                       "scale_error", "cross_axis", "g_sensitivity_dps"))
        if not (np.isfinite(self.bias_time_constant_s) and self.bias_time_constant_s > 0):
            raise ValueError(f"Invalid bias_time_constant_s: {self.bias_time_constant_s!r} (need > 0 s)")
        if self.scale_error >= 0.5 or self.cross_axis >= 0.5:
            raise ValueError("Invalid scale_error / cross_axis (need < 0.5)")
        try:
            object.__setattr__(self, "range", GyroRange(self.range))
        except ValueError as exc:
            raise ValueError(f"Invalid gyro range: {self.range!r} (expected a GyroRange code 0..4)") from exc
        if not (isinstance(self.chip_seed, (int, np.integer)) and self.chip_seed >= 0):
            raise ValueError(f"Invalid chip_seed: {self.chip_seed!r} (need an integer >= 0)")

    @classmethod
    def part(cls, name: str, **overrides) -> "GyroModel":
        """A preset of `GYRO_PARTS`, fields overridden by keyword."""
        if name not in GYRO_PARTS:
            raise ValueError(f"Unknown gyroscope part {name!r} (expected one of {', '.join(GYRO_PARTS)})")
        return cls(**{**GYRO_PARTS[name], **overrides})

    @property
    def sensitivity(self) -> float:
        """Nominal counts per °/s at the range."""
        return gyro_nominal_sensitivity(self.range)

    def noise_std_rps(self, rate_hz: float) -> float:
        """White noise per sample at ``rate_hz``: ``N √(rate/2)``, rad/s."""
        return self.noise_density_dps * np.sqrt(rate_hz / 2.0) * _DPS

    def errors(self, n_links: int) -> GyroErrors:
        """The fixed errors of chips ``0 .. n_links-1`` (drawn in a fixed order from ``chip_seed``)."""
        g = np.random.Generator(np.random.MT19937([int(self.chip_seed), 0x6790]))
        z_scale = g.standard_normal((n_links, 3, 3))
        z_bias = g.standard_normal((n_links, 3))
        z_g = g.standard_normal((n_links, 3, 3))
        eye = np.eye(3, dtype=bool)
        S = np.where(eye, z_scale * self.scale_error, z_scale * self.cross_axis)
        return GyroErrors(scale=np.eye(3) + S, bias_rps=z_bias * self.bias_dps * _DPS,
                          g_sensitivity=z_g * self.g_sensitivity_dps * _DPS)


@dataclass(frozen=True)
class MagErrors:
    """A magnetometer array's fixed errors (`MagModel.errors`).

    Attributes
    ----------
    soft_iron : ndarray, shape (n, 3, 3)
        ``W`` (symmetric).
    hard_iron_t : ndarray, shape (n, 3)
        ``h``, tesla, the part's axes.
    mounting : ndarray, shape (n, 3, 3)
        ``M_m``: columns are the part's axes in its link's sensor frame.
    """

    soft_iron: np.ndarray
    hard_iron_t: np.ndarray
    mounting: np.ndarray

    @property
    def distortion(self) -> np.ndarray:
        """``W M_mᵀ``: link-frame field -> what the part reads, less hard iron and noise."""
        return self.soft_iron @ np.transpose(self.mounting, (0, 2, 1))


@dataclass(frozen=True)
class MagModel:
    """A magnetometer part (module docstring). Standard deviations; validated when built.

    Parameters
    ----------
    noise_t : tuple of 3 floats
        RMS noise per axis per sample, tesla.
    hard_iron_t : float
        Per-axis hard iron, tesla.
    soft_iron : float
        Each independent term of ``W − I`` (symmetric: 3 diagonal, 3 off-diagonal).
    mounting_rad : float
        Each component of the mounting rotation vector, radians.
    range : MagRange
    chip_seed : int
    """

    noise_t: tuple[float, float, float] = (0.32e-6, 0.32e-6, 0.41e-6)
    hard_iron_t: float = 30e-6
    soft_iron: float = 0.02
    mounting_rad: float = float(np.radians(1.5))
    range: MagRange = MagRange.GAUSS4
    chip_seed: int = 0

    def __post_init__(self) -> None:
        nt = np.asarray(self.noise_t, dtype=float)
        if nt.shape != (3,) or not np.all(np.isfinite(nt)) or np.any(nt < 0):
            raise ValueError(f"Invalid noise_t: {self.noise_t!r} (need 3 finite values >= 0, tesla)")
        object.__setattr__(self, "noise_t", tuple(float(x) for x in nt))
        _nonneg(self, ("hard_iron_t", "soft_iron", "mounting_rad"))
        if self.soft_iron >= 0.2:
            raise ValueError(f"Invalid soft_iron: {self.soft_iron!r} (need < 0.2)")
        try:
            object.__setattr__(self, "range", MagRange(self.range))
        except ValueError as exc:
            raise ValueError(f"Invalid magnetometer range: {self.range!r} (expected a MagRange code 0..3)") from exc
        if not (isinstance(self.chip_seed, (int, np.integer)) and self.chip_seed >= 0):
            raise ValueError(f"Invalid chip_seed: {self.chip_seed!r} (need an integer >= 0)")

    @classmethod
    def part(cls, name: str, **overrides) -> "MagModel":
        """A preset of `MAG_PARTS`, fields overridden by keyword."""
        if name not in MAG_PARTS:
            raise ValueError(f"Unknown magnetometer part {name!r} (expected one of {', '.join(MAG_PARTS)})")
        return cls(**{**MAG_PARTS[name], **overrides})

    @property
    def sensitivity(self) -> float:
        """Nominal counts per gauss at the range."""
        return mag_nominal_sensitivity(self.range)

    def errors(self, n_links: int) -> MagErrors:
        g = np.random.Generator(np.random.MT19937([int(self.chip_seed), 0x3A6]))
        z_w = g.standard_normal((n_links, 3, 3))
        z_h = g.standard_normal((n_links, 3))
        z_m = g.standard_normal((n_links, 3))
        E = np.triu(z_w) * self.soft_iron
        W = np.eye(3) + E + np.transpose(np.triu(E, 1), (0, 2, 1))
        return MagErrors(soft_iron=W, hard_iron_t=z_h * self.hard_iron_t,
                         mounting=_small_rotations(z_m, self.mounting_rad))


GYRO_PARTS: dict[str, dict] = {
    "icm42688p": {},
    "icm42605": {"noise_density_dps": 0.0038},
    "ideal": {"noise_density_dps": 0.0, "bias_dps": 0.0, "bias_instability_dps": 0.0, "scale_error": 0.0,
              "cross_axis": 0.0, "g_sensitivity_dps": 0.0},
}

MAG_PARTS: dict[str, dict] = {
    "lis3mdl": {},
    "ideal": {"noise_t": (0.0, 0.0, 0.0), "hard_iron_t": 0.0, "soft_iron": 0.0, "mounting_rad": 0.0},
}


def accel_model(part: str = "icm42688p", *, noise_pct_g: float | None = None, chip_seed: int = 0,
                **overrides) -> SensorModel:
    """The accelerometer of a 6-axis part as a `sensor.SensorModel` (12-bit counts on the wire).

    ``icm42688p``: 70 µg/√Hz over 72.5 Hz (0.06 % g per sample), zero-g offset 20 mg (σ), scale
    0.5 %, mounting 1.5° per axis, uncalibrated (the chips report the nominal calibration);
    ``ideal``: none of it. ``noise_pct_g`` overrides the noise (the benchmarks': 1 % g)."""
    if part == "icm42688p":
        fields = {"noise_pct_g": 70e-6 * np.sqrt(72.5) * 100, "bias_mps2": 0.020 * G0, "scale_error": 0.005,
                  "misalignment_rad": float(np.radians(1.5)), "factory_calibrated": False}
    elif part == "ideal":
        fields = {}
    else:
        raise ValueError(f"Unknown accelerometer part {part!r} (expected 'icm42688p' or 'ideal')")
    if noise_pct_g is not None:
        fields["noise_pct_g"] = noise_pct_g
    return SensorModel(chip_seed=chip_seed, **{**fields, **overrides})


@dataclass(frozen=True)
class ImuReading:
    """What the chips report for ``T`` SYNCs (`ImuArray.read`); SI values are the counts converted
    with the nominal (or, for the accelerometer, the chips' stored) calibration — what a host sees
    before any calibration of its own.

    Attributes
    ----------
    t_s : ndarray, shape (T,)
        Sample instants, s.
    timestamp_us : ndarray of int32, shape (T, n)
        Each sample's time after its SYNC, µs (the per-sample chip timestamp).
    accel_counts : ndarray of int16, shape (T, n, 3); accel_status : uint8 (T, n)
    accel_mps2 : ndarray, shape (T, n, 3)
    gyro_counts : ndarray of int32, shape (T, n, 3) or None; gyro_saturated : bool (T, n)
    gyro_rps : ndarray, shape (T, n, 3) or None
    mag_counts : ndarray of int32, shape (T, n, 3) or None; mag_saturated : bool (T, n)
    mag_t : ndarray, shape (T, n, 3) or None
    """

    t_s: np.ndarray
    timestamp_us: np.ndarray
    accel_counts: np.ndarray
    accel_status: np.ndarray
    accel_mps2: np.ndarray
    gyro_counts: np.ndarray | None = None
    gyro_saturated: np.ndarray | None = None
    gyro_rps: np.ndarray | None = None
    mag_counts: np.ndarray | None = None
    mag_saturated: np.ndarray | None = None
    mag_t: np.ndarray | None = None

    @property
    def sensors(self) -> str:
        """``accel``, ``accel+gyro`` or ``accel+gyro+mag``."""
        return "+".join(["accel"] + (["gyro"] if self.gyro_counts is not None else [])
                        + (["mag"] if self.mag_counts is not None else []))


def _adc(value: np.ndarray, bits: int = 16) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = count_limits(bits)
    raw = np.rint(value)
    counts = np.clip(raw, lo, hi).astype(np.int32)
    sat = np.any((counts == lo) | (counts == hi), axis=-1)
    return counts, sat


class ImuArray:
    """The chips of ``n_links`` links: an accelerometer each, optionally a gyroscope and a
    magnetometer (module docstring). Stateful: the gyroscopes' bias processes run on from one
    `read` to the next (times must increase).

    Parameters
    ----------
    n_links : int
    accel : SensorModel
        The accelerometers (`accel_model`); its ``misalignment`` is the package's mounting.
    gyro : GyroModel, optional
    mag : MagModel, optional
    field : MagneticField, optional
        Where the magnetometers are (default Earth's field alone).
    rate_hz : float
        The SYNC rate: sets the gyroscope's noise bandwidth (``rate/2``).
    seed : int
        Seeds the noise streams (one per sensor) and the bias processes.
    sample_delay_us : int
        Time from a SYNC to the sample, µs (every chip alike: `ImuReading.timestamp_us`).
    """

    def __init__(self, n_links: int, *, accel: SensorModel | None = None, gyro: GyroModel | None = None,
                 mag: MagModel | None = None, field: MagneticField | None = None, rate_hz: float = 145.0,
                 seed: int = 0, sample_delay_us: int = 0) -> None:
        if not (isinstance(n_links, (int, np.integer)) and n_links > 0):
            raise ValueError(f"Invalid n_links: {n_links!r} (need an integer > 0)")
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"Invalid rate_hz: {rate_hz!r} (need > 0)")
        if not (isinstance(seed, (int, np.integer)) and seed >= 0):
            raise ValueError(f"Invalid seed: {seed!r} (need an integer >= 0)")
        if not (isinstance(sample_delay_us, (int, np.integer)) and 0 <= sample_delay_us < 1e6 / rate_hz):
            raise ValueError(f"Invalid sample_delay_us: {sample_delay_us!r} (need 0 <= delay < one period)")
        self.n_links = int(n_links)
        self.accel = accel if accel is not None else SensorModel()
        self.gyro = gyro
        self.mag = mag
        self.field = field if field is not None else MagneticField()
        self.rate_hz = float(rate_hz)
        self.seed = int(seed)
        self.sample_delay_us = int(sample_delay_us)
        self._accel_errors = self.accel.chip_errors(self.n_links)
        self._cal = self.accel.stored_calibration(self.n_links)
        self._gyro_errors = gyro.errors(self.n_links) if gyro is not None else None
        self._mag_errors = mag.errors(self.n_links) if mag is not None else None
        #: ``W M_mᵀ``, computed once (`MagErrors.distortion` computes it at each call)
        self._mag_distortion = self._mag_errors.distortion if mag is not None else None
        self.reset()

    def reset(self) -> None:
        """Power-on again: fresh noise streams and a fresh bias process (the fixed errors stay)."""
        s = self.seed
        self._rng_accel = np.random.Generator(np.random.MT19937([s, 0xACC]))
        self._rng_gyro = np.random.Generator(np.random.MT19937([s, 0x6790]))
        self._rng_bias = np.random.Generator(np.random.MT19937([s, 0xB1A5]))
        self._rng_mag = np.random.Generator(np.random.MT19937([s, 0x3A6]))
        n = self.n_links
        self._last_t: float | None = None
        g = self.gyro
        sigma = 0.0 if g is None else g.bias_instability_dps * _DPS
        self._gm = self._rng_bias.standard_normal((n, 3)) * sigma  # stationary start
        self._rw = np.zeros((n, 3))

    # ------------------------------------------------------------------ hidden truth
    @property
    def accel_errors(self):
        """`sensor.ChipErrors` of the accelerometers (offset, sensitivity, mounting ``M``)."""
        return self._accel_errors

    @property
    def gyro_errors(self) -> GyroErrors | None:
        return self._gyro_errors

    @property
    def mag_errors(self) -> MagErrors | None:
        return self._mag_errors

    @property
    def gyro_bias_rps(self) -> np.ndarray:
        """The gyroscopes' total bias now (turn-on + instability), rad/s, shape (n, 3)."""
        if self._gyro_errors is None:
            raise ValueError("no gyroscopes")
        return self._gyro_errors.bias_rps + self._gm + self._rw

    # ------------------------------------------------------------------ reading
    def _bias_path(self, t: np.ndarray) -> np.ndarray:
        """Bias instability at every instant of ``t`` (T,), continuing the state: (T, n, 3) rad/s."""
        g = self.gyro
        T, n = t.size, self.n_links
        dt = np.diff(t, prepend=t[0] if self._last_t is None else self._last_t)  # increasing: `read`
        sigma = g.bias_instability_dps * _DPS
        z = self._rng_bias.standard_normal((T, n, 3))
        out = np.empty((T, n, 3))
        b = self._gm
        if sigma > 0:
            phi = np.exp(-dt / g.bias_time_constant_s)
            q = sigma * np.sqrt(1.0 - phi * phi)
            for k in range(T):
                b = phi[k] * b + q[k] * z[k]
                out[k] = b
        else:
            out[:] = b
        self._gm = b
        if g.rate_random_walk_dps > 0:
            w = self._rng_bias.standard_normal((T, n, 3)) * (g.rate_random_walk_dps * _DPS * np.sqrt(dt))[:, None, None]
            rw = self._rw + np.cumsum(w, axis=0)
            self._rw = rw[-1].copy()
            out += rw
        self._last_t = float(t[-1])
        return out

    def read(self, truth) -> ImuReading:
        """Every chip's sample at every instant of ``truth`` (`motion.Truth`, sample instants).

        Returns
        -------
        ImuReading
        """
        f = np.asarray(truth.specific_force, dtype=float)
        t = np.asarray(truth.t_s, dtype=float)
        if f.ndim != 3 or f.shape[1:] != (self.n_links, 3) or t.shape != (f.shape[0],):
            raise ValueError(f"Expected a truth of {self.n_links} links, got specific force {f.shape}, "
                             f"times {t.shape}.")
        T, n = f.shape[:2]
        if np.any(np.diff(t) <= 0) or (self._last_t is not None and t[0] <= self._last_t):
            raise ValueError("ImuArray.read: sample times must increase (within and across reads)")
        acounts, astatus = self.accel.sample(f, self._rng_accel)
        off, sens = self._cal
        out = {"t_s": t, "timestamp_us": np.full((T, n), self.sample_delay_us, dtype=np.int32),
               "accel_counts": acounts, "accel_status": astatus,
               "accel_mps2": counts_to_si(acounts.astype(float), off, sens)}
        M = self._accel_errors.misalignment
        if self.gyro is not None:
            g, e = self.gyro, self._gyro_errors
            w_chip = np.einsum("nji,tnj->tni", M, np.asarray(truth.angular_velocity, dtype=float))
            f_chip = np.einsum("nji,tnj->tni", M, f)
            w = np.einsum("nij,tnj->tni", e.scale, w_chip) + e.bias_rps
            w += np.einsum("nij,tnj->tni", e.g_sensitivity, f_chip / G0)
            w += self._bias_path(t)
            sd = g.noise_std_rps(self.rate_hz)
            noise = self._rng_gyro.standard_normal((T, n, 3))
            if sd > 0:
                w += sd * noise
            counts, sat = _adc(w / _DPS * g.sensitivity)
            out.update(gyro_counts=counts, gyro_saturated=sat,
                       gyro_rps=counts / g.sensitivity * _DPS)
        else:
            self._last_t = float(t[-1])
        if self.mag is not None:
            m, e = self.mag, self._mag_errors
            B = field_in_sensor_frames(self.field, truth.position, truth.frames)  # (T, n, 3) T
            val = np.einsum("nij,tnj->tni", self._mag_distortion, B) + e.hard_iron_t
            val += self._rng_mag.standard_normal((T, n, 3)) * np.asarray(m.noise_t)
            counts, sat = _adc(val / TESLA_PER_GAUSS * m.sensitivity)
            out.update(mag_counts=counts, mag_saturated=sat,
                       mag_t=counts / m.sensitivity * TESLA_PER_GAUSS)
        return ImuReading(**out)


#: the three sensor sets (`capsheet ... --sensors`)
SENSOR_SETS = ("accel", "accel+gyro", "accel+gyro+mag")


def imu_array(n_links: int, sensors: str = "accel+gyro", *, gyro_part: str = "icm42688p",
              mag_part: str = "lis3mdl", accel_part: str = "icm42688p", noise_pct_g: float | None = None,
              field: MagneticField | None = None, rate_hz: float = 145.0, seed: int = 0,
              chip_seed: int | None = None, gyro_range: GyroRange = GyroRange.DPS1000,
              mag_range: MagRange = MagRange.GAUSS4) -> ImuArray:
    """An `ImuArray` of named parts for a sensor set (`SENSOR_SETS`); ``chip_seed`` (default
    ``seed``) draws the fixed errors, ``seed`` the noise."""
    if sensors not in SENSOR_SETS:
        raise ValueError(f"Invalid sensors: {sensors!r} (expected one of {', '.join(SENSOR_SETS)})")
    cs = seed if chip_seed is None else chip_seed
    acc = accel_model(accel_part, noise_pct_g=noise_pct_g, chip_seed=cs)
    gyro = GyroModel.part(gyro_part, chip_seed=cs, range=gyro_range) if "gyro" in sensors else None
    mag = MagModel.part(mag_part, chip_seed=cs, range=mag_range) if "mag" in sensors else None
    return ImuArray(n_links, accel=acc, gyro=gyro, mag=mag, field=field, rate_hz=rate_hz, seed=seed)


def simulate(scene, imu: ImuArray, duration_s: float, *, start_s: float = 0.0, chunk_s: float = 1.0,
             jitter_s: float = 0.0):
    """Stream ``duration_s`` of ``scene`` read by ``imu`` at its rate, in chunks of ``chunk_s``:
    yields ``(truth, reading)`` per chunk (`motion.Truth`, `ImuReading`). SYNC instants from
    `motion.sample_times` (``jitter_s``: a host timer's jitter, seeded by the imu's seed); the
    samples are taken ``imu.sample_delay_us`` after each SYNC."""
    from .motion import sample_times

    if not (np.isfinite(chunk_s) and chunk_s > 0):
        raise ValueError(f"Invalid chunk_s: {chunk_s!r} (need > 0)")
    rng = np.random.Generator(np.random.MT19937([imu.seed, 0x5C]))
    syncs = sample_times(duration_s, imu.rate_hz, start_s=start_s, jitter_s=jitter_s, rng=rng if jitter_s else None)
    t = syncs + imu.sample_delay_us * 1e-6
    per = max(1, int(round(chunk_s * imu.rate_hz)))
    for k in range(0, t.size, per):
        truth = scene.sample(t[k:k + per])
        yield truth, imu.read(truth)
