"""Shape while the sheet moves: the fused estimator against its peers, on the same
simulated data, and its speed. Prints JSON.

One sheet of 9-axis chips (`virtual_sheet.imu`: ICM-42688-P gyroscope and accelerometer with the
accelerometer's noise raised to 1 % g, LIS3MDL magnetometer; every fixed error of the parts —
turn-on bias, scale, cross-axis, g-sensitivity, mounting, hard and soft iron), 14x14 joints,
L = 1 cm, 145 Hz, Earth's field 50 µT dipping 60° (declination 0: world x is magnetic north).
The chips are first calibrated as a user would (`host.analysis.imu_calibration.fit_capture` on
the board scene's capture, 84 s), and every estimator takes the same calibrated readings
(`host.analysis.motion.calibrated`):

* ``accel_only`` — the static estimator, warm-started (`host.analysis.motion.accel_only`);
* ``per_link_filter`` — VQF on every link, then the joints from the directions
  (`host.analysis.motion.per_link_filter`);
* ``fused`` — `host.analysis.motion.MotionEstimator` told the chips' truth (`TRUE_NOISE`:
  1 % g, 0.35 µT, the gyroscope bias the calibration leaves: 0.0002 °/s shared by the chips,
  0.001 °/s each chip's own, and its scale and cross-axis residue against the accelerometers'
  frame, 0.01–0.02 % per entry, and g-sensitivity residue, 0.0005 °/s/g, fixed per chip:
  `SCALE_RESIDUE`, `GSENS_RESIDUE`; the accelerometers' residue, 0.012° of tilt each chip's own
  and a 0.023 / 0.040 / 0.038° rotation of their frames shared, fixed: `ACCEL_RESIDUE_RAD`,
  `ACCEL_COMMON_RESIDUE_RAD`; beyond the noise only the counts' quantisation,
  `ACCEL_QUANTISATION_MPS2`), as a user of such chips would;
* ``fused_defaults`` — the same with `FusedConfig()`, whose noise is the datasheets'.

Rows (``rows``): every moving scene of `virtual_sheet.motion.MOTION_SCENES` (``flat_turn`` is
the flat horizontal one) and the level sheets with sheared cells (``level``, ``level_turn``:
their shear is seen by magnetometers only), with ``sensors`` ``accel+gyro`` and
``accel+gyro+mag`` — the same accelerometer and gyroscope samples in both (the chips' noise
streams are separate) — and ``<scene>+disturbed``: the same with a magnet under a quarter of the
sheet (`virtual_sheet.magfield.quarter_disturbance`), ``accel+gyro+mag``. Per row:
``mean_error_pct_side`` (the paper's error, `host.analysis.metrics.error_percent_of_side`,
averaged over joints and every snapshot of the run, the first included), ``max_error_pct_side``
(the worst snapshot's mean), ``heading_err_deg`` where heading is defined (with
magnetometers): the mean over snapshots of the absolute mean heading error of the links (the
rotation about world z between each estimated frame and the true one), else null; and for the
fused rows ``consistency`` (`consistency`): the links' joint tilt NEES per degree of freedom,
the sheet's common tilt NEES and the accelerometers' mean NIS per degree of freedom, each against
its χ² band at 95 %.

``targets`` checks: fused ≤ 0.15 % of side while moving and heading ≤ 0.5°; the level sheets
with magnetometers ≤ 0.3 % and heading ≤ 0.5°; told the true noise no worse than 1.25x the
defaults; ≥ 5x lower than accel_only where that is above 1 %; ≥ 2x lower than per_link_filter
where that is above 0.5 %; with the disturbance no worse than without magnetometers (fused, same
scene, moving scenes); ``drift``: a sheet at rest for ``--drift-minutes`` (10), error over its
last 10 s ≤ 1.2x that over seconds 10–20 (after the filter settled); ``speed``: snapshots per
second of the fused estimator, one core, warm (14x14 ≥ 145, 32x32 ≥ 60, 64x64 ≥ 145; CPU time,
the machine's load beside it; with its defaults, and beside them told `TRUE_NOISE`, whose
fixed scale error is a consider state); ``bias_learning``: gyroscope biases of 0.5 °/s learned while
moving (`bias_learning`), the time to 0.05 °/s RMS.

    .venv/bin/python benchmarks/bench_motion.py --json [--seconds 6] [--drift-minutes 10]
    .venv/bin/python benchmarks/bench_motion.py --json --png out     # out/motion_error_time.png, out/motion_heading_time.png, out/motion_paper.png
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
             "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"  # one core, before numpy is imported

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from host.analysis.imu_calibration import fit_capture  # noqa: E402
from host.analysis.metrics import error_percent_of_side  # noqa: E402
from host.analysis.motion import FusedConfig, MotionEstimator, accel_only, calibrated, per_link_filter  # noqa: E402
from host.analysis.motion.fused import G0  # noqa: E402
from host.analysis.motion.peers import have_vqf, yaw_of_frames  # noqa: E402
from virtual_sheet.imu import imu_array, simulate  # noqa: E402
from virtual_sheet.magfield import EarthField, MagneticField, quarter_disturbance  # noqa: E402
from virtual_sheet.motion import MOTION_SCENES, board_scene, make_motion_scene  # noqa: E402

L = 0.01
EARTH = EarthField(50e-6, np.radians(60.0), 0.0)
METHODS = ("accel_only", "per_link_filter", "fused")
TARGETS = {"fused_max_pct": 0.15, "vs_accel_only": 5.0, "accel_only_above_pct": 1.0,
           "vs_per_link": 2.0, "per_link_above_pct": 0.5, "flat_mag_pct": 0.3,
           "flat_heading_deg": 0.5, "heading_deg": 0.5, "true_noise_ratio": 1.25, "drift_ratio": 1.2,
           "rate_14": 145.0, "rate_32": 60.0, "rate_64": 145.0}
#: the chips' true noise (1 % g accelerometers, the LIS3MDL's 0.32 / 0.41 µT, its RMS over the
#: three axes 0.35 µT) and what the board calibration leaves of their gyroscopes (each chip's
#: calibrated rate against the simulator's exact one, the still level sheet and each chip's exact
#: errors; the calibration's held poses cut to where the gyroscopes are still): biases 0.0001-0.0002
#: °/s shared by the chips and 0.0009-0.001 °/s each chip's own (before the poses were cut by the
#: gyroscopes, the turns' ends in the rests left 0.029-0.065 °/s shared, 0.002-0.007 °/s each);
#: the fused estimator's defaults are the datasheets' (0.06 % g) and a calibration's 0.01 °/s. The
#: gyroscopes' scale and cross-axis error the calibration leaves lasts (`SCALE_RESIDUE`), so it is
#: told as fixed (a consider state) rather than white, and the orientation walk that stood for it
#: is reduced to a floor; the lattice's relative accelerations are off by 0.85 % per axis
#: (measured against the exact kinematics on the wave)
#:
#: the calibrated gyroscopes' fixed error ``E`` (``ω_read = (I + E) ω``, link frame; row: the
#: axis read, column: the axis turned about) against the frame the filter follows, the
#: accelerometers': ``E − W_a``, ``W_a`` the antisymmetric part of the calibrated accelerometers'
#: own fixed error ``E_a`` (``f_read = (I + E_a) f + b``), the small rotation of their frame off
#: the link's. RMS over the 14x14 sheet's chips per entry, from the chips' exact errors and their
#: calibration: 0.01 % on the diagonal, 0.02 % in the cross terms. ``E`` itself is 0.06-0.07 %
#: in the cross terms, but nearly all of that is the rotation the two frames share (the board's
#: pose at calibration, 0.02-0.04° per axis, and each chip's mounting about it, 0.0075°): a
#: gyroscope turned with its accelerometer measures the rate of the frame the filter tracks, so
#: that rotation is no error of the rates; it is the frame's offset from the link's, told as the
#: accelerometers' residue below. Told as a gyroscope error the filter claimed 1.3-1.4x the
#: variance of the rotating scenes' tilt errors (the carry's tilt NEES 0.74, flat_turn's 0.70)
SCALE_RESIDUE = ((1.1e-4, 2.0e-4, 2.2e-4), (1.9e-4, 1.1e-4, 2.3e-4), (2.1e-4, 2.1e-4, 1.4e-4))
#: the calibrated gyroscopes' fixed g-sensitivity ``Γ`` (``Γ f / g`` of the rate), rad/s per g,
#: per entry, from the chips' exact errors and their calibration: 0.0005 °/s/g RMS (0.016-0.040
#: before the poses were cut by the gyroscopes; the simulator's parts: 0.1 °/s/g before calibration)
GSENS_RESIDUE = float(np.radians(0.0005))
#: what the board calibration leaves of the accelerometers' errors, as the tilt it gives (the
#: residue ``A f + b`` of each calibrated chip against the simulator's truth, its part across
#: the specific force turned into the world, over the seven scenes' poses): each chip's own part
#: about the chips' mean 0.010-0.019° per horizontal axis, RMS 0.012°. What the chips share is
#: a rotation of their frames (the antisymmetric part of each calibrated chip's ``E_a``, turned
#: into the frame of the flat sheet the board held): 0.023 / 0.040 / 0.038° about its x, y, z
#: (each chip's about it 0.0076° per axis), fixed in the chips' frames, so a bent sheet's links
#: carry it turned apart (`FusedConfig.accel_common_fixed_error_rad`, per axis: it is one
#: board's pose, and on another board, chip set 11's, it was 0.17 / 0.08 / 0.02°, where one
#: figure for the three axes put the curved scenes under the band). Both fixed: told as noise
#: that averages out, the still level sheet's tilt NEES was 1.06-1.10 on five chip sets
ACCEL_RESIDUE_RAD = float(np.radians(0.012))
ACCEL_COMMON_RESIDUE_RAD = tuple(float(np.radians(x)) for x in (0.023, 0.040, 0.038))
#: what the accelerometers' readings carry beyond their noise: their counts' quantisation, 12
#: bits at ±2 g, 1024 counts per g (docs/protocol.md §5.2, `protocol.constants.Range.G2`, the
#: simulator's chips), one count / √12 = 0.0028 m/s². The estimator's default floor (0.02 m/s²)
#: stands for what a model leaves out; told here beside every error the chips make, it claimed
#: 4 % more accelerometer noise than they have
ACCEL_QUANTISATION_MPS2 = G0 / 1024.0 / float(np.sqrt(12.0))
TRUE_NOISE = FusedConfig(accel_noise_mps2=0.01 * G0, mag_noise_t=0.35e-6,
                         gyro_bias_std_rps=float(np.radians(0.001)),
                         gyro_common_bias_std_rps=float(np.radians(0.001)),
                         gyro_scale_error=0.0, gyro_scale_fixed_error=SCALE_RESIDUE,
                         gyro_gsens_fixed_error=GSENS_RESIDUE,
                         accel_fixed_error_rad=ACCEL_RESIDUE_RAD,
                         accel_common_fixed_error_rad=ACCEL_COMMON_RESIDUE_RAD,
                         accel_floor_mps2=ACCEL_QUANTISATION_MPS2,
                         orientation_walk_rad=5e-5, rel_accel_error=0.0085)
MAGNETOMETER_SCENES = ("level", "level_turn")


def _load() -> str:
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def chips(n: int, seed: int, field=None):
    """The sheet's 9-axis chips (the same chips for every run: ``chip_seed`` 7), noise ``seed``."""
    return imu_array(2 * n * (n - 1), "accel+gyro+mag", noise_pct_g=1.0, seed=seed, chip_seed=7,
                     field=MagneticField(EARTH, () if field is None else (field,)))


