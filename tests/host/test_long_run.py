"""Runs of days on a simulated clock: the 16-bit SYNC counter wraps every 65536 SYNCs
(452 s at 145 Hz) and every history, queue and log a host, a recorder or the virtual sheet keeps
stays at its bound, what is cut counted. Exact counts, no wall-clock rates."""

from __future__ import annotations

import numpy as np
import pytest

from host.snapshots.aggregator import Aggregator
from host.snapshots.feed import SnapshotFeed
from host.record.recording import Recorder, read
from host.session.core import EVENTS_KEPT, Host, Layout
from protocol.lattice import Lattice
from protocol.messages import Sample, SampleBatch
from tests.host.test_back2back import Rig
from virtual_sheet.chip import ChipModel
from virtual_sheet.sheet import SYNC_TIMES_KEPT, VirtualSheet

RATE_HZ = 145.0


class SimClock:
    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def test_the_feed_over_a_counter_wrap_emits_every_counter_once_in_order_and_stays_bounded():
    """65536 + 2000 SYNCs at 145 Hz (7.8 simulated minutes), nobody consuming the queue: every
    counter is emitted once, complete, in order across the wrap; the queue holds its 64 and
    counts the rest as dropped; nothing else grows. (The soak benchmark crosses two wraps live.)"""
    n_links, n_sync = 4, 65536 + 2000
    clock = SimClock()
    agg = Aggregator(n_links, {k + 1: k for k in range(n_links)}, deadline_s=0.02)
    feed = SnapshotFeed(agg, clock=clock, queue_size=64)
    emitted: list[tuple[int, float, bool]] = []
    feed.add_listener(lambda s: emitted.append((s.counter, s.timestamp, s.complete)) if len(emitted) < 3 else None)
    seen = {"n": 0, "order_ok": True, "last": None, "last_t": -1.0}

    def check(s):
        seen["n"] += 1
        if seen["last"] is not None and ((s.counter - seen["last"]) % 65536 != 1 or s.timestamp <= seen["last_t"]
                                         or not s.complete):
            seen["order_ok"] = False
        seen["last"], seen["last_t"] = s.counter, s.timestamp
    feed.add_listener(check)
    # each SYNC's answers as the decoder hands them over, one batch of the links' SAMPLEs (one
    # `Sample` event per chip took 3x longer for the same aggregator path past the conversion)
    nodes = np.arange(1, n_links + 1, dtype=np.uint16)
    counts = np.tile(np.array([0, 0, 1024], np.int16), (n_links, 1))
    status = np.zeros(n_links, np.uint8)
    max_open = 0
    for k in range(n_sync):
        c = k & 0xFFFF
        clock.t = 1000.0 + k / RATE_HZ
        feed.open_counter(c, clock.t, restart=k == 0)
        clock.t += 0.002
        feed.ingest([SampleBatch(nodes, np.full(n_links, c, np.uint16), counts, status)], 0, clock.t)
        max_open = max(max_open, agg.n_open)
    clock.t += 1.0
    feed.poll(clock.t)
    st = agg.stats
    assert seen["n"] == n_sync and seen["order_ok"]
    assert st.emitted == st.complete == n_sync and st.incomplete == 0
    assert st.resyncs == 0 and st.late == 0 and st.stray == 0 and len(agg.resync_events) == 0
    assert feed.pending == 64 and st.dropped == n_sync - 64  # the queue at its bound, the rest counted
    assert max_open <= 1  # each counter complete when its frames arrive
    assert [c for c, _, _ in emitted] == [0, 1, 2]


def test_a_host_crosses_the_counter_wrap_on_a_simulated_clock_and_its_recording_replays(tmp_path):
    """A real Host (virtual chips in memory) starting 40 SYNCs before the wrap: every snapshot on
    both sides complete, consecutive mod 65536, timestamps rising; recorded and replayed identical
    (the replay matches by (counter, timestamp), as a counter repeats after a wrap)."""
    from host.record.replay import Replay

    rig = Rig("memory", chip_class=ChipModel, lattice="3x3", rate_hz=RATE_HZ)
    try:
        host = Host(rig.host.transports, rig.sheet.lattice, layout=Layout(dict(rig.sheet.layout)),
                    clock=rig.clock, driver=rig.host._driver, timeout_s=0.15, deadline_s=0.02,
                    rate_hz=RATE_HZ, start_counter=0xFFFF - 40)
        path = tmp_path / "wrap.mcap"
        rec = Recorder(path, rig.sheet.lattice, 0.01)
        rec.tap(host.transports, host.feed)
        rec.tap_sync(host.feed)
        host.feed.add_listener(rec.snapshot)
        assert host.bring_up(0.2)["started"] == rig.sheet.n_links
        rec.add_host_facts(host)
        snaps = list(host.snapshots(count=100))
        host.stop()
        rec.close()
    finally:
        rig.close()
    counters = [s.counter for s in snaps]
    assert len(snaps) == 100 and all(s.complete for s in snaps)
    assert 0xFFFF in counters and 0 in counters and counters.index(0) == counters.index(0xFFFF) + 1
    assert all((b - a) % 65536 == 1 for a, b in zip(counters, counters[1:]))
    assert all(b.timestamp > a.timestamp for a, b in zip(snaps, snaps[1:]))
    back = read(path)
    assert back.counter.tolist()[:100] == counters
    replayed = list(Replay(path).snapshots())
    by_key = {(int(s.counter), float(s.timestamp)): s for s in replayed}
    for k in range(100):
        r = by_key[(int(back.counter[k]), float(back.timestamp[k]))]
        np.testing.assert_array_equal(r.readings.astype(np.float32), back.readings[k])


