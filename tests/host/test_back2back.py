"""Back-to-back: the host against the virtual sheet over every transport, the same assertions for each
(in-memory link, pty serial, python-can virtual with two buses, SLCAN adapters on ptys through
python-can's own slcan interface), then under every injected fault.

Every rig is torn down in its fixture: host threads stopped and joined, device thread stopped.
"""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

from host.aggregator import LinkFlag
from host.session import Host, Layout
from host.transport import CanTransport, MemoryTransport, SerialTransport
from protocol.constants import G0
from virtual_sheet.devices import CanDevice, MemoryDevice, PtyDevice
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import SensorModel
from virtual_sheet.sheet import VirtualSheet

try:
    from virtual_sheet.slcan import SlcanDevice
except ImportError:  # pragma: no cover
    SlcanDevice = None

KINDS = ["memory", "pty", "can-virtual", "slcan"]
_channel = itertools.count()
COUNT = G0 / 1024  # one ADC count at ±2 g, m/s²


class Rig:
    """A virtual sheet behind a device, and a Host connected to it."""

    def __init__(self, kind: str, *, shape="flat", lattice="4x4", faults=None, sensor=None, packed=False,
                 rate_hz=100.0, watchdog_s=None, layout=True, seed=1, gateway_sync_hz=None) -> None:
        can_kind = kind in ("can-virtual", "slcan")
        self.kind = kind
        self.sheet = VirtualSheet(shape, lattice, seed=seed, transport="can" if can_kind else "serial",
                                  faults=faults, sensor=sensor, fd=packed and can_kind)
        if kind == "memory":
            self.device = MemoryDevice(self.sheet, packed=packed, sync_rate_hz=gateway_sync_hz)
        elif kind == "pty":
            self.device = PtyDevice(self.sheet, packed=packed, sync_rate_hz=gateway_sync_hz)
        elif kind == "can-virtual":
            n = next(_channel)
            self.device = CanDevice(self.sheet, n_buses=2, channels=[f"b2b_{n}_a", f"b2b_{n}_b"], packed=packed)
        else:
            if SlcanDevice is None:
                pytest.skip("virtual_sheet.slcan.SlcanDevice has not landed")
            self.device = SlcanDevice(self.sheet, n_buses=2, packed=packed)
        self.device.start()
        try:
            if kind == "memory":
                ts = [MemoryTransport(self.device.port)]
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
            # python-can's slcan reads one byte per call: two adapters plus the emulator in one
            # process on a small box keep up with 50 Hz x 24 chips, not always with 100 Hz
            rate_hz = min(rate_hz, 50.0)
        self.host = Host(ts, lattice, layout=Layout(dict(self.sheet.layout)) if layout else None,
                         rate_hz=rate_hz, watchdog_s=watchdog_s, timeout_s=0.15, retries=5,
                         sync="follow" if gateway_sync_hz else "drive",
                         deadline_s=0.2)  # generous: a loaded 2-core CI box; latency is not under test
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
        snaps += self.host.aggregator.drain()
        return snaps


@pytest.fixture
def rig_factory():
    rigs: list[Rig] = []

    def make(kind, **kw) -> Rig:
        r = Rig(kind, **kw)
        rigs.append(r)
        return r

    yield make
    for r in rigs:
        r.close()


def check_accounting(rig: Rig, snaps: list) -> None:
    """No exception anywhere; every snapshot delivered; every accepted sample in a snapshot."""
    st = rig.host.aggregator.stats
    assert rig.host._rx_errors == []
    assert st.dropped == 0
    assert len(snaps) == st.emitted
    received = sum(int(np.count_nonzero((s.status & LinkFlag.MISSING) == 0)) for s in snaps)
    assert received == st.samples
    counters = [s.counter for s in snaps]
    assert all(((b - a) & 0xFFFF) < 0x8000 and a != b for a, b in zip(counters, counters[1:])), "counter order"


# --------------------------------------------------------------------------------------------- clean

