"""`host.snapshots.feed.SnapshotFeed`: the sans-I/O aggregator for threads, and the one place snapshots are read
from. On a simulated clock, exact counts: the correction is applied once, before any listener or
consumer sees a snapshot; listeners see every snapshot in emission order; the queue drops the oldest
(counted); inputs are observed at the ``now`` they are applied with. And a Host: every consumer —
`get`, `latest`, `drain`, ``on_snapshot``, the health check — gets the corrected snapshot."""

from __future__ import annotations

import numpy as np
import pytest

from host.snapshots.aggregator import Aggregator
from host.snapshots.feed import SnapshotFeed
from protocol import SampleBatch
from protocol.constants import G0


class Clock:
    def __init__(self) -> None:
        self.t = 10.0

    def __call__(self) -> float:
        return self.t


def batch(counter: int, nodes=(1, 2, 3), z=1024) -> SampleBatch:
    n = len(nodes)
    counts = np.zeros((n, 3), dtype=np.int16)
    counts[:, 2] = z
    return SampleBatch(np.asarray(nodes, dtype=np.uint16), np.full(n, counter, dtype=np.uint16), counts,
                       np.zeros(n, dtype=np.uint8))


def test_the_correction_is_applied_once_before_anyone_sees_a_snapshot():
    clock = Clock()
    feed = SnapshotFeed(Aggregator(3, deadline_s=0.05), clock=clock, queue_size=100)
    calls = []

    def correct(r):
        calls.append(r.copy())
        return 2.0 * r + 1.0
    feed.set_correction(correct)
    heard = []
    feed.add_listener(heard.append)
    for c in range(5):
        feed.open_counter(c)
        clock.t += 0.001
        feed.ingest([batch(c, nodes=(1, 2, 3) if c != 2 else (1, 2))])
        clock.t += 0.01
    clock.t += 1.0
    feed.poll()
    got = feed.drain()
    assert [s.counter for s in got] == [s.counter for s in heard] == [0, 1, 2, 3, 4]
    assert all(a is b for a, b in zip(got, heard))  # the very snapshot: corrected once, for all
    assert len(calls) == 5  # once per snapshot
    for s, raw in zip(got, calls):
        np.testing.assert_array_equal(s.readings, 2.0 * raw + 1.0)
        assert not s.readings.flags.writeable
    assert np.isnan(got[2].readings[2]).all() and not got[2].valid[2]  # a missing link stays missing
    np.testing.assert_allclose(got[0].readings[:, 2], 2.0 * G0 + 1.0)


def test_listeners_and_the_queue_see_every_snapshot_in_order_and_the_slow_consumer_loses_the_oldest():
    clock = Clock()
    agg = Aggregator(3, deadline_s=0.05)
    feed = SnapshotFeed(agg, clock=clock, queue_size=4)
    heard = []
    feed.add_listener(lambda s: heard.append(s.counter))
    for c in range(10):
        feed.open_counter(c)
        feed.ingest([batch(c)])
    assert heard == list(range(10))  # listeners miss nothing
    assert [s.counter for s in feed.drain()] == [6, 7, 8, 9] and agg.stats.dropped == 6
    for c in range(10, 13):
        feed.open_counter(c)
        feed.ingest([batch(c)])
    snap = feed.latest(0.0)
    assert snap.counter == 12 and agg.stats.dropped == 8 and feed.pending == 0


def test_inputs_are_observed_at_the_now_they_are_applied_with():
    clock = Clock()
    feed = SnapshotFeed(Aggregator(3, deadline_s=0.05, n_buses=2), clock=clock, wall_clock=lambda: clock.t + 1000.0)
    seen = []
    feed.add_open_listener(lambda counter, now: seen.append(("open", counter, now)))
    feed.add_ingest_listener(lambda bus, now: seen.append(("ingest", bus, now)))
    feed.add_listener(lambda s: seen.append(("snapshot", s.counter, s.timestamp)))
    feed.open_counter(7)
    clock.t = 10.004
    feed.ingest([batch(7)], bus=1)
    assert seen == [("open", 7, 10.0), ("ingest", 1, 10.004), ("snapshot", 7, 10.0)]
    [snap] = feed.drain()
    assert snap.latency_s == pytest.approx(0.004) and snap.wall_time == pytest.approx(1010.0)


def test_the_aggregator_of_a_feed_has_no_listener_of_its_own():
    with pytest.raises(ValueError, match="add_listener"):
        SnapshotFeed(Aggregator(3, on_snapshot=print))
    with pytest.raises(ValueError, match="queue_size"):
        SnapshotFeed(Aggregator(3), queue_size=0)


