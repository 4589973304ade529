"""6/9-axis chip models: exact counts from the truth with ideal parts, the datasheet's noise density
recovered by an independent Allan deviation and Welch PSD from seeded long streams, the bias
instability's Gauss–Markov statistics, the fixed errors as stated, and streams that do not depend on
which sensors are present or how the run is chunked.

Expected values come from the datasheet figures and the truth, never from the model's own output."""

import numpy as np
import pytest
from scipy.signal import welch

from protocol.constants import G0
from protocol.imu_units import GyroRange, MagRange
from virtual_sheet.imu import (GyroModel, ImuArray, MagModel, accel_model, imu_array, simulate)
from virtual_sheet.magfield import EarthField, MagneticField, field_in_sensor_frames
from virtual_sheet.motion import make_motion_scene
from virtual_sheet.sensor import SensorModel

L = 0.01
RATE = 145.0
QUIET = dict(bias_dps=0.0, bias_instability_dps=0.0, scale_error=0.0, cross_axis=0.0, g_sensitivity_dps=0.0)


def _rest(n_samples: int, rows: int = 3):
    scene = make_motion_scene("rest", rows, rows, L, shape="flat")
    return scene.sample(np.arange(n_samples) / RATE)


def _allan(y: np.ndarray, m: int) -> float:
    """Non-overlapping Allan deviation of ``y (N, ...)`` (every series pooled) at m samples."""
    K = y.shape[0] // m
    means = y[: K * m].reshape(K, m, -1).mean(axis=1)
    return float(np.sqrt(0.5 * np.mean(np.diff(means, axis=0) ** 2)))


def test_ideal_parts_report_the_truth_rounded_to_counts():
    env = MagneticField(EarthField(50e-6, np.radians(60), 0.4))
    scene = make_motion_scene("wave", 6, 6, L)
    tr = scene.sample(np.arange(1.0, 2.0, 1 / RATE))
    imu = ImuArray(60, accel=SensorModel(), gyro=GyroModel.part("ideal", range=GyroRange.DPS1000),
                   mag=MagModel.part("ideal"), field=env)
    r = imu.read(tr)
    np.testing.assert_array_equal(r.gyro_counts, np.rint(np.degrees(tr.angular_velocity) * 32768 / 1000))
    B = np.einsum("tkji,tkj->tki", tr.frames, env.at(tr.position))
    np.testing.assert_array_equal(r.mag_counts, np.rint(B / 1e-4 * 32768 / 4))
    np.testing.assert_array_equal(r.accel_counts, np.rint(tr.specific_force / G0 * 1024))
    assert np.max(np.abs(r.gyro_rps - tr.angular_velocity)) <= np.radians(0.5 * 1000 / 32768) + 1e-15
    assert r.sensors == "accel+gyro+mag" and not r.gyro_saturated.any() and not r.mag_saturated.any()
    np.testing.assert_array_equal(r.timestamp_us, 0)


def test_gyro_white_noise_has_the_datasheet_density_by_allan_deviation_and_welch():
    N = 1 << 15
    nd = 0.0028  # ICM-42688-P, °/s/√Hz
    imu = ImuArray(12, gyro=GyroModel(noise_density_dps=nd, range=GyroRange.DPS125, **QUIET), seed=11)
    y = np.degrees(imu.read(_rest(N)).gyro_rps)  # (N, 12, 3) °/s
    for m in (1, 10, 100):
        tau = m / RATE
        assert _allan(y, m) == pytest.approx(nd / np.sqrt(2 * tau), rel=0.03)
    f, p = welch(y.reshape(N, -1), fs=RATE, nperseg=1024, axis=0)
    band = (f > 1.0) & (f < 60.0)
    assert np.sqrt(p[band].mean()) == pytest.approx(nd, rel=0.03)


