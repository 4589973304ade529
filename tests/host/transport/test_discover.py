"""What a probe makes of what it hears (host/transport/discover.py's `ProbeCollector`, sans-I/O,
simulated time), and `probe_port` on real ptys: a virtual sheet's chips and gateway nodes, a port
where nothing answers, a port another session holds; `probe_ports` (the ports at once, in the
listing's order) with a stand-in probe."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import pytest

from host.transport.discover import PortEntry, ProbeCollector, ProbeResult, QUIET_S, probe_port, probe_ports
from protocol import encode
from protocol.framing import DecodeError, ErrorReason
from protocol.messages import (Announce, Capability, GatewayFlag, GatewayInfo, GetInfo, Info, SampleFormat, Sync)


def test_chips_and_a_gateway_from_their_answers():
    c = ProbeCollector()
    gw = 0x6A7E000000000001
    c.feed([Announce(0x8001, uid=0x10), Info(0x8001, fw_major=1, fw_minor=2, fw_patch=3),
            Announce(0x8002, uid=gw), Info(0x8002, capabilities=Capability.GATEWAY | Capability.SNAPSHOT),
            GatewayInfo(0x8002, flags=GatewayFlag.PACKING | GatewayFlag.SYNC_SOURCE,
                        sample_format=SampleFormat.IMU6, first_link=56, link_count=56, sync_rate_hz=145),
            GatewayInfo(0x8002, flags=GatewayFlag.PACKING, first_link=56, link_count=56)], now=1.0)  # a repeat
    # a second chip answering from the node id the first one used: its own uid, its own INFO
    c.feed([Announce(0x8001, uid=0x20), Info(0x8001, fw_major=1, fw_minor=2, fw_patch=4),
            Sync(counter=7), Sync(counter=8), DecodeError(ErrorReason.BAD_CRC, "bad CRC")], now=1.1)
    r = c.result(elapsed_s=1.5, bytes_in=999)
    assert r.status == "answered" and r.chips == 2
    assert r.chip_uids == ["0x0000000000000010", "0x0000000000000020"]
    assert r.firmware == ["1.2.3", "1.2.4"] and r.syncs == 2 and r.undecodable == 1 and r.bytes_in == 999
    assert r.gateways == [{"uid": "0x6A7E000000000001", "flags": ["PACKING", "SYNC_SOURCE"], "sample_format": "IMU6",
                           "links": "56-111", "sync_rate_hz": 145}]
    assert r.formats == ["IMU6"]
    line = r.line()
    assert "2 chips (ids 0x0000000000000010 .. 0x0000000000000020)" in line and "links 56-111" in line
    assert "SYNC source at 145 Hz" in line and "\n" not in line


def test_quiet_only_after_something_answered_and_then_nothing_new():
    c = ProbeCollector()
    assert not c.quiet(100.0)  # nothing answered: never quiet (the probe waits its budget)
    c.feed([Announce(0x8001, uid=1)], now=0.0)
    c.feed([Announce(0x8001, uid=1), Sync(counter=1)], now=QUIET_S * 0.9)  # nothing new
    assert not c.quiet(QUIET_S * 0.99) and c.quiet(QUIET_S)
    c.feed([Announce(0x8003, uid=2)], now=QUIET_S)  # something new: the window starts again
    assert not c.quiet(QUIET_S * 1.5)


def test_frames_without_an_answer_and_nothing_at_all():
    c = ProbeCollector()
    c.feed([Sync(counter=1)], now=0.1)
    r = c.result(elapsed_s=2.0, bytes_in=40)
    assert r.status == "traffic" and "no node answered" in r.detail and r.chips == 0
    r = ProbeCollector().result(elapsed_s=2.0, bytes_in=0)
    assert r.status == "silent" and r.detail == "nothing answered in 2.0 s (0 bytes)"


def test_the_probe_of_a_silent_port_writes_get_info_and_nothing_else():
    """A pty where nothing answers: the probe writes GET_INFO and nothing else (no ASSIGN, CONFIG,
    START, STOP, RESET); its result says nothing answered."""
    m, s = os.openpty()
    try:
        r = probe_port(PortEntry("serial", os.ttyname(s)), budget_s=0.6)
        os.set_blocking(m, False)
        written = b""
        try:
            while True:
                written += os.read(m, 65536)
        except BlockingIOError:
            pass
        assert r.status == "silent" and r.chips == 0, r
        from protocol.framing import StreamDecoder
        sent = StreamDecoder().feed(written)
        assert sent and all(isinstance(x, GetInfo) for x in sent), sent
    finally:
        os.close(m)
        os.close(s)


def test_a_port_another_session_holds_is_not_probed():
    m, s = os.openpty()
    holder = subprocess.Popen([sys.executable, "-c", "import serial, sys, time; p = serial.serial_for_url(sys.argv[1], "
                               "exclusive=True); print('held', flush=True); time.sleep(60)", os.ttyname(s)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        r = probe_port(PortEntry("serial", os.ttyname(s)), budget_s=0.5)
        assert r.status == "in_use" and f"process {holder.pid}" in r.detail and "not probed" in r.detail
        os.set_blocking(m, False)
        with pytest.raises(BlockingIOError):
            os.read(m, 100)  # not a byte written
    finally:
        holder.kill()
        holder.wait()
        os.close(m)
        os.close(s)


def test_probe_of_a_virtual_sheet_finds_its_chips():
    from virtual_sheet.devices import PtyDevice
    from virtual_sheet.sheet import VirtualSheet
    sheet = VirtualSheet("flat", "3x3", seed=3)
    with PtyDevice(sheet) as dev:
        r = probe_port(PortEntry("serial", dev.path), budget_s=3.0)
    uids = sorted(f"0x{c.uid:016X}" for c in sheet.chips)
    assert r.status == "answered" and r.chips == 12 and r.chip_uids == uids, r
    assert r.baud == 3_000_000 and r.protocol == ["1"] and not r.gateways


def _answered(entry, budget_s):
    return ProbeResult("answered", chips=1, chip_uids=[entry.name])


def test_probe_ports_asks_the_ports_at_once():
    """Two ports' probes meet at a barrier both must reach: probed one after another, the first
    waits there alone until the barrier's timeout breaks it (both then "error")."""
    barrier = threading.Barrier(2, timeout=10)

    def probe(entry, budget_s):
        barrier.wait()
        return _answered(entry, budget_s)

    got = list(probe_ports([PortEntry("serial", "/dev/one"), PortEntry("serial", "/dev/two")], 5.0, probe=probe))
    assert [(e.name, r.status, r.chip_uids) for e, r in got] == [("/dev/one", "answered", ["/dev/one"]),
                                                                ("/dev/two", "answered", ["/dev/two"])]


