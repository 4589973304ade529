"""The virtual devices, reached as hardware: a real pty opened with pyserial, python-can's own
``virtual`` and ``slcan`` interfaces, the in-memory link. Frames decode with the protocol decoder
and, on CAN, with cantools and the DBC. Every device thread is stopped by its fixture."""

from __future__ import annotations

import json
import os
import time

import can
import cantools
import numpy as np
import pytest
import serial

from protocol.can import decode_can, to_can
from protocol.constants import SampleStatus
from protocol.dbc import DBC_PATH, dbc_frame_id
from protocol.framing import StreamDecoder, encode
from protocol.layout import load_layout
from protocol.messages import (Ack, Announce, Assign, Capability, GetInfo, ImuSample, Info, MsgType, Sample, Snapshot,
                               SnapshotImu, Start, Status, Sync)
from virtual_sheet.chip import ChipModel
from virtual_sheet.devices import CanDevice, MemoryDevice, PtyDevice
from virtual_sheet.sheet import VirtualSheet
from virtual_sheet.slcan import SlcanAdapter, SlcanDevice

TIMEOUT_S = 3.0


@pytest.fixture(scope="module")
def db():
    return cantools.database.load_file(str(DBC_PATH))


def read_until(read, pred, timeout_s=TIMEOUT_S):
    """Call ``read()`` (returns a list of events) until ``pred(all_events)``; returns them."""
    got = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got += read()
        if pred(got):
            return got
    raise AssertionError(f"timed out; got {len(got)} events: {got[:5]}")


def chips_announced(events) -> dict[int, int]:
    """``{uid: node}`` of the chips among the ANNOUNCE + INFO pairs (a gateway node's INFO has
    capability GATEWAY: docs/protocol.md §13.1)."""
    out, last = {}, {}
    for m in events:
        if isinstance(m, Announce):
            last[m.node] = m.uid
        elif isinstance(m, Info) and m.node in last and not m.capabilities & Capability.GATEWAY:
            out[last[m.node]] = m.node
    return out


# ------------------------------------------------------------------ serial

def serial_session(port, sheet, dec):
    """Discover, assign by the layout, start; return the events seen."""
    def read():
        return dec.feed(port.read(65536))
    port.write(encode(GetInfo(0)))
    ev = read_until(read, lambda e: len(chips_announced(e)) >= sheet.n_links)
    nodes = chips_announced(ev)
    layout = sheet.layout
    for uid, node in nodes.items():
        k = layout[uid]
        port.write(encode(Assign(node, new_node=k + 1, link=k, uid_low=uid & 0xFFFFFFFF)))
    port.write(encode(Start(0)))
    acks = read_until(read, lambda e: sum(isinstance(m, Ack) for m in e) >= 2 * sheet.n_links)
    assert {m.node for m in acks if isinstance(m, Ack)} == set(range(1, sheet.n_links + 1))


@pytest.fixture
def pty_device():
    sheet = VirtualSheet("tilted", "3x4", seed=11, noise=0.1)
    with PtyDevice(sheet) as dev:
        yield dev


def test_pty_serial_port_by_path(pty_device):
    dev, sheet = pty_device, pty_device.sheet
    assert os.path.islink(dev.path) and os.readlink(dev.path) == dev.tty
    with serial.Serial(dev.path, baudrate=3_000_000, timeout=0.05) as port:
        dec = StreamDecoder()
        serial_session(port, sheet, dec)
        for c in range(20):
            port.write(encode(Sync(counter=c)))
        ev = read_until(lambda: dec.feed(port.read(65536)),
                        lambda e: sum(isinstance(m, Sample) for m in e) >= 20 * sheet.n_links)
    samples = [m for m in ev if isinstance(m, Sample)]
    assert dec.stats.error_count == 0
    assert {(s.node, s.counter) for s in samples} == {(k + 1, c) for k in range(sheet.n_links) for c in range(20)}
    for c in (0, 19):
        assert sheet.truth(c).shape == (3, 4, 3)