def test_the_allan_check_sees_the_wrong_density():
    # the same check on the ICM-42605 (3.8 mdps/√Hz) against the ICM-42688-P's figure fails
    imu = ImuArray(12, gyro=GyroModel.part("icm42605", range=GyroRange.DPS125, **QUIET), seed=11)
    y = np.degrees(imu.read(_rest(1 << 13)).gyro_rps)
    assert _allan(y, 10) > 1.2 * 0.0028 / np.sqrt(2 * 10 / RATE)


def test_bias_instability_is_a_gauss_markov_process_of_the_stated_spread_and_time():
    N, tau_c, sigma = 1 << 15, 2.0, 0.01
    imu = ImuArray(12, gyro=GyroModel(noise_density_dps=0.0, range=GyroRange.DPS125, bias_time_constant_s=tau_c,
                                      **{**QUIET, "bias_instability_dps": sigma}), seed=5)
    y = np.degrees(imu.read(_rest(N)).gyro_rps).reshape(N, -1)
    assert y.std() == pytest.approx(sigma, rel=0.06)
    lag = int(round(tau_c * RATE))
    yc = y - y.mean(axis=0)
    rho = np.mean(yc[:-lag] * yc[lag:]) / np.mean(yc * yc)
    assert rho == pytest.approx(np.exp(-1), abs=0.05)
    assert np.mean(yc[:-1] * yc[1:]) / np.mean(yc * yc) > 0.97  # slow: a bias, not noise (less 1 % quantisation)


def test_fixed_gyro_errors_are_scale_cross_axis_mounting_bias_and_g_sensitivity():
    scene = make_motion_scene("carry", 5, 5, L)
    tr = scene.sample(np.arange(1.0, 3.0, 1 / RATE))
    acc = accel_model("icm42688p", noise_pct_g=0.0, chip_seed=3)
    gyro = GyroModel.part("icm42688p", noise_density_dps=0.0, bias_instability_dps=0.0, range=GyroRange.DPS500,
                          chip_seed=3)
    imu = ImuArray(40, accel=acc, gyro=gyro)
    r = imu.read(tr)
    e, M = imu.gyro_errors, imu.accel_errors.misalignment
    assert np.abs(np.degrees(e.bias_rps)).max() > 0.3 and np.abs(M - np.eye(3)).max() > 0.01
    w = np.einsum("kji,tkj->tki", M, tr.angular_velocity)
    f = np.einsum("kji,tkj->tki", M, tr.specific_force)
    expect = (np.einsum("kij,tkj->tki", e.scale, w) + e.bias_rps
              + np.einsum("kij,tkj->tki", e.g_sensitivity, f / G0))
    assert np.max(np.abs(r.gyro_rps - expect)) <= np.radians(0.5 / (32768 / 500)) + 1e-12
    assert np.max(np.abs(r.gyro_rps - tr.angular_velocity)) > np.radians(1.0)  # the errors are there


def test_magnetometer_reads_soft_iron_mounting_and_hard_iron():
    env = MagneticField(EarthField(48e-6, np.radians(55), -0.2))
    tr = make_motion_scene("tumble", 4, 4, L).sample(np.arange(0.0, 5.0, 0.1))
    mag = MagModel.part("lis3mdl", noise_t=(0.0, 0.0, 0.0), chip_seed=9)
    imu = ImuArray(24, mag=mag, field=env)
    r = imu.read(tr)
    e = imu.mag_errors
    np.testing.assert_allclose(e.soft_iron, np.transpose(e.soft_iron, (0, 2, 1)))  # symmetric
    B = field_in_sensor_frames(env, tr.position, tr.frames)
    expect = np.einsum("kij,tkj->tki", e.soft_iron @ np.transpose(e.mounting, (0, 2, 1)), B) + e.hard_iron_t
    assert np.max(np.abs(r.mag_t - expect)) <= 0.5e-4 / 8192 + 1e-18
    assert np.abs(e.hard_iron_t).max() > 20e-6