def capture(scene, imu, seconds: float) -> tuple:
    runs = list(simulate(scene, imu, seconds))
    truth = {k: np.concatenate([getattr(t, k) for t, _r in runs]) for k in ("joints", "frames")}
    rd = {k: np.concatenate([getattr(r, k) for _t, r in runs]) for k in ("t_s", "accel_mps2",
                                                                           "gyro_rps", "mag_t")}
    return truth, rd


def calibrate(n: int):
    """The chips calibrated on the board, as docs/calibration.md says (returns the calibration and
    the CPU seconds it took, simulation excluded)."""
    board = board_scene(n, n, L, jitter_rad=0.03, seed=7)
    _truth, rd = capture(board, chips(n, 900), board.board.period_s)
    c0 = time.process_time()
    cal = fit_capture(rd["t_s"], rd["accel_mps2"], n, n, rd["gyro_rps"], rd["mag_t"],
                      field_t=EARTH.magnitude_t, threshold_mps2=0.3)  # 3x the 1 % g noise
    return cal, time.process_time() - c0


def heading_error(frames_est: np.ndarray, frames_true: np.ndarray) -> np.ndarray:
    """Per snapshot, the links' mean heading error, rad: the circular mean over links of the
    rotation about world z between each estimated frame and the true one."""
    d = yaw_of_frames(frames_est) - yaw_of_frames(frames_true)
    return np.arctan2(np.sin(d).mean(axis=-1), np.cos(d).mean(axis=-1))