def test_a_packing_6_axis_gateway_on_a_pty_packs_its_faulty_chips_records_too():
    """docs §13.1, §13.2, §16.5 over a real pty: a packing gateway of 6-axis chips, one chip flooding
    STATUS frames beside its records and one wrapped for a death that never comes (both faulty chips,
    both packed like the rest). 30 SYNCs give exactly 30 SNAPSHOT_IMU frames, one per counter, each with
    every link valid; not one IMU_SAMPLE reaches the host; the rest is STATUS."""
    sheet = VirtualSheet("wave", "2x3", seed=11, noise=0.1, sensors="accel+gyro",
                         faults="babble_chip=2,babble_mode=flood,babble_rate=1,dead_chip=4,dead_after_s=1000,seed=3")
    n_sync = 30
    with PtyDevice(sheet, packed=True) as dev, serial.Serial(dev.path, baudrate=3_000_000, timeout=0.05) as port:
        dec = StreamDecoder()
        serial_session(port, sheet, dec)
        for c in range(n_sync):
            port.write(encode(Sync(counter=c)))
        ev = read_until(lambda: dec.feed(port.read(65536)),
                        lambda e: sum(isinstance(m, SnapshotImu) for m in e) >= n_sync)
        end = time.monotonic() + 0.3  # anything the SYNCs still draw arrives in this time
        while time.monotonic() < end:
            ev += dec.feed(port.read(65536))
    snaps = [m for m in ev if isinstance(m, SnapshotImu)]
    assert sorted(m.counter for m in snaps) == list(range(n_sync))  # exactly one frame per SYNC
    assert all(m.count == sheet.n_links and m.first_link == 0 and m.format == 1 for m in snaps)
    st = np.concatenate([m.arrays()[1] for m in snaps]).reshape(n_sync, sheet.n_links)
    assert not (st & SampleStatus.INVALID).any()  # no INVALID record: the faulty chips' links are there too
    assert not [m for m in ev if isinstance(m, (ImuSample, Sample))]
    assert {type(m) for m in ev} == {SnapshotImu, Status}
    flood = [m for m in ev if isinstance(m, Status) and m.node == 3 and m.uptime_s == 0]
    assert 0 < len(flood) <= sheet.fault_stats.babble_frames
    assert dec.stats.error_count == 0


def test_pty_outage_relinks_the_same_path():
    sheet = VirtualSheet("flat", "2x2", seed=1, faults="outage_at_s=0.3,outage_s=0.3")
    with PtyDevice(sheet) as dev:
        first_tty = dev.tty
        port = serial.Serial(dev.path, timeout=0.05)
        with pytest.raises(serial.SerialException):
            deadline = time.monotonic() + TIMEOUT_S
            while time.monotonic() < deadline:
                port.read(1000)
        port.close()
        assert sheet.fault_stats.outages == 1
        deadline = time.monotonic() + TIMEOUT_S
        while not (dev.running and not dev.down and os.path.exists(dev.path)):
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert dev.tty != first_tty or os.readlink(dev.path) == dev.tty
        with serial.Serial(dev.path, timeout=0.05) as port:
            port.write(encode(GetInfo(0)))
            dec = StreamDecoder()
            ev = read_until(lambda: dec.feed(port.read(1000)),
                            lambda e: sum(isinstance(m, Announce) for m in e) >= 4)
        assert len({m.uid for m in ev if isinstance(m, Announce)}) == 4