@pytest.mark.parametrize("kind", KINDS)
def test_bring_up_and_stream_complete_calibrated_snapshots(rig_factory, kind):
    sensor = SensorModel(bias_counts=15.0, scale_error=0.03, chip_seed=5)
    rig = rig_factory(kind, shape="gaussian", sensor=sensor)
    n = rig.sheet.n_links
    summary = rig.host.bring_up(0.3)
    assert summary == {"discovered": n, "assigned": n, "configured": n, "calibrated": n, "started": n}
    assert {r.link for r in rig.host.chips.values()} == set(range(n))
    snaps = rig.stream(0.6)
    check_accounting(rig, snaps)
    assert len(snaps) >= 25
    assert all(s.complete and s.valid.all() for s in snaps), (
        [(s.counter, s.n_valid, round(s.latency_s, 3)) for s in snaps if not s.complete], rig.host.stats["aggregator"],
        rig.host.stats["buses"])
    assert [((b.counter - a.counter) & 0xFFFF) for a, b in zip(snaps, snaps[1:])] == [1] * (len(snaps) - 1)
    # readings after per-chip calibration match the truth to ADC quantisation (bias is 15 counts)
    for s in snaps[5:8]:
        ideal = ideal_readings(rig.sheet.truth(s.counter))
        assert np.max(np.abs(s.readings - ideal)) < 2.5 * COUNT
    stats = rig.host.stats
    assert sum(b["errors"] and sum(b["errors"].values()) or 0 for b in stats["buses"]) == 0
    assert stats["aggregator"]["late"] == stats["aggregator"]["duplicates"] == stats["aggregator"]["unknown"] == 0
    assert all(c["frames"] >= len(snaps) for c in stats["chips"].values())
    if kind in ("can-virtual", "slcan"):
        assert len(stats["buses"]) == 2 and all(b["samples"] > 0 for b in stats["buses"])  # merged


@pytest.mark.parametrize("kind", ["memory", "can-virtual"])
def test_auto_assign_without_layout_places_chips_in_uid_order(rig_factory, kind):
    rig = rig_factory(kind, layout=False)
    rig.host.bring_up(0.2)
    uids = sorted(rig.sheet.layout)
    assert [rig.host.chips[u].link for u in uids] == list(range(len(uids)))
    assert rig.host.layout.is_auto
    snaps = rig.stream(0.2)
    assert snaps and all(s.complete for s in snaps)


def test_packed_gateway_snapshots_fill_the_lattice(rig_factory):
    rig = rig_factory("pty", lattice="8x8", packed=True)
    rig.host.bring_up(0.3)
    snaps = rig.stream(0.4)
    check_accounting(rig, snaps)
    assert len(snaps) >= 20 and all(s.complete for s in snaps)
    np.testing.assert_allclose(snaps[-1].readings, np.tile([0, 0, G0], (rig.sheet.n_links, 1)), atol=1.5 * COUNT)


def test_counter_wraps_while_streaming(rig_factory):
    rig = rig_factory("memory")
    rig.host.counter = 0xFFF0
    rig.host.bring_up(0.2)
    snaps = rig.stream(0.4)
    check_accounting(rig, snaps)
    counters = [s.counter for s in snaps]
    assert 0xFFFF in counters and 0 in counters
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
    errors = rig.host.transports[0].stats.errors
    assert sum(errors.values()) > 0 and set(errors) <= {"BAD_CRC", "BAD_COBS", "SHORT", "BAD_LENGTH", "OVERSIZE",
                                                          "UNKNOWN_TYPE", "BAD_VERSION", "BAD_FIELD"}
    fs = rig.sheet.fault_stats
    assert fs.frames_corrupted > 0
    # every damaged frame is lost and counted, never delivered wrong: each missing link is one
    # corrupted frame (the CRC lets none through), and complete snapshots still come
    st = rig.host.aggregator.stats
    assert 0 < st.link_missing.sum() <= fs.frames_corrupted + st.late  # late: a slow test machine
    assert st.unknown == 0 and st.complete > 0


def test_can_bit_errors_become_error_frames_and_retransmissions(rig_factory):
    rig = rig_factory("can-virtual", faults="bitflip=1e-3,seed=4")
    snaps = _stream_faulty(rig, 0.6)
    check_accounting(rig, snaps)
    n_err = sum(t.stats.errors["CAN_ERROR_FRAME"] for t in rig.host.transports)
    assert 0 < n_err <= rig.sheet.fault_stats.error_frames  # the device keeps going after the host stops
    assert all(s.complete for s in snaps)  # the bus retransmits: nothing is lost


@pytest.mark.parametrize("kind", ["memory", "can-virtual"])
def test_dropped_frames_give_masked_snapshots_at_the_deadline(rig_factory, kind):
    rig = rig_factory(kind, faults="drop_frame=0.02,seed=5")
    snaps = _stream_faulty(rig)
    check_accounting(rig, snaps)
    st = rig.host.aggregator.stats
    assert st.incomplete > 0 and st.link_missing.sum() > 0
    inc = [s for s in snaps if not s.complete]
    assert all((~s.valid).any() and np.isnan(s.readings[~s.valid]).all() for s in inc)
    assert st.complete > 0


