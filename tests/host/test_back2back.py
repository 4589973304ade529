"""Back-to-back: the host against the virtual sheet over every transport, the same assertions for each
(in-memory link, pty serial, python-can virtual with two buses, SLCAN adapters on ptys through
capsheet's own SLCAN bus, host/transport/slcan.py's ``capsheet_slcan`` python-can interface), then under
every injected fault.

The in-process rigs (memory link, python-can ``virtual``) run on a **simulated clock**: host and
sheet in one thread (`Host(driver=...)`, `Device(clock=...)`), time advanced 1 ms per step, so
their counts are exact and do not depend on how busy the machine is. The pty and SLCAN rigs run on
the real clock in threads and assert correctness only — every frame delivered or counted, nothing
valid lost, snapshots right — never a rate or a latency.

Every rig is torn down in its fixture: host threads stopped and joined, device thread stopped.
The chips are the Python model and the C firmware in turn (the ``chip_class`` fixture).
"""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

from host.snapshots.snapshot import LinkFlag
from host.session.core import Host, Layout
from host.transport.ports import CanTransport, MemoryTransport, SerialTransport
from protocol.constants import G0
from virtual_sheet.devices import CanDevice, MemoryDevice, PtyDevice
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import SensorModel
from virtual_sheet.sheet import VirtualSheet
from virtual_sheet.slcan import SlcanDevice

KINDS = ["memory", "pty", "can-virtual", "slcan"]
SIMULATED = ("memory", "can-virtual")  #: rigs on the simulated clock (exact counts)
_channel = itertools.count()
COUNT = G0 / 1024  # one ADC count at ±2 g, m/s²