def test_memory_device_packed_snapshots_and_own_sync(tmp_path):
    sheet = VirtualSheet("gaussian", "4x4", seed=2, noise=0.0)
    with MemoryDevice(sheet, packed=True, sync_rate_hz=200) as dev:
        dec = StreamDecoder()
        serial_session(dev.port, sheet, dec)
        ev = read_until(lambda: dec.feed(dev.port.read(65536)),
                        lambda e: sum(isinstance(m, Snapshot) for m in e) >= 10)
    syncs = [m for m in ev if isinstance(m, Sync)]
    snaps = [m for m in ev if isinstance(m, Snapshot)]
    assert syncs and all(s.count == sheet.n_links and s.first_link == 0 for s in snaps)
    last = snaps[-1]
    assert last.counter in {s.counter for s in syncs}
    expect, _st = sheet.counts_at(sheet.sync_times[last.counter])
    np.testing.assert_array_equal(last.counts, expect)
    assert not last.status.any()
    path = sheet.write_layout(tmp_path / "layout.csv")
    assert dict(load_layout(path).links) == sheet.layout
    assert dict(load_layout(sheet.write_layout(tmp_path / "layout.json")).links) == sheet.layout


def test_chip_factory_hook():
    made = []

    class Counted(ChipModel):
        def __init__(self, *a, **kw):
            super().__init__(*a, **kw)
            made.append(self)

    sheet = VirtualSheet("flat", "3x3", chip_factory=Counted)
    assert len(made) == sheet.n_links and sheet.chips == made


# ------------------------------------------------------------------ CAN: python-can virtual

def can_session(buses, sheet, *, timeout_s=TIMEOUT_S):
    """Discover and assign over several python-can buses; return every message received."""
    received = []

    def read():
        out = []
        for b in buses:
            m = b.recv(0.01)
            while m is not None:
                out.append(m)
                m = b.recv(0)
        received.extend(out)
        return [decode_can(m.arbitration_id, m.data, is_fd=m.is_fd) for m in out]

    def send(bus, msg):
        f = to_can(msg)
        bus.send(can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True, is_fd=f.is_fd))

    for b in buses:
        send(b, GetInfo(0))
    ev = read_until(read, lambda e: len(chips_announced(e)) >= sheet.n_links)
    layout = sheet.layout
    blocks = sheet.split(len(buses))
    for uid, node in chips_announced(ev).items():
        k = layout[uid]
        bus = buses[next(i for i, blk in enumerate(blocks) if k in blk)]
        send(bus, Assign(node, new_node=k + 1, link=k, uid_low=uid & 0xFFFFFFFF))
    for b in buses:
        send(b, Start(0))
    read_until(read, lambda e: sum(isinstance(m, Ack) for m in e) >= 2 * sheet.n_links)
    return read, send, received


@pytest.mark.parametrize("fd", [False, True])
def test_python_can_virtual_two_buses_decode_with_cantools(fd, db):
    sheet = VirtualSheet("tilted", "3x4", seed=5, transport="can", fd=fd)
    with CanDevice(sheet, n_buses=2, channels=[f"t-{fd}-a", f"t-{fd}-b"], packed=fd) as dev:
        buses = [can.Bus(interface="virtual", channel=ch, fd=fd) for ch in dev.channels]
        try:
            read, send, received = can_session(buses, sheet)
            for c in range(5):
                for b in buses:
                    send(b, Sync(counter=c))
            want = (lambda e: sum(isinstance(m, Snapshot) for m in e) >= 5 * 2) if fd else \
                (lambda e: sum(isinstance(m, Sample) for m in e) >= 5 * sheet.n_links)
            read_until(read, want)
        finally:
            for b in buses:
                b.shutdown()
    for m in received:
        ours = decode_can(m.arbitration_id, m.data, is_fd=m.is_fd)
        assert not hasattr(ours, "reason"), ours
        dbm = db.get_message_by_frame_id(dbc_frame_id(m.arbitration_id))
        assert dbm.name == MsgType(ours.TYPE).name
        sig = dbm.decode(bytes(m.data), decode_choices=False, allow_truncated=True)
        if isinstance(ours, Sample):
            assert (sig["counter"], sig["x"], sig["y"], sig["z"], sig["status"]) == (
                ours.counter, ours.x, ours.y, ours.z, ours.status)
        elif isinstance(ours, Snapshot):
            assert m.is_fd and sig["count"] == ours.count
            assert [sig[f"z_{k}"] for k in range(ours.count)] == ours.counts[:, 2].tolist()
        elif isinstance(ours, Announce):
            assert sig["uid"] == ours.uid


