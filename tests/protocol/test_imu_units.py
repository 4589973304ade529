"""Gyroscope and magnetometer ranges and counts <-> SI (protocol/imu_units.py): the range table as
the protocol states it (gyro ±125 … ±2000 °/s, magnetometer ±4 … ±16 gauss) and exact round trips."""

import math

import numpy as np
import pytest

from protocol.imu_units import (GyroRange, MagRange, count_limits, gyro_counts_to_si, gyro_nominal_sensitivity,
                                mag_counts_to_si, mag_nominal_sensitivity, si_to_gyro_counts, si_to_mag_counts)


def test_the_range_codes_are_the_issues_ranges():
    assert [r.full_scale_dps for r in GyroRange] == [125, 250, 500, 1000, 2000]
    assert [r.full_scale_gauss for r in MagRange] == [4, 8, 12, 16]
    assert [gyro_nominal_sensitivity(r) for r in GyroRange] == [262.144, 131.072, 65.536, 32.768, 16.384]
    assert [mag_nominal_sensitivity(r) for r in MagRange] == [8192.0, 4096.0, 32768 / 12, 2048.0]


@pytest.mark.parametrize("code", list(GyroRange))
def test_gyro_full_scale_count_is_the_full_scale_rate(code):
    assert gyro_counts_to_si(32768, code) == pytest.approx(math.radians(code.full_scale_dps), rel=1e-15)
    w = np.linspace(-1, 1, 11) * math.radians(code.full_scale_dps)
    np.testing.assert_allclose(gyro_counts_to_si(si_to_gyro_counts(w, code, 3.0, 30.0), code, 3.0, 30.0), w,
                               rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("code", list(MagRange))
def test_mag_full_scale_count_is_the_full_scale_field(code):
    assert mag_counts_to_si(32768, code) == pytest.approx(code.full_scale_gauss * 1e-4, rel=1e-15)
    b = np.linspace(-1, 1, 11) * code.full_scale_gauss * 1e-4
    np.testing.assert_allclose(mag_counts_to_si(si_to_mag_counts(b, code), code), b, rtol=1e-14, atol=1e-19)


def test_limits_and_bad_codes():
    assert count_limits(12) == (-2048, 2047)
    with pytest.raises(ValueError):
        GyroRange(5)
    with pytest.raises(ValueError, match="bits"):
        count_limits(1)