class SimClock:
    """A clock that moves only when told: ``clock()`` -> seconds."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class PacedEnd:
    """The host's end of a memory link delivered at a UART's pace on the rig's simulated clock: what
    the sheet sends reaches the host ``bytes_per_s`` at a time, as over a real serial line, not at
    once. Credit for the wire is not saved up while nothing waits (at most 10 ms of it)."""

    def __init__(self, end, clock, bytes_per_s: float) -> None:
        self.end, self.clock, self.bytes_per_s = end, clock, float(bytes_per_s)
        self.timeout = 0.0  # never waits: the simulated clock moves only between the host's steps
        self._credit, self._t = 0.0, clock()

    @property
    def in_waiting(self) -> int:
        now = self.clock()
        self._credit = min(self._credit + (now - self._t) * self.bytes_per_s, 0.01 * self.bytes_per_s)
        self._t = now
        return min(self.end.in_waiting, int(self._credit))

    def read(self, size: int = 1) -> bytes:
        n = min(size, self.in_waiting)
        if n <= 0:
            return b""
        data = self.end.read(n)
        self._credit -= len(data)
        return data

    def write(self, data: bytes) -> int:
        return self.end.write(data)

    @property
    def is_open(self) -> bool:
        return self.end.is_open

    def close(self) -> None:
        self.end.close()


class Rig:
    """A virtual sheet behind a device, and a Host connected to it. ``uart_bytes_per_s`` (memory
    only): the host reads the link at that pace (`PacedEnd`)."""

    def __init__(self, kind: str, *, shape="flat", lattice="4x4", faults=None, sensor=None, packed=False,
                 rate_hz=100.0, watchdog_s=None, layout=True, seed=1, gateway_sync_hz=None,
                 chip_class=None, gateway_node=None, uart_bytes_per_s=None) -> None:
        can_kind = kind in ("can-virtual", "slcan")
        self.kind = kind
        self.sim = kind in SIMULATED
        self.clock = SimClock() if self.sim else None
        self.sheet = VirtualSheet(shape, lattice, seed=seed, transport="can" if can_kind else "serial",
                                  faults=faults, sensor=sensor, fd=packed and can_kind, chip_factory=chip_class)
        if kind == "memory":
            self.device = MemoryDevice(self.sheet, packed=packed, sync_rate_hz=gateway_sync_hz, clock=self.clock,
                                       gateway_node=gateway_node)
        elif kind == "pty":
            self.device = PtyDevice(self.sheet, packed=packed, sync_rate_hz=gateway_sync_hz)
        elif kind == "can-virtual":
            n = next(_channel)
            self.device = CanDevice(self.sheet, n_buses=2, channels=[f"b2b_{n}_a", f"b2b_{n}_b"], packed=packed,
                                    clock=self.clock)
        else:
            self.device = SlcanDevice(self.sheet, n_buses=2, packed=packed)
        # real clock: the chips are powered once the host has its port open (nothing sent unheard)
        self.device.start(power_on=self.sim)
        try:
            if kind == "memory":
                end = self.device.port if uart_bytes_per_s is None else PacedEnd(self.device.port, self.clock,
                                                                                  uart_bytes_per_s)
                ts = [MemoryTransport(end)]
            elif kind == "pty":
                ts = [SerialTransport(self.device.path, reconnect_interval_s=0.05)]
            elif kind == "can-virtual":
                ts = [CanTransport(f"virtual:{ch}", fd=self.sheet.fd) for ch in self.device.channels]
            else:
                ts = [CanTransport(f"slcan:{p}", bitrate=1_000_000, sleep_after_open=0, fd=self.sheet.fd)
                      for p in self.device.paths]
        except Exception:
            self.device.stop()
            raise
        if kind == "slcan":
            # two SLCAN adapters (ASCII lines both ways) plus the emulator in one process on a
            # small box keep up with 50 Hz x 24 chips, not always with 100 Hz
            rate_hz = min(rate_hz, 50.0)
        if not self.sim:
            self.device.power_on()
        if self.sim:
            def driver(dt: float) -> None:  # the world runs dt seconds: the sheet steps once
                self.clock.t += dt
                self.device.step()
            timing = dict(clock=self.clock, driver=driver, deadline_s=0.02)
        else:
            timing = dict(deadline_s=0.2)  # generous: a loaded 2-core CI box; latency is not under test
        self.host = Host(ts, lattice, layout=Layout(dict(self.sheet.layout)) if layout else None,
                         rate_hz=rate_hz, watchdog_s=watchdog_s, timeout_s=0.15, retries=5,
                         sync="follow" if gateway_sync_hz else "drive", **timing)
        self.host.open()

    def close(self) -> None:
        try:
            self.host.close()
        finally:
            self.device.stop()
        assert self.device.error is None, self.device.error

    def stream(self, duration_s: float) -> list:
        snaps = list(self.host.snapshots(duration_s=duration_s))
        self.host.stop()
        snaps += self.host.drain()
        return snaps


@pytest.fixture
def rig_factory(chip_class):
    rigs: list[Rig] = []

    def make(kind, **kw) -> Rig:
        r = Rig(kind, chip_class=chip_class, **kw)
        rigs.append(r)
        return r

    yield make
    for r in rigs:
        r.close()


def check_accounting(rig: Rig, snaps: list) -> None:
    """No exception anywhere; every snapshot delivered; every accepted sample in a snapshot."""
    st = rig.host.aggregator.stats
    assert rig.host.event_log.rx_errors == []
    assert st.dropped == 0
    assert len(snaps) == st.emitted
    received = sum(int(np.count_nonzero((s.status & LinkFlag.MISSING) == 0)) for s in snaps)
    assert received == st.samples
    counters = [s.counter for s in snaps]
    assert all(((b - a) & 0xFFFF) < 0x8000 and a != b for a, b in zip(counters, counters[1:])), "counter order"
    if rig.sim:  # one thread, simulated time: every counter sent is a snapshot, and none is late
        assert rig.host.syncs_sent in (0, len(snaps))
        assert st.late == 0
        n_exp = int(np.count_nonzero(~rig.host.aggregator.unassigned))
        silent = sum(int(np.count_nonzero(s.status & LinkFlag.SILENT)) for s in snaps)
        assert st.samples + int(st.link_missing.sum()) + silent == len(snaps) * n_exp  # each link: here or missing


def check_readings(rig: Rig, snaps: list, tol_counts: float = 2.5) -> None:
    """Every valid reading is the truth of its own counter (to ADC quantisation + the model's bias)."""
    for s in snaps:
        ideal = ideal_readings(rig.sheet.truth(s.counter))
        assert np.all(np.abs(s.readings[s.valid] - ideal[s.valid]) < tol_counts * COUNT), s.counter


def check_delivered(rig: Rig, timeout_s: float = 20.0) -> None:
    """Real-clock rigs: every frame the sheet put on the wire reached the host and was decoded or
    counted (waits for the wire to drain; asserts no loss, never how fast)."""
    ports = getattr(rig.device, "ports", [rig.device])
    # frames the device dropped whole because the host did not read (a bounded gateway buffer) are
    # counted there; every other frame must arrive
    sent = lambda: (sum(gw.stats.frames_to_host for gw in rig.device.gateways)  # noqa: E731
                    - sum(p.tx_overflow_frames for p in ports))
    got = lambda: sum(t.stats.frames_in + t.stats.error_count for t in rig.host.transports)  # noqa: E731
    # the chips keep sending (heartbeats) while this waits: the two counts are read once a pass and
    # must meet; reading them again for the assertion raced a burst sent in between
    end = time.monotonic() + timeout_s
    while True:
        pair = (got(), sent())
        if pair[0] == pair[1] or time.monotonic() >= end:
            break
        time.sleep(0.02)
    assert pair[0] == pair[1], pair


# --------------------------------------------------------------------------------------------- clean

@pytest.mark.parametrize("kind", KINDS)
def test_bring_up_and_stream_complete_calibrated_snapshots(rig_factory, kind):
    sensor = SensorModel(bias_counts=15.0, scale_error=0.03, chip_seed=5)
    rig = rig_factory(kind, shape="gaussian", sensor=sensor)
    n = rig.sheet.n_links
    summary = rig.host.bring_up(0.3)
    assert summary == {"discovered": n, "assigned": n, "configured": n, "calibrated": n, "started": n, "gateways": 0}
    assert {r.link for r in rig.host.chips.values()} == set(range(n))
    snaps = rig.stream(0.6)
    check_accounting(rig, snaps)
    # readings after per-chip calibration match the truth to ADC quantisation (bias is 15 counts)
    check_readings(rig, snaps)
    stats = rig.host.stats
    assert sum(b["errors"] and sum(b["errors"].values()) or 0 for b in stats["buses"]) == 0
    assert stats["aggregator"]["duplicates"] == stats["aggregator"]["unknown"] == 0
    if rig.sim:
        rate = rig.host.rate_hz
        assert rig.host.syncs_sent == len(snaps) == round(0.6 * rate)  # one SYNC per slot, none missed
        assert stats["live"]["syncs_missed"] == 0
        assert all(s.complete and s.valid.all() for s in snaps)
        assert [((b.counter - a.counter) & 0xFFFF) for a, b in zip(snaps, snaps[1:])] == [1] * (len(snaps) - 1)
        assert stats["aggregator"]["samples"] == n * len(snaps) and stats["aggregator"]["late"] == 0
        assert stats["live"]["complete_snapshots_pct"] == stats["live"]["valid_links_pct"] == 100.0
        assert all(c["frames"] == len(snaps) for c in stats["chips"].values())
    else:
        check_delivered(rig)
        assert snaps and np.any([s.valid for s in snaps], axis=0).all()  # every chip was heard
    if kind in ("can-virtual", "slcan"):
        assert len(stats["buses"]) == 2 and all(b["samples"] > 0 for b in stats["buses"])  # merged


def test_discovery_lasts_while_answers_are_still_arriving(rig_factory):
    """A 10x10 sheet (180 chips) behind a 115,200 baud UART, on the simulated clock: its answers to
    GET_INFO take ~0.5 s of wire, far more than the two windows asked for (the first is
    `DISCOVER_QUIET_S` at least, the second 50 ms). A round's window lasts until no new chip has been
    heard for `DISCOVER_QUIET_S` (host/session/bringup.py), so every chip is found. The property the
    command line's 1,984-chip run shows (tests/host/cli/test_host.py), here whatever the machine's
    load. Without the lasting window 39 of 180 chips are found, with it cut at one window 108."""
    from host.session.bringup import DISCOVER_QUIET_S
    rig = rig_factory("memory", lattice="10x10", uart_bytes_per_s=115_200 / 10)
    t0 = rig.clock.t
    chips = rig.host.discover(0.05, rounds=2)
    assert sorted(u for u, c in chips.items() if c.info is not None) == sorted(rig.sheet.layout)
    assert rig.clock.t - t0 > DISCOVER_QUIET_S + 0.05  # the answers took longer than the windows asked


@pytest.mark.parametrize("kind", ["memory", "can-virtual"])
def test_auto_assign_without_layout_places_chips_in_uid_order(rig_factory, kind):
    rig = rig_factory(kind, layout=False)
    rig.host.bring_up(0.2)
    uids = sorted(rig.sheet.layout)
    assert [rig.host.chips[u].link for u in uids] == list(range(len(uids)))
    assert rig.host.layout.is_auto
    snaps = rig.stream(0.2)
    check_accounting(rig, snaps)
    assert len(snaps) == 20 and all(s.complete for s in snaps)


@pytest.mark.parametrize("kind", ["memory", "pty"])
def test_packed_gateway_snapshots_fill_the_lattice(rig_factory, kind):
    rig = rig_factory(kind, lattice="8x8", packed=True)
    rig.host.bring_up(0.3)
    snaps = rig.stream(0.4)
    check_accounting(rig, snaps)
    check_readings(rig, snaps, tol_counts=1.5)
    if rig.sim:
        assert len(snaps) == 40 and all(s.complete for s in snaps)
        assert rig.device.gateway.stats.snapshots == 40  # 112 links: one SNAPSHOT frame per counter
    else:
        check_delivered(rig)
        assert any(s.complete for s in snaps)
    np.testing.assert_allclose(snaps[-1].readings[snaps[-1].valid],
                               np.tile([0, 0, G0], (snaps[-1].n_valid, 1)), atol=1.5 * COUNT)


def test_counter_wraps_while_streaming(rig_factory):
    rig = rig_factory("memory")
    rig.host.counter = 0xFFF0
    rig.host.bring_up(0.2)
    snaps = rig.stream(0.4)
    check_accounting(rig, snaps)
    counters = [s.counter for s in snaps]
    assert counters == [(0xFFF0 + k) & 0xFFFF for k in range(40)]
    assert all(s.complete for s in snaps)


# --------------------------------------------------------------------------------------------- faults

def _stream_faulty(rig: Rig, duration_s: float = 1.0) -> list:
    rig.host.bring_up(0.3)
    return rig.stream(duration_s)


@pytest.mark.parametrize("kind", ["memory", "pty"])
def test_bit_flips_and_dropped_bytes_are_counted_as_framing_errors(rig_factory, kind):
    rig = rig_factory(kind, faults="bitflip=2e-4,drop_byte=5e-4,seed=3")
    snaps = _stream_faulty(rig)
    check_accounting(rig, snaps)
    check_readings(rig, snaps)  # what does arrive is right: the CRC lets no damaged frame through
    errors = rig.host.transports[0].stats.errors
    assert sum(errors.values()) > 0 and set(errors) <= {"BAD_CRC", "BAD_COBS", "SHORT", "BAD_LENGTH", "OVERSIZE",
                                                          "UNKNOWN_TYPE", "BAD_VERSION", "BAD_FIELD"}
    fs = rig.sheet.fault_stats
    assert fs.frames_corrupted > 0
    # every damaged frame is lost and counted, never delivered wrong: each missing link is one
    # corrupted frame, or (real clock only) one that came after its deadline
    st = rig.host.aggregator.stats
    assert 0 < st.link_missing.sum() <= fs.frames_corrupted + st.late
    assert st.unknown == 0 and st.complete > 0


def test_can_bit_errors_become_error_frames_and_retransmissions(rig_factory):
    rig = rig_factory("can-virtual", faults="bitflip=1e-3,seed=4")
    snaps = _stream_faulty(rig, 0.6)
    check_accounting(rig, snaps)
    n_err = sum(t.stats.errors["CAN_ERROR_FRAME"] for t in rig.host.transports)
    assert n_err == rig.sheet.fault_stats.error_frames > 0  # one thread: every error frame was read
    assert len(snaps) == 60 and all(s.complete for s in snaps)  # the bus retransmits: nothing is lost


@pytest.mark.parametrize("kind", ["memory", "can-virtual"])
def test_dropped_frames_give_masked_snapshots_at_the_deadline(rig_factory, kind):
    rig = rig_factory(kind, faults="drop_frame=0.02,seed=5")
    snaps = _stream_faulty(rig)
    check_accounting(rig, snaps)
    st = rig.host.aggregator.stats
    assert st.incomplete > 0 and st.link_missing.sum() > 0
    assert st.link_missing.sum() <= rig.sheet.fault_stats.frames_dropped
    inc = [s for s in snaps if not s.complete]
    assert all((~s.valid).any() and np.isnan(s.readings[~s.valid]).all() for s in inc)
    assert all(s.latency_s >= rig.host.aggregator.min_deadline_s - 1e-9 for s in inc)  # waited its deadline
    assert st.complete > 0
    assert rig.host.silent_links == []  # a few lost frames are not a silent chip


@pytest.mark.parametrize("kind", ["memory", "can-virtual"])
def test_duplicated_frames_are_counted_and_ignored(rig_factory, kind):
    rig = rig_factory(kind, faults="dup_frame=0.05,seed=6")
    snaps = _stream_faulty(rig, 0.6)
    check_accounting(rig, snaps)
    assert rig.host.aggregator.stats.duplicates > 0
    assert len(snaps) == 60 and all(s.complete for s in snaps)


@pytest.mark.parametrize("kind", ["memory", "pty"])
def test_reordered_and_jittered_frames_still_complete(rig_factory, kind):
    rig = rig_factory(kind, faults="reorder=0.05,jitter_ms=3,seed=7")
    snaps = _stream_faulty(rig, 0.6)
    check_accounting(rig, snaps)
    check_readings(rig, snaps)
    assert rig.sheet.fault_stats.frames_reordered > 0
    st = rig.host.aggregator.stats
    if rig.sim:
        assert st.late == 0 and st.complete == len(snaps) == 60
    else:
        assert st.duplicates == st.unknown == 0


def test_dead_chip_is_reported_marked_missing_and_streaming_goes_on(rig_factory):
    rig = rig_factory("memory", faults="dead_chip=5,dead_after_s=0.6,seed=8", watchdog_s=0.2)
    snaps = _stream_faulty(rig, 1.2)
    check_accounting(rig, snaps)
    silent = [e for e in rig.host.events if e.kind == "silent"]
    assert [e.link for e in silent] == [5]
    assert rig.host.silent_links == [5]
    after = [s for s in snaps if s.status[5] & LinkFlag.SILENT]
    assert len(after) > 10
    assert all(s.complete and s.valid.sum() == rig.sheet.n_links - 1 for s in after)  # not waited for
    assert not snaps[0].status[5] & LinkFlag.SILENT and snaps[0].valid[5]


def test_a_stalled_host_blames_no_chip(rig_factory):
    """The host's own loop stops for 1 s (5x the watchdog) while the sheet keeps going: no link is
    reported silent, no SYNC burst follows (the missed slots are counted), streaming resumes."""
    rig = rig_factory("memory", watchdog_s=0.2)
    rig.host.bring_up(0.2)
    snaps = list(rig.host.snapshots(duration_s=0.3))
    for _ in range(1000):  # 1 s of the world without a single host service
        rig.clock.t += 0.001
        rig.device.step()
    sent_before = rig.host.syncs_sent
    snaps += list(rig.host.snapshots(duration_s=0.3))
    rig.host.stop()
    snaps += rig.host.drain()
    check_accounting(rig, snaps)
    assert [e for e in rig.host.events if e.kind == "silent"] == []
    assert rig.host.stats["live"]["syncs_missed"] == 100  # 1 s at 100 Hz skipped, not caught up
    # after the stall: one SYNC for the slot the host woke in, then one per 10 ms for 0.3 s — no burst
    assert rig.host.syncs_sent - sent_before == 1 + 30
    assert all(s.complete for s in snaps)


def test_a_chip_that_answers_late_is_blamed_but_not_its_neighbours(rig_factory):
    """A drifting chip whose replies always leave after the deadline: only it is reported silent."""
    rig = rig_factory("memory", faults="drift_chip=7,drift=0.0,drift_late_ms=40,seed=12", watchdog_s=0.1)
    rig.host.aggregator.adaptive = False  # a fixed 20 ms deadline: the chip's 40 ms are beyond it
    snaps = _stream_faulty(rig, 0.6)
    silent = {e.link for e in rig.host.events if e.kind == "silent"}
    assert silent == {7}
    assert rig.host.aggregator.stats.link_late[7] > 0 and rig.host.aggregator.stats.link_late.sum() == \
        rig.host.aggregator.stats.link_late[7]


@pytest.mark.parametrize("kind", ["memory", "can-virtual"])
def test_babbling_chip_is_counted_and_the_lattice_unharmed(rig_factory, kind):
    rig = rig_factory(kind, faults="babble_chip=3,babble_rate=2,seed=9")
    snaps = _stream_faulty(rig, 0.6)
    check_accounting(rig, snaps)
    assert rig.sheet.fault_stats.babble_frames > 0
    errs = sum(t.stats.error_count for t in rig.host.transports)
    assert errs > 0
    assert len(snaps) == 60 and all(s.complete for s in snaps)


def test_drifting_chip_sends_stale_samples_flagged_but_valid(rig_factory):
    rig = rig_factory("memory", faults="drift_chip=2,drift=0.2,seed=10")
    snaps = _stream_faulty(rig, 0.6)
    check_accounting(rig, snaps)
    stale = sum(bool(s.status[2] & LinkFlag.STALE) for s in snaps)
    assert stale == rig.sheet.fault_stats.stale_samples > 0
    assert all(s.valid[2] for s in snaps) and all(s.complete for s in snaps)
    assert rig.host.aggregator.stats.late == 0


def _stream_past_the_last_event(rig: Rig, duration_s: float, after: int = 20, limit_s: float = 30.0) -> list:
    """`_stream_faulty` for ``duration_s``; on a real clock then on until ``after`` snapshots have
    come since the host's last event (its recovery from the outage on a loaded machine may take the
    whole ``duration_s``: the test is about what follows it, not how soon), ``limit_s`` at most."""
    if rig.sim:
        return _stream_faulty(rig, duration_s)
    import time
    rig.host.bring_up(0.3)
    snaps, t0 = [], time.monotonic()
    for s in rig.host.snapshots(duration_s=limit_s):
        snaps.append(s)
        if time.monotonic() - t0 >= duration_s and rig.host.events:
            last = rig.host.events[-1].t
            if sum(x.timestamp > last for x in snaps) >= after:
                break
    rig.host.stop()
    return snaps + rig.host.drain()


@pytest.mark.parametrize("kind", ["pty", "memory"])
def test_bus_outage_is_survived(rig_factory, kind):
    rig = rig_factory(kind, faults="outage_at_s=0.7,outage_s=0.3,seed=11", watchdog_s=0.15)
    snaps = _stream_past_the_last_event(rig, 1.6)
    check_accounting(rig, snaps)
    t = rig.host.transports[0]
    if kind == "pty":
        assert t.stats.disconnects >= 1 and t.stats.reconnects >= 1
        assert any(e.kind == "reconnect" for e in rig.host.events)
    assert any(e.kind == "silent" for e in rig.host.events)
    assert any(e.kind == "recovered" for e in rig.host.events)
    if rig.sim:  # streaming resumed: the snapshots after the outage are complete again
        assert snaps[-3].complete and snaps[-2].complete
    else:  # every chip was heard after the outage
        after = [s for s in snaps if s.timestamp > rig.host.events[-1].t]
        assert after and np.any([s.valid for s in after], axis=0).all()


@pytest.mark.parametrize("kind", ["memory", "pty"])
def test_follow_a_gateways_sync(rig_factory, kind):
    rig = rig_factory(kind, gateway_sync_hz=100.0)
    rig.host.bring_up(0.2)
    snaps = rig.stream(0.5)
    check_accounting(rig, snaps)
    check_readings(rig, snaps)
    assert rig.host.syncs_sent == 0 and rig.host.syncs_seen > 0
    if rig.sim:
        assert len(snaps) >= 50 and sum(not s.complete for s in snaps) <= 1  # the last may be cut by STOP
    else:
        assert snaps
    assert all(not np.isnan(s.timestamp) for s in snaps)


def test_the_suite_runs_the_chip_implementation_under_test(rig_factory, chip_class):
    """Every test here runs once with the Python model (the vectorised array of it) and once with
    the C reference firmware behind cffi (the ``chip_class`` fixture; no monkeypatching)."""
    rig = rig_factory("memory")
    assert all(isinstance(c, chip_class) for c in rig.sheet.chips)
    assert rig.sheet.engine_name == ("array" if chip_class.__name__ == "ChipModel" else "chips")