def test_a_can_device_takes_a_sync_at_its_time_on_the_bus_not_when_its_thread_read_it():
    """python-can stamps every frame with its time on the bus (``virtual``: when it was sent;
    ``udp_multicast``: the kernel's receive time). A device thread that reads late — held here by a
    call until after the SYNC was sent, as a loaded machine holds it — takes the SYNC's time on the
    bus as its arrival: the instant its chips sample and `VirtualSheet.truth_time` says."""
    import threading

    sheet = VirtualSheet("tilted", "2x2", seed=5, transport="can")
    with CanDevice(sheet, channels=["t-bus-time"]) as dev:
        bus = can.Bus(interface="virtual", channel="t-bus-time")
        try:
            held, sent, released = threading.Event(), threading.Event(), []

            def hold(now_s):
                held.set()
                sent.wait(5.0)
                time.sleep(0.05)
                released.append(dev.now())

            th = threading.Thread(target=dev.call, args=(hold,))
            th.start()
            assert held.wait(5.0)
            f = to_can(Sync(counter=7))
            bus.send(can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True))
            after_send = dev.now()
            sent.set()
            th.join()
            deadline = time.monotonic() + 5.0
            while 7 not in sheet.sync_times and time.monotonic() < deadline:
                time.sleep(0.01)
        finally:
            bus.shutdown()
    # the device read the SYNC only after the call released it; its chips sampled when it was sent
    assert 7 in sheet.sync_times and released
    assert sheet.sync_times[7] <= after_send < released[0], (sheet.sync_times[7], after_send, released[0])


def test_a_frame_stamped_before_what_the_chips_were_given_is_taken_at_that_time():
    """A frame's time on the bus can be older than the last time the device thread gave its chips
    (it polled them, or ran a call, after the frame was sent and before reading it): the frame is
    taken then, never before — the chips' clock never goes back (a SYNC taken 0.5 s in the past
    here would make the chips sample before the instant they were already at)."""
    sheet = VirtualSheet("tilted", "2x2", seed=5, transport="can")
    f = to_can(Sync(counter=9))
    with CanDevice(sheet, channels=["t-bus-floor"]) as dev:
        def take_old_frame(now_s):
            msg = can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True,
                              timestamp=time.time() - 0.5)
            dev._on_msg(0, msg)
            return now_s
        given = dev.call(take_old_frame)
    assert 9 in sheet.sync_times
    assert sheet.sync_times[9] >= given, (sheet.sync_times[9], given)


# ------------------------------------------------------------------ SLCAN on a pty

def test_slcan_adapter_with_python_can_slcan_interface():
    sheet = VirtualSheet("tilted", "3x3", seed=8, transport="can")
    with SlcanDevice(sheet) as dev:
        bus = can.Bus(interface="slcan", channel=dev.path, bitrate=1_000_000, sleep_after_open=0)
        try:
            assert bus.get_version(1.0) == (10, 13)
            assert bus.get_serial_number(1.0) == "CS01"
            read, send, received = can_session([bus], sheet)
            for c in range(5):
                send(bus, Sync(counter=c))
            ev = read_until(read, lambda e: sum(isinstance(m, Sample) for m in e) >= 5 * sheet.n_links)
        finally:
            bus.shutdown()
    assert {(m.node, m.counter) for m in ev if isinstance(m, Sample)} == {
        (k + 1, c) for k in range(sheet.n_links) for c in range(5)}
    assert dev.adapters[0].bad_commands <= 2  # python-can's repeated O on open


