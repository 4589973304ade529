"""Counter trust in the aggregator: a stray or foreign frame costs at most its own sample;
a driving host accepts only counters it sent; a follower resynchronises after a counter reset or jump.
Simulated clock, exact counts."""

from __future__ import annotations

import pytest

from host.snapshots.aggregator import Aggregator
from tests.host.snapshots.test_aggregator import FakeClock, feed, full_counter, sample, wire

N = 4


def make(trust, **kw):
    clock = FakeClock()
    return Aggregator(N, deadline_s=0.05, trust=trust, queue_size=1000, **kw), clock


def run_counters(agg, clock, counters, *, sync: bool, stray_after=None, stray=None):
    """Per counter: (SYNC ->) all N frames; a stray frame is injected after counter ``stray_after``."""
    for c in counters:
        if sync:
            agg.open_counter(c, clock.t)
        feed(agg, wire(full_counter(N, c)), now=clock.t)
        clock.t += 0.01
        agg.poll(clock.t)
        if c == stray_after:
            feed(agg, wire([stray]), now=clock.t)
    agg.flush(clock.t)
    return agg.drain()


@pytest.mark.parametrize("jump", [1, 1000, 16384, 32767])
def test_drive_mode_a_future_counter_frame_is_stray_and_costs_nothing(jump):
    agg, clock = make("sent")
    snaps = run_counters(agg, clock, range(100, 400), sync=True, stray_after=150,
                         stray=sample(2, (151 + jump) & 0xFFFF))
    assert len(snaps) == 300 and all(s.complete for s in snaps)
    assert agg.stats.stray == 1 and agg.stats.late == 0


def test_without_trust_the_same_stray_frame_loses_snapshots():
    """The broken rule (frames open counters) that trust="sent" replaces: the stray moves the sequence."""
    agg, clock = make("frames")
    snaps = run_counters(agg, clock, range(100, 400), sync=True, stray_after=150, stray=sample(2, 151 + 1000))
    assert sum(s.complete for s in snaps) < 290


def test_drive_mode_frames_never_open_counters():
    agg, clock = make("sent")
    feed(agg, wire(full_counter(N, 7)), now=clock.t)  # no SYNC sent for 7: a foreign frame source
    agg.flush(clock.t)
    assert agg.drain() == [] and agg.stats.stray == N


@pytest.mark.parametrize("sync", [True, False])
def test_follow_mode_resynchronises_after_a_counter_reset(sync):
    agg, clock = make("follow")
    before = run_counters(agg, clock, range(5000, 5100), sync=sync)
    after = run_counters(agg, clock, range(0, 200), sync=sync)  # the gateway restarted its counter
    assert len(before) == 100 and all(s.complete for s in before)
    assert agg.stats.resyncs == 1 and list(agg.resync_events) == [(5099, 2)]
    # the first resync_after - 1 counters of the new sequence are the price, counted as stray
    assert [s.counter for s in after] == list(range(2, 200)) and all(s.complete for s in after)
    assert agg.stats.stray == 2 * N + (0 if sync else 0)


def test_follow_mode_a_single_stray_frame_is_not_a_resync():
    agg, clock = make("follow")
    snaps = run_counters(agg, clock, range(100, 400), sync=True, stray_after=150, stray=sample(2, 151 + 16384))
    assert len(snaps) == 300 and all(s.complete for s in snaps)
    assert agg.stats.stray == 1 and agg.stats.resyncs == 0


def test_invalid_trust_is_refused():
    with pytest.raises(ValueError, match="trust"):
        Aggregator(N, trust="maybe")


def test_follow_mode_a_sync_reset_to_a_recent_counter_is_followed_at_once():
    """The gateway restarts at 0 while the newest counter was 149: its SYNCs are within max_age behind
    (they looked like late frames: ~150 snapshots lost). A SYNC source never goes back: resync."""
    agg, clock = make("follow")
    run_counters(agg, clock, range(0, 150), sync=True)
    after = run_counters(agg, clock, range(0, 100), sync=True)
    assert agg.stats.resyncs == 1 and list(agg.resync_events) == [(149, 2)]
    assert [s.counter for s in after] == list(range(2, 100)) and all(s.complete for s in after)


def test_follow_mode_late_frames_of_a_slow_chip_are_not_a_resync():
    """Frames (not SYNCs) for counters already emitted are late, however many in a row."""
    agg, clock = make("follow")
    run_counters(agg, clock, range(0, 50), sync=True)
    feed(agg, wire([sample(1, c) for c in range(40, 50)]), now=clock.t)
    assert agg.stats.resyncs == 0 and agg.stats.late == 10 and agg.stats.stray == 0


@pytest.mark.parametrize("restart, expected", [(False, [69, 70, 71]), (True, [69, 69, 70, 71])])
def test_follow_mode_a_host_starting_inside_the_sequence_emits_each_counter_once(restart, expected):
    """Two gateways on one SYNC line: SYNC 69 heard on bus 0 just before the host starts streaming;
    bus 1's copy of SYNC 69 and a frame for 69 come after. The gateway's sequence goes on, so a
    following host does not restart it (host/session/core.py): 69 is emitted once, complete. A restart
    there (emit what is open, forget the order) opened 69 a second time — seen live: counters
    [69, 69, 70, ...] in a loaded suite run."""
    agg, clock = make("follow")
    agg.open_counter(69, clock.t)
    feed(agg, wire([sample(k + 1, 69) for k in range(N // 2)]), now=clock.t)
    clock.t += 0.01
    if restart:
        agg.restart(clock.t)
    agg.open_counter(69, clock.t)  # the other port's copy of the SYNC
    feed(agg, wire([sample(k + 1, 69) for k in range(N // 2, N)]), now=clock.t)  # and its frames
    snaps = run_counters(agg, clock, [70, 71], sync=True)
    assert [s.counter for s in snaps] == expected
    assert all(s.complete for s in snaps) == (not restart)
