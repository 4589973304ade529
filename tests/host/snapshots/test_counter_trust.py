"""`host.snapshots.counter_trust.CounterTrust` alone: the verdict on a counter not yet open, given the newest
opened and the last emitted, for each rule; exact counts of what a follower takes for a new
sequence. (Through the aggregator, with frames: tests/host/snapshots/test_aggregator_trust.py.)"""

from __future__ import annotations

import pytest

from host.snapshots.counter_trust import LATE, OPEN, RESYNC, STRAY, CounterTrust, serial_diff


def test_serial_arithmetic_wraps_at_2_16():
    assert serial_diff(0, 0xFFFF) == 1 and serial_diff(0xFFFF, 0) == -1
    assert serial_diff(0x8000, 0) == -0x8000 and serial_diff(0x7FFF, 0) == 0x7FFF


def test_frames_rule_opens_anything():
    t = CounterTrust("frames")
    assert {t.verdict(c, 100, 99, from_frame=f) for c in (0, 50, 101, 40000) for f in (True, False)} == {OPEN}


def test_sent_rule_only_syncs_open_and_a_frame_is_late_or_stray():
    t = CounterTrust("sent", max_age=256)
    assert t.verdict(500, 100, 99, from_frame=False) == OPEN  # a SYNC the host sends
    assert t.verdict(101, 100, 99, from_frame=True) == STRAY  # newer than any sent: never sent
    assert t.verdict(100, 100, 99, from_frame=True) == LATE  # sent, and gone
    assert t.verdict(100 - 256, 100, 99, from_frame=True) == LATE
    assert t.verdict(100 - 257, 100, 99, from_frame=True) == STRAY  # too old to be one of ours
    # before any SYNC of the sequence: a frame newer than the last emitted was never sent
    assert t.verdict(7, None, None, from_frame=True) == STRAY
    assert t.verdict(7, None, 5, from_frame=True) == STRAY
    assert t.verdict(5, None, 5, from_frame=True) == LATE


def test_follow_rule_opens_within_the_window_and_a_sync_only_forwards():
    t = CounterTrust("follow", max_jump=64, max_age=256)
    assert t.verdict(164, 100, 99, from_frame=True) == OPEN
    assert t.verdict(165, 100, 99, from_frame=True) == STRAY
    assert t.verdict(100 - 256, 100, 99, from_frame=True) == OPEN  # an old frame: late, not stray
    assert t.verdict(100 - 65, 100, 99, from_frame=False) == STRAY  # a SYNC source never goes back
    assert t.verdict(101, 100, 99, from_frame=False) == OPEN
    assert list(t.resync_events) == []


@pytest.mark.parametrize("resync_after", [1, 3, 5])
def test_follow_rule_resyncs_after_exactly_resync_after_counters_of_a_new_sequence(resync_after):
    t = CounterTrust("follow", resync_after=resync_after)
    newest = 5000
    verdicts = [t.verdict(c, newest, newest - 1, from_frame=False) for c in range(2, 2 + resync_after)]
    assert verdicts == [STRAY] * (resync_after - 1) + [RESYNC]
    assert list(t.resync_events) == [(5000, 1 + resync_after)]


def test_follow_rule_a_broken_run_starts_counting_again():
    t = CounterTrust("follow", resync_after=3)
    v = [t.verdict(c, 5000, 4999, from_frame=False) for c in (2, 3, 9, 10, 11)]
    assert v == [STRAY, STRAY, STRAY, STRAY, RESYNC]  # 3 -> 9 is no continuation: 9, 10, 11 are
    assert list(t.resync_events) == [(5000, 11)]


def test_follow_rule_a_counter_back_in_sequence_forgets_the_candidate():
    t = CounterTrust("follow", resync_after=3)
    assert t.verdict(2, 5000, 4999, from_frame=False) == STRAY
    assert t.verdict(3, 5000, 4999, from_frame=False) == STRAY
    assert t.verdict(5001, 5000, 4999, from_frame=False) == OPEN  # the old sequence goes on
    assert t.verdict(4, 5001, 5000, from_frame=False) == STRAY  # a run of one again, not three
    assert list(t.resync_events) == []