def run_fused(n, t, acc, gyr, mag, config=TRUE_NOISE, truth_frames=None):
    """The fused estimator over a run: joints, frames and, given the true frames, its
    consistency per snapshot (`tilt_nees`): the links' joint tilt NEES per degree of freedom,
    the sheet's common tilt NEES (2 degrees of freedom) and the links' mean accelerometer NIS
    per degree of freedom."""
    est = MotionEstimator(n, n, L, config=config)
    J = np.empty((t.size, n, n, 3))
    F = np.empty((t.size, 2 * n * (n - 1), 3, 3))
    nees = np.full((t.size, 3), np.nan)
    for k in range(t.size):
        e = est.update(t[k], acc[k], gyr[k], None if mag is None else mag[k])
        J[k], F[k] = e.joints, e.frames
        if truth_frames is not None:
            d = orientation_error(e.frames, truth_frames[k], heading=mag is not None)
            nees[k, :2] = tilt_nees(d[:, :2], e.orientation_cov_rad2[:, :2, :2], e.common_tilt_cov_rad2)
            if k:  # the first snapshot initialises: no innovation
                nees[k, 2] = np.nanmean(e.accel_nis) / 3.0
    return J, F, nees


def orientation_error(frames: np.ndarray, true_frames: np.ndarray, heading: bool) -> np.ndarray:
    """Every link's orientation error, rad, a rotation vector in the world frame
    (``R_true = exp([d]×) R``); without an absolute heading (no magnetometers) the estimate is
    first turned about world z by the links' mean heading error (`heading_error`): the heading
    is then a gauge, not an error."""
    from scipy.spatial.transform import Rotation
    R = frames
    if not heading:
        psi = float(heading_error(frames, true_frames))
        c, s = np.cos(psi), np.sin(psi)
        R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ frames
    return Rotation.from_matrix(true_frames @ R.transpose(0, 2, 1)).as_rotvec()


