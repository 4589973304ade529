"""`host.session.watchdog.Watchdog` alone, on a simulated clock: a real aggregator and feed, and the host's
stall-free time passed in by hand, so each of the two rules is seen on its own with exact counts —
missing while the neighbours came (``watchdog_s`` worth of SYNCs, at least 3), and no frame for
``watchdog_s`` of stall-free time. (Through a running host: tests/host/session/test_session.py.)"""

from __future__ import annotations

from types import SimpleNamespace

from host.snapshots.aggregator import Aggregator
from host.snapshots.snapshot import LinkFlag
from host.snapshots.feed import SnapshotFeed
from host.session.report import EventLog
from host.session.watchdog import Watchdog
from protocol.lattice import Lattice
from protocol.messages import Sample

LATTICE = Lattice.parse("2x2")  # 4 links: nodes 1..4


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def setup(watchdog_s=0.5, rate_hz=100.0):
    """What a watchdog asks of its host (its public names), made of the real parts."""
    clock = Clock()
    agg = Aggregator(LATTICE.n_links, deadline_s=0.005, queue_size=1000)
    log = EventLog(clock)
    host = SimpleNamespace(lattice=LATTICE, aggregator=agg, feed=SnapshotFeed(agg, clock=clock, queue_size=1000),
                           report=log.report, rate_hz=rate_hz)
    wd = Watchdog(host, watchdog_s)
    wd.restart(clock.t, 0.0)
    return wd, host, log, clock


def one_counter(host, clock, counter, links):
    """Frames of ``links`` for ``counter``, then past the deadline: the snapshot is emitted."""
    host.feed.ingest([Sample(k + 1, counter, 0, 0, 1024, 0) for k in links])
    clock.t += 0.01
    host.feed.poll()


def test_a_link_missing_while_its_neighbours_came_is_silent_after_watchdog_s_of_syncs():
    wd, host, log, clock = setup(watchdog_s=0.5, rate_hz=100.0)  # 50 snapshots
    for c in range(49):
        one_counter(host, clock, c, [0, 1, 2])
        wd.check(clock.t, service_s=0.0)  # no stall-free time passes: only the first rule can fire
    assert wd.silent_links == [] and log.event_counts["silent"] == 0
    one_counter(host, clock, 49, [0, 1, 2])
    wd.check(clock.t, service_s=0.0)
    assert wd.silent_links == [3] and log.event_counts["silent"] == 1
    assert log.events[-1].link == 3 and log.events[-1].node == 4
    one_counter(host, clock, 50, [0, 1, 2])  # now flagged SILENT, no longer waited for: complete
    snap = host.feed.drain()[-1]
    assert snap.complete and snap.status[3] & LinkFlag.SILENT
    one_counter(host, clock, 51, [0, 1, 2, 3])  # it speaks again
    wd.check(clock.t, service_s=0.0)
    assert wd.silent_links == [] and log.event_counts["recovered"] == 1


def test_at_least_three_snapshots_even_at_a_slow_rate():
    wd, host, log, clock = setup(watchdog_s=0.5, rate_hz=2.0)  # 0.5 s x 2 Hz = 1 SYNC: 3 it is
    for c in range(2):
        one_counter(host, clock, c, [0, 1, 2])
        wd.check(clock.t, service_s=0.0)
    assert wd.silent_links == []
    one_counter(host, clock, 2, [0, 1, 2])
    wd.check(clock.t, service_s=0.0)
    assert wd.silent_links == [3]


def test_a_link_missing_while_most_others_are_missing_too_is_not_blamed():
    wd, host, log, clock = setup()
    for c in range(100):
        one_counter(host, clock, c, [0])  # 1 of 4 came: not "its neighbours came"
        wd.check(clock.t, service_s=0.0)
    assert wd.silent_links == [] and log.event_counts["silent"] == 0


def test_no_frame_for_watchdog_s_of_stall_free_time_is_silent_host_time_alone_is_not():
    wd, host, log, clock = setup(watchdog_s=0.5)
    clock.t = 100.0  # the host stalled for 100 s of wall time: no stall-free time passed
    wd.check(clock.t, service_s=0.0)
    assert wd.silent_links == []
    wd.check(clock.t, service_s=0.5)  # exactly watchdog_s: not yet
    assert wd.silent_links == []
    wd.check(clock.t, service_s=0.51)
    assert wd.silent_links == [0, 1, 2, 3] and log.event_counts["silent"] == 4


def test_a_status_keeps_a_link_alive_and_tick_checks_every_min_50ms_or_a_quarter():
    wd, host, log, clock = setup(watchdog_s=0.1)
    wd.status_seen(2, now=0.2)
    wd.tick(0.2, service_s=0.2)
    assert wd.silent_links == [0, 1, 3] and wd.next_check == 0.2 + 0.025
    wd.status_seen(0, now=0.21)
    wd.tick(0.21, service_s=0.21)  # not due: nothing looked at
    assert wd.silent_links == [0, 1, 3]
    wd.tick(0.225, service_s=0.225)
    assert wd.silent_links == [1, 3] and log.event_counts["recovered"] == 1
