"""The sheet's per-SYNC readings: what the chips read is `SensorModel.sample` of the scene, exactly."""

from __future__ import annotations

import numpy as np
import pytest

from virtual_sheet.sensor import SensorModel
from virtual_sheet.sheet import VirtualSheet


@pytest.mark.parametrize("sensor", [
    SensorModel(noise_pct_g=2.0, bias_counts=20.0, scale_error=0.02, misalignment_rad=0.02, chip_seed=3),
    SensorModel(noise_pct_g=0.0, bias_counts=5.0, misalignment_rad=0.01, chip_seed=4),
    SensorModel(noise_pct_g=1.0, bias_counts=900.0, scale_error=0.3, chip_seed=5),  # many axes saturate
])
def test_readings_per_sync_are_the_sensor_models_samples(sensor):
    """Each SYNC's counts and status are what `SensorModel.sample` gives for that scene step with
    the same noise draws (the sheet keeps what does not change per SYNC; the numbers must not)."""
    sheet = VirtualSheet("grow", "6x5", seed=2, sensor=sensor, scene_rate_hz=20.0)
    rng = sheet._noise_rng
    idx = np.arange(sheet.n_links)
    saturated = 0
    for i in range(40):
        t = 0.013 + i * (1 / 145)  # several SYNCs per scene step, then the next steps
        state = rng.bit_generator.state
        want_c, want_s = sheet.counts_at(t)  # SensorModel.sample of this step's readings
        after = rng.bit_generator.state["state"]
        rng.bit_generator.state = state  # the same draws again, for the SYNC path
        got_c, got_s = sheet._batch_source(t, idx)
        now = rng.bit_generator.state["state"]  # and as many of them
        assert now["pos"] == after["pos"] and np.array_equal(now["key"], after["key"])
        np.testing.assert_array_equal(got_c, want_c.astype(np.int64))
        np.testing.assert_array_equal(got_s, want_s.astype(np.int64))
        assert got_c.dtype == got_s.dtype == np.int64
        saturated += int(np.count_nonzero(got_s))
    if sensor.bias_counts > 500:
        assert saturated > 0