@pytest.mark.parametrize("kind", ["memory", "can-virtual"])
def test_duplicated_frames_are_counted_and_ignored(rig_factory, kind):
    rig = rig_factory(kind, faults="dup_frame=0.05,seed=6")
    snaps = _stream_faulty(rig, 0.6)
    check_accounting(rig, snaps)
    assert rig.host.aggregator.stats.duplicates > 0
    assert all(s.complete for s in snaps)


@pytest.mark.parametrize("kind", ["memory", "pty"])
def test_reordered_and_jittered_frames_still_complete(rig_factory, kind):
    rig = rig_factory(kind, faults="reorder=0.05,jitter_ms=3,seed=7")
    snaps = _stream_faulty(rig, 0.6)
    check_accounting(rig, snaps)
    assert rig.sheet.fault_stats.frames_reordered > 0
    st = rig.host.aggregator.stats
    assert st.late == 0
    assert st.complete >= len(snaps) - 1


def test_dead_chip_is_reported_marked_missing_and_streaming_goes_on(rig_factory):
    rig = rig_factory("memory", faults="dead_chip=5,dead_after_s=0.6,seed=8", watchdog_s=0.2)
    snaps = _stream_faulty(rig, 1.2)
    check_accounting(rig, snaps)
    silent = [e for e in rig.host.events if e.kind == "silent"]
    assert [e.link for e in silent] == [5]
    assert rig.host.silent_links == [] or rig.host.silent_links == [5]
    after = [s for s in snaps if s.status[5] & LinkFlag.SILENT]
    assert len(after) > 10
    assert all(s.complete and s.valid.sum() == rig.sheet.n_links - 1 for s in after)  # not waited for
    assert not snaps[0].status[5] & LinkFlag.SILENT and snaps[0].valid[5]


@pytest.mark.parametrize("kind", ["memory", "can-virtual"])
def test_babbling_chip_is_counted_and_the_lattice_unharmed(rig_factory, kind):
    rig = rig_factory(kind, faults="babble_chip=3,babble_rate=2,seed=9")
    snaps = _stream_faulty(rig, 0.6)
    check_accounting(rig, snaps)
    assert rig.sheet.fault_stats.babble_frames > 0
    errs = sum(t.stats.error_count for t in rig.host.transports)
    assert errs > 0
    assert sum(s.complete for s in snaps) >= len(snaps) - 2


def test_drifting_chip_sends_stale_samples_flagged_but_valid(rig_factory):
    rig = rig_factory("memory", faults="drift_chip=2,drift=0.2,seed=10")
    snaps = _stream_faulty(rig, 0.6)
    check_accounting(rig, snaps)
    stale = sum(bool(s.status[2] & LinkFlag.STALE) for s in snaps)
    assert stale > 0 and all(s.valid[2] for s in snaps if s.complete)
    assert rig.host.aggregator.stats.late == 0


@pytest.mark.parametrize("kind", ["pty", "memory"])
def test_bus_outage_is_survived(rig_factory, kind):
    rig = rig_factory(kind, faults="outage_at_s=0.7,outage_s=0.3,seed=11", watchdog_s=0.15)
    snaps = _stream_faulty(rig, 1.6)
    check_accounting(rig, snaps)
    t = rig.host.transports[0]
    if kind == "pty":
        assert t.stats.disconnects >= 1 and t.stats.reconnects >= 1
        assert any(e.kind == "reconnect" for e in rig.host.events)
    assert any(e.kind == "silent" for e in rig.host.events)
    assert any(e.kind == "recovered" for e in rig.host.events), [(round(e.t - rig.host.events[0].t, 3), e.kind, e.link) for e in rig.host.events if e.link in (None, 0)] + [rig.host.stats["buses"], rig.host.aggregator.stats.summary()]
    # streaming resumed: the last snapshots are complete again
    assert snaps[-3].complete and snaps[-2].complete


@pytest.mark.parametrize("kind", ["memory", "pty"])
def test_follow_a_gateways_sync(rig_factory, kind):
    rig = rig_factory(kind, gateway_sync_hz=100.0)
    rig.host.bring_up(0.2)
    snaps = rig.stream(0.5)
    check_accounting(rig, snaps)
    assert rig.host.syncs_sent == 0 and rig.host.syncs_seen >= 30
    assert len(snaps) >= 30 and sum(not s.complete for s in snaps) <= 1  # the last may be cut by STOP
    assert all(not np.isnan(s.timestamp) for s in snaps)
