"""Sensor model: ideal chips reproduce the geometry, the ADC quantises and saturates as the
protocol says, seeded noise is reproducible and has the stated size."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from protocol.constants import ADC_MAX, ADC_MIN, G0, Range, SampleStatus, counts_to_si
from virtual_sheet.geometry import ideal_readings, link_angles, link_frames, roll_pitch
from virtual_sheet.sensor import SensorModel, noisy_readings
from virtual_sheet.shapes import make_sheet


@pytest.fixture(scope="module")
def bump():
    return make_sheet("gaussian", 14, 14, 0.01)


def test_flat_level_sheet_samples_one_g_on_z():
    r = ideal_readings(make_sheet("flat", 5, 5, 0.01))
    counts, status = SensorModel().sample(r)
    assert counts.dtype == np.int16 and status.dtype == np.uint8
    assert np.all(counts == [0, 0, 1024]) and np.all(status == SampleStatus.OK)


def test_zero_noise_counts_give_the_geometry_roll_pitch_to_quantisation(bump):
    counts, _ = SensorModel().sample(ideal_readings(bump))
    alpha, beta = roll_pitch(counts.astype(float))
    a_true, b_true, _ = link_angles(bump)
    # half a count of 1024 per g: angle error below ~1/1024 rad
    assert np.max(np.abs(alpha - a_true)) < 1.5e-3
    assert np.max(np.abs(beta - b_true)) < 1.5e-3


@pytest.mark.parametrize("rng", [np.random.Generator(np.random.MT19937(1)), 1])
def test_noise_is_reproducible_from_the_seed(bump, rng):
    model = SensorModel(noise_pct_g=2.0)
    a, _ = model.sample(ideal_readings(bump), 1)
    b, _ = model.sample(ideal_readings(bump), rng)
    np.testing.assert_array_equal(a, b)
    c, _ = model.sample(ideal_readings(bump), 2)
    assert not np.array_equal(a, c)


def test_noise_has_the_stated_standard_deviation():
    n = 20_000
    truth = np.tile([0.0, 0.0, G0], (n, 1))
    model = SensorModel(noise_pct_g=1.0, range=Range.G4)  # 512 counts/g: sigma = 5.12 counts
    counts, _ = model.sample(truth, 42)
    si = counts_to_si(counts.astype(float), 0.0, model.nominal_sensitivity)
    std = si.std(axis=0)
    expected = np.sqrt(model.noise_std_mps2 ** 2 + (G0 / 512) ** 2 / 12)  # + quantisation
    np.testing.assert_allclose(std, expected, rtol=0.03)  # 3 % >> 1/sqrt(2n) = 0.5 %
    np.testing.assert_allclose(si.mean(axis=0), [0, 0, G0], atol=4 * expected / np.sqrt(n))


def test_noisy_readings_for_the_estimator():
    truth = np.tile([0.0, 0.0, G0], (20_000, 1))
    r = noisy_readings(truth, 5.0, 3)
    np.testing.assert_allclose((r - truth).std(axis=0), 0.05 * G0, rtol=0.03)
    np.testing.assert_array_equal(r, noisy_readings(truth, 5.0, 3))


@pytest.mark.parametrize("rng_code", list(Range))
def test_quantisation_step_is_one_over_sensitivity(rng_code):
    model = SensorModel(range=rng_code)
    sens = model.nominal_sensitivity
    f = np.linspace(-1.5 * G0, 1.5 * G0, 4001)
    r = np.stack([f, np.zeros_like(f), np.zeros_like(f)], axis=1)
    counts, _ = model.sample(r)
    steps = np.unique(np.diff(counts[:, 0].astype(int)))
    assert set(steps) <= {0, 1}
    si = counts_to_si(counts[:, 0].astype(float), 0.0, sens)
    assert np.max(np.abs(si - f)) <= 0.5 * G0 / sens + 1e-12
    np.testing.assert_allclose(np.diff(np.unique(si)), G0 / sens)


def test_motion_acceleration_beyond_range_saturates_and_is_flagged(bump):
    frames = link_frames(bump)
    readings = ideal_readings(bump)
    calm, s_calm = SensorModel(motion_accel_mps2=(0.0, 0.0, 0.5 * G0)).sample(readings,
                                                                              frames=frames)
    assert np.all(s_calm == SampleStatus.OK)
    hard, s_hard = SensorModel(motion_accel_mps2=(0.0, 0.0, 3 * G0)).sample(readings,
                                                                            frames=frames)
    assert np.all(s_hard & SampleStatus.SATURATED)  # 4 g up on z-ish axes, range ±2 g
    assert np.all(np.any((hard == ADC_MAX) | (hard == ADC_MIN), axis=1))
    ok, s_ok = SensorModel(motion_accel_mps2=(0.0, 0.0, 3 * G0), range=Range.G8).sample(
        readings, frames=frames)
    assert np.all(s_ok == SampleStatus.OK)


def test_motion_acceleration_is_rotated_into_the_sensor_frame(bump):
    frames = link_frames(bump)
    a = np.array([1.0, -2.0, 0.5])
    model = SensorModel(motion_accel_mps2=tuple(a))
    got = model.chip_readings(ideal_readings(bump), frames=frames)
    np.testing.assert_allclose(got, ideal_readings(bump) + frames.transpose(0, 2, 1) @ a,
                               atol=1e-12)
    with pytest.raises(ValueError, match="frames"):
        model.sample(ideal_readings(bump))


def test_true_calibration_undoes_bias_and_scale(bump):
    model = SensorModel(bias_mps2=0.3, bias_counts=5, scale_error=0.03, chip_seed=9)
    r = ideal_readings(bump)
    counts, _ = model.sample(r)
    offset, sens = model.true_calibration(len(r))
    assert np.std(offset) > 10 and np.std(sens / 1024 - 1) > 0.01
    np.testing.assert_allclose(counts_to_si(counts, offset, sens), r, atol=0.5 * G0 / sens.min() + 1e-9)
    np.testing.assert_array_equal(model.true_calibration(len(r))[0], offset)  # same chips


def test_misalignment_rotates_the_reading_by_the_stated_amount(bump):
    model = SensorModel(misalignment_rad=0.01, chip_seed=4)
    r = ideal_readings(bump)
    got = model.chip_readings(r)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), G0, rtol=1e-12)
    angle = np.arccos(np.clip(np.sum(got * r, 1) / G0 ** 2, -1, 1))
    assert 0.003 < np.median(angle) < 0.03


@settings(max_examples=30)
@given(f=st.lists(st.floats(-40.0, 40.0), min_size=3, max_size=3),
       code=st.sampled_from(list(Range)))
def test_saturation_flag_iff_an_axis_is_at_the_adc_limit(f, code):
    counts, status = SensorModel(range=code).sample(np.array([f]))
    at_limit = bool(np.any((counts == ADC_MIN) | (counts == ADC_MAX)))
    assert bool(status[0] & SampleStatus.SATURATED) == at_limit
    assert ADC_MIN <= counts.min() and counts.max() <= ADC_MAX


@pytest.mark.parametrize("bad", [{"noise_pct_g": -1}, {"scale_error": float("nan")},
                                 {"range": 7}, {"motion_accel_mps2": (1.0, 2.0)},
                                 {"chip_seed": -1}])
def test_model_validates_itself(bad):
    with pytest.raises(ValueError, match="Invalid"):
        SensorModel(**bad)


def test_noise_needs_a_seed_and_readings_need_the_right_shape():
    with pytest.raises(ValueError, match="rng"):
        SensorModel(noise_pct_g=1.0).sample(np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"shape \(\.\.\., n_links, 3\), got \(2, 2\)"):
        SensorModel().sample(np.zeros((2, 2)))


# ------------------------------------------------------------------ chip-error presets

def test_realistic_chip_errors_have_the_documented_spreads_and_no_factory_calibration():
    from protocol.constants import G0 as _G0
    from virtual_sheet.sensor import CHIP_ERRORS, chip_error_model
    from virtual_sheet.sheet import VirtualSheet

    m = chip_error_model("realistic", noise_pct_g=0.3, chip_seed=2)
    e = m.chip_errors(4000)
    bias_mg = e.offset_counts / m.nominal_sensitivity * 1000
    assert np.std(bias_mg) == pytest.approx(30, rel=0.05)
    assert np.std(e.sensitivity / m.nominal_sensitivity - 1) == pytest.approx(0.015, rel=0.05)
    from scipy.spatial.transform import Rotation
    assert np.degrees(np.std(Rotation.from_matrix(e.misalignment).as_rotvec())) == pytest.approx(1.5, rel=0.05)
    # the chips report the nominal calibration, the truth is still available
    off, sens = m.stored_calibration(5)
    assert np.array_equal(off, np.zeros((5, 3))) and np.array_equal(sens, np.full((5, 3), 1024.0))
    assert not np.allclose(m.true_calibration(5)[0], 0)
    sheet = VirtualSheet("flat", "3x3", sensor=m)
    assert all(c.cal == [(0, 1024.0, 1)] * 3 for c in sheet.chips)
    # "none" is the default model: ideal chips, factory calibrated
    assert chip_error_model("none", noise_pct_g=0.3, chip_seed=2) == SensorModel(noise_pct_g=0.3, chip_seed=2)
    assert set(CHIP_ERRORS) == {"none", "realistic"}
    assert m.bias_mps2 == pytest.approx(0.030 * _G0)
    with pytest.raises(ValueError, match="Unknown chip errors 'typical'"):
        chip_error_model("typical")
    with pytest.raises(ValueError, match="factory_calibrated"):
        SensorModel(factory_calibrated="no")