def test_every_consumer_of_a_host_gets_the_calibrated_snapshot():
    """A host on a simulated clock (memory link, manual mode) with a calibration: what `get`,
    `latest`, `drain` and ``on_snapshot`` hand over, and what the health check is fed, is the
    aggregator's snapshot corrected exactly once, as `Calibration.apply` says."""
    from host.analysis.calibration import Calibration
    from host.snapshots.health import HealthChecker
    from host.session.core import Host, Layout
    from host.transport.ports import MemoryTransport
    from virtual_sheet.devices import MemoryDevice
    from virtual_sheet.sheet import VirtualSheet

    class Fed(HealthChecker):
        """The health check, keeping what it is fed."""

        def update(self, readings, valid, now):
            fed.append(readings)
            return super().update(readings, valid, now)

    clock = Clock()
    sheet = VirtualSheet("flat", "3x3", seed=4)
    dev = MemoryDevice(sheet, clock=clock)
    dev.start(power_on=True)
    cal = Calibration(3, 3, bias=np.tile([0.2, -0.1, 0.5], (12, 1)), scale=np.full((12, 3), 1.02),
                      misalignment=np.tile([0.0, 0.0, 0.03], (12, 1)))
    heard, fed = [], []

    def driver(dt):
        clock.t += dt
        dev.step()
    host = Host(MemoryTransport(dev.port), "3x3", layout=Layout(dict(sheet.layout)), rate_hz=50, clock=clock,
                driver=driver, deadline_s=0.02, on_snapshot=heard.append)
    try:
        host.set_calibration(cal)
        host.health = Fed(3, 3, window=5)
        host.bring_up(0.2)
        got = list(host.snapshots(count=20))
        host.stop()
        got += host.drain()
    finally:
        host.close()
        dev.stop()
    assert len(got) >= 20 and [s.counter for s in got] == [s.counter for s in heard]
    assert all(a is b for a, b in zip(got, heard))
    assert len(fed) == len(heard) and all(f is s.readings for f, s in zip(fed, heard))
    assert host.calibration is not None and np.allclose(host.calibration.bias, cal.bias)  # nominal chips
    flat = np.tile([0.0, 0.0, G0], (12, 1))
    for s in got:
        if s.complete:
            np.testing.assert_allclose(s.readings, cal.apply(flat), atol=0.02)  # once, not twice, not zero


def test_a_sync_goes_out_while_a_receive_thread_holds_the_feed_stamped_when_it_is_written():
    """A driving host's SYNC thread does not wait for the feed's lock, which a receive thread holds
    across a read: the SYNC is written at once, its counter stamped with the clock read right
    before it (the chips sample when it arrives), and the open is applied when the lock is free,
    at that time (simulated clock; the other thread really holds the lock). Before
    `SnapshotFeed.post_open` the SYNC waited for the lock: a 64x64 sheet's SYNC went out 17 ms
    late at p99 and missed its slots."""
    import threading

    from host.session.core import Host, Layout
    from host.transport.ports import MemoryTransport
    from virtual_sheet.devices import MemoryDevice
    from virtual_sheet.sheet import VirtualSheet

    clock = Clock()
    sheet = VirtualSheet("flat", "3x3", seed=4)
    dev = MemoryDevice(sheet, clock=clock)
    dev.start(power_on=True)

    def driver(dt):
        clock.t += dt
        dev.step()
    host = Host(MemoryTransport(dev.port), "3x3", layout=Layout(dict(sheet.layout)), rate_hz=50, clock=clock,
                driver=driver, deadline_s=0.02)
    holding, release = threading.Event(), threading.Event()
    opened = []
    try:
        host.bring_up(0.2)
        list(host.snapshots(count=3))
        t_step = clock.t + 0.1  # past the next SYNC slot: the step sends one
        clock.t = t_step
        before = host.sync_driver.syncs_sent
        host.feed.add_open_listener(lambda c, now: opened.append((c, now)))

        def hold(bus, now):
            holding.set()
            release.wait(5.0)
        host.feed.add_ingest_listener(hold)
        receiver = threading.Thread(target=host.feed.ingest, args=([],))
        receiver.start()
        assert holding.wait(5.0)
        sender = threading.Thread(target=lambda: host.sync_driver.step(t_step))
        sender.start()
        for _ in range(500):  # the SYNC is written while the receive thread holds the feed
            if host.sync_driver.syncs_sent > before:
                break
            threading.Event().wait(0.01)
        assert host.sync_driver.syncs_sent == before + 1
        assert opened == []  # posted, not yet applied: the feed is held
        clock.t = t_step + 0.05
        release.set()
        receiver.join(5.0)
        sender.join(5.0)  # (its poll, past POLL_WAIT_S since the last, waited for the feed)
        assert not sender.is_alive()
    finally:
        release.set()
        host.close()
        dev.stop()
    assert len(opened) == 1 and opened[0][1] == t_step  # stamped when written, not when applied


