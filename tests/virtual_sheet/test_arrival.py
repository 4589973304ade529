"""`arrival.SyncArrival`: when a SYNC reached the chips, from when a virtual sheet read it (exact
counts on a simulated clock)."""

from __future__ import annotations

import pytest

from virtual_sheet.arrival import SyncArrival

P = 1 / 128  # a SYNC period exact in binary: sums of it are exact


def _stream(arr: SyncArrival, reads, first_counter=0):
    return [arr.arrival((first_counter + i) & 0xFFFF, r) for i, r in enumerate(reads)]


def test_reads_on_time_arrive_when_read_and_late_reads_one_period_after_the_previous_arrival():
    arr = SyncArrival(slack_s=0.0, window=8)
    reads = [k * P for k in range(6)] + [6 * P + 0.020, 7 * P + 0.0201, 8 * P, 9 * P]
    got = _stream(arr, reads)
    assert got[:6] == reads[:6]  # on time: when read (the period known from the 5th)
    # 20 ms late twice: one period after the previous arrival; the late reads' spacings do not
    # move the period (the median spacing)
    assert got[6] == 6 * P and got[7] == 7 * P
    assert got[8:] == [8 * P, 9 * P]
    assert arr.pulled == 2 and arr.pulled_s == pytest.approx(0.0401, abs=1e-12)


def test_several_syncs_in_one_read_arrive_a_period_apart_and_none_before_the_window_is_full():
    arr = SyncArrival(slack_s=0.0, window=8)
    assert _stream(arr, [0.0, 0.0, 0.0]) == [0.0, 0.0, 0.0]  # before the period is known: when read
    arr = SyncArrival(slack_s=0.0, window=8)
    reads = [0.0, P, 2 * P, 3 * P, 4 * P, 7 * P, 7 * P, 7 * P]  # the last three read together
    assert _stream(arr, reads) == [k * P for k in range(8)]
    assert arr.pulled == 2


def test_slack_lets_a_host_that_sent_a_little_late_keep_its_time():
    arr = SyncArrival(slack_s=0.001, window=8)
    reads = [k * P for k in range(6)] + [6 * P + 0.0008, 7 * P + 0.0008]
    assert _stream(arr, reads) == reads  # within the slack of one period after the previous: as read
    assert arr.pulled == 0
    arr2 = SyncArrival(slack_s=0.001, window=8)
    got = _stream(arr2, [k * P for k in range(6)] + [6 * P + 0.003])
    assert got[-1] == 5 * P + P + 0.001  # 3 ms late: one period and the slack after the previous


def test_the_same_counter_on_a_second_port_arrives_as_on_the_first_and_a_gap_starts_afresh():
    arr = SyncArrival(slack_s=0.0, window=8)
    got = _stream(arr, [k * P for k in range(5)] + [5 * P + 0.01])
    assert got[-1] == 5 * P
    assert arr.arrival(5, 5 * P + 0.012) == 5 * P  # counter 5 again (the second gateway): its arrival
    assert arr.arrival(11, 5 * P + 0.02) == 5 * P + 0.02  # a gap in the counters: as read
    assert arr.arrival(12, 5 * P + 0.03) == 5 * P + 0.03  # the window refills: as read
    assert arr.period_s is None
    for c in range(13, 16):
        arr.arrival(c, 5 * P + 0.03 + (c - 12) * P)
    assert arr.period_s == P


def test_counters_wrap_and_a_stream_restarted_after_a_pause_arrives_when_read():
    arr = SyncArrival(slack_s=0.0, window=8, max_gap_s=0.5)
    got = _stream(arr, [k * P for k in range(5)] + [5 * P + 0.01], first_counter=0xFFFC)  # ... 0xFFFF, 0, 1
    assert got[-1] == 5 * P
    assert arr.arrival(2, 10.0) == 10.0  # 10 s later: a new stream, not a late read


def test_invalid_parameters_are_refused():
    for kw in ({"slack_s": -1e-3}, {"window": 1}, {"max_gap_s": 0.0}):
        with pytest.raises(ValueError):
            SyncArrival(**kw)