def test_probe_ports_keeps_the_listing_order_and_a_failure_is_its_own_result():
    """The last port finishes first and the second one's probe raises: the results come in the
    listing's order, the failure as that port's "error", the others as their probes said."""
    last_done = threading.Event()

    def probe(entry, budget_s):
        if entry.name == "/dev/c":
            last_done.set()
            return _answered(entry, budget_s)
        assert last_done.wait(10), "the ports were not probed at once"
        if entry.name == "/dev/b":
            raise OSError("the adapter went away")
        return _answered(entry, budget_s)

    got = list(probe_ports([PortEntry("serial", f"/dev/{n}") for n in "abc"], 5.0, probe=probe))
    assert [e.name for e, _ in got] == ["/dev/a", "/dev/b", "/dev/c"]
    assert [r.status for _, r in got] == ["answered", "error", "answered"]
    assert got[1][1].detail == "probe failed: the adapter went away"


def test_probe_ports_probes_the_paths_of_one_device_one_after_another(tmp_path):
    """A probe holds its port exclusively: a path, a symlink to it and ``slcan:`` on the symlink are
    one device, probed in turn (at once, two of them would find it in use); another device beside
    them is probed at the same time."""
    dev, other = tmp_path / "tty0", tmp_path / "tty1"
    dev.touch()
    other.touch()
    (tmp_path / "link").symlink_to(dev)
    entries = [PortEntry("serial", str(dev)), PortEntry("serial", str(tmp_path / "link")),
               PortEntry("can", f"slcan:{tmp_path / 'link'}"), PortEntry("serial", str(other))]
    lock = threading.Lock()
    busy: dict = {}
    overlapped: list = []
    other_started = threading.Event()

    def probe(entry, budget_s):
        key = os.path.realpath(entry.name.removeprefix("slcan:"))
        with lock:
            if busy.get(key):
                overlapped.append(entry.name)
            busy[key] = busy.get(key, 0) + 1
        if entry.name == str(other):
            other_started.set()
        else:
            assert other_started.wait(10), "the other device waited for this one"
            time.sleep(0.05)  # long enough for a second probe of the same device to arrive if one were started
        with lock:
            busy[key] -= 1
        return _answered(entry, budget_s)

    got = list(probe_ports(entries, 5.0, probe=probe))
    assert [r.status for _, r in got] == ["answered"] * 4 and overlapped == []