def test_the_virtual_sheet_keeps_the_newest_sync_times_over_three_wraps():
    sheet = VirtualSheet("flat", "3x3", seed=1)
    n = 3 * 65536 + 500
    for k in range(n):
        sheet.record_sync(k, 10.0 + k / RATE_HZ)
    assert len(sheet.sync_times) == SYNC_TIMES_KEPT and sheet.sync_times_cut == n - SYNC_TIMES_KEPT
    newest = (n - 1) & 0xFFFF
    assert sheet.sync_times[newest] == 10.0 + (n - 1) / RATE_HZ  # the counter's newest SYNC, after 3 wraps
    with pytest.raises(KeyError):
        sheet.truth_time((n - 1 - SYNC_TIMES_KEPT) & 0xFFFF)  # cut: older than the bound


def test_host_events_and_receive_errors_stay_bounded_and_counted():
    """A flood of incidents over a long run: the host keeps the newest EVENTS_KEPT, counts every
    one by kind and counts what it cut."""
    rig = Rig("memory", chip_class=ChipModel, lattice="3x3")
    try:
        host = rig.host
        n = 3 * EVENTS_KEPT + 123
        for k in range(n):
            host.report("info", f"event {k}", quiet=True)
        assert len(host.events) <= EVENTS_KEPT and host.events_cut + len(host.events) == n
        assert host.events[-1].detail == f"event {n - 1}" and host.event_counts["info"] == n
        assert host.summary()["events_cut"] == host.events_cut
    finally:
        rig.close()


def test_a_recorder_over_a_long_split_run_keeps_only_counts_and_file_names(tmp_path):
    """Hours of snapshots and raw chunks (simulated, few links): the recorder's own state is its
    per-topic counts and the list of its files; each file readable."""
    from host.snapshots.snapshot import LatticeSnapshot
    lat = Lattice(2, 2)
    n = lat.n_links
    with Recorder(tmp_path / "long.mcap", lat, 0.01, split_size=20_000) as rec:
        for k in range(30_000):
            c = np.full((n, 3), k % 100, np.int16)
            rec.snapshot(LatticeSnapshot(k & 0xFFFF, k / RATE_HZ, 1.7e9 + k / RATE_HZ, c.astype(float),
                                         np.ones(n, bool), np.zeros(n, np.uint8), True, 0.003, counts=c))
            rec.sync(k & 0xFFFF, k / RATE_HZ)
            if k % 1000 == 999:
                rec.flush()
    assert set(rec.counts) == {"/capsheet/snapshot", "/capsheet/sync"}
    assert rec.counts["/capsheet/snapshot"] == 30_000 and len(rec.paths) >= 3
    whole = read(tmp_path / "long.mcap", raw=False)
    assert len(whole) == 30_000 and np.all(np.diff(whole.counter.astype(int)) % 65536 == 1)


def _stalled_host_run(hold: bool) -> tuple:
    """4 links at 145 Hz, deadline 20 ms. SYNCs 0..29 on time; the host process then sleeps 120 ms
    (SYNCs 30..46 are sent late, at its wake-up: a SyncSchedule catches up) while the chips answer
    SYNC 30 and 31 into the port. At wake-up the SYNC thread polls *before* the receive thread reads
    the port. Returns (emitted complete, incomplete, late frames, input holds)."""
    period, dl = 1 / RATE_HZ, 0.02
    agg = Aggregator(4, {k + 1: k for k in range(4)}, deadline_s=dl, trust="sent", hold_for_input=hold)

    def frames(c):
        return [Sample(node, c, 0, 0, 1024, 0) for node in range(1, 5)]
    t = 0.0
    for c in range(30):
        t = c * period
        agg.open_counter(c, t)
        agg.ingest(frames(c), 0, now=t + 0.001)
    # the stall: SYNC 30 and 31 went out, their answers wait in the port
    agg.open_counter(30, 30 * period)
    agg.open_counter(31, 31 * period)
    wake = 31 * period + 0.120
    agg.poll(wake)  # the SYNC thread, first to get the interpreter
    agg.ingest(frames(30) + frames(31), 0, now=wake + 0.0005)  # the receive thread reads the port
    for c in range(32, 40):  # back to normal
        t = wake + (c - 31) * period
        agg.open_counter(c, t)
        agg.ingest(frames(c), 0, now=t + 0.001)
    agg.input_idle(0, t + 0.05)  # the chips stop; the reader finds the port empty
    agg.poll(t + 0.05)
    st = agg.stats
    return st.complete, st.incomplete, st.late, st.input_holds