@pytest.mark.parametrize("kw, match", [
    (dict(trust="any"), "trust"), (dict(max_jump=0), "max_jump"), (dict(max_jump=1 << 15), "max_jump"),
    (dict(resync_after=0), "resync_after"),
])
def test_invalid_settings_are_refused_by_name(kw, match):
    with pytest.raises(ValueError, match=match):
        CounterTrust(**kw)


def test_follow_rule_a_sync_copy_from_a_lagging_port_is_late_and_never_a_new_sequence():
    """Five gateways on one SYNC line: every SYNC comes once per port, a port read later brings
    copies 0..max_jump behind the newest. They are late, and a run of them never resyncs (it did:
    three consecutive copies were taken for a restarted source)."""
    t = CounterTrust("follow", max_jump=64, resync_after=3)
    newest = 5000
    for c in range(newest - 64, newest + 1):
        assert t.verdict(c, newest, newest - 1, from_frame=False) == LATE, c
    assert list(t.resync_events) == []
    # a source restarted far back is still followed after resync_after SYNCs
    assert [t.verdict(c, newest, newest - 1, from_frame=False) for c in (0, 1, 2)] == [STRAY, STRAY, RESYNC]
    # and copies behind the newest leave a candidate run alone
    t2 = CounterTrust("follow", max_jump=64, resync_after=3)
    assert t2.verdict(0, newest, newest - 1, from_frame=False) == STRAY
    assert t2.verdict(newest - 2, newest, newest - 1, from_frame=False) == LATE
    assert t2.verdict(1, newest, newest - 1, from_frame=False) == STRAY
    assert t2.verdict(2, newest, newest - 1, from_frame=False) == RESYNC


def test_a_ports_own_sync_run_far_behind_the_newest_is_a_copy_and_a_restart_is_not():
    """Five ports on one SYNC line, one read 75 SYNCs behind the others (more than max_jump): its
    SYNCs continue its own sequence, so they are copies (not handed on); before, a run of them was
    taken for a restarted source and the host resynced back and forth (93 resyncs in 16 s). A
    source that restarts breaks every port's own sequence: its SYNCs go on, and the counter trust
    follows them after resync_after."""
    from host.snapshots.counter_trust import SyncCopies
    s = SyncCopies(max_jump=64)
    t = CounterTrust("follow", max_jump=64, resync_after=3)
    newest = None
    handed = []

    def hear(port, c):
        nonlocal newest
        if s.fresh(port, c, newest):
            handed.append((port, c))
            v = t.verdict(c, newest, None, from_frame=False)
            if v == RESYNC or (v == OPEN and (newest is None or serial_diff(c, newest) > 0)):
                newest = c
            return v

    for c in range(1000, 1200):  # ports 0-3 on time, port 4 75 behind, interleaved as read
        for port in range(4):
            hear(port, c)
        if c - 75 >= 1000:
            hear(4, c - 75)
    assert handed == [(0, c) for c in range(1000, 1200)]  # ports 1-3 and the lagging 4: copies
    assert s.copies == 3 * 200 + (1124 - 1000 + 1)
    assert list(t.resync_events) == [] and newest == 1199
    # without SyncCopies the same lagging run resyncs the sheet back (what the host did)
    t_old = CounterTrust("follow", max_jump=64, resync_after=3)
    assert [t_old.verdict(c, 1199, 1198, from_frame=False) for c in (1125, 1126, 1127)] == [STRAY, STRAY, RESYNC]
    # the source restarts at 0: port 0's run goes back, is handed on and followed after 3 SYNCs
    assert [hear(0, c) for c in (0, 1, 2)] == [STRAY, STRAY, RESYNC] and newest == 2
    # the other ports' copies of the new run: each port's own sequence broke, so handed on (late)
    assert [hear(p, 0) for p in (1, 2, 3, 4)] == [LATE] * 4
