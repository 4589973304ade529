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


def test_syncs_read_late_together_are_sampled_a_period_apart_at_their_arrival_not_at_the_read():
    """A gateway reads SYNCs on time (128 Hz) for a while, then three at once, two and one periods
    late (the sheet's process was busy): the chips sample each at its arrival (on the period grid
    from the last SYNC read on time, plus the slack once), say ``time_us`` against it, and the truth of each counter is
    that instant — as real chips on a wire would. Without arrival estimates all three sample the
    read instant."""
    import math

    from protocol.framing import StreamDecoder, encode
    from protocol.messages import ConfigImu, ImuSample, Sync
    from virtual_sheet.gateway import Gateway

    P = 1 / 128
    grid = 290.0  # `ImuSource`'s grid (wave: rounded up to a whole number of steps a period)

    def run(sync_arrival: bool):
        sheet = VirtualSheet("wave", "3x3", seed=2, noise=1.0, sensors="accel+gyro", sync_arrival=sync_arrival)
        gw = Gateway(sheet)
        gw.power_on(0.0)
        gw.commission(0.0, start=False)
        gw.feed(encode(ConfigImu(0, 1, 3, 0, 0)), 0.01)  # broadcast: every chip, 6-axis
        from protocol.messages import Start
        gw.feed(encode(Start(0)), 0.02)
        gw.pop_output(0.03)
        t0, n_on_time = 1.5, 80
        for k in range(n_on_time):
            gw.feed(encode(Sync(counter=k)), t0 + k * P)
            gw.pop_output(t0 + k * P)
        late = t0 + (n_on_time + 2) * P  # SYNCs n, n+1, n+2 all read then
        gw.feed(b"".join(encode(Sync(counter=n_on_time + j)) for j in range(3)), late)
        dec = StreamDecoder()
        recs = [m for m in dec.feed(b"".join(gw.pop_output(late))) if isinstance(m, ImuSample)]
        return sheet, recs, t0, n_on_time, late, sheet.imu_source.grid_hz

    sheet, recs, t0, n, late, grid = run(True)
    assert len(recs) == 3 * 12  # every chip answered each SYNC
    slack = sheet.sync_arrival.slack_s  # a host may send that much late: the arrival keeps it
    on_time = t0 + (n - 1) * P  # the last SYNC read on time: the grid goes on from it
    for j in range(3):
        arrival = min(late, on_time + (j + 1) * P + slack)  # never after the read
        k = math.floor(arrival * grid + 1e-9)
        want_us = round((k / grid - arrival) * 1e6)
        mine = [r for r in recs if r.counter == n + j]
        assert {r.time_us for r in mine} == {want_us}
        assert sheet.truth_time(n + j) == k / grid
        assert all(r.status == 0 for r in mine)  # three distinct conversions: none STALE
    assert sheet.sync_arrival.pulled == 2
    # at the read instead: the three SYNCs share the read instant, one conversion answered thrice
    sheet2, recs2, *_ = run(False)
    k = math.floor(late * grid + 1e-9)
    assert {sheet2.truth_time(n + j) for j in range(3)} == {k / grid}
    by_counter = [sorted((r.node, r.gyro) for r in recs2 if r.counter == n + j) for j in range(3)]
    assert by_counter[0] == by_counter[1] == by_counter[2]
    mine = sorted((r.node, r.gyro) for r in recs if r.counter == n + 2)
    assert mine != sorted((r.node, r.gyro) for r in recs if r.counter == n + 1)  # with arrivals: new ones


def test_a_periodic_scenes_fade_in_is_solved_before_streaming_and_reads_the_same_as_solved_live():
    """The wave fades in over 1 s before it repeats: `precompute` solves those instants too, so a
    stream that starts within the fade-in solves nothing live (the scene is not sampled again), and
    what the chips read there is what a source that solves as it goes reads (the counts exactly)."""
    a, b = _source(), _source()
    ks = a.precompute()
    import math
    period_steps = round(a.scene.period_s * a.grid_hz)  # a whole number of grid steps a period
    assert ks == period_steps + math.ceil(1.0 * a.grid_hz - 1e-9)  # the period and the 1 s fade-in
    calls = []
    real = a.scene.sample
    a.scene.sample = lambda t: calls.append(t) or real(t)
    idx = np.arange(a.imu.n_links)
    for t in np.arange(0.3, 1.6, 1 / 145):  # across the fade-in's end
        ra, rb = a.read(t, idx), b.read(t, idx)
        for x, y in zip(ra, rb):
            assert (x is None and y is None) or np.array_equal(x, y)
        # the same truth: solved in other batches, to the last bits of the compass construction
        np.testing.assert_allclose(a.joints(t), b.joints(t), rtol=0, atol=1e-14)
    assert calls == []