def test_a_host_that_slept_reads_the_frames_waiting_for_it_before_it_gives_their_counters_up():
    """The deadline counts from when frames could have been read (host.aggregator, "Input
    watermark"): without it, a 120 ms stall of the whole host loses the two counters whose frames
    sat in the port (8 late frames, 2 incomplete snapshots); with it, all 40 complete."""
    assert _stalled_host_run(hold=False) == (38, 2, 8, 0)
    assert _stalled_host_run(hold=True) == (40, 0, 0, 2)  # counters 30 and 31 held, then complete


def test_holding_for_input_gives_a_counter_up_once_the_bus_is_idle_or_after_the_hold():
    """A chip that never answers: its counter is emitted incomplete at the deadline once the bus
    was found idle, or once later counters' frames were read; a bus that says nothing at all (its
    reader stopped) holds a counter at most INPUT_HOLD_S past the deadline."""
    from host.snapshots.aggregator import INPUT_HOLD_S
    dl = 0.02
    # one bus: link 3 silent; the frames of later counters move the watermark
    agg = Aggregator(4, {k + 1: k for k in range(4)}, deadline_s=dl, trust="sent", hold_for_input=True)
    agg.open_counter(0, 0.0)
    agg.ingest([Sample(n, 0, 0, 0, 1024, 0) for n in (1, 2, 3)], 0, now=0.001)
    agg.poll(0.03)
    assert agg.stats.emitted == 0  # past the deadline, but nothing read past it yet
    agg.open_counter(5, 0.025)
    agg.ingest([Sample(n, 5, 0, 0, 1024, 0) for n in (1, 2, 3)], 0, now=0.031)
    assert (agg.stats.emitted, agg.stats.incomplete) == (1, 0 + 1)  # counter 0, read past: given up
    # two buses: bus 1 idle (found empty) releases it; bus 1 silent (reader gone) holds it
    for idle, expect_at in ((True, 0.021), (False, dl + INPUT_HOLD_S)):
        agg = Aggregator(4, {k + 1: k for k in range(4)}, deadline_s=dl, trust="sent", n_buses=2,
                         hold_for_input=True)
        agg.open_counter(0, 0.0)
        agg.ingest([Sample(n, 0, 0, 0, 1024, 0) for n in (1, 2)], 0, now=0.001)
        agg.input_idle(0, 0.021)
        if idle:
            agg.input_idle(1, 0.021)
        t = 0.021
        while agg.stats.emitted == 0 and t < 1.0:
            agg.poll(t)
            t = round(t + 0.001, 6)
        assert agg.stats.emitted == 1 and abs((t - 0.001 if not idle else 0.021) - expect_at) < 1.5e-3


def test_the_estimators_structure_cache_keeps_the_newest_masks_only_over_a_long_run():
    """A live host estimates incomplete snapshots now and then, each missing another link: after
    N_MASKS different masks the cache holds the structure of all links valid and MASKED_KEPT masked
    ones (~1.1 MB apiece at 14x14; one cache of 16 for all kept 16 one-offs, a creep of megabytes
    in the soak run); a mask that repeats (a chip that stays missing) is reused, not rebuilt.
    N_MASKS is 100x MASKED_KEPT: the bound is the cache's size, met after MASKED_KEPT + 1 masks
    (2000 masks checked the same at 10x the time)."""
    from host.analysis.estimator import structure as S
    S.cached_structure.cache_clear()
    rows = cols = 4
    n = Lattice(rows, cols).n_links
    full = S.structure_of(rows, cols, None)
    bits = 1 << np.arange(n - 1)
    n_masks = 100 * S.MASKED_KEPT
    assert n_masks < 2 ** (n - 1)
    for k in range(1, n_masks + 1):  # different masks: link j+1 missing where bit j of k is set
        S.structure_of(rows, cols, np.r_[True, (k & bits) == 0])
    info = S.cached_structure.cache_info()
    assert (info.misses, info.currsize) == (n_masks, S.MASKED_KEPT)
    assert S.structure_of(rows, cols, None) is full  # not pushed out by the masks
    dead = np.ones(n, bool)
    dead[5] = False
    first = S.structure_of(rows, cols, dead)
    assert all(S.structure_of(rows, cols, dead) is first for _ in range(100))
    assert S.cached_structure.cache_info().currsize == S.MASKED_KEPT
