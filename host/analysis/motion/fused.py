"""The fused estimator: the lattice's loops with gyroscopes, accelerometers and magnetometers.
docs/estimator.md §8 gives the model, why it is built this way, and where it fails.

One `MotionEstimator` per sheet, fed one snapshot at a time (sans-I/O: the snapshot's time is an
argument, nothing reads a clock)::

    est = MotionEstimator(rows, cols, link_length)
    for t, accel, gyro, mag in stream:                # calibrated SI values, link frames
        e = est.update(t, accel, gyro, mag)           # -> MotionEstimate (joints, frames, ...)

Per link the state is its orientation ``R`` (sensor -> world) and its gyroscope's bias ``b``
(link frame), with an error-state covariance ``P`` (6 x 6: a small rotation in the world frame,
``R = exp([δθ]×) R̂``, and the bias error). Every snapshot:

1. **Gyroscope: the process model.** ``R ← R exp([Δθ]×)`` with the rate less the bias, second
   order over the sample interval (the two samples' mean plus the coning term); ``P`` grows by
   the gyroscope's noise, a rate-proportional term (residual scale and cross-axis errors: white,
   or fixed per chip as a consider state, `_consider`) and a small floor for what the model
   leaves out; the bias is a random walk.
2. **Linear acceleration from the lattice.** Every link's direction ``d = R e_x`` has the second
   derivative ``d̈ = R (ω × (ω × e_x) + ω̇ × e_x)`` (``ω̇`` a second-order backward difference of the
   rates); the joints' accelerations follow from the ``d̈`` exactly as the joints follow from the
   ``d`` (`joints_from_directions`: ``p_b − p_a = L d`` holds at every instant, so it holds for
   the derivatives), and a chip's is the mean of its link's ends'. That fixes every link's
   acceleration relative to the others; what is common to all links (the sheet's translation,
   3 numbers) is taken from the accelerometers themselves, so each link's update (step 3)
   measures its tilt *relative to the sheet's*. The sheet's own tilt — a tilt of every link by
   ``c`` reads as a translation ``g × c`` at any one instant — is its own small filter
   (`_common.CommonMotion`): a sheet's velocity and position stay bounded
   (`FusedConfig.sheet_velocity_std_mps`, `FusedConfig.sheet_position_std_m`), so its
   translation averages out while a tilt persists; that filter's covariance is the part every
   link's tilt covariance shares (`MotionEstimate.common_tilt_cov_rad2`).
3. **Accelerometers: gravity plus that acceleration**, per link, an extended Kalman update of
   ``(δθ, δb)`` (the reading predicts ``Rᵀ (g + a)``); its noise grows with the link's relative
   acceleration (the model's own error) and a gate inflates it for a reading far off.
4. **The lattice and the magnetometers: one sparse least-squares problem in all links' yaw
   corrections** ``δψ`` (a rotation about world z), solved jointly: loop closure (eq. 4, xy part,
   per unit), the cells' normals (per link, its sensor y ⊥ the mean normal of its cells: exact on a
   Chebyshev net, docs/estimator.md §2), every link's own prediction (variance from ``P``), and the
   magnetometers' heading, each weighted by its agreement with the lattice's consensus and with
   Earth's field (magnitude and dip), averaged over `FusedConfig.disturbance_tau_s`: a local
   disturbance is detected and down-weighted per link. Before that, a disturbance that a point
   dipole explains across the sheet is fitted and its field taken out of the readings
   (`_dipole.LocalField`, `FusedConfig.dipole_significance`). The solution updates each link's whole
   state through its covariance (the bias about z learns from the loops).
5. **Joints** from the directions by least squares (`host.analysis.estimator.joints_from_directions`;
   all links are present, so by the cosine transform: `_lattice.joints_from_vectors`).

Without magnetometers the loops fix every relative yaw and the common heading is the only free
gauge (held by the gyroscopes: it wanders slowly, and `overlay` removes it); a group's common
offset (step 4) has a variance of its own where the loops see it (a curved sheet: the start's
offsets are corrected as it bends) and is held by its links' own variances where they do not (a
flat sheet, `_GROUP_SEEN`). With them heading is
absolute (world x is magnetic north turned by ``declination_rad``) and a flat horizontal sheet (the
paper's Case 1) is solvable.

The first snapshot initialises: roll, pitch and the relative yaws from the accelerometer-only
estimator (`host.analysis.estimator.estimate`, the sheet is assumed still at that instant), the
heading from the magnetometers' robust mean when present, and Earth's field (magnitude, dip) from
the magnetometers' median.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from ..estimator import G0, estimate
from ._consider import accel as consider_accel, propagate as consider_propagate, yaw as consider_yaw
from ._common import CommonMotion, add_fixed_tilt
from ._config import FusedConfig
from ._dipole import LocalField
from ._lattice import CLOSURE_SIGNS, joints_from_vectors, link_midpoints, topology
from ._linalg import (NUMPY_STEPS, USE_KERNEL, cross3, ddot, frames_from_angles,  # noqa: F401
                      ddot_rates, dist_tests, inv_sym3, mag_terms, mag_weights, mean_rows,
                      orientation_cov as _orientation_cov, pcg, robust_mode,
                      rotate_all, rotation_matrices, skew, turn_all, wrap)
from ._linalg import (coarse_inverse as _coarse_inverse, group_info as _group_info,  # noqa: F401
                      jt_times as _jt_times, kernel_args as _kernel_args,
                      kernel_ffi as _kffi,
                      kernel_lib as _klib, kernel_step as _kernel_step,
                      lattice_terms as _lattice_terms, normal_matvec as _normal_matvec,
                      np_lattice as _np_lattice, step as _step, step_apply as _step_apply,
                      yaw_solve as _yaw_solve)


__all__ = ["FusedConfig", "MotionEstimate", "MotionEstimator", "rotation_matrices", "frames_from_angles",
           "calibrated", "relative_accelerations"]

_EX = np.array([1.0, 0.0, 0.0])
#: Without magnetometers a group's common yaw offset (`_lattice.LatticeTopology.group`) is kept
#: apart from its links' own yaws where the loops see it: where turning the group's links
#: together keeps more than about this fraction of the lattice's information about them (a
#: curved sheet). On a flat sheet, which keeps nearly none, it is held by the links' own
#: variances (docs/estimator.md §8).
_GROUP_SEEN = 3e-3
#: the yaw solve's relative residual: its corrections are ~1e-4 rad a snapshot, so 1e-3 of them
#: (~1e-7 rad) is far below every noise, and what a snapshot leaves the next one measures again.
#: 3-4 iterations at 64x64 instead of 1e-6's 5-8; the bench's 14x14 shapes, headings and NEES
#: are the same to the digits it prints (the carry without magnetometers 0.0573 -> 0.0572 %, the
#: level sheet turning beside the magnet 1.6753 -> 1.6752 %), and a 64x64 wave's joints over
#: 3 s stay within 1e-4 % of the side of 1e-6's
_YAW_RTOL = 1e-3
_COARSE_EVERY = 8
_COLLECTIVE_MAX = 1.0  # rad²: a cap on the collective yaw variances (a mode nothing measures)
#: a link without a sample turns at its last rate this long (s), then at the sheet's (`_missing_rates`)
MISSING_HOLD_S = 0.03
#: A link carried without samples (`_missing_rates`) turns away from the truth by its rate's error
#: times the gap: its tilt variance grows by the valid links' rate spread times the gap squared,
#: up to this (rad; beyond it the linearised updates would not hold), so that its accelerometer
#: sets its tilt again when it returns. Only the tilt: a yaw so uncertain is not fixed by the loops
#: on a flat sheet. Half of a 14x14 sheet missing for 0.8 s (`MotionEstimator.update`'s `valid`),
#: mean error over 4 s, % of side, before → after: elbow 0.57 → 0.10, wave 2.0 → 1.2 (the gap
#: itself 4-7 %; 1-1.5 % for seconds after it before, 0.1 % after), tap 0.83 → 0.58.
_MISSING_MAX_RAD = 0.1
_GRAVITY_SF = np.array([0.0, 0.0, G0])  # the specific force of gravity alone, world (docs/design.md)


@dataclass(frozen=True, eq=False)
class MotionEstimate:
    """The fused estimator's output for one snapshot.

    Attributes
    ----------
    t_s : float
        The snapshot's time, s (the latest of its samples').
    joints : ndarray, shape (rows, cols, 3)
        Metres, world frame, joint ``(0, 0)`` at the origin.
    frames : ndarray, shape (n_links, 3, 3)
        Every link's sensor -> world rotation (its direction is the first column).
    gyro_bias_rps : ndarray, shape (n_links, 3)
        The estimated bias, rad/s, link frames (what is left after calibration).
    mag_weight : ndarray, shape (n_links,) or None
        Each magnetometer's weight in (0, 1] (a disturbed one near 0); None without them.
    common_accel_mps2 : ndarray, shape (3,)
        The acceleration common to all links (the sheet's translation), world.
    heading_absolute : bool
        True when magnetometers make the heading absolute (world x: magnetic north turned by the
        declination); False: heading is a gauge.
    timings : dict
        Wall time of the stages, s: ``propagate``, ``accel``, ``lattice``, ``joints``, ``total``.
    orientation_cov_rad2 : ndarray, shape (n_links, 3, 3)
        Each link's orientation error covariance, rad², a small rotation in the world frame
        (``R_true = exp([δθ]×) R``): its own part plus what it shares with the sheet (the common
        tilt; with magnetometers its group's and the sheet's heading). Without magnetometers the
        yaw's is relative to the first snapshot's heading (a gauge).
    accel_nis : ndarray, shape (n_links,)
        Each link's accelerometer innovation ``y`` against its predicted covariance ``S``:
        ``yᵀ S⁻¹ y`` (χ² with 3 degrees of freedom for a consistent filter), NaN where the link
        had no sample (and at the first snapshot).
    common_tilt_cov_rad2 : ndarray, shape (2, 2)
        The part of every link's tilt covariance (the x, y block of ``orientation_cov_rad2``)
        that all links share: the sheet's common tilt, rad², world x and y. The links' tilt
        errors are correlated by it and independent otherwise.
    """

    t_s: float
    joints: np.ndarray
    frames: np.ndarray
    gyro_bias_rps: np.ndarray
    mag_weight: np.ndarray | None
    common_accel_mps2: np.ndarray
    heading_absolute: bool
    timings: dict = field(default_factory=dict)
    orientation_cov_rad2: np.ndarray | None = None
    common_tilt_cov_rad2: np.ndarray | None = None
    accel_nis: np.ndarray | None = None

    @property
    def directions(self) -> np.ndarray:
        """Unit link directions, shape (n_links, 3), world."""
        return self.frames[:, :, 0]




def relative_accelerations(frames: np.ndarray, omega: np.ndarray, omega_dot: np.ndarray,
                           rows: int, cols: int, link_length: float,
                           endpoints: np.ndarray | None = None) -> np.ndarray:
    """Every chip's acceleration less the mean of all chips', from the links' frames, rates and
    angular accelerations alone (module docstring, step 2): a link's direction ``d = R e_x`` has
    ``d̈ = R (ω × (ω × e_x) + ω̇ × e_x)``; the joints' accelerations follow from the ``d̈`` as the
    joints from the ``d`` (`_lattice.joints_from_vectors`), and a chip (at its link's midpoint) has the
    mean of its link's ends'.

    Parameters
    ----------
    frames : ndarray, shape (n_links, 3, 3)
        Sensor -> world.
    omega, omega_dot : ndarray, shape (n_links, 3)
        Angular velocity (rad/s) and its time derivative (rad/s²), link frames.

    Returns
    -------
    ndarray, shape (n_links, 3)
        m/s², world frame, summing to zero over the links.
    """
    dd = ddot(np.asarray(frames, dtype=float), np.asarray(omega, dtype=float),
              np.asarray(omega_dot, dtype=float))
    return _chips_relative(dd, rows, cols, link_length)


def _chips_relative(dd, rows, cols, link_length) -> np.ndarray:
    """`relative_accelerations` from the links' ``d̈`` (n_links, 3)."""
    a = link_midpoints(joints_from_vectors(dd, rows, cols, link_length))
    return a - mean_rows(a)


def calibrated(cal, accel_mps2, gyro_rps=None, mag_t=None):
    """The chips' readings corrected by one board capture's calibration
    (`host.analysis.imu_calibration.CaptureCalibration`, docs/calibration.md): what the fused
    estimator and its peers take. Arrays ``(..., n_links, 3)``, SI, as the chips report them;
    returns ``(accel, gyro, mag)`` in the link frames (None where not given). The gyroscope's
    g-sensitivity term uses the bias- and scale-corrected specific force in the chip's axes."""
    a = np.asarray(accel_mps2, dtype=float)
    acc = cal.accel.apply(a)
    gyr = mag = None
    if gyro_rps is not None:
        if cal.gyro is None:
            raise ValueError("The calibration has no gyroscope part (captured without gyroscopes).")
        gyr = cal.gyro.apply(gyro_rps, (a - cal.accel.bias) / cal.accel.scale)
    if mag_t is not None:
        if cal.mag is None:
            raise ValueError("The calibration has no magnetometer part (captured without them).")
        mag = cal.mag.apply(mag_t)
    return acc, gyr, mag


class MotionEstimator:
    """The fused estimator of one sheet (module docstring). Stateful, sans-I/O.

    Parameters
    ----------
    rows, cols : int
        Joints along i and j, each >= 2.
    link_length : float
        ``L``, metres.
    config : FusedConfig, optional
    declination_rad : float
        The yaw of magnetic north from world x (with magnetometers), radians.
    earth_field_t, dip_rad : float, optional
        Earth's field where the sheet is (a geomagnetic model's magnitude, tesla, and
        inclination, radians): the disturbance tests' reference. Default: the magnetometers'
        median at the first snapshot (a magnet under most of the sheet then biases it).
    initial_frames : ndarray, shape (n_links, 3, 3), optional
        A starting shape, every link's sensor -> world rotation: a known sheet, the last
        session's `MotionEstimate.frames`, or the static estimator's (`frames_from_angles` of
        its ``alpha, beta, yaws``). Default: the accelerometer-only estimate of the first
        snapshot (a level sheet's shear unknown to it).
    initial_std_rad : float or ndarray, shape (n_links,), optional
        The starting shape's uncertainty per link and axis, radians (default: the
        accelerometers' for tilt, `FusedConfig.initial_yaw_std_rad` for yaw).
    initial_bias_rps : ndarray, shape (n_links, 3), optional
        Starting gyroscope biases, rad/s, link frames (the last session's
        `MotionEstimate.gyro_bias_rps`); default 0.
    """

    def __init__(self, rows: int, cols: int, link_length: float, *,
                 config: FusedConfig | None = None, declination_rad: float = 0.0,
                 earth_field_t: float | None = None, dip_rad: float | None = None,
                 initial_frames: np.ndarray | None = None, initial_std_rad=None,
                 initial_bias_rps: np.ndarray | None = None) -> None:
        for name, v in (("rows", rows), ("cols", cols)):
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v < 2:
                raise ValueError(f"Invalid {name}: {v!r} (need an integer >= 2)")
        if isinstance(link_length, (bool, np.bool_)) or not isinstance(
                link_length, (int, float, np.number)) or not (np.isfinite(link_length)
                                                               and link_length > 0):
            raise ValueError(f"Invalid link_length: {link_length!r} (need a finite value > 0 m)")
        if not np.isfinite(declination_rad):
            raise ValueError(f"Invalid declination_rad: {declination_rad!r}")
        self.rows, self.cols = int(rows), int(cols)
        self.link_length = float(link_length)
        self.config = FusedConfig() if config is None else config
        if not isinstance(self.config, FusedConfig):
            raise ValueError(f"Invalid config: {config!r} (expected a FusedConfig)")
        self.declination_rad = float(declination_rad)
        if (earth_field_t is None) != (dip_rad is None):
            raise ValueError("Give Earth's field as both earth_field_t and dip_rad, or neither.")
        if earth_field_t is not None and not (
                np.isfinite(earth_field_t) and 0 < earth_field_t < 1e-3
                and np.isfinite(dip_rad) and abs(dip_rad) < np.pi / 2):
            raise ValueError(f"Invalid Earth's field: earth_field_t={earth_field_t!r} T (Earth: "
                             f"25e-6 .. "
                             f"65e-6), dip_rad={dip_rad!r} (need |dip| < pi/2)")
        self.earth_field = None if earth_field_t is None else (float(earth_field_t), float(dip_rad))
        self.topo = topology(self.rows, self.cols)
        self.n_links = self.topo.n_links
        self._j_links = np.flatnonzero(self.topo.group >= self.rows - 1)
        self._initial = self._check_initial(initial_frames, initial_std_rad, initial_bias_rps)
        self.reset()

    def _check_initial(self, frames, std, bias):
        n = self.n_links
        if frames is not None:
            R = np.array(frames, dtype=float)
            if R.shape != (n, 3, 3):
                raise ValueError(f"Expected `initial_frames` to have shape ({n}, 3, 3), got "
                                 f"{R.shape}.")
            if not np.all(np.isfinite(R)) \
                    or np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max() > 1e-6 \
                    or np.any(np.linalg.det(R) < 0):
                raise ValueError("Invalid initial_frames: need finite rotation matrices "
                                 "(sensor -> world).")
            frames = R
        if std is not None:
            sd = np.broadcast_to(np.asarray(std, dtype=float), (n,)) if np.ndim(std) <= 1 else None
            if sd is None or sd.shape != (n,) or not np.all(np.isfinite(sd)) or np.any(sd <= 0):
                raise ValueError(f"Invalid initial_std_rad: need radians > 0, a scalar or shape "
                                 f"({n},).")
            std = np.array(sd)
        if bias is not None:
            b = np.array(bias, dtype=float)
            if b.shape != (n, 3) or not np.all(np.isfinite(b)):
                raise ValueError(f"Expected `initial_bias_rps` to have shape ({n}, 3), finite, "
                                 f"got {b.shape}.")
            bias = b
        return frames, std, bias

    def reset(self) -> None:
        """Forget everything: the next snapshot initialises again."""
        self.R: np.ndarray | None = None
        self.bias = np.zeros((self.n_links, 3))
        self.P = np.zeros((self.n_links, 6, 6))
        self._C = None  # cross-covariance with the gyroscopes' fixed errors (`_consider`)
        self._t = None
        self._w_hist: list[np.ndarray] = []  # the last two bias-corrected rates
        self._with_mag: bool | None = None
        self._b_ref = None
        self._dist = None
        self._joints = None  # the last snapshot's joints (their midpoints: `_dipole` fits there)
        self._local = None  # the local disturbance's fit (`_dipole.LocalField`)
        self.snapshots = 0

    @property
    def sample_times_s(self) -> np.ndarray | None:
        """Each link's sample time as of the last `update` (a copy; None before the first)."""
        return None if self._t is None else np.array(self._t, dtype=float)

    # ------------------------------------------------------------------------------- input
    def _check(self, t_s, accel, gyro, mag, valid):
        n = self.n_links
        arrays = {}
        for name, a in (("accel", accel), ("gyro", gyro), ("mag", mag)):
            if a is None:
                arrays[name] = None
                continue
            x = np.asarray(a)
            if x.dtype.kind not in "iuf":
                raise ValueError(f"Invalid {name}: dtype {x.dtype} (need real numbers)")
            if x.shape != (n, 3):
                raise ValueError(f"Expected `{name}` to have shape ({n}, 3) for a {self.rows}x"
                                 f"{self.cols} lattice, got {x.shape}.")
            arrays[name] = x.astype(float, copy=False)
        if arrays["gyro"] is None:
            raise ValueError("The fused estimator needs gyroscopes (`gyro` of shape (n_links, 3)); "
                             "for accelerometers alone use host.analysis.estimator.estimate.")
        if valid is None:
            v = np.ones(n, bool)
        else:
            v = np.asarray(valid)
            if v.dtype != bool or v.shape != (n,):
                raise ValueError(f"Invalid valid: need a boolean mask of shape ({n},), got "
                                 f"{v.dtype} {v.shape}.")
        for name, x in arrays.items():
            if x is not None and not np.isfinite(np.add.reduce(x, axis=None)):
                # the sum is finite when every value is (the common case: one reduction)
                bad = v & ~np.all(np.isfinite(x), axis=1)
                if bad.any():
                    k = np.flatnonzero(bad)
                    raise ValueError(f"Non-finite {name} on valid links {k[:8].tolist()}"
                                     f"{' ...' if k.size > 8 else ''}; mask them with `valid`.")
        t = np.asarray(t_s, dtype=float)
        if t.shape not in ((), (n,)):
            raise ValueError(f"Invalid t_s: need seconds, a scalar or shape ({n},), got shape "
                             f"{t.shape}.")
        t = np.broadcast_to(t, (n,)).astype(float)
        if not np.all(np.isfinite(t[v])) or not v.any() and not np.all(np.isfinite(t)):
            raise ValueError("Invalid t_s: the valid links' sample times must be finite seconds.")
        if not v.all():  # a link without a sample has no time of its own: the snapshot's
            t[~v] = np.max(t[v]) if v.any() else t[0]
        if self._with_mag is not None and (arrays["mag"] is not None) != self._with_mag:
            raise ValueError("Magnetometer readings must be given on every snapshot or on none "
                             f"(this estimator started {'with' if self._with_mag else 'without'}).")
        if self._t is not None:
            dt = t - self._t
            back = v & (dt <= 0)
            if back.any():
                raise ValueError(f"Sample times must increase: links {np.flatnonzero(back)[:8].tolist()} "
                                 f"go from {self._t[back][0]!r} to {t[back][0]!r} s.")
        return t, arrays["accel"], arrays["gyro"], arrays["mag"], v

    # ------------------------------------------------------------------------------- update
    def update(self, t_s, accel, gyro, mag=None, valid=None) -> MotionEstimate:
        """Feed one snapshot, get the shape.

        Parameters
        ----------
        t_s : float or ndarray, shape (n_links,)
            Sample time(s), s: one for the snapshot or each link's own (the chip timestamps;
            ignored, and may be NaN, where ``valid`` is False); increasing from snapshot to
            snapshot.
        accel : ndarray, shape (n_links, 3)
            Specific force, m/s², link frames, calibrated.
        gyro : ndarray, shape (n_links, 3)
            Angular rate, rad/s, link frames, calibrated.
        mag : ndarray, shape (n_links, 3), optional
            Magnetic field, tesla, link frames, calibrated (every snapshot or none).
        valid : ndarray of bool, shape (n_links,), optional
            False: that link's sample did not arrive (its orientation is carried by its last
            rate for `MISSING_HOLD_S`, then by the sheet's, the valid links' mean in the world
            frame; its accelerometer and magnetometer are not used). Default: all valid.

        Returns
        -------
        MotionEstimate

        Raises
        ------
        ValueError
            Wrong shapes or dtypes, non-finite values on valid links, no gyroscope, times that do
            not increase, magnetometers on some snapshots only, no valid link at the first
            snapshot.
        """
        t0 = time.perf_counter()
        t, f, w, m, v = self._check(t_s, accel, gyro, mag, valid)
        self._cov_out = None
        if self.R is None:
            self._initialise(t, f, w, m, v)
            t1 = t2 = t3 = time.perf_counter()
            a_c = np.zeros(3)
        else:
            dt = t - self._t
            self._h = float(dt.mean())
            w_c = w - self.bias
            self._missing_s = np.where(v, 0.0, self._missing_s + dt)
            if not v.all():
                w_c = np.where(v[:, None], w_c, self._missing_rates(w_c, v))
            self._propagate(w_c, dt, f, v)
            t1 = time.perf_counter()
            a_c = self._accel_update(f, w_c, dt, v)
            t2 = time.perf_counter()
            self._lattice_update(m, v, dt)
            t3 = time.perf_counter()
            self._w_hist = [self._w_hist[-1], w_c]
            self._t = t
        joints = joints_from_vectors(self.R[:, :, 0], self.rows, self.cols, self.link_length)
        self._joints = joints
        t4 = time.perf_counter()
        cov, self._cov_out = self._cov_out, None
        cov, common = self._with_fixed(cov)
        self.snapshots += 1
        return MotionEstimate(t_s=float(np.max(t)), joints=joints, frames=self.R.copy(),
                              gyro_bias_rps=self.bias.copy(),
                              mag_weight=None if self._dist is None else self._weights.copy(),
                              common_accel_mps2=a_c, heading_absolute=bool(self._with_mag),
                              timings={"propagate": t1 - t0, "accel": t2 - t1,
                                       "lattice": t3 - t2, "joints": t4 - t3, "total": t4 - t0},
                              orientation_cov_rad2=cov, common_tilt_cov_rad2=common,
                              accel_nis=self._nis.copy())

    def orientation_cov(self) -> np.ndarray:
        """Every link's orientation error covariance, rad², world frame, shape (n_links, 3, 3)
        (`MotionEstimate.orientation_cov_rad2`)."""
        if self.R is None:
            raise ValueError("No orientation yet: feed a snapshot to `update` first.")
        return self._with_fixed(None)[0]

    def _with_fixed(self, cov):
        """The links' and the common tilt's covariances (`add_fixed_tilt`); ``cov`` None: from P."""
        cov = _orientation_cov(self.P, *self._cov_terms()) if cov is None else cov
        return add_fixed_tilt(cov, self._common.tilt_cov, self.R, self._j_links, self.config)

    def _cov_terms(self):
        """`_linalg.orientation_cov`'s terms beside ``P``: the common tilt's covariance and,
        with magnetometers, each link's share of its group's and the sheet's yaw variances."""
        return (self._common.tilt_cov,
                (self._s_group[self.topo.group] + self._s0) if self._with_mag else None)

    def _initialise(self, t, f, w, m, v) -> None:
        cfg = self.config
        if not v.any():
            raise ValueError("No valid link in the first snapshot: cannot initialise.")
        R0, std0, bias0 = self._initial
        if R0 is None:
            e = estimate(np.where(v[:, None], f, (0.0, 0.0, G0)), self.rows, self.cols,
                         self.link_length, valid=v if not v.all() else None, bad_readings="mask")
            gamma = np.where(np.isfinite(e.yaws), e.yaws, 0.0)
            alpha = np.where(np.isfinite(e.alpha), e.alpha, 0.0)
            beta = np.where(np.isfinite(e.beta), e.beta, 0.0)
            R = frames_from_angles(alpha, beta, gamma)
        else:
            R = R0.copy()
        n = self.n_links
        self._with_mag = m is not None
        if m is not None:
            R = self._initial_heading(R, m, v)
            if cfg.dipole_significance > 0:
                # a local disturbance's shape, fitted in the frame the first heading gives, is
                # taken out, and the heading taken again from what is left (`_dipole`)
                self._local = LocalField(self.topo.group >= self.rows - 1, cfg.dipole_significance,
                                         0.5 * self.link_length,
                                         (max(self.rows, self.cols) - 1) * self.link_length,
                                         cfg.dipole_position_std * self.link_length)
                m = self._local.remove(R, m, self._midpoints(joints_from_vectors(
                    R[:, :, 0], self.rows, self.cols, self.link_length)), v)
                if self._local.fit is not None:
                    R = self._initial_heading(R, m, v)
            W = np.einsum("kij,kj->ki", R, m)[v]
            F = float(np.median(np.linalg.norm(W, axis=1)))
            dip = float(np.median(np.arcsin(np.clip(-W[:, 2] / np.linalg.norm(W, axis=1), -1, 1))))
            self._b_ref = (F, dip) if self.earth_field is None else self.earth_field
            F, dip = self._b_ref
            self._dist = np.zeros((n, 3))
            self._dist_count = np.zeros(n)
            self._mode_psi = None  # the last robust mode of the heading residuals
            self._resid_avg = np.zeros(n)
            self._weights = np.zeros(n)  # none is used before its tests have run
        self.R = R
        tilt = (cfg.accel_noise_mps2 / G0) ** 2 + cfg.lattice_floor_rad ** 2
        yaw = np.full(n, cfg.initial_yaw_std_rad ** 2)
        if std0 is not None:
            tilt = yaw = std0 ** 2
        self.P[:] = 0.0
        self.P[:, 0, 0] = self.P[:, 1, 1] = tilt
        self.P[:, 2, 2] = yaw
        self.P[:, 3:, 3:] = np.eye(3) * cfg.gyro_bias_std_rps ** 2
        # each link's error's cross-covariance with its gyroscope's fixed scale and cross-axis
        # error (`_consider`), none at the start: the start's error does not come from it
        self._fixed = cfg.fixed_errors
        self._C = None if self._fixed is None else np.zeros((n, 6, 9 * len(self._fixed[0])))
        # the specific force each chip read at the start, in g (the g-sensitivity's error there
        # is part of its bias)
        self._f0 = np.where(v[:, None], f, _GRAVITY_SF) / G0
        if bias0 is not None:
            self.bias[:] = bias0
        self._t = t.copy()
        self._w_hist = [w.copy(), w.copy()]
        self._missing_s = np.where(v, 0.0, np.inf)  # how long each link has had no sample (s)
        self._missing_rate_var = 0.0
        g = self.topo.group
        self._s_group = (np.bincount(g, weights=yaw, minlength=self.topo.n_groups)
                         / self.topo.group_size)
        # without magnetometers the heading is a gauge the first snapshot sets: known exactly
        # then, it drifts only as the gyroscopes let it
        self._s0 = cfg.initial_heading_std_rad ** 2 if m is not None else cfg.lattice_floor_rad ** 2
        # the common tilt starts as the links' mean start (independent errors); its rate is the
        # biases' calibration residual, which the chips share
        self._common = CommonMotion(float(np.mean(tilt)) / max(int(v.sum()), 1),
                                    (cfg.gyro_bias_std_rps if cfg.gyro_common_bias_std_rps is None
                                     else cfg.gyro_common_bias_std_rps) ** 2,
                                    cfg.sheet_velocity_std_mps, cfg.sheet_velocity_time_s,
                                    cfg.sheet_position_std_m, cfg.sheet_position_time_s)
        self._nis = np.full(n, np.nan)
        self._cinv = None  # the yaw solve's coarse preconditioner (`_linalg.coarse_inverse`)

    def _initial_heading(self, R, m, v):
        """``R`` turned about world z so that the magnetometers' robust mean heading is magnetic
        north (`declination_rad`)."""
        W = np.einsum("kij,kj->ki", R, m)
        head = np.arctan2(W[:, 1], W[:, 0])
        off = wrap(self.declination_rad - head[v])
        phi = float(np.arctan2(np.median(np.sin(off)), np.median(np.cos(off))))
        phi += float(np.median(wrap(off - phi)))
        return rotate_all(rotation_matrices(np.array([0.0, 0.0, phi])), R)

    def _midpoints(self, joints):
        """Every link's midpoint, (n_links, 3), from the joints (rows, cols, 3)."""
        return link_midpoints(joints)

    # ------------------------------------------------------------------------------- 1. gyro
    def _missing_rates(self, w_c, v) -> np.ndarray:
        """The rates links without a sample turn at: for `MISSING_HOLD_S` each its last rate (a
        sample or two lost: nothing knows the link's own motion better), then the sheet's — the
        valid links' mean rate in the world frame, in the link's own frame (with no valid link,
        each its last). Held for the whole gap, the last rate turned a carried sheet's links by the
        carry's change of rate since: a gateway's links missing for 0.6 s (half of a 14x14
        sheet) left the estimate 2.8 % of side off for seconds after they came back, against
        0.40 % with the sheet's rate (and 0.40 % without the gap)."""
        last = self._w_hist[-1]
        if not v.any():
            return last
        w_all = np.einsum("kij,kj->ki", self.R[v], w_c[v])
        w_world = w_all.mean(axis=0)
        # how far a link's own rate may be from the sheet's: the valid links' spread about it
        # (rad²/s² per axis), the rate error of a link carried without its gyroscope
        self._missing_rate_var = float(np.mean((w_all - w_world) ** 2))
        sheet = np.einsum("kji,j->ki", self.R, w_world)
        return np.where((self._missing_s <= MISSING_HOLD_S)[:, None], last, sheet)

    def _propagate(self, w_c, dt, f, v) -> None:
        cfg = self.config
        q = cfg.orientation_walk_rad ** 2 * dt + (cfg.gyro_noise_rps * dt) ** 2 \
            + cfg.gyro_scale_error ** 2 * np.einsum("ki,ki->k", w_c, w_c) * dt * dt
        if self._missing_s.any():
            # a link carried by a rate not its own (`_MISSING_MAX_RAD`): an error that lasts the
            # whole gap, its variance grows as t², not t
            ms = np.where(np.isfinite(self._missing_s), self._missing_s, 0.0)
            grown = np.minimum(self._missing_rate_var * ms * ms, _MISSING_MAX_RAD ** 2)
            before = np.minimum(self._missing_rate_var * np.maximum(ms - dt, 0.0) ** 2,
                                _MISSING_MAX_RAD ** 2)
            extra = grown - before
        else:
            extra = None
        qb = cfg.gyro_bias_walk_rps ** 2 * dt
        _step("propagate", self.R, self.P, self._w_hist[-1], w_c, dt, q, qb)
        if self._C is not None:  # the gyroscopes' fixed errors' terms (`_consider`)
            U = [0.5 * (self._w_hist[-1] + w_c) if name == "rate" else
                 np.where(v[:, None], f / G0 - self._f0, 0.0) for name in self._fixed[0]]
            consider_propagate(self.R, self.P, self._C, np.stack(U, axis=1), dt, self._fixed[1])
        if extra is not None:
            self.P[:, 0, 0] += extra
            self.P[:, 1, 1] += extra
        self._q_last = q

    # ------------------------------------------------------------------------------- 2, 3. accel
    def _relative_accel(self, w_c, dt) -> np.ndarray:
        """Every chip's acceleration less the chips' mean, world (step 2 of the docstring)."""
        dd = ddot_rates(self.R, w_c, self._w_hist[-1], self._w_hist[-2], dt, self.snapshots >= 2)
        return _chips_relative(dd, self.rows, self.cols, self.link_length)

    def _accel_update(self, f, w_c, dt, v) -> np.ndarray:
        cfg = self.config
        da = self._relative_accel(w_c, dt)
        nv = int(v.sum())
        if nv == v.size:  # the links' mean reading in the world, one product: M[j, 3i + l] =
            # Σ_k f[k, j] R[k, i, l], and Σ_k R_k f_k is M's entries with j = l
            M = (f.T @ self.R.reshape(-1, 9)).reshape(3, 3, 3)
            a_c = np.einsum("jij->i", M) / nv - _GRAVITY_SF - mean_rows(da)
        elif nv:
            a_c = np.einsum("kij,kj->i", self.R[v], f[v]) / nv - _GRAVITY_SF - da[v].mean(axis=0)
        else:
            a_c = np.zeros(3)
        # every link's reading less the lattice's relative acceleration and the links' common one:
        # what is left measures the link's tilt relative to the sheet's (`_common`)
        vec = _GRAVITY_SF + da + a_c
        r2 = cfg.accel_noise_mps2 ** 2 + cfg.accel_floor_mps2 ** 2 \
            + cfg.rel_accel_error ** 2 * np.einsum("ki,ki->k", da, da)
        # the sheet's own tilt: what the links share, from its bounded translation (its filter
        # needs nothing of the links' updates: its turn and bias correction, which follow them,
        # are applied in the same pass, `_linalg.step_apply`)
        turn = turn_bias = None
        if nv:
            h = float(np.mean(dt[v]))
            self._common.step(a_c[:2], h, float(np.mean(self._q_last)) / nv,
                              cfg.gyro_bias_walk_rps ** 2 * h / nv, cfg.accel_noise_mps2 ** 2 / nv)
            c, turn_bias = self._common.take()
            turn = rotation_matrices(np.array([c[0], c[1], 0.0]))
        x = np.empty((self.n_links, 6))
        if self._C is not None:
            consider_accel(self.R, self.P, self._C, f, vec, r2, cfg.gate, v)
        _step_apply("accel", self.R, self.bias, self.P, f, vec, r2, cfg.gate, v, x, self._nis,
                    turn=turn, turn_bias=turn_bias)
        return a_c

    def _apply(self, x) -> None:
        _step("apply", self.R, self.bias, self.P, x)

    # ------------------------------------------------------------------------------- 4. lattice
    def _lattice_update(self, m, v, dt) -> None:
        cfg = self.config
        topo = self.topo
        n = self.n_links
        P = self.P
        res, wts, jd, lat_diag = _lattice_terms(self.R, P, topo, cfg.lattice_floor_rad ** 2)
        if not USE_KERNEL:  # the numpy path's products (`_linalg.normal_matvec`)
            topo.jac.data = jd
            topo.jac_T.data = jd[topo.jac_T_from]
        normal = _normal_matvec(topo, jd, wts)
        # the prior: each link's own yaw variance for what is local to it, and the groups' and
        # the sheet's common yaw variances for what the links share (`_yaw_prior`)
        self._grow_collective(dt)
        # what the loops say of each group's common offset (its information, 1/rad²): a group
        # the magnetometers do not hold (none, or disturbed) is kept apart from its links' own
        # yaws where the loops see it
        jg, info, seen = _group_info(topo, jd, wts, lat_diag)
        prior, prior_diag = self._yaw_prior(P[:, 2, 2], seen / _GROUP_SEEN, m is None)
        rhs = -_jt_times(topo, jd, wts * res)
        mw = np.zeros(n)
        if m is not None:  # every link's own heading from its magnetometer: weight mw, error me
            self._dt_last = dt
            if self._local is not None:  # a local disturbance's fitted field out (`_dipole`)
                m = self._local.remove(self.R, m, lambda: self._midpoints(self._joints), v)
            mw, me = self._magnetometer(m, v)
            rhs -= mw * me
        a_diag = prior_diag + lat_diag + mw
        # the coarse preconditioner changes slowly: made anew every `_COARSE_EVERY` snapshots
        # (any symmetric positive definite one leaves the solution as it is)
        if self._cinv is None or self.snapshots % _COARSE_EVERY == 0:
            self._cinv = _coarse_inverse(topo, jg, wts, self._prior_terms, mw)
        cinv = self._cinv
        if USE_KERNEL:
            mu = _yaw_solve(topo, jd, wts, self._prior_terms, mw, rhs, 1.0 / a_diag, _YAW_RTOL,
                            coarse_inv=cinv)
        else:
            mu = pcg(lambda x: normal(x) + prior(x) + mw * x, rhs, 1.0 / a_diag, _YAW_RTOL,
                     coarse=(topo.group, cinv))
        if m is not None:  # the disturbance tests: each heading against the loops' solution
            self._disturbance_tests(me + mu, v, dt)
        if m is not None:
            self._shrink_collective(mw, info)
        else:  # without magnetometers the loops alone say what a group's offset is
            self._s_group = 1.0 / (1.0 / self._s_group + (1.0 - self._held) * info)
        # each link's whole state follows its yaw through its covariance; the yaw's posterior
        # variance is taken as the conditional one, 1 / A_kk
        x = np.empty((n, 6))
        if self._C is not None:
            consider_yaw(P, self._C, a_diag)
        # the heading's turn (it needs nothing of the links' updates) and the output's
        # covariance (`orientation_cov`: the collective variances are final now) in the same pass
        self._cov_out = _step_apply("yaw", self.R, self.bias, P, mu, a_diag, x,
                                    turn=None if m is None else self._heading_mode(dt),
                                    cov=self._cov_terms())

    # the collective yaw modes: docs/estimator.md §8 "what the links share"
    def _yaw_prior(self, p, seen=None, six_axis=False):
        """The yaw problem's prior information as a matrix-vector product and its diagonal.

        A link's yaw variance ``p`` (its conditional one after the last solve) says how well it
        is known *relative to its neighbours*; as a diagonal prior it would also claim ``Σ 1/p``
        for a mode all links share, which nothing measured. So the prior is built in three
        nested levels: each link's own ``1/p`` for what is not a group's common offset; each
        group's common offset (a row of i-links, a column of j-links: what the loops cannot see
        on a flat sheet) with variance ``s_g`` for what is not the sheet's common offset; and
        the sheet's common yaw (its heading) with variance ``s_0``.

        Without magnetometers (``six_axis``) the heading is a gauge held by the links' own
        variances. A group the magnetometers do not hold (none, or too disturbed:
        `FusedConfig.mag_hold_weight`) is held by the links' own variances in proportion
        ``1 / (1 + seen)`` (``seen``: the loops' information about its offset, as a multiple of
        what `_GROUP_SEEN` calls seen): on a flat sheet fully, on a curved one by ``s_g``, which
        the loops' information shrinks (the accelerometer-only start's group offsets, a few
        hundredths of a radian, are then corrected as soon as the sheet bends, not held by
        the links' variances, which say how well each is known against its neighbours)."""
        topo = self.topo
        g, r, size = topo.group, topo.n_groups, topo.group_size
        D = 1.0 / p
        dg = np.bincount(g, weights=D, minlength=r)
        # a mode whose magnetometers are not trusted (weights near 0: disturbed) is held as each
        # link's own variance holds it, as if the magnetometers were not there
        hw = self.config.mag_hold_weight
        if six_axis:  # the sheet's heading is a gauge, held by the links' own variances
            held_mag, held0 = np.ones(r), 1.0
        else:
            w_mean = np.bincount(g, weights=self._weights, minlength=r) / size
            held_mag = np.clip(1.0 - w_mean / hw, 0.0, 1.0)
            held0 = float(np.clip(1.0 - float(self._weights.mean()) / hw, 0.0, 1.0))
            # magnetometers not trusted for the sheet's heading do not shear it either: a group
            # whose few clean links would free it is held as much as the heading is
            held_mag = np.maximum(held_mag, held0)
        held = held_mag if seen is None else held_mag / (1.0 + seen)
        self._held, self._held0, self._held_mag = held, held0, held_mag
        Eg = (1.0 - held) / self._s_group + held * dg
        sE = float(Eg.sum())
        I0 = (1.0 - held0) / self._s0 + held0 * sE

        # coordinates: a group's offset is its links' mean weighted by D, the sheet's the groups'
        # weighted by E (so that a fully held mode gets exactly the links' own prior back)
        def sigma_a(y):  # the group offsets' prior information (r x r) times y
            ey = float(Eg @ y)
            return Eg * y - Eg * (ey / sE) + Eg * (ey * I0 / (sE * sE))

        def prior(x):
            abar = np.bincount(g, weights=D * x, minlength=r) / dg
            return D * x - D * abar[g] + D * (sigma_a(abar) / dg)[g]

        self._prior_terms = (D, dg, Eg, sE, I0)  # the same prior for the C kernel's solve
        sig_diag = Eg - Eg * Eg / sE + Eg * Eg * I0 / (sE * sE)
        diag = D - D * D / dg[g] + D * D * (sig_diag / (dg * dg))[g]
        return prior, diag

    def _grow_collective(self, dt) -> None:
        """The groups' and the sheet's common yaw variances grow by the links' process noise
        (averaged over the links that share the offset) and the heading walk."""
        cfg = self.config
        q = self._q_last
        h = self._h
        walk = cfg.heading_walk_rad ** 2 * h
        topo = self.topo
        q_g = np.bincount(topo.group, weights=q, minlength=topo.n_groups) / topo.group_size ** 2
        self._s_group = np.minimum(self._s_group + q_g + walk, _COLLECTIVE_MAX)
        self._s0 = min(self._s0 + float(q.mean()) / q.size + walk, _COLLECTIVE_MAX)

    def _shrink_collective(self, mw, info) -> None:
        """The groups' and the sheet's common yaw variances after the solve: each gains what the
        magnetometers say of its offset where they hold it (the loops' say is not kept there:
        they hold the shape at every snapshot anew, and on a flat sheet they say nothing of
        these offsets), and what the loops say (``info``) where the magnetometers do not hold
        it and the loops do, as without magnetometers."""
        topo = self.topo
        trusted = 1.0 - self._held_mag  # a held group's offset is the links' own prior's
        by_loops = self._held_mag - self._held
        self._s_group = 1.0 / (1.0 / self._s_group + trusted * np.bincount(
            topo.group, weights=mw, minlength=topo.n_groups) + by_loops * info)
        self._s0 = 1.0 / (1.0 / self._s0 + float(mw.sum()))

    def _magnetometer(self, m, v):
        """Per link: the weight (information, 1/rad²) of its magnetometer's heading and its
        heading's offset from Earth's field (rad) (module docstring, step 4).

        The weight is the magnetometer's noise and floor, with two tests of a local disturbance
        averaged over `FusedConfig.disturbance_tau_s` (`_disturbance_tests`): the field's
        magnitude and dip against Earth's measure two of the three components of what a
        disturbance adds to the field, and the third, the one that turns the heading, is taken
        to be as large (its variance added to the heading's); the heading against the loops'
        solution scales the weight by ``1 / (1 + (s / scale)²)``. ``self._weights`` keeps each
        link's weight as a fraction of an undisturbed one's, in [0, 1]."""
        cfg = self.config
        F, dip = self._b_ref
        e, hz, t_field, t_dip = mag_terms(self.R, m, self.declination_rad, F, dip,
                                          cfg.disturbance_field_frac, cfg.disturbance_dip_rad)
        ok = v & (hz > 0.1 * F)
        self._field_tests = (ok, t_field, t_dip)
        # the averaged field tests beyond their noise (3x its mean: the 95 % point of the
        # 2-degree-of-freedom chi-square) as a bias over `disturbance_persist_s`; their noise the
        # magnetometer's, averaged, and the link's tilt (the dip is measured in the world frame
        # the link's estimated orientation gives); until the tests have averaged over their time
        # constant a link's magnetometer is not used (a magnet there from the start would
        # otherwise be believed first): `_linalg.np_mag_weights` has the formulas
        lasts = cfg.disturbance_persist_s / max(self._h, 1e-6)
        self._weights, mw = mag_weights(hz, ok, self._dist, self.P, self._dist_count,
                                        self._dt_last, cfg.mag_noise_t ** 2,
                                        cfg.mag_floor_rad ** 2, F, cfg.disturbance_field_frac,
                                        cfg.disturbance_dip_rad, cfg.disturbance_tau_s, lasts,
                                        cfg.disturbance_scale ** 2, self._h, cfg.mag_warmup_s, e)
        mv = None if self._local is None else self._local.model_var_t2
        if mv is not None:
            self._explained(mv, hz, ok, F, lasts, self._weights, mw)
        return mw, e

    def _explained(self, mv, hz, ok, F, lasts, weights, mw) -> None:
        """The links whose field the dipole's fit explains but for its own error (``mv``, T²
        per component: `_dipole.LocalField.model_var_t2`), weighed again in place: that error
        enters their tests as noise that lasts (it is a bias of the fit, not averaged away) and
        their heading's variance as the horizontal field's error, so their magnetometers keep
        their corrected heading at the information it has instead of being taken as disturbed;
        their ``weights`` (the groups' holds) are of that information, so a group of explained
        links is not held (`_yaw_prior`). The formulas are `_linalg.np_mag_weights`' with the
        fit's error added."""
        cfg = self.config
        k = np.flatnonzero(ok & (mv > (0.1 * cfg.mag_noise_t) ** 2))
        if k.size == 0:
            return
        mvk, hz2 = mv[k], np.maximum(hz[k], 1e-30) ** 2
        noise2 = cfg.mag_noise_t ** 2
        var0 = (noise2 + mvk) / hz2 + cfg.mag_floor_rad ** 2
        cnt = self._dist_count[k]
        a = np.clip(np.maximum(self._dt_last[k] / cfg.disturbance_tau_s,
                               1.0 / np.maximum(cnt, 1.0)), 1e-6, 1.0)
        Pk = self.P[k]
        n2 = 2.0 * noise2 * a / (2.0 - a) + F * F * (Pk[:, 0, 0] + Pk[:, 1, 1]) + mvk
        dk = self._dist[k]
        d2 = ((dk[:, 1] * cfg.disturbance_field_frac) ** 2
              + (dk[:, 2] * cfg.disturbance_dip_rad) ** 2) * F * F
        d2 = np.maximum(d2 - 3.0 * n2, 0.0) * lasts
        # the heading test's unit grows by the fit's error over the horizontal field
        scale2 = cfg.disturbance_scale ** 2 * (1.0 + (mvk / hz2) / cfg.disturbance_heading_rad ** 2)
        wgt = var0 / (var0 + d2 / hz2) / (1.0 + dk[:, 0] ** 2 / scale2)
        wgt = np.where(cnt * self._h >= cfg.mag_warmup_s, wgt, 0.0)
        weights[k] = wgt
        mw[k] = wgt / var0

    def _heading_mode(self, dt) -> np.ndarray | None:
        """The turn (3 x 3, world; None: none) of the sheet's heading towards the robust mode
        of its links' averaged heading residuals (`robust_mode`), by the part of the heading the
        magnetometers' weights do not hold (``held0``, `_yaw_prior`) over
        `FusedConfig.heading_mode_time_s`: the gyroscopes
        carry the heading while a disturbance is detected, and the links that agree with each
        other — not the mean of every link the disturbance turns a little — correct it slowly.
        The links vote in proportion to how much their groups are held: a group whose
        magnetometers are trusted has taken their heading in the solve, its residuals are zero
        by construction (docs/estimator.md §8)."""
        cfg = self.config
        if cfg.heading_mode_rad <= 0 or self._held0 <= 0:
            return None
        use = self._field_tests[0] & (self._dist_count * self._h >= cfg.mag_warmup_s)
        w = np.where(use, self._held[self.topo.group], 0.0)
        psi = robust_mode(self._resid_avg, w, cfg.heading_mode_rad, self._mode_psi)
        if psi is None:
            return None
        g = self._held0 * min(1.0, self._h / cfg.heading_mode_time_s)
        self._resid_avg -= g * psi
        self._mode_psi = (1.0 - g) * psi  # where the mode is after the turn: the next start
        return rotation_matrices(np.array([0.0, 0.0, -g * psi]))

    def _disturbance_tests(self, resid, v, dt) -> None:
        """Average each link's tests over `FusedConfig.disturbance_tau_s`: its heading against the
        lattice's solution (``resid``, rad: what is left of its magnetometer's heading once the
        loops and every other link have had their say), its field's magnitude and dip against
        Earth's (`_magnetometer` weighs them)."""
        cfg = self.config
        ok, t_mag, t_dip = self._field_tests
        # the heading against its group's (links the loops turn alike on a flat sheet): what a
        # group shares is the shape's to explain, what one link alone shows is its own
        topo = self.topo
        self._dist = dist_tests(topo.group, topo.n_groups, ok, resid, t_mag, t_dip, dt,
                                cfg.disturbance_tau_s, cfg.disturbance_heading_rad, self._dist,
                                self._resid_avg, self._dist_count)