def tilt_nees(e: np.ndarray, cov: np.ndarray, common: np.ndarray) -> tuple[float, float]:
    """The links' tilt errors ``e`` (n, 2), rad, world x and y, against the estimator's
    covariance: each link's ``cov`` (n, 2, 2) is its own part plus the ``common`` one (2, 2)
    that every link shares, so the joint covariance is ``blockdiag(cov − common) + 1 1ᵀ ⊗
    common``. Returns its NEES per degree of freedom (χ²(2n) / 2n for a consistent filter;
    Woodbury's identity, no 2n x 2n matrix) and the NEES of the links' mean error against its
    covariance (χ²(2))."""
    own = cov - common
    B = np.linalg.inv(own)
    z = np.einsum("kij,kj->ki", B, e)
    s = float(np.einsum("ki,ki->", e, z))
    Z = z.sum(axis=0)
    M = np.eye(2) + B.sum(axis=0) @ common
    joint = s - float(Z @ common @ np.linalg.solve(M, Z))
    n = e.shape[0]
    eb = e.mean(axis=0)
    cb = common + own.mean(axis=0) / n
    return joint / (2 * n), float(eb @ np.linalg.solve(cb, eb))


def consistency(nees: np.ndarray, n_links: int) -> dict:
    """The consistency checks, per snapshot after the first second, against χ² bands at 95 %
    (bounds from scipy.stats.chi2): the links' joint tilt NEES per degree of freedom (band of
    χ²(2n) / 2n), the common tilt's NEES (band of χ²(2)) and the links' mean accelerometer NIS
    per degree of freedom (band of χ²(3n) / 3n, the links' innovations independent); for each
    the mean over the run and the fraction of snapshots inside the band (0.95 for a consistent
    filter)."""
    from scipy.stats import chi2
    out = {}
    for col, (name, dof, norm) in enumerate((("tilt_joint", 2 * n_links, True),
                                             ("tilt_common", 2, False),
                                             ("accel_nis", 3 * n_links, True))):
        v = nees[145:, col]
        if v.size == 0 or np.all(np.isnan(v)):
            continue
        lo, hi = (chi2.ppf(q, dof) / (dof if norm else 1) for q in (0.025, 0.975))
        out[name] = {"mean": round(float(v.mean()), 3), "band": [round(lo, 3), round(hi, 3)],
                     "inside": round(float(np.mean((v >= lo) & (v <= hi))), 3)}
    return out


def errors(J, truth_joints) -> np.ndarray:
    return np.array([error_percent_of_side(J[k], truth_joints[k], L).mean() for k in range(len(J))])


