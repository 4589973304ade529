"""`ImuSource.hold` / `start_at`: a moving sheet lies at its scene's start until told to move, so a
stream begun after a bring-up of any length starts at rest (exact, device times as arguments)."""

from __future__ import annotations

import numpy as np
import pytest

from virtual_sheet.sheet import VirtualSheet


def source():
    return VirtualSheet("carry", "3x3", seed=4, sensors="accel+gyro").imu_source


def test_a_held_sheet_reads_the_start_and_moves_from_start_at():
    src = source()
    grid = src.grid_hz
    src.hold()
    idx = np.arange(12)
    for now in (0.0, 2.5, 7.0):  # however long the bring-up: the scene's instant 0, time_us 0
        assert src.time_of(now) == 0.0
        assert src.read(now, idx)[4].tolist() == [0] * 12
    rest = src.joints(7.0)
    src.start_at(7.0)
    assert src.time_of(7.0) == 0.0 and src.time_of(7.0 + 10 / grid) == 10 / grid
    now = 7.0 + 10.5 / grid  # half a grid step after instant 10: sampled then, 0.5 step before the read
    assert src.read(now, idx)[4].tolist() == [int(round(-0.5 / grid * 1e6))] * 12
    np.testing.assert_array_equal(rest, src.joints_at(0.0))
    moved = src.joints(7.0 + 1.0)
    assert np.abs(moved - rest).max() > 1e-3  # carried 1 s: it moved (metres)
    np.testing.assert_array_equal(moved, src.joints_at(src.time_of(8.0)))


def test_without_hold_the_scene_runs_from_the_devices_start_and_start_at_refuses_a_moved_scene():
    src = source()
    assert src.time_of(2.0) == np.floor(2.0 * src.grid_hz + 1e-9) / src.grid_hz
    src.read(2.0, np.arange(12))
    with pytest.raises(ValueError, match="already moved on"):
        src.start_at(2.5)
    with pytest.raises(ValueError, match="finite"):
        source().start_at(float("nan"))