def test_slcan_codec_lines():
    sent = []
    a = SlcanAdapter(lambda f, r, e: sent.append((f, r, e)), fd=True)
    assert a.feed(b"T0101000020000\r") == b"\a"  # closed: refused
    assert a.feed(b"S8\rO\r") == b"\r\r"
    assert a.feed(b"S6\r") == b"\a"  # bit rate only while closed
    assert a.feed(b"T0101000023412\r") == b"Z\r"
    assert sent[-1][0] == to_can(Sync(counter=0x1234)) and sent[-1][2]
    assert a.feed(b"D14100001" + b"9" + b"00" * 12 + b"\r") == b"Z\r" and len(sent[-1][0].data) == 12
    assert a.feed(b"T01010000") == b"" and a.feed(b"23412\r") == b"Z\r"  # split across reads
    assert a.feed(b"Tzz\r") == b"\a"
    line = a.frames_to_host([to_can(Info(3, 0, 1, 0))], 0.0)
    assert line.startswith(b"T14210003") and line.endswith(b"\r")
    a.feed(b"Z1\r")
    assert len(a.frames_to_host([to_can(Sync(counter=1))], 1.5)) == len(b"T010100002") + 4 + 4 + 1
    assert a.feed(b"F\r") == b"F00\r"


def test_slcan_batch_of_samples_is_formatted_as_the_per_frame_loop_does():
    rng = np.random.Generator(np.random.MT19937(4))
    samples = [to_can(Sample(int(rng.integers(1, 0xFFFF)), int(rng.integers(0, 1 << 16)),
                             *(int(v) for v in rng.integers(-2048, 2048, 3)), int(rng.integers(0, 16))))
               for _ in range(300)]
    a = SlcanAdapter(lambda *_: None)
    a.is_open = True
    one_by_one = b"".join(a.frames_to_host([f], 0.0) for f in samples)  # below the batch size: the loop
    assert a.frames_to_host(samples, 0.0) == one_by_one
    # a batch the fast path does not take falls back to the loop, in order
    mixed = samples[:20] + [to_can(Info(3, 0, 1, 0))] + samples[20:40]
    assert a.frames_to_host(mixed, 0.0) == b"".join(a.frames_to_host([f], 0.0) for f in mixed)
    sync = [to_can(Sync(counter=k)) for k in range(6)]  # 2 data bytes: 8 of them sum to 16, not 7 each
    uneven = samples[:10] + sync + samples[10:12]
    assert a.frames_to_host(uneven, 0.0) == b"".join(a.frames_to_host([f], 0.0) for f in uneven)


# ------------------------------------------------------------------ CLI

def test_cli_prints_the_port_and_runs_for_a_duration(capsys, tmp_path):
    from host.cli import main
    layout = tmp_path / "sheet.csv"
    rc = main(["virtual", "--lattice", "3x3", "--transport", "pty", "--rate", "20", "--duration", "1.1",
               "--layout-out", str(layout), "--faults", "drop_frame=0.5,seed=1"])
    out = capsys.readouterr().out
    assert rc == 0 and "connect to: serial port" in out and "sync 2" in out and "frames_dropped" in out
    assert len(load_layout(layout).links) == 12


def test_cli_firmware_c_fails_clearly_when_missing(capsys):
    pytest.importorskip("firmware_ref")
    try:
        import firmware_ref.chip  # noqa: F401
        pytest.skip("the C firmware is available")
    except Exception:
        pass
    from host.cli import main
    assert main(["virtual", "--lattice", "2x2", "--firmware", "c", "--duration", "0.1"]) == 2
    assert "firmware_ref.chip.CFirmwareChip" in capsys.readouterr().err