def scene_rows(name: str, n: int, seconds: float, cal, seed: int, curves: dict) -> list[dict]:
    scene = make_motion_scene(name, n, n, L)
    with_nees = name in MAGNETOMETER_SCENES or MOTION_SCENES[name].moving
    out = []
    data = {}
    for variant, field in (("", None), ("+disturbed", quarter_disturbance(n, n, L))):
        truth, rd = capture(scene, chips(n, seed, field), seconds)
        acc, gyr, mag = calibrated(cal, rd["accel_mps2"], rd["gyro_rps"], rd["mag_t"])
        data[variant] = (truth, rd["t_s"], acc, gyr, mag)
    truth, t, acc, gyr, mag = data[""]
    ea = errors([e.joints for e in accel_only(acc, n, n, L)], truth["joints"])
    runs = [("accel+gyro", "", None), ("accel+gyro+mag", "", mag),
            ("accel+gyro+mag", "+disturbed", data["+disturbed"][4])]
    for sensors, variant, m in runs:
        tr = data[variant][0]
        assert np.array_equal(data[variant][2], acc) and np.array_equal(data[variant][3], gyr)
        res = {"accel_only": (ea, None)}
        if have_vqf():
            Jp, Fp = per_link_filter(t, acc, gyr, n, n, L, m)
            res["per_link_filter"] = (errors(Jp, tr["joints"]), Fp)
        # "fused": told the chips' noise (1 % g), as a user of such chips would; beside it the
        # estimator's datasheet defaults, which these noisier chips do not meet
        Jf, Ff, nees = run_fused(n, t, acc, gyr, m, TRUE_NOISE, tr["frames"] if with_nees else None)
        res["fused"] = (errors(Jf, tr["joints"]), Ff)
        Jd, Fd, nees_d = run_fused(n, t, acc, gyr, m, None, tr["frames"] if with_nees else None)
        res["fused_defaults"] = (errors(Jd, tr["joints"]), Fd)
        cons = {"fused": nees, "fused_defaults": nees_d}
        for method, (err, frames) in res.items():
            head = hseries = None
            if m is not None and frames is not None:
                hseries = np.degrees(np.abs(heading_error(frames, tr["frames"])))
                head = float(hseries.mean())
            row = {"scene": name + variant, "sensors": sensors, "method": method,
                   "mean_error_pct_side": round(float(err.mean()), 4),
                   "max_error_pct_side": round(float(err.max()), 4),
                   "heading_err_deg": None if head is None else round(head, 3)}
            if method in cons and with_nees:
                row["consistency"] = consistency(cons[method], 2 * n * (n - 1))
            out.append(row)
            curves[(name + variant, sensors, method)] = (t, err, hseries)
    return out


def drift(n: int, minutes: float, cal, seed: int) -> dict:
    """A sheet at rest (`rest` scene, a Gaussian) for ``minutes``: fused and per-link errors over
    seconds 10-20 and over the last 10 s, 9-axis chips read as 6-axis (the gyroscopes' bias
    instability is what drifts)."""
    scene = make_motion_scene("rest", n, n, L)
    imu = chips(n, seed)
    est = MotionEstimator(n, n, L, config=TRUE_NOISE)
    errs, t_all, keep = [], [], {}
    for truth, rd in simulate(scene, imu, minutes * 60.0, chunk_s=10.0):
        acc, gyr, _m = calibrated(cal, rd.accel_mps2, rd.gyro_rps)
        for k in range(rd.t_s.size):
            e = est.update(rd.t_s[k], acc[k], gyr[k])
            errs.append(error_percent_of_side(e.joints, truth.joints[k], L).mean())
        t_all.append(rd.t_s)
        if have_vqf():
            keep.setdefault("acc", []).append(acc)
            keep.setdefault("gyr", []).append(gyr)
            keep.setdefault("truth", truth.joints[0])
    t = np.concatenate(t_all)
    err = np.array(errs)
    start, end = (t >= 10) & (t < 20), t >= t[-1] - 10
    row = {"scene": "rest", "minutes": minutes, "sensors": "accel+gyro",
           "fused_start_pct": round(float(err[start].mean()), 4),
           "fused_end_pct": round(float(err[end].mean()), 4)}
    row["fused_ratio"] = round(row["fused_end_pct"] / row["fused_start_pct"], 3)
    if keep:
        Jp, _F = per_link_filter(t, np.concatenate(keep["acc"]), np.concatenate(keep["gyr"]), n, n, L,
                                 with_frames=False)
        ep = np.array([error_percent_of_side(Jp[k], keep["truth"], L).mean() for k in range(t.size)])
        row["per_link_start_pct"] = round(float(ep[start].mean()), 4)
        row["per_link_end_pct"] = round(float(ep[end].mean()), 4)
    return row


