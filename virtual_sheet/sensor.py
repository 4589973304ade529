"""Accelerometer model: from true specific force to the 12-bit counts a chip reports.

Per chip (link), fixed for the chip's life and drawn once from ``chip_seed``:

* offset (bias), counts, per axis;
* sensitivity, counts/g per axis: the range's nominal value times ``1 + scale error``;
* axis misalignment: the chip's axes are the link's sensor axes (docs/design.md) turned by a small
  rotation ``M`` (rotation vector with ``misalignment_rad`` standard deviation per component);
  the chip measures ``Mᵀ f``.

Per sample: white noise of ``noise_pct_g`` % of g per axis (seeded Mersenne Twister,
``np.random.Generator(np.random.MT19937(seed))``, as the paper), then the ADC:
``counts = clip(round(sensitivity · f / G0 + offset), −2048, +2047)``, flagged
`SampleStatus.SATURATED` when any axis sits at a limit. Optional motion acceleration (world frame)
breaks the paper's Assumption 1 on purpose.

A chip can report its true calibration (`SensorModel.true_calibration`); then
``protocol.constants.counts_to_si(counts, offset, sensitivity)`` undoes everything but the
misalignment, the noise and the quantisation. With ``factory_calibrated=False`` it reports the
nominal calibration instead (offset 0, nominal sensitivity), as a real chip fresh from the reel:
its bias and scale errors then reach the host, until the sheet is calibrated (docs/calibration.md)
and CAL_WRITE stores the result in the chip.

Named chip-error presets (`CHIP_ERRORS`, `chip_error_model`; ``capsheet virtual --chip-errors``):

============ ===================================================================================
none         ideal chips (bias, scale and misalignment 0), factory calibrated (the default)
realistic    a MEMS part glued by hand, uncalibrated: bias 30 mg, scale 1.5 %, misalignment
             1.5° per axis (standard deviations; scale draws clipped at 3 sigma). Of the order of
             MEMS datasheets (e.g. ADXL345: 0 g offset tens of mg, sensitivity tolerance a few %,
             cross-axis sensitivity ±1 % ≈ 0.6°) plus the mounting of a chip on a textile link
============ ===================================================================================

>>> import numpy as np
>>> counts, status = SensorModel().sample(np.array([[0.0, 0.0, G0]]))
>>> counts.tolist(), status.tolist()
([[0, 0, 1024]], [0])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocol.constants import ADC_MAX, ADC_MIN, G0, Range, SampleStatus, nominal_sensitivity
from protocol.rotations import rotvec_matrices

__all__ = ["SensorModel", "ChipErrors", "noisy_readings", "make_rng", "CHIP_ERRORS", "chip_error_model"]


def make_rng(rng: np.random.Generator | int) -> np.random.Generator:
    """A seeded Mersenne Twister generator from a seed, or ``rng`` itself if it is a Generator."""
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool) and rng >= 0:
        return np.random.Generator(np.random.MT19937(int(rng)))
    raise ValueError(f"Invalid rng: {rng!r} (expected a numpy Generator or a seed >= 0)")


def check_readings(readings: np.ndarray, batched: bool = False) -> np.ndarray:
    r = np.asarray(readings, dtype=float)
    if (r.ndim < 2 if batched else r.ndim != 2) or r.shape[-1] != 3:
        shape = "(..., n_links, 3)" if batched else "(n_links, 3)"
        raise ValueError(f"Expected `readings` to have shape {shape}, got {r.shape}.")
    if not np.all(np.isfinite(r)):
        raise ValueError("Expected `readings` to be finite; got NaN or inf.")
    return r


def noisy_readings(readings: np.ndarray, noise_pct_g: float,
                   rng: np.random.Generator | int) -> np.ndarray:
    """Readings plus white Gaussian noise, no ADC (for estimator tests, the paper's section 3.3).

    Parameters
    ----------
    readings : ndarray, shape (n_links, 3)
        Specific force, m/s², sensor frame.
    noise_pct_g : float
        Standard deviation per axis as a percentage of g (the paper's "noise level"; 5 means
        0.49 m/s²).
    rng : numpy Generator or int
        Seeded generator, or a seed for ``Generator(MT19937(seed))``.

    Returns
    -------
    ndarray, shape (n_links, 3)
        m/s², sensor frame.
    """
    r = check_readings(readings)
    if not (np.isfinite(noise_pct_g) and noise_pct_g >= 0):
        raise ValueError(f"Invalid noise_pct_g: {noise_pct_g!r} (need a finite value >= 0)")
    return r + make_rng(rng).normal(0.0, noise_pct_g / 100.0 * G0, r.shape)


@dataclass(frozen=True)
class ChipErrors:
    """The fixed errors of ``n`` chips (`SensorModel.chip_errors`).

    Attributes
    ----------
    offset_counts : ndarray, shape (n, 3)
        ADC offset per axis, counts (what the chip reads at zero specific force).
    sensitivity : ndarray, shape (n, 3)
        Counts per g per axis.
    misalignment : ndarray, shape (n, 3, 3)
        Rotation ``M`` whose columns are the chip's axes in the link's sensor frame.
    """

    offset_counts: np.ndarray
    sensitivity: np.ndarray
    misalignment: np.ndarray


_CHIP_ERRORS: dict = {}  # (SensorModel, n_links) -> ChipErrors, read-only arrays


@dataclass(frozen=True)
class SensorModel:
    """How the chips turn specific force into counts (module docstring). Validated when built.

    Parameters
    ----------
    noise_pct_g : float
        White noise per axis per sample, standard deviation in % of g (ADXL345 ≈ 0.26, the
        paper's worst usable 5).
    bias_mps2 : float
        Standard deviation of the per-chip, per-axis offset, m/s².
    bias_counts : float
        Further per-chip offset standard deviation, ADC counts (adds to ``bias_mps2``).
    scale_error : float
        Standard deviation of the per-chip, per-axis relative sensitivity error (0.01 = 1 %).
    misalignment_rad : float
        Standard deviation of each component of the per-chip axis rotation vector, radians.
    range : Range
        ADC full-scale range (``protocol.constants.Range``); sets the nominal sensitivity.
    motion_accel_mps2 : tuple of 3 floats, optional
        Motion acceleration of every link, world frame, m/s² (Assumption 1 broken); `sample`
        then needs the link frames.
    chip_seed : int
        Seed of the per-chip errors (the same chips every run).
    factory_calibrated : bool
        The chips report their true offset and sensitivity in CAL_DATA (default); False: the
        nominal ones (`stored_calibration`).
    """

    noise_pct_g: float = 0.0
    bias_mps2: float = 0.0
    bias_counts: float = 0.0
    scale_error: float = 0.0
    misalignment_rad: float = 0.0
    range: Range = Range.G2
    motion_accel_mps2: tuple[float, float, float] | None = None
    chip_seed: int = 0
    factory_calibrated: bool = True

    def __post_init__(self) -> None:
        for name in ("noise_pct_g", "bias_mps2", "bias_counts", "scale_error", "misalignment_rad"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float, np.floating, np.integer))
                    and np.isfinite(value) and value >= 0):
                raise ValueError(f"Invalid {name}: {value!r} (need a finite number >= 0)")
        if self.scale_error >= 0.5:
            raise ValueError(f"Invalid scale_error: {self.scale_error!r} (need < 0.5)")
        try:
            object.__setattr__(self, "range", Range(self.range))
        except ValueError as exc:
            raise ValueError(f"Invalid range: {self.range!r} (expected a Range code 0..3)") from exc
        if self.motion_accel_mps2 is not None:
            a = np.asarray(self.motion_accel_mps2, dtype=float)
            if a.shape != (3,) or not np.all(np.isfinite(a)):
                raise ValueError(f"Invalid motion_accel_mps2: {self.motion_accel_mps2!r} "
                                 "(expected 3 finite numbers, m/s², world frame)")
            object.__setattr__(self, "motion_accel_mps2", tuple(float(x) for x in a))
        if not isinstance(self.factory_calibrated, (bool, np.bool_)):
            raise ValueError(f"Invalid factory_calibrated: {self.factory_calibrated!r} (need True or False)")
        if not (isinstance(self.chip_seed, (int, np.integer)) and self.chip_seed >= 0):
            raise ValueError(f"Invalid chip_seed: {self.chip_seed!r} (need an integer >= 0)")

    @property
    def nominal_sensitivity(self) -> float:
        """Counts per g of the configured range."""
        return nominal_sensitivity(self.range)

    @property
    def noise_std_mps2(self) -> float:
        """Noise standard deviation per axis, m/s²."""
        return self.noise_pct_g / 100.0 * G0

    def chip_errors(self, n_links: int) -> ChipErrors:
        """The fixed errors of chips ``0 .. n_links-1``, drawn from ``chip_seed``.

        The draws are made in a fixed order whatever the standard deviations, so changing one
        error's size does not change the others' pattern.
        """
        if not (isinstance(n_links, (int, np.integer)) and n_links >= 0):
            raise ValueError(f"Invalid n_links: {n_links!r} (need an integer >= 0)")
        key = (self, int(n_links))
        hit = _CHIP_ERRORS.get(key)  # the same model and size: the same draws (sample() per SYNC)
        if hit is not None:
            return hit
        g = np.random.Generator(np.random.MT19937(int(self.chip_seed)))
        z_bias = g.standard_normal((n_links, 3))
        z_scale = g.standard_normal((n_links, 3))
        z_rot = g.standard_normal((n_links, 3))
        sens0 = self.nominal_sensitivity
        offset = z_bias * (self.bias_mps2 / G0 * sens0 + self.bias_counts)
        sensitivity = sens0 * (1.0 + self.scale_error * np.clip(z_scale, -3, 3))
        if n_links:
            M = rotvec_matrices(z_rot * self.misalignment_rad)
        else:
            M = np.zeros((0, 3, 3))
        e = ChipErrors(offset_counts=offset, sensitivity=sensitivity, misalignment=M.reshape(n_links, 3, 3))
        for a in (e.offset_counts, e.sensitivity, e.misalignment):
            a.setflags(write=False)
        if len(_CHIP_ERRORS) >= 16:
            _CHIP_ERRORS.clear()
        _CHIP_ERRORS[key] = e
        return e

    def true_calibration(self, n_links: int) -> tuple[np.ndarray, np.ndarray]:
        """What an ideal calibration of each chip finds (for CAL_DATA).

        Returns
        -------
        offset_counts : ndarray, shape (n_links, 3)
            Counts at zero specific force, per axis.
        sensitivity : ndarray, shape (n_links, 3)
            Counts per g, per axis.
        """
        e = self.chip_errors(n_links)
        return e.offset_counts, e.sensitivity

    def stored_calibration(self, n_links: int) -> tuple[np.ndarray, np.ndarray]:
        """What the chips hold and report in CAL_DATA before any CAL_WRITE: `true_calibration` if
        ``factory_calibrated``, else offset 0 and the nominal ±2 g sensitivity.

        Returns ``(offset_counts (n_links, 3), sensitivity (n_links, 3))``, ±2 g counts.
        """
        if self.factory_calibrated:
            return self.true_calibration(n_links)
        return np.zeros((n_links, 3)), np.full((n_links, 3), nominal_sensitivity(Range.G2))

    def chip_readings(self, readings: np.ndarray, rng: np.random.Generator | int | None = None,
                      *, frames: np.ndarray | None = None) -> np.ndarray:
        """Specific force along each chip's own axes, with motion and noise, before the ADC.

        Parameters and the order of random draws are those of `sample`; m/s², shape of ``readings``.
        """
        f = check_readings(readings, batched=True)
        n = f.shape[-2]
        if self.motion_accel_mps2 is not None:
            if frames is None:
                raise ValueError("motion_accel_mps2 is set: sample() needs `frames` "
                                 "(link_frames(joints)) to rotate it into the sensor frames")
            frames = np.asarray(frames, dtype=float)
            if frames.shape != f.shape + (3,):
                raise ValueError(f"Expected `frames` to have shape {f.shape + (3,)}, got {frames.shape}.")
            f = f + np.einsum("...nij,i->...nj", frames, np.asarray(self.motion_accel_mps2))
        e = self.chip_errors(n)
        f = np.einsum("nij,...ni->...nj", e.misalignment, f)  # Mᵀ f
        if self.noise_pct_g > 0:
            if rng is None:
                raise ValueError("noise_pct_g > 0: sample() needs a seeded `rng` (Generator or seed)")
            f = f + make_rng(rng).normal(0.0, self.noise_std_mps2, f.shape)
        return f

    def sample(self, readings: np.ndarray, rng: np.random.Generator | int | None = None, *,
               frames: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """One SYNC's samples of all chips.

        Parameters
        ----------
        readings : ndarray, shape (n_links, 3) or (..., n_links, 3)
            True specific force, m/s², each link's sensor frame (`geometry.ideal_readings`); leading
            dimensions are successive SYNCs (the same draws as one call per SYNC, in order).
        rng : numpy Generator or int, optional
            Noise source (seeded); required when ``noise_pct_g > 0``.
        frames : ndarray, shape (..., n_links, 3, 3), optional
            Rotations sensor -> world (`geometry.link_frames`); required with motion acceleration.

        Returns
        -------
        counts : ndarray of int16, shape (..., n_links, 3)
            12-bit two's-complement ADC counts, in ``[-2048, 2047]``.
        status : ndarray of uint8, shape (..., n_links)
            `SampleStatus` flags: ``SATURATED`` when any axis sits at an ADC limit.
        """
        f = self.chip_readings(readings, rng, frames=frames)
        e = self.chip_errors(f.shape[-2])
        raw = np.rint(f / G0 * e.sensitivity + e.offset_counts)
        counts = np.clip(raw, ADC_MIN, ADC_MAX).astype(np.int16)
        saturated = np.any((counts == ADC_MIN) | (counts == ADC_MAX), axis=-1)
        status = np.where(saturated, np.uint8(SampleStatus.SATURATED),
                          np.uint8(SampleStatus.OK)).astype(np.uint8)
        return counts, status


#: Named chip-error presets (module docstring): SensorModel fields, standard deviations.
CHIP_ERRORS: dict[str, dict] = {
    "none": {},
    "realistic": {"bias_mps2": 0.030 * G0, "scale_error": 0.015,
                  "misalignment_rad": float(np.radians(1.5)), "factory_calibrated": False},
}


def chip_error_model(name: str, *, noise_pct_g: float = 0.0, chip_seed: int = 0,
                     **overrides) -> SensorModel:
    """The `SensorModel` of a named chip-error preset (`CHIP_ERRORS`), seeded by ``chip_seed``.

    >>> m = chip_error_model("realistic", noise_pct_g=0.3, chip_seed=4)
    >>> round(m.bias_mps2 / G0 * 1000), m.scale_error, m.factory_calibrated
    (30, 0.015, False)
    """
    if name not in CHIP_ERRORS:
        raise ValueError(f"Unknown chip errors {name!r} (expected one of {', '.join(CHIP_ERRORS)})")
    return SensorModel(noise_pct_g=noise_pct_g, chip_seed=chip_seed, **{**CHIP_ERRORS[name], **overrides})
