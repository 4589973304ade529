"""The fused estimator's consistency: its errors against the uncertainty it reports.

Seeded simulated runs (virtual_sheet.motion's exact kinematics, virtual_sheet.imu's chips with
their true noise told to the filter; a simulated clock: the samples' own times). The errors are
measured here, against the simulator's true frames, and the χ² bounds come from scipy.stats.chi2
here, not from the code under test:

* the links' **tilt NEES** — the world-frame rotation error's x and y parts, against the
  joint covariance the estimator reports: each link's ``orientation_cov_rad2`` is its own part
  plus ``common_tilt_cov_rad2``, which every link shares, so the joint covariance of all links is
  ``blockdiag(cov − common) + 1 1ᵀ ⊗ common`` (inverted here by Woodbury's identity); χ² with
  2 n_links degrees of freedom for a consistent filter;
* the accelerometers' **NIS** — each link's normalised innovation squared (``accel_nis``, the
  filter's own ``yᵀ S⁻¹ y``), summed over the links: χ² with 3 n_links degrees of freedom.

Per snapshot after the first second, each statistic per degree of freedom; the run's mean must
lie in the 95 % band of one snapshot's statistic."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from host.analysis.motion import FusedConfig, MotionEstimator
from host.analysis.motion.peers import yaw_of_frames
from virtual_sheet.imu import GyroModel, ImuArray, accel_model, simulate
from virtual_sheet.magfield import EarthField, MagneticField
from virtual_sheet.motion import MOTION_SCENES, make_motion_scene

L = 0.01
N = 6
N_LINKS = 2 * N * (N - 1)
MOVING = [s for s, spec in MOTION_SCENES.items() if spec.moving]
PCT_G = 1.0  # the chips' accelerometer noise, % g per sample
#: the truth about these chips: their accelerometer noise, and nothing left out of the gyroscope's
#: model (ideal parts: no orientation walk; the rate-proportional term kept at 0.1 % for the
#: integration's own error at the wave's 500 °/s)
TOLD = FusedConfig(accel_noise_mps2=PCT_G / 100 * 9.80665, orientation_walk_rad=0.0,
                   gyro_scale_error=1e-3)


def record(name, seconds=3.0, seed=21):
    imu = ImuArray(N_LINKS, accel=accel_model("ideal", noise_pct_g=PCT_G),
                   gyro=GyroModel.part("ideal", noise_density_dps=0.0028),
                   field=MagneticField(EarthField(50e-6, np.radians(60.0))), seed=seed)
    return next(simulate(make_motion_scene(name, N, N, L), imu, seconds, chunk_s=seconds))


def joint_tilt_nees(err, cov, common):
    """``errᵀ Σ⁻¹ err`` for Σ = blockdiag(cov − common) + 1 1ᵀ ⊗ common (module docstring)."""
    own = cov - common
    B = np.linalg.inv(own)
    z = np.einsum("kij,kj->ki", B, err)
    Z = z.sum(axis=0)
    M = np.eye(2) + B.sum(axis=0) @ common
    return float(np.einsum("ki,ki->", err, z)) - float(Z @ common @ np.linalg.solve(M, Z))


def tilt_error(frames, true_frames):
    """Every link's orientation error as a world-frame rotation vector (``R_true = exp([d]×)
    R``), the estimate first turned about world z by the links' mean heading error: without
    magnetometers the heading is a gauge (the first snapshot's), not an error."""
    d = yaw_of_frames(frames) - yaw_of_frames(true_frames)
    psi = np.arctan2(np.sin(d).mean(), np.cos(d).mean())
    c, s = np.cos(psi), np.sin(psi)
    R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ frames
    return Rotation.from_matrix(true_frames @ R.transpose(0, 2, 1)).as_rotvec()


def statistics(truth, rd, config):
    """Per snapshot after the first second: tilt NEES and NIS per degree of freedom."""
    est = MotionEstimator(N, N, L, config=config)
    nees, nis = [], []
    for k in range(rd.t_s.size):
        e = est.update(rd.t_s[k], rd.accel_mps2[k], rd.gyro_rps[k])
        if rd.t_s[k] - rd.t_s[0] < 1.0:
            continue
        err = tilt_error(e.frames, truth.frames[k])
        nees.append(joint_tilt_nees(err[:, :2], e.orientation_cov_rad2[:, :2, :2],
                                    e.common_tilt_cov_rad2) / (2 * N_LINKS))
        nis.append(float(np.sum(e.accel_nis)) / (3 * N_LINKS))
    return np.array(nees), np.array(nis)


def band(dof):
    return chi2.ppf(0.025, dof) / dof, chi2.ppf(0.975, dof) / dof


@pytest.mark.parametrize("name", MOVING)
def test_the_tilt_nees_and_the_accelerometer_nis_lie_in_their_bands(name):
    truth, rd = record(name)
    nees, nis = statistics(truth, rd, TOLD)
    lo, hi = band(2 * N_LINKS)
    assert lo <= nees.mean() <= hi, (name, nees.mean(), (lo, hi))
    lo, hi = band(3 * N_LINKS)
    assert lo <= nis.mean() <= hi, (name, nis.mean(), (lo, hi))


def test_a_filter_told_too_little_noise_fails_the_bands():
    # the same chips, the filter told half their accelerometer noise: overconfident, and the
    # checks above see it
    truth, rd = record("carry")
    nees, nis = statistics(truth, rd, dataclasses.replace(TOLD, accel_noise_mps2=0.5 * TOLD.accel_noise_mps2))
    assert nees.mean() > band(2 * N_LINKS)[1] and nis.mean() > band(3 * N_LINKS)[1], \
        (nees.mean(), nis.mean())


#: chips whose gyroscopes keep a fixed scale and cross-axis error (each entry of ``E`` 0.3 %, as
#: an uncalibrated part's leaves after a rough calibration), else ideal
FIXED_E = 3e-3


def record_fixed_error(name, seconds=3.0, seed=23):
    imu = ImuArray(N_LINKS, accel=accel_model("ideal", noise_pct_g=PCT_G),
                   gyro=GyroModel.part("ideal", noise_density_dps=0.0028, scale_error=FIXED_E,
                                       cross_axis=FIXED_E, chip_seed=5),
                   field=MagneticField(EarthField(50e-6, np.radians(60.0))), seed=seed)
    return next(simulate(make_motion_scene(name, N, N, L), imu, seconds, chunk_s=seconds))


@pytest.mark.parametrize("name", ["carry", "elbow", "wave"])
def test_a_fixed_scale_error_told_as_fixed_keeps_the_tilt_nees_in_its_band(name):
    # the error is each chip's own and lasts: carried as a consider state its tilt error grows
    # with the angle turned (the carry's and the elbow's sustained turns) and averages out over
    # the wave's back-and-forth, and the reported covariance says so
    truth, rd = record_fixed_error(name)
    nees, nis = statistics(truth, rd, dataclasses.replace(TOLD, gyro_scale_fixed_error=FIXED_E))
    lo, hi = band(2 * N_LINKS)
    assert lo <= nees.mean() <= hi, (name, nees.mean(), (lo, hi))
    lo, hi = band(3 * N_LINKS)
    assert lo <= nis.mean() <= hi, (name, nis.mean(), (lo, hi))


def test_a_fixed_scale_error_told_as_white_noise_fails_the_band():
    # the same chips, the same error told as white noise per step (its variance the fixed one's
    # per step): one process cannot hold an error that grows with the angle turned on one
    # scene and averages out on another
    white = dataclasses.replace(TOLD, gyro_scale_error=float(np.hypot(TOLD.gyro_scale_error,
                                                                      FIXED_E)))
    means = {}
    for name in ("carry", "wave"):
        truth, rd = record_fixed_error(name)
        means[name] = statistics(truth, rd, white)[0].mean()
    lo, hi = band(2 * N_LINKS)
    assert any(not lo <= m <= hi for m in means.values()), (means, (lo, hi))


#: chips whose gyroscopes keep a fixed g-sensitivity (°/s per g, each entry), else ideal
FIXED_G_DPS = 0.3


def test_a_fixed_g_sensitivity_told_as_fixed_keeps_the_tilt_nees_in_its_band():
    # ``Γ f / g`` at the start pose is a bias (told: the bias's uncertainty covers it); as the
    # elbow's links turn, f changes in their frames and so does the rate's error, which the
    # consider state carries
    imu = ImuArray(N_LINKS, accel=accel_model("ideal", noise_pct_g=PCT_G),
                   gyro=GyroModel.part("ideal", noise_density_dps=0.0028,
                                       g_sensitivity_dps=FIXED_G_DPS, chip_seed=6),
                   field=MagneticField(EarthField(50e-6, np.radians(60.0))), seed=29)
    truth, rd = next(simulate(make_motion_scene("elbow", N, N, L), imu, 3.0, chunk_s=3.0))
    g = float(np.radians(FIXED_G_DPS))
    base = dataclasses.replace(TOLD, gyro_bias_std_rps=float(np.sqrt(3.0)) * g)
    nees = statistics(truth, rd, dataclasses.replace(base, gyro_gsens_fixed_error=g))[0].mean()
    lo, hi = band(2 * N_LINKS)
    assert lo <= nees <= hi, (nees, (lo, hi))
    # the check can fail: not told, the filter is overconfident
    untold = statistics(truth, rd, base)[0].mean()
    assert untold > hi, (untold, (lo, hi))


#: chips whose accelerometers are each turned by a fixed small rotation (what a calibration
#: leaves: its residue, rad per axis), else ideal
FIXED_ACCEL_RAD = float(np.radians(0.05))


def record_fixed_accel(seconds=3.0, seed=31):
    imu = ImuArray(N_LINKS, accel=accel_model("ideal", noise_pct_g=PCT_G, chip_seed=8,
                                              misalignment_rad=FIXED_ACCEL_RAD),
                   gyro=GyroModel.part("ideal", noise_density_dps=0.0028),
                   field=MagneticField(EarthField(50e-6, np.radians(60.0))), seed=seed)
    return next(simulate(make_motion_scene("level", N, N, L), imu, seconds, chunk_s=seconds))


def test_a_fixed_accelerometer_error_told_keeps_the_still_sheets_tilt_nees_in_its_band():
    # a still sheet: the accelerometers' noise averages out and their fixed error does not, so
    # the links' tilts settle on the chips' frames, each off its link's by its own error;
    # told, the reported covariance carries it
    truth, rd = record_fixed_accel()
    nees = statistics(truth, rd, dataclasses.replace(
        TOLD, accel_fixed_error_rad=FIXED_ACCEL_RAD))[0].mean()
    lo, hi = band(2 * N_LINKS)
    assert lo <= nees <= hi, (nees, (lo, hi))
    # the check can fail: not told, the filter claims the averaged noise's precision
    untold = statistics(truth, rd, TOLD)[0].mean()
    assert untold > hi, (untold, (lo, hi))


#: the rotation every chip's frame keeps after a calibration (the board's pose then, rad per
#: world axis; bench_motion's board leaves 0.02-0.04°)
BOARD_POSE_RAD = float(np.radians(0.05))


@pytest.mark.parametrize("name", ["carry", "flat_turn"])
def test_a_rotation_the_accelerometer_and_the_gyroscope_share_is_no_error_of_the_rates(name):
    # every chip's accelerometer and gyroscope read in the same frame, turned off the link's
    # alike in the world at the start (the calibration's board pose): the rates are those of
    # the frame the filter follows (the accelerometers'), and the rotation is that frame's
    # offset, the shared fixed error of the accelerometers. In the gyroscopes' ``E`` the same
    # rotation is 0.05 % per cross term; told as a fixed error of the rates as well, the filter
    # claims a tilt error growing with the angle turned that the chips do not make
    truth, rd = record(name, seed=41)
    a = BOARD_POSE_RAD
    q = Rotation.from_rotvec(np.einsum("nji,j->ni", truth.frames[0], np.full(3, a))).as_matrix()
    rd = dataclasses.replace(rd, accel_mps2=np.einsum("nij,tnj->tni", q, rd.accel_mps2),
                             gyro_rps=np.einsum("nij,tnj->tni", q, rd.gyro_rps))
    told = dataclasses.replace(TOLD, accel_common_fixed_error_rad=a)
    nees = statistics(truth, rd, told)[0].mean()
    lo, hi = band(2 * N_LINKS)
    assert lo <= nees <= hi, (name, nees, (lo, hi))
    # the check can fail: the rotation told as the gyroscopes' error too, underconfident
    as_rates = dataclasses.replace(told, gyro_scale_fixed_error=((0.0, a, a), (a, 0.0, a),
                                                                  (a, a, 0.0)))
    twice = statistics(truth, rd, as_rates)[0].mean()
    assert twice < lo, (name, twice, (lo, hi))


#: the rotation every chip's frame keeps after a calibration on a board (the sheet laid flat):
#: alike in the world there, rad per axis
BOARD_FRAME_RAD = float(np.radians(0.2))


@pytest.mark.parametrize("name", ["wave", "elbow"])
def test_a_rotation_the_chips_share_turns_apart_with_the_links_and_the_covariance_says_so(name):
    # every chip's frame (its accelerometer's and its gyroscope's) turned alike in the world
    # while the sheet lay flat, fixed in the chips since: as the sheet bends each link carries
    # it turned by its own turn since, no longer a tilt every link shares. Told as the shared
    # fixed error (`accel_common_fixed_error_rad`), the reported covariance follows the links'
    # turns; told as one common world tilt, as it was, the links' differences were claimed
    # alike, and the bending scenes' NEES was 1.9 (the wave) and 4.7 (the elbow)
    truth, rd = record(name, seed=43)
    flat = np.broadcast_to(np.eye(3), (N_LINKS, 3, 3)).copy()
    flat[N_LINKS // 2:] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]  # the j-links
    w = np.einsum("nji,j->ni", flat, np.full(3, BOARD_FRAME_RAD))  # each chip's frame
    q = Rotation.from_rotvec(w).as_matrix()
    rd = dataclasses.replace(rd, accel_mps2=np.einsum("nij,tnj->tni", q, rd.accel_mps2),
                             gyro_rps=np.einsum("nij,tnj->tni", q, rd.gyro_rps))
    nees = statistics(truth, rd, dataclasses.replace(
        TOLD, accel_common_fixed_error_rad=BOARD_FRAME_RAD))[0].mean()
    lo, hi = band(2 * N_LINKS)
    assert lo <= nees <= hi, (name, nees, (lo, hi))


@pytest.mark.parametrize("name", ["elbow", "carry"])
def test_a_shared_rotation_about_the_boards_vertical_is_told_per_axis(name):
    # the chips' frames turned alike about the flat board's vertical (its heading when they were
    # calibrated: no tilt while the sheet lies flat), 0.4°: as the sheet bends it becomes the
    # links' tilt. Told per axis of the board, the covariance says so; told as one figure for
    # every axis (their RMS, 0.23°), the bending scenes' NEES was 1.50 (the elbow) and 1.52
    # (the carry)
    truth, rd = record(name, seed=43)
    flat = np.broadcast_to(np.eye(3), (N_LINKS, 3, 3)).copy()
    flat[N_LINKS // 2:] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]  # the j-links
    w = np.array([0.0, 0.0, np.radians(0.4)])
    q = Rotation.from_rotvec(np.einsum("nji,j->ni", flat, w)).as_matrix()
    rd = dataclasses.replace(rd, accel_mps2=np.einsum("nij,tnj->tni", q, rd.accel_mps2),
                             gyro_rps=np.einsum("nij,tnj->tni", q, rd.gyro_rps))
    nees = statistics(truth, rd, dataclasses.replace(
        TOLD, accel_common_fixed_error_rad=tuple(float(x) for x in w)))[0].mean()
    lo, hi = band(2 * N_LINKS)
    assert lo <= nees <= hi, (name, nees, (lo, hi))


def test_the_shared_rotation_takes_one_figure_or_three():
    assert FusedConfig(accel_common_fixed_error_rad=(1e-4, 2e-4, 0.0)).accel_common_fixed_error_rad \
        == (1e-4, 2e-4, 0.0)
    with pytest.raises(ValueError, match="accel_common_fixed_error_rad"):
        FusedConfig(accel_common_fixed_error_rad=(1e-4, 1e-4))
    with pytest.raises(ValueError, match="accel_common_fixed_error_rad"):
        FusedConfig(accel_common_fixed_error_rad=(1e-4, -1e-4, 0.0))


def common_tilt_nees(truth, rd, config):
    """Per snapshot after the first second: the links' mean tilt error against its covariance,
    the shared part plus the mean of the links' own (χ² with 2 degrees of freedom)."""
    est = MotionEstimator(N, N, L, config=config)
    out = []
    for k in range(rd.t_s.size):
        e = est.update(rd.t_s[k], rd.accel_mps2[k], rd.gyro_rps[k])
        if rd.t_s[k] - rd.t_s[0] >= 1.0:
            eb = tilt_error(e.frames, truth.frames[k])[:, :2].mean(axis=0)
            common = e.common_tilt_cov_rad2
            cb = common + (e.orientation_cov_rad2[:, :2, :2] - common).mean(axis=0) / N_LINKS
            out.append(float(eb @ np.linalg.solve(cb, eb)))
    return np.array(out)


def test_a_fixed_accelerometer_error_the_chips_share_told_keeps_the_common_tilt_in_its_band():
    # every accelerometer turned alike (the board's own tilt against gravity, 0.5° about x):
    # the sheet's tilt settles on it, and nothing the sheet reads tells it apart
    truth, rd = record("level", seed=37)
    q = Rotation.from_rotvec([float(np.radians(0.5)), 0.0, 0.0]).as_matrix()
    rd = dataclasses.replace(rd, accel_mps2=np.einsum("ij,tnj->tni", q, rd.accel_mps2))
    lo, hi = chi2.ppf(0.025, 2), chi2.ppf(0.975, 2)
    told = common_tilt_nees(truth, rd, dataclasses.replace(
        TOLD, accel_common_fixed_error_rad=float(np.radians(0.5))))
    assert lo <= told.mean() <= hi, (told.mean(), (lo, hi))
    # the check can fail: not told, the sheet's tilt claims what the translation's bounds give
    untold = common_tilt_nees(truth, rd, TOLD)
    assert untold.mean() > hi, (untold.mean(), (lo, hi))