def bias_learning(n: int, seconds: float, seed: int = 500) -> list[dict]:
    """Gyroscope biases learned while moving: chips with the ICM-42688-P's datasheet noise (0.06 %
    g, 2.8 mdps/√Hz) and an uncalibrated turn-on bias of 0.5 °/s per axis, the estimator told
    both (``gyro_bias_std_rps`` 0.5 °/s); per scene the links' RMS bias error over time and the
    first second from which it stays under 0.05 °/s."""
    from virtual_sheet.imu import GyroModel, ImuArray, MagModel, accel_model
    cfg = FusedConfig(gyro_bias_std_rps=float(np.radians(0.5)))
    out = []
    for name in ("carry", "wave", "elbow"):
        imu = ImuArray(2 * n * (n - 1), accel=accel_model("ideal", noise_pct_g=0.06),
                       gyro=GyroModel.part("ideal", noise_density_dps=0.0028, bias_dps=0.5, chip_seed=7),
                       mag=MagModel.part("ideal", noise_t=(0.32e-6, 0.32e-6, 0.41e-6)),
                       field=MagneticField(EARTH), seed=seed)
        truth, rd = next(simulate(make_motion_scene(name, n, n, L), imu, seconds, chunk_s=seconds))
        b_true = imu.gyro_bias_rps
        est = MotionEstimator(n, n, L, config=cfg)
        rms = np.empty(rd.t_s.size)
        for k in range(rd.t_s.size):
            e = est.update(rd.t_s[k], rd.accel_mps2[k], rd.gyro_rps[k])
            rms[k] = np.degrees(np.sqrt(np.mean((b_true - e.gyro_bias_rps) ** 2)))
        above = np.flatnonzero(rms > 0.05)
        t_05 = None if above.size and above[-1] == rms.size - 1 else \
            float(rd.t_s[above[-1] + 1] - rd.t_s[0]) if above.size else 0.0
        out.append({"scene": name, "sensors": "accel+gyro", "seconds": seconds,
                    "bias_rms_dps_at": {f"{s:g}s": round(float(rms[min(int(s * 145), rms.size - 1)]), 4)
                                        for s in (1, 2, 4, seconds)},
                    "seconds_to_0.05_dps": None if t_05 is None else round(t_05, 2)})
    return out


def _rate(n: int, rd: dict, config) -> tuple[float, float]:
    est = MotionEstimator(n, n, L, config=config)
    m = rd["mag_t"]
    k0 = 145
    for k in range(k0):
        est.update(rd["t_s"][k], rd["accel_mps2"][k], rd["gyro_rps"][k], m[k])
    c0, w0 = time.process_time(), time.perf_counter()
    for k in range(k0, rd["t_s"].size):
        est.update(rd["t_s"][k], rd["accel_mps2"][k], rd["gyro_rps"][k], m[k])
    c1, w1 = time.process_time(), time.perf_counter()
    count = rd["t_s"].size - k0
    return count / (c1 - c0), count / (w1 - w0)


def speed(n: int, seconds: float = 3.0) -> dict:
    """The fused estimator's snapshots per second on one core, warm (the first second skipped):
    with its defaults, and told the bench's chips (`TRUE_NOISE`: the gyroscopes' fixed scale
    and cross-axis error carried as a consider state, `host.analysis.motion._consider`)."""
    scene = make_motion_scene("wave", n, n, L)
    imu = chips(n, 5)
    _truth, rd = capture(scene, imu, seconds)
    cpu, wall = _rate(n, rd, None)
    cpu_t, _wall_t = _rate(n, rd, TRUE_NOISE)
    return {"lattice": f"{n}x{n}", "links": 2 * n * (n - 1), "sensors": "accel+gyro+mag",
            "snapshots_per_s_cpu": round(cpu, 1),
            "snapshots_per_s_wall": round(wall, 1),
            "snapshots_per_s_cpu_true_noise": round(cpu_t, 1),
            "target": {14: TARGETS["rate_14"], 32: TARGETS["rate_32"], 64: TARGETS["rate_64"]}.get(n),
            "load": _load()}