def test_magnetometer_noise_is_the_datasheet_rms_per_axis():
    imu = ImuArray(12, mag=MagModel.part("lis3mdl", hard_iron_t=0.0, soft_iron=0.0, mounting_rad=0.0), seed=4)
    y = imu.read(_rest(1 << 13)).mag_t
    sd = (y - y.mean(axis=0)).reshape(-1, 3).std(axis=0)
    np.testing.assert_allclose(sd, [0.32e-6, 0.32e-6, 0.41e-6], rtol=0.03)  # LIS3MDL: 3.2/3.2/4.1 mgauss


def test_each_sensor_has_its_own_stream_and_chunks_read_like_one_run():
    scene = make_motion_scene("elbow", 4, 4, L)
    env = MagneticField(EarthField())
    six = imu_array(24, "accel+gyro", seed=2)
    nine = imu_array(24, "accel+gyro+mag", seed=2, field=env)
    whole = [r for _t, r in simulate(scene, six, 2.0, chunk_s=2.0)]
    parts = [r for _t, r in simulate(scene, nine, 2.0, chunk_s=0.3)]
    a6 = np.concatenate([r.accel_counts for r in whole])
    g6 = np.concatenate([r.gyro_counts for r in whole])
    np.testing.assert_array_equal(a6, np.concatenate([r.accel_counts for r in parts]))
    np.testing.assert_array_equal(g6, np.concatenate([r.gyro_counts for r in parts]))
    assert whole[0].mag_counts is None and parts[0].mag_counts is not None
    other = np.concatenate([r.gyro_counts for _t, r in simulate(scene, imu_array(24, "accel+gyro", seed=3), 2.0)])
    assert np.any(other != g6)  # another seed, other noise


def test_rates_beyond_the_range_saturate_and_are_flagged():
    tr = make_motion_scene("wave", 6, 6, L).sample(np.arange(1.0, 2.0, 1 / RATE))
    imu = ImuArray(60, gyro=GyroModel.part("ideal", range=GyroRange.DPS125))
    r = imu.read(tr)
    over = np.any(np.abs(np.degrees(tr.angular_velocity)) > 125.1, axis=-1)
    assert over.any()
    np.testing.assert_array_equal(r.gyro_saturated[over], True)
    assert np.abs(r.gyro_counts).max() in (32767, 32768)


def test_presets_and_sensor_sets():
    imu = imu_array(10, "accel+gyro+mag", noise_pct_g=1.0, seed=1)
    assert imu.accel.noise_pct_g == 1.0 and imu.gyro.noise_density_dps == 0.0028
    assert imu.mag.range == MagRange.GAUSS4 and imu.gyro.range == GyroRange.DPS1000
    assert accel_model("icm42688p").noise_pct_g == pytest.approx(0.0596, abs=5e-4)  # 70 µg/√Hz · √72.5 Hz
    assert imu_array(10, "accel").gyro is None


def test_bad_parts_inputs_and_times_are_refused():
    with pytest.raises(ValueError, match="Unknown gyroscope part 'mpu6050'"):
        GyroModel.part("mpu6050")
    with pytest.raises(ValueError, match="Unknown magnetometer part"):
        MagModel.part("hmc5883")
    with pytest.raises(ValueError, match="Invalid sensors: 'accel\\+mag'"):
        imu_array(4, "accel+mag")
    with pytest.raises(ValueError, match="gyro range"):
        GyroModel(range=9)
    with pytest.raises(ValueError, match="noise_t"):
        MagModel(noise_t=(1e-6, -1.0, 0.0))
    imu = ImuArray(12, gyro=GyroModel())
    with pytest.raises(ValueError, match="truth of 12 links"):
        imu.read(make_motion_scene("rest", 4, 4, L).sample([0.0]))
    tr = _rest(4)
    imu.read(tr)
    with pytest.raises(ValueError, match="must increase"):
        imu.read(tr)
    with pytest.raises(ValueError, match="must increase"):  # within one read, without a gyroscope too
        ImuArray(12).read(tr[[0, 2, 1]])