def test_a_pty_nobody_reads_drops_whole_frames_counted_and_stays_bounded():
    """A host that stops reading: the gateway's buffer is bounded, what does not fit is dropped
    whole and counted, and what the host reads later is still whole frames (no framing error)."""
    import serial

    from protocol.framing import DecodeError, StreamDecoder
    from virtual_sheet.devices import PtyDevice
    from virtual_sheet.sheet import VirtualSheet
    sheet = VirtualSheet("flat", "4x4", seed=2)
    dev = PtyDevice(sheet, sync_rate_hz=400.0)
    dev.max_pending = 4096
    with dev:
        dev.commission()
        end = time.monotonic() + 60
        while dev.tx_overflow_frames == 0 and time.monotonic() < end:
            time.sleep(0.05)
        assert dev.tx_overflow_frames > 0 and dev.tx_overflow_bytes > 0
        assert dev.call(lambda now: len(dev._pending)) <= dev.max_pending
        port = serial.Serial(dev.path, timeout=0.2)
        try:
            dec = StreamDecoder()
            data = port.read(8192)
        finally:
            port.close()
    events = dec.feed(data)
    assert data and not any(isinstance(e, DecodeError) for e in events[1:])  # the first may be cut by open


def test_two_serial_gateways_share_the_leaders_sync_line():
    """Gateway 0 generates SYNC; gateway 1 takes every SYNC over the SYNC line at the same instant:
    each stream carries every SYNC before the SNAPSHOT that answers it, each SNAPSHOT covers only its
    gateway's links, and both halves hold the readings of the same SYNC time."""
    from virtual_sheet.gateway import Gateway
    sheet = VirtualSheet("gaussian", "4x4", seed=3, noise=0.0)  # 24 links
    lead = Gateway(sheet, range(0, 12), packed=True, sync_rate_hz=100.0, stream=0)
    follow = Gateway(sheet, range(12, 24), packed=True, stream=1)
    lead.followers = [follow]
    for gw in (lead, follow):
        gw.power_on(0.0)
        gw.commission(0.0)
    streams = {0: [], 1: []}
    decs = {0: StreamDecoder(), 1: StreamDecoder()}
    for i in range(1, 101):  # 0.1 s on a simulated clock
        t = i * 1e-3
        lead.poll(t)
        follow.poll(t)
        for b, gw in ((0, lead), (1, follow)):
            streams[b] += decs[b].feed(gw.pop_bytes(t))
    for b, first in ((0, 0), (1, 12)):
        syncs = [m.counter for m in streams[b] if isinstance(m, Sync)]
        snaps = [m for m in streams[b] if isinstance(m, Snapshot)]
        assert syncs == list(range(len(syncs))) and len(syncs) >= 9, syncs  # 100 Hz for 0.1 s
        assert [s.counter for s in snaps] == syncs
        assert all(s.first_link == first and s.count == 12 for s in snaps)
        for s in snaps:  # the SYNC precedes its SNAPSHOT in the stream
            kinds = [(type(m), m.counter) for m in streams[b] if isinstance(m, (Sync, Snapshot))]
            assert kinds.index((Sync, s.counter)) < kinds.index((Snapshot, s.counter))
            expect, _st = sheet.counts_at(sheet.sync_times[s.counter])
            np.testing.assert_array_equal(s.counts, expect[first:first + 12])
    assert lead.stats.syncs_generated == len(syncs) and follow.stats.syncs_generated == 0
    assert follow.stats.syncs == lead.stats.syncs