def check(rows: list[dict], drift_row: dict | None, speed_rows: list[dict]) -> dict:
    by = {(r["scene"], r["sensors"], r["method"]): r for r in rows}
    fails = []
    for (scene, sensors, method), r in by.items():
        if method != "fused":
            continue
        e = r["mean_error_pct_side"]
        dflt = by.get((scene, sensors, "fused_defaults"))
        if dflt and e > TARGETS["true_noise_ratio"] * dflt["mean_error_pct_side"]:
            fails.append(f"{scene} {sensors}: told the true noise {e} > "
                         f"{TARGETS['true_noise_ratio']}x the defaults' {dflt['mean_error_pct_side']}")
        level = scene.split("+")[0] in MAGNETOMETER_SCENES
        if level:
            if sensors == "accel+gyro+mag" and not scene.endswith("+disturbed") and (
                    e > TARGETS["flat_mag_pct"] or r["heading_err_deg"] > TARGETS["flat_heading_deg"]):
                fails.append(f"{scene}: {e} % / heading {r['heading_err_deg']} deg")
            continue  # accel+gyro alone cannot see a level sheet's shear: no target
        if r["heading_err_deg"] is not None and not scene.endswith("+disturbed") \
                and r["heading_err_deg"] > TARGETS["heading_deg"]:
            fails.append(f"{scene} {sensors}: heading {r['heading_err_deg']} deg")
        if e > TARGETS["fused_max_pct"]:
            fails.append(f"{scene} {sensors}: fused {e} > {TARGETS['fused_max_pct']} %")
        a = by[(scene, sensors, "accel_only")]["mean_error_pct_side"]
        if a > TARGETS["accel_only_above_pct"] and a / e < TARGETS["vs_accel_only"]:
            fails.append(f"{scene} {sensors}: accel_only {a} only {a / e:.1f}x fused {e}")
        p = by.get((scene, sensors, "per_link_filter"))
        if p and p["mean_error_pct_side"] > TARGETS["per_link_above_pct"] \
                and p["mean_error_pct_side"] / e < TARGETS["vs_per_link"]:
            fails.append(f"{scene} {sensors}: per_link {p['mean_error_pct_side']} only "
                         f"{p['mean_error_pct_side'] / e:.1f}x fused {e}")
        if scene.endswith("+disturbed"):
            base = by[(scene.removesuffix("+disturbed"), "accel+gyro", "fused")]["mean_error_pct_side"]
            if e > base * 1.05 + 0.005:
                fails.append(f"{scene}: with the disturbance {e} > without magnetometers {base}")
        if "flat" in scene and not scene.endswith("+disturbed") and sensors == "accel+gyro+mag":
            if e > TARGETS["flat_mag_pct"] or r["heading_err_deg"] > TARGETS["flat_heading_deg"]:
                fails.append(f"{scene}: {e} % / heading {r['heading_err_deg']} deg")
    if drift_row and drift_row["fused_ratio"] > TARGETS["drift_ratio"]:
        fails.append(f"drift: end/start {drift_row['fused_ratio']}")
    for s in speed_rows:
        if s["target"] and s["snapshots_per_s_cpu"] < s["target"]:
            fails.append(f"speed {s['lattice']}: {s['snapshots_per_s_cpu']} < {s['target']}")
    return {"met": not fails, "failures": fails}


