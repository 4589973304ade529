"""The fused estimator's noise model and tuning (`host.analysis.motion.fused`, docs/estimator.md
§8): one frozen dataclass, its defaults the chips' datasheets."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..estimator import G0


@dataclass(frozen=True)
class FusedConfig:
    """The fused estimator's noise model and tuning (standard deviations).

    Parameters
    ----------
    accel_noise_mps2 : float
        Accelerometer white noise per axis per sample, m/s²: the ICM-42688-P's 70 µg/√Hz
        (TDK InvenSense DS-000347, Table 2, "Noise spectral density") over the Nyquist band of
        145 Hz samples, 0.060 % g (`datasheet_noise`). Chips noisier than their datasheet (the
        benchmarks' 1 % g) need it told.
    gyro_noise_rps : float
        Gyroscope white noise per axis per sample, rad/s: the ICM-42688-P's 2.8 mdps/√Hz
        (DS-000347, Table 1, "Rate noise spectral density") at 145 Hz, 0.024 °/s.
    gyro_bias_std_rps : float
        Each chip's own bias uncertainty at the start, rad/s (after calibration: 0.01 °/s),
        independent from chip to chip.
    gyro_common_bias_std_rps : float or None
        The uncertainty of the bias all chips share, rad/s (the sheet's common tilt rate, step
        2): a calibration's residual is mostly this — the board's chips, calibrated together,
        keep 0.05–0.07 °/s in common and 0.002–0.007 °/s each of their own
        (benchmarks/bench_motion.py). None: `gyro_bias_std_rps` (chips whose biases are
        independent, uncalibrated parts).
    gyro_bias_walk_rps : float
        The bias's random walk, rad/s/√s (3 °/h of bias instability over 100 s ≈ 2e-6).
    gyro_scale_error : float
        Residual scale and cross-axis error after calibration taken as white: process noise
        ``∝ |ω| Δt``, independent from step to step.
    gyro_scale_fixed_error : float or tuple of 3 tuples of 3 floats
        Residual scale and cross-axis error after calibration taken as fixed per chip: the
        standard deviation of each entry of ``E`` in ``ω_read = (I + E) ω + b`` (link frame;
        row: the axis read, column: the axis turned about), the entries independent; one number
        for all nine, or a 3 x 3 of them (a calibration determines some columns better than
        others: bench_motion's board leaves 0.03-0.05 % in the column of turns about z, 0.07-0.2 %
        in the others). Carried as a consider state (`host.analysis.motion._consider`), so its
        tilt error grows with the angle turned and averages out over a back-and-forth turn, as a
        fixed error's does. 0: not modelled (the white term alone).
    gyro_gsens_fixed_error : float or tuple of 3 tuples of 3 floats
        Residual g-sensitivity after calibration, fixed per chip: the standard deviation of each
        entry of ``Γ`` in ``ω_read = ω + Γ f / g + b``, rad/s per g (one number or a 3 x 3, as
        `gyro_scale_fixed_error`). What it adds at the first snapshot's pose is part of the bias
        there; as the link turns, the specific force ``f`` in its frame changes and so does the
        rate's error, ``Γ (f − f₀) / g``: carried as a consider state beside the scale error's.
        0: not modelled.
    accel_fixed_error_rad : float
    accel_common_fixed_error_rad : float or tuple of 3 floats
        What a calibration leaves of the accelerometers' errors, rad: each chip's own, as the
        tilt it gives per horizontal axis (`accel_fixed_error_rad`), and the rotation the chips'
        frames share, one figure for every axis or three (`accel_common_fixed_error_rad`: about
        the flat board's x, y and z — along the i-links, along the j-links, up; the board's
        pose when they were calibrated, alike in the world while the sheet lay flat on it and
        fixed in the chips' frames since, so a bent sheet's links carry it each turned by its
        own turn since the flat layout). A fixed error does not average out as the noise does,
        and nothing the sheet reads tells it from a tilt: the filter follows the accelerometers'
        frames, and the links' frames lie off them by it, so it is added to the covariances
        reported (`MotionEstimate.orientation_cov_rad2`, the part every link shares also to
        `common_tilt_cov_rad2`; `_common.add_fixed_tilt`), not estimated. 0: not told.
    orientation_walk_rad : float
        A floor of process noise on every orientation, rad/√s (what the model leaves out).
    rel_accel_error : float
        Fraction of a link's relative acceleration taken as the model's error (step 2).
    accel_floor_mps2 : float
        A floor on the accelerometer update's noise, m/s².
    sheet_velocity_std_mps, sheet_velocity_time_s : float
        The sheet's horizontal velocity: its spread about zero, m/s, and its correlation time,
        s (a sheet held in the hands, worn or waved: 0.5 m/s over 0.5 s). With
        `sheet_position_std_m` and `sheet_position_time_s` (its position about its mean: 0.1 m
        over 1 s) this is what tells the sheet's common tilt from its translation (step 2): a
        sheet under a steady acceleration of its own for longer (a car's, a lift's) breaks it.
    gate : float
        Mahalanobis distance² (3 axes) beyond which an accelerometer update is inflated.
    lattice_floor_rad : float
        Model floor of the closure and normal residuals (unit vectors ≈ radians).
    mag_noise_t : float
        Magnetometer white noise per axis per sample, tesla: the LIS3MDL's 3.2 / 4.1 mG RMS
        (x, y / z, ultra-high-performance mode; ST DocID024204, Table 3), 0.32–0.41 µT, taken
        as 0.4 µT (an MMC5983MA's 0.04–0.12 µT would be told).
    mag_floor_rad : float
        A floor on a link's heading error from its calibrated magnetometer, rad.
    mag_common_floor_rad : float
        A floor on the error of the links' mean magnetic heading, rad.
    heading_walk_rad : float
        Random walk of the sheet's common heading between magnetometer updates, rad/√s.
    initial_heading_std_rad : float
        Uncertainty of the first snapshot's heading (the magnetometers' median), rad.
    disturbance_tau_s : float
        Time constant of the per-link disturbance tests' averages, s.
    disturbance_heading_rad, disturbance_field_frac, disturbance_dip_rad : float
        One standard unit of each test: heading off the lattice's consensus, field magnitude off
        Earth's (fraction), dip off Earth's.
    disturbance_scale : float
        A link's magnetometer weight is scaled by ``1 / (1 + (s / scale)²)``, ``s`` its heading
        test in standard units.
    disturbance_persist_s : float
        How long a local disturbance is taken to last, s: what it adds to the field is a bias
        over that time, not noise that averages out, so the heading variance it implies enters
        every sample multiplied by ``persist / Δt``.
    mag_hold_weight : float
        A group of links (or the whole sheet) whose magnetometers' mean weight falls below this
        fraction of an undisturbed one's is held by the links' own yaw variances, as without
        magnetometers, fully at weight 0 (docs/estimator.md §8).
    mag_warmup_s : float
        A link's magnetometer is used once its tests have averaged this long, s (a magnet there
        from the start would otherwise be believed before it is seen).
    initial_yaw_std_rad : float
        Uncertainty of the first snapshot's yaws (the accelerometer-only estimate).
    heading_mode_rad, heading_mode_time_s : float
        While the magnetometers' weights do not hold the sheet's heading (a disturbance under
        much of the sheet), it follows the mode of the links' averaged heading residuals
        (Tukey's biweight of this width, rad; 0: not at all) with this time constant, s.
    dipole_significance : float
        A local disturbance is fitted as a point dipole beside uniform fields
        (`host.analysis.motion._dipole`) and its field taken out of the magnetometers' readings
        while the dipole explains the links' fields better than uniform fields alone by at
        least this F statistic (its six numbers against the residual; 0: never fitted).
    dipole_position_std : float
        How far a link's estimated position may be off, in link lengths, where the fitted
        dipole's field is taken out: the fit's field is then known only to its gradient times
        that, which enters the link's disturbance tests and its heading's variance as the fit's
        error (a link next to the magnet keeps its corrected heading at what it is worth
        instead of being taken as disturbed). 0: the fit's field taken as exact.
    """

    accel_noise_mps2: float = 70e-6 * G0 * float(np.sqrt(145.0 / 2.0))
    gyro_noise_rps: float = float(np.radians(2.8e-3 * np.sqrt(145.0 / 2.0)))
    gyro_bias_std_rps: float = float(np.radians(0.01))
    gyro_common_bias_std_rps: float | None = None
    gyro_bias_walk_rps: float = 2e-6
    gyro_scale_error: float = 2e-3
    gyro_scale_fixed_error: float | tuple = 0.0
    gyro_gsens_fixed_error: float | tuple = 0.0
    accel_fixed_error_rad: float = 0.0
    accel_common_fixed_error_rad: float | tuple = 0.0
    orientation_walk_rad: float = float(np.radians(0.05))
    rel_accel_error: float = 0.01
    accel_floor_mps2: float = 0.02
    sheet_velocity_std_mps: float = 0.5
    sheet_velocity_time_s: float = 0.5
    sheet_position_std_m: float = 0.1
    sheet_position_time_s: float = 1.0
    gate: float = 25.0
    lattice_floor_rad: float = 1e-3
    mag_noise_t: float = 0.4e-6
    mag_floor_rad: float = float(np.radians(0.5))
    mag_common_floor_rad: float = float(np.radians(0.1))
    heading_walk_rad: float = float(np.radians(0.05))
    initial_heading_std_rad: float = float(np.radians(2.0))
    disturbance_tau_s: float = 0.3
    disturbance_heading_rad: float = float(np.radians(0.5))
    disturbance_field_frac: float = 0.01
    disturbance_dip_rad: float = float(np.radians(0.5))
    disturbance_scale: float = 2.0
    disturbance_persist_s: float = 5.0
    mag_hold_weight: float = 0.5
    mag_warmup_s: float = 0.1
    initial_yaw_std_rad: float = 0.05
    heading_mode_rad: float = float(np.radians(0.75))
    heading_mode_time_s: float = 1.0
    dipole_significance: float = 25.0
    dipole_position_std: float = 0.5

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            v = getattr(self, name)
            if v is None and name == "gyro_common_bias_std_rps":
                continue
            if name in ("gyro_scale_fixed_error", "gyro_gsens_fixed_error") \
                    and isinstance(v, (tuple, list, np.ndarray)):
                a = np.asarray(v, dtype=object)
                if a.shape != (3, 3) or not all(
                        isinstance(x, (int, float, np.number)) and not isinstance(x, bool)
                        and np.isfinite(x) and x >= 0 for x in a.ravel()):
                    raise ValueError(f"Invalid {name}: {v!r} (need a number >= 0 or 3 x 3 of them)")
                continue
            if name == "accel_common_fixed_error_rad" and isinstance(v, (tuple, list, np.ndarray)):
                a = np.asarray(v, dtype=object)
                if a.shape != (3,) or not all(
                        isinstance(x, (int, float, np.number)) and not isinstance(x, bool)
                        and np.isfinite(x) and x >= 0 for x in a):
                    raise ValueError(f"Invalid {name}: {v!r} (need a number >= 0 or 3 of them)")
                continue
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.number)) \
                    or not np.isfinite(v) or v < 0:
                raise ValueError(f"Invalid {name}: {v!r} (need a finite number >= 0)")
        for name in ("accel_noise_mps2", "gyro_bias_std_rps", "disturbance_tau_s",
                     "disturbance_heading_rad", "disturbance_field_frac", "disturbance_dip_rad",
                     "disturbance_scale", "initial_yaw_std_rad", "lattice_floor_rad", "gate",
                     "sheet_velocity_std_mps", "sheet_velocity_time_s", "sheet_position_std_m",
                     "sheet_position_time_s", "heading_mode_time_s"):
            if getattr(self, name) <= 0:
                raise ValueError(f"Invalid {name}: {getattr(self, name)!r} (need > 0)")

    @property
    def fixed_errors(self) -> tuple[tuple[str, ...], np.ndarray] | None:
        """The gyroscopes' fixed errors told (`host.analysis.motion._consider`): their inputs'
        names (``"rate"`` for `gyro_scale_fixed_error`, ``"force"`` for
        `gyro_gsens_fixed_error`) and their entries' variances, shape (9 m,), row by row, block
        by block; None when neither is told."""
        names, var = [], []
        for name, v in (("rate", self.gyro_scale_fixed_error),
                        ("force", self.gyro_gsens_fixed_error)):
            v = np.broadcast_to(np.asarray(v, dtype=float), (3, 3))
            if v.any():
                names.append(name)
                var.append((v * v).ravel())
        return (tuple(names), np.concatenate(var)) if names else None
