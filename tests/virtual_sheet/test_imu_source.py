"""`imu_source.ImuSource`: what 6/9-axis chips read at a SYNC on a moving sheet (sans-I/O, time as
an argument)."""

from __future__ import annotations

import numpy as np

from virtual_sheet.sheet import VirtualSheet


def _source(shape="wave", sensors="accel+gyro+mag", seed=3):
    return VirtualSheet(shape, "4x4", seed=seed, noise=1.0, sensors=sensors).imu_source


def test_counts_at_each_chips_own_range_are_the_models_counts_rescaled_by_the_datasheet_ratio():
    """The model reads at ±1000 °/s and ±4 gauss; chips configured at other ranges (per chip) get
    the same reading in their own counts: ±2000 °/s halves a count (32768/2000 vs 32768/1000
    counts per °/s), ±8 gauss halves it, ±16 gauss quarters it; rounded to the nearest count."""
    a, b = _source(), _source()
    n = a.imu.n_links
    idx = np.arange(n)
    g_code = np.where(idx % 2 == 0, 3, 4)  # every other chip at ±2000 °/s
    m_code = np.where(idx % 3 == 0, 0, np.where(idx % 3 == 1, 1, 3))  # ±4, ±8, ±16 gauss
    t = 0.5
    _a, _s, g_model, m_model, t_model = a.read(t, idx)
    _a2, _s2, g_chip, m_chip, t_chip = b.read(t, idx, g_code, m_code)
    g_factor = np.where(g_code == 3, 1.0, 0.5)[:, None]
    m_factor = np.choose(m_code, [1.0, 0.5, 0.0, 0.25])[:, None]
    assert np.array_equal(g_chip, np.rint(g_model * g_factor).astype(np.int64))
    assert np.array_equal(m_chip, np.rint(m_model * m_factor).astype(np.int64))
    assert np.array_equal(t_chip, t_model)
    # every chip at the model's own ranges: the counts themselves
    c = _source()
    _a3, _s3, g_same, m_same, _t3 = c.read(t, idx, np.full(n, 3), np.zeros(n, dtype=int))
    assert np.array_equal(g_same, g_model) and np.array_equal(m_same, m_model)
    assert np.abs(g_model).max() > 10 and np.abs(m_model).max() > 10  # a reading that rescaling changes