def test_a_symlink_path_is_taken_only_when_it_is_free_or_a_stale_one_of_ours(tmp_path, monkeypatch):
    """`claim_symlink`: a folder is never taken; a file or a foreign symlink only when the caller says
    so (it is then removed); a symlink a device published is taken over only once its process is
    gone (a sheet killed with SIGKILL), never while that process runs."""
    import subprocess
    import sys

    from virtual_sheet import pty as devices  # the symlink records live with the ptys
    from virtual_sheet.devices import claim_symlink

    monkeypatch.setattr(devices, "SYMLINK_RECORDS", str(tmp_path / "records"))
    folder, mine, foreign = tmp_path / "folder", tmp_path / "notes.txt", tmp_path / "foreign"
    folder.mkdir()
    mine.write_text("mine")
    os.symlink("/dev/null", foreign)
    claim_symlink(tmp_path / "free")  # nothing there: fine
    for path, what in ((folder, "is a folder"), (mine, "is a file"), (foreign, "no capsheet sheet published")):
        with pytest.raises(FileExistsError, match=what):
            claim_symlink(path)
    with pytest.raises(FileExistsError, match="is a folder"):
        claim_symlink(folder, replace=True)
    assert mine.read_text() == "mine" and os.readlink(foreign) == "/dev/null"
    claim_symlink(mine, replace=True)
    assert not mine.exists()
    # a published one: recorded with its target and process
    link = tmp_path / "port"
    os.symlink("/dev/pts/999", link)
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    devices._write_record(str(link), "/dev/pts/999")
    rec = devices._read_record(str(link))
    for pid, ok in ((int(gone.stdout), True), (1, False)):  # its process gone / still running (init)
        rec["pid"] = pid
        with open(devices._record_file(str(link)), "w") as fh:
            json.dump(rec, fh)
        if ok:
            claim_symlink(link)  # stale and ours: the device replaces it when it starts
        else:
            with pytest.raises(FileExistsError, match="port of a running virtual sheet"):
                claim_symlink(link)
    os.unlink(link)
    os.symlink("/dev/pts/998", link)  # re-pointed by someone else since: not ours any more
    with pytest.raises(FileExistsError, match="no capsheet sheet published"):
        claim_symlink(link)


def test_a_device_publishes_replaces_its_stale_symlink_and_removes_only_its_own(tmp_path, monkeypatch):
    from virtual_sheet import pty as devices  # the symlink records live with the ptys

    monkeypatch.setattr(devices, "SYMLINK_RECORDS", str(tmp_path / "records"))
    link = tmp_path / "port"
    sheet = VirtualSheet("flat", "2x2")
    dev = PtyDevice(sheet, symlink_path=link)
    dev.start()
    try:
        assert os.readlink(link) == dev.tty and devices._read_record(str(link))["target"] == dev.tty
    finally:
        os.unlink(link)
        os.symlink("/dev/null", link)  # replaced under it: at stop the device leaves it alone
        dev.stop()
    assert os.readlink(link) == "/dev/null"


def test_a_pty_group_stamps_every_port_when_read_before_any_port_is_handled():
    """The host writes a SYNC to every gateway's pty at once: port 1's bytes arrived when they were
    read, not after port 0's answers were made (its chips sample then, docs/motion.md). The clock
    is simulated: handling port 0 takes it 5 s forward; port 1 keeps the stamp of its read."""
    from virtual_sheet.devices import PtyGroup

    group = PtyGroup("t", 2)
    group.open()
    slaves = []
    try:
        for p in group:
            slaves.append(os.open(p.path, os.O_RDWR | os.O_NOCTTY))
        for b, fd in enumerate(slaves):
            os.write(fd, bytes([0x10 + b, 0x00]))
        clock = {"t": 0.0}

        def tick():
            clock["t"] += 1.0
            return clock["t"]

        got = []

        def on_data(b, data, t):
            got.append((b, bytes(data), t))
            clock["t"] += 5.0  # the answers of this port take time

        import select
        masters = [p.master for p in group]
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:  # both ports readable before the one serve
            if len(select.select(masters, [], [], 0.05)[0]) == 2:
                break
        group.serve(0.2, on_data, tick)
        assert [(b, d) for b, d, _ in got] == [(0, b"\x10\x00"), (1, b"\x11\x00")] or \
            [(b, d) for b, d, _ in got] == [(1, b"\x11\x00"), (0, b"\x10\x00")]
        # each stamped at its read (1 s, 2 s), neither after a port's handling (which adds 5 s)
        assert sorted(t for _, _, t in got) == [1.0, 2.0]
    finally:
        for fd in slaves:
            os.close(fd)
        group.cleanup()