def test_a_posted_open_is_applied_by_the_next_holder_of_the_feed_before_its_own_work():
    """`SnapshotFeed.post_open`: on a free feed at once; while another thread holds the feed,
    without waiting, and applied by the next call that takes the lock before that call's ingest
    (so the frames answering the SYNC find their counter open); inside a read (`one_read`, this or
    another thread) only when the read ends, so the read stays whole as a replay ingests it. The
    recorder's listeners see open and ingest in the order they were applied."""
    import threading

    clock = Clock()
    feed = SnapshotFeed(Aggregator(3, deadline_s=0.05), clock=clock)
    order = []
    feed.add_open_listener(lambda c, now: order.append(("open", c, now)))
    feed.add_ingest_listener(lambda bus, now: order.append(("ingest", bus, now)))
    assert feed.post_open(1, 10.0) is True and order == [("open", 1, 10.0)]  # a free feed: at once
    feed.ingest([batch(1)], now=10.001)
    with feed.one_read():  # this thread inside a read: posted, applied when the read ends
        assert feed.post_open(2, 10.02) is False
        feed.ingest([], now=10.021)
        assert [e[0] for e in order] == ["open", "ingest", "ingest"]
    result = []
    done = threading.Event()

    def other():  # another thread posts while this one holds a read
        result.append(feed.post_open(3, 10.04))
        done.set()
    with feed.one_read():
        assert order[-1] == ("open", 2, 10.02)  # the read's entry applied the earlier post
        t = threading.Thread(target=other)
        t.start()
        assert done.wait(5.0) and result == [False]  # it did not wait for the feed
        feed.ingest([batch(2)], now=10.041)
        assert order[-1] == ("ingest", 0, 10.041)
    t.join(5.0)
    feed.ingest([batch(3)], now=10.042)
    assert order[-3:] == [("ingest", 0, 10.041), ("open", 3, 10.04), ("ingest", 0, 10.042)]
    feed.poll(11.0)
    got = feed.drain()
    assert [s.counter for s in got] == [1, 2, 3] and all(s.complete for s in got)
    assert [s.timestamp for s in got] == [10.0, 10.02, 10.04]


def test_poll_without_waiting_does_nothing_while_another_thread_holds_the_feed():
    import threading

    clock = Clock()
    feed = SnapshotFeed(Aggregator(3, deadline_s=0.05), clock=clock)
    feed.open_counter(1, now=10.0)
    held, release = threading.Event(), threading.Event()

    def hold():
        with feed.one_read():
            held.set()
            release.wait(5.0)
    t = threading.Thread(target=hold)
    t.start()
    try:
        assert held.wait(5.0)
        assert feed.poll(11.0, wait=False) is False and feed.pending == 0
    finally:
        release.set()
        t.join(5.0)
    assert feed.poll(11.0, wait=False) is True and [s.counter for s in feed.drain()] == [1]


def test_one_read_keeps_other_threads_from_emitting_between_its_parts():
    """A read of a bus whose data comes in two parts around a control frame (the receive thread
    ingests the first part, handles the STATUS, ingests the rest) is one read: the recorder writes
    it once, at the first ingest, and a replay ingests it whole. The SYNC thread's poll, past the
    counter's deadline, waits until `one_read` ends, so the snapshot holds both parts live as in
    the replay (without it: link 3 missing live, present in the replay)."""
    import threading

    clock = Clock()
    feed = SnapshotFeed(Aggregator(3, deadline_s=0.05), clock=clock)
    feed.open_counter(4)
    polled = threading.Event()

    def sync_thread():
        feed.poll(clock.t + 1.0)  # far past the deadline
        polled.set()

    with feed.one_read():
        feed.ingest([batch(4, nodes=(1, 2))])
        t = threading.Thread(target=sync_thread)
        t.start()
        polled.wait(0.3)  # the poll cannot get in: nothing is emitted yet
        assert not polled.is_set() and feed.pending == 0
        clock.t += 0.001
        feed.ingest([batch(4, nodes=(3,))])
    t.join(5.0)
    [snap] = feed.drain()
    assert snap.counter == 4 and snap.complete and snap.valid.all()