def test_a_host_that_skipped_a_slot_is_followed_again_after_steady_syncs_one_period_apart():
    """The host skipped slot 6 (its thread woke too late) and sends 7, 8, ... on its grid: SYNC 7 is
    read two periods after 5 and looks late; it and the next two are put one period (and the
    slack) after their predecessors, closing by the slack each; the third read one period apart
    while still put early is taken as read again, and so are the rest."""
    arr = SyncArrival(slack_s=0.0, window=8, steady=3)
    reads = [k * P for k in range(6)] + [k * P for k in range(7, 12)]  # no SYNC in slot 6
    got = _stream(arr, reads)
    assert got[:6] == reads[:6]
    assert got[6:9] == [6 * P, 7 * P, 8 * P]  # counters 6-8 (slots 7-9): one slot early
    assert got[9:] == [10 * P, 11 * P]  # counter 9 (slot 10): the third steady one, as read
    assert arr.rephased == 1 and arr.pulled == 3


def test_a_stalled_reader_reading_its_backlog_at_once_is_not_taken_for_a_host_that_changed_phase():
    arr = SyncArrival(slack_s=0.0, window=8, steady=2)
    reads = [k * P for k in range(6)] + [9 * P] * 4 + [10 * P, 11 * P]  # 6-9 read together at slot 9
    got = _stream(arr, reads)
    assert got == [k * P for k in range(12)]
    assert arr.rephased == 0 and arr.pulled == 3


def test_a_reader_that_stays_behind_does_not_let_the_arrivals_creep_by_the_slack():
    """40 SYNCs read 18–22 ms late (a loaded machine's reader, behind for 0.3 s): each arrives on
    the host's grid plus the slack once — not the slack once a SYNC after the previous arrival, which
    put the last of them 18.5 ms late (time stretched by 6 %, which a gyroscope scale fit takes for
    the gyroscopes'); then on time again."""
    slack = 0.0005
    arr = SyncArrival(slack_s=slack, window=64)
    lag = [0.020 + (0.002 if k % 2 else -0.002) for k in range(40)]
    reads = [k * P for k in range(10)] + [(10 + k) * P + lag[k] for k in range(40)] + [k * P for k in range(50, 53)]
    got = _stream(arr, reads)
    assert got[:10] == reads[:10] and got[50:] == reads[50:]
    off = [got[k] - k * P for k in range(10, 50)]
    assert max(off) == pytest.approx(slack, abs=1e-12) and min(off) == pytest.approx(slack, abs=1e-12)
    assert arr.pulled == 40 and arr.rephased == 0


def test_two_gateways_reading_a_backlog_each_whole_give_every_copy_its_first_arrival():
    """A device serves each port's read whole: after a 3-period stall the first gateway reads SYNCs
    6, 7, 8 together, then the second gateway reads its copies of 6, 7, 8. Every copy arrives when
    its first read did (on the host's grid), and the model goes on as if the copies were not there:
    SYNC 9, read 1 ms late, is still put on the grid (the period was kept). Taken as new SYNCs, the
    copies came two counters back: they arrived at the late read (3 periods late) and the period
    was thrown away, so SYNC 9 arrived at its late read too."""
    arr = SyncArrival(slack_s=0.0, window=8)
    on_time = [(arr.arrival(k, k * P), arr.arrival(k, k * P + 0.0002)) for k in range(6)]  # port 0, port 1
    assert on_time == [(k * P, k * P) for k in range(6)]
    backlog = 8 * P + 0.001  # the stall ends a millisecond after slot 8: each port's read whole
    gw0 = [arr.arrival(c, backlog) for c in (6, 7, 8)]
    gw1 = [arr.arrival(c, backlog + 0.0002) for c in (6, 7, 8)]
    assert gw0 == gw1 == [6 * P, 7 * P, 8 * P]
    assert arr.copies == 6 + 3
    assert arr.arrival(9, 9 * P + 0.001) == 9 * P
    assert arr.period_s == P