def figures(curves: dict, rows: list[dict], outdir: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    outdir.mkdir(parents=True, exist_ok=True)
    colours = {"accel_only": "tab:red", "per_link_filter": "tab:blue", "fused": "tab:green"}
    names = list(dict.fromkeys(k[0] for k in curves if not k[0].endswith("+disturbed")))

    # error over time: one column per scene; top row the undisturbed field, bottom row the magnet
    # under a quarter of the sheet, each with the run without magnetometers as its baseline
    fig, axes = plt.subplots(2, len(names), figsize=(4.2 * len(names), 6.6), squeeze=False,
                             sharex=True)
    for j, name in enumerate(names):
        for i, variant in enumerate(("", "+disturbed")):
            ax = axes[i, j]
            t, ea, _h = curves[(name, "accel+gyro", "accel_only")]
            ax.plot(t, ea, color=colours["accel_only"], lw=0.6, label="accel_only (accel)")
            for method in ("per_link_filter", "fused"):
                c = colours[method]
                t, e, _h = curves[(name, "accel+gyro", method)]
                ax.plot(t, e, color=c, lw=3.0, alpha=0.3, label=f"{method} (accel+gyro)")
                t, e, _h = curves[(name + variant, "accel+gyro+mag", method)]
                ax.plot(t, e, color=c, lw=0.9,
                        label=f"{method} (accel+gyro+mag{', magnet' if variant else ''})")
            ax.set_yscale("log")
            ax.axhline(0.5, color="grey", lw=0.6, ls=":")
            ax.set_title(name + (" — magnet under a quarter" if variant else ""), fontsize=9)
            if i == 1:
                ax.set_xlabel("time [s]")
            if j == 0:
                ax.set_ylabel("mean joint error [% of side]")
    handles = [h for ax in axes[:, 0] for h in ax.get_legend_handles_labels()[0]]
    labels = [lb for ax in axes[:, 0] for lb in ax.get_legend_handles_labels()[1]]
    keep = dict(zip(labels, handles))
    fig.legend(keep.values(), keep.keys(), loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.suptitle("Shape error over time, 14x14, L = 1 cm, 1 % g accelerometers, ICM-42688-P gyroscopes, "
                 "LIS3MDL magnetometers (bench_motion.py; dotted: 0.5 % of side; the fused estimator's "
                 "magnetometers turn the sheet rigidly, so its thin and thick curves coincide)", fontsize=9)
    fig.tight_layout(rect=(0, 0.07, 1, 0.96))
    fig.savefig(outdir / "motion_error_time.png", dpi=110)
    plt.close(fig)

    # heading over time (with magnetometers): where the disturbance shows in the fused estimator
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.3), squeeze=False, sharey=True)
    for ax, name in zip(axes[0], names):
        for method in ("per_link_filter", "fused"):
            for variant, ls in (("", "-"), ("+disturbed", "--")):
                t, _e, h = curves[(name + variant, "accel+gyro+mag", method)]
                ax.plot(t, h, ls, color=colours[method], lw=0.9,
                        label=f"{method}{' (magnet)' if variant else ''}")
        ax.axhline(2.0, color="grey", lw=0.6, ls=":")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("time [s]")
    axes[0, 0].set_ylabel("|mean heading error| [deg]")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Heading with magnetometers, undisturbed (solid) and with a magnet under a quarter of "
                 "the sheet (dashed); dotted: 2 deg (bench_motion.py)", fontsize=9)
    fig.tight_layout()
    fig.savefig(outdir / "motion_heading_time.png", dpi=110)
    plt.close(fig)

    # paper-style (its Fig. 10: mean error with its spread, per condition and method)
    fig, ax = plt.subplots(figsize=(12, 4.5))
    groups = [(r["scene"], r["sensors"]) for r in rows if r["method"] == "fused"]
    w = 0.27
    for i, method in enumerate(METHODS):
        ys, lo, hi = [], [], []
        for g in groups:
            key = (g[0], g[1], method)
            if key not in curves:
                ys.append(np.nan), lo.append(0), hi.append(0)
                continue
            err = curves[key][1]
            ys.append(err.mean())
            lo.append(err.mean() - np.percentile(err, 5))
            hi.append(np.percentile(err, 95) - err.mean())
        ax.bar(np.arange(len(groups)) + (i - 1) * w, ys, w, yerr=[lo, hi], capsize=2,
               color=colours[method], label=method)
    ax.set_yscale("log")
    ax.set_xticks(np.arange(len(groups)))
    ax.set_xticklabels([f"{s}\n{x}" for s, x in groups], fontsize=7, rotation=30, ha="right")
    ax.set_ylabel("joint error [% of side] (mean, 5-95 % over time)")
    ax.axhline(0.5, color="grey", lw=0.6, ls=":")
    ax.legend()
    ax.set_title("Error of the shape while the sheet moves, three estimators on the same data "
                 "(14x14, 1 % g; dotted: 0.5 % of side)")
    fig.tight_layout()
    fig.savefig(outdir / "motion_paper.png", dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print JSON (the only output format)")
    ap.add_argument("--lattice", type=int, default=14)
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--scenes", nargs="*", default=[s for s, v in MOTION_SCENES.items() if v.moving]
                    + list(MAGNETOMETER_SCENES))
    ap.add_argument("--drift-minutes", type=float, default=10.0, help="0: leave the drift run out")
    ap.add_argument("--speed-lattices", type=int, nargs="*", default=[14, 32, 64])
    ap.add_argument("--bias-seconds", type=float, default=10.0, help="0: leave the bias-learning run out")
    ap.add_argument("--png", type=Path, help="write the figures into this folder")
    args = ap.parse_args(argv)
    n = args.lattice
    unknown = [s for s in args.scenes if s not in MOTION_SCENES]
    if unknown or n < 3 or args.seconds <= 0 or args.drift_minutes < 0:
        print(f"bench_motion.py: invalid arguments (unknown scenes {unknown}, lattice {n}, "
              f"seconds {args.seconds}, drift minutes {args.drift_minutes})", file=sys.stderr)
        return 2
    cal, cal_cpu = calibrate(n)
    rows, curves = [], {}
    for i, name in enumerate(args.scenes):
        rows += scene_rows(name, n, args.seconds, cal, 100 + i, curves)
    drift_row = drift(n, args.drift_minutes, cal, 300) if args.drift_minutes > 0 else None
    speed_rows = [speed(k) for k in args.speed_lattices]
    bias_rows = bias_learning(n, args.bias_seconds) if args.bias_seconds > 0 else None
    if args.png:
        figures(curves, rows, args.png)
    print(json.dumps({"lattice": f"{n}x{n}", "link_length_m": L, "rate_hz": 145.0,
                      "seconds": args.seconds, "calibration_cpu_s": round(cal_cpu, 1),
                      "vqf": have_vqf(), "rows": rows, "drift": drift_row, "speed": speed_rows,
                      "bias_learning": bias_rows, "true_noise_config": {
                          k: getattr(TRUE_NOISE, k) for k in ("accel_noise_mps2", "mag_noise_t")},
                      "targets": TARGETS, "check": check(rows, drift_row, speed_rows),
                      "load": _load()}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
