"""`Transport.begin_capture` (pycyphal's capture): every transport hands its subscribers what it
received and sent, raw and decoded, in wire order; raw sends (`SerialTransport.send_bytes`,
`CanTransport.send_frame`) are captured and known to the echo filter. On real parts: the in-memory
link, pyserial's ``loop://``, python-can's ``virtual`` bus (with ``receive_own_messages`` standing
for a bus that hands a sender its frames back, as ``udp_multicast`` does), SLCAN on a real pty."""

from __future__ import annotations

import itertools
import logging
import os
import time

import pytest

from host.transport.ports import CanTransport, Capture, MemoryTransport, RawFrame, SerialTransport
from protocol import DecodeError, SampleBatch, encode, to_can
from protocol.can import FrameBlock, make_id
from protocol.messages import Ack, MsgType, Sample, Status, Sync
from tests.host.transport.test_slcan import pty_pair  # noqa: F401 - a fixture: a raw pty, its master fd and slave path
from virtual_sheet.memport import memory_link

can = pytest.importorskip("can")
_chan = itertools.count()


def receive_all(t, until, timeout_s: float = 3.0) -> list:
    out: list = []
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not until(out):
        out += t.recv(0.05)
    return out


def flat(events) -> list:
    return [m for ev in events for m in (ev.messages() if isinstance(ev, SampleBatch) else [ev])]


def test_serial_capture_holds_every_byte_both_ways_and_the_events_recv_returned():
    host_end, dev_end = memory_link("cap")
    t = MemoryTransport(host_end)
    caps: list[Capture] = []
    t.begin_capture(caps.append)
    try:
        t.send(Sync(counter=7))
        t.send_bytes(b"\x01\x02\x00")  # raw: not a frame
        wire = b"".join(encode(m) for m in [Sample(3, 7, 1, 2, 3, 0), Ack(3, MsgType.START, 0)])
        wire += b"\x05\x05\x00"  # damage
        half = len(wire) // 2 + 3
        dev_end.write(wire[:half])
        got = receive_all(t, lambda ev: ev)
        dev_end.write(wire[half:])
        got += receive_all(t, lambda ev: any(isinstance(e, DecodeError) for e in ev))
    finally:
        t.close()
    tx = [c for c in caps if c.direction == "tx"]
    rx = [c for c in caps if c.direction == "rx"]
    assert [(c.kind, c.raw, c.events) for c in tx] == [("serial", encode(Sync(counter=7)), (Sync(counter=7),)),
                                                        ("serial", b"\x01\x02\x00", ())]
    assert dev_end.read(100) == encode(Sync(counter=7)) + b"\x01\x02\x00"  # what the capture says went out
    assert b"".join(c.raw for c in rx) == wire  # every byte read, in order, however the reads cut it
    assert [e for c in rx for e in c.events] == got  # the very events recv returned
    assert all(c.transport is t and c.timestamp > 0 and c.wall_time > 1e9 for c in caps)


def test_a_capture_handler_that_raises_is_counted_and_does_not_stop_the_traffic(caplog):
    t = SerialTransport("loop://")
    seen: list = []

    def broken(cap):
        raise RuntimeError("subscriber bug")
    t.begin_capture(broken)
    t.begin_capture(seen.append)
    try:
        with caplog.at_level(logging.ERROR, logger="capsheet.host.transport"):
            for c in range(3):
                t.send(Sync(counter=c))
            got = receive_all(t, lambda ev: len(ev) >= 3)
    finally:
        t.close()
    assert got == [Sync(counter=c) for c in range(3)]
    assert t.stats.capture_errors == len(seen) >= 4  # 3 sends and at least one receive, each failed once
    assert sum("subscriber bug" in r.exc_text for r in caplog.records if r.exc_text) == 1  # logged once


def test_end_capture_stops_it():
    t = SerialTransport("loop://")
    seen: list = []
    t.begin_capture(seen.append)
    t.send(Sync(counter=1))
    t.end_capture(seen.append)
    t.send(Sync(counter=2))
    t.close()
    assert [c.events for c in seen] == [(Sync(counter=1),)] and not t.capturing
    with pytest.raises(TypeError, match="capture handler"):
        t.begin_capture(None)


def test_can_capture_both_ways_and_a_raw_frame_echo_is_dropped_not_blamed():
    """A bus that hands the sender its frames back (``receive_own_messages``; udp_multicast does it
    always): a frame sent raw with `send_frame` is dropped as an echo like a message sent with
    `send`, listed in ``echoes`` and left out of `Capture.frames`; the chip's frames are not."""
    channel = f"capture-{os.getpid()}-{next(_chan)}"
    t = CanTransport(f"virtual:{channel}", receive_own_messages=True)
    chip = can.Bus(interface="virtual", channel=channel)
    caps: list[Capture] = []
    t.begin_capture(caps.append)
    try:
        t.send(Sync(counter=5))
        raw_id = make_id(MsgType.STATUS, 9, priority=4)  # a chip-to-host type, the wrong priority
        t.send_frame(raw_id, bytes(8))
        t.send_frame(0x123, b"\x01\x02", extended=False)
        for msg in (Sample(9, 5, 1, 2, 3, 0), Status(9, 3, 0, 0, 0, 1)):
            f = to_can(msg)
            chip.send(can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True))
        events = receive_all(t, lambda ev: len(flat(ev)) >= 2)
        assert receive_all(t, lambda ev: False, timeout_s=0.2) == []  # nothing else: the echoes were dropped
    finally:
        t.close()
        chip.shutdown()
    assert flat(events) == [Sample(9, 5, 1, 2, 3, 0), Status(9, 3, 0, 0, 0, 1)]
    assert t.echo.echoes == 3 and not t.stats.errors  # the standard frame's echo is not damage either
    tx = [c for c in caps if c.direction == "tx"]
    assert [(c.raw[0].arbitration_id, c.events) for c in tx] == [
        (to_can(Sync(counter=5)).arbitration_id, (Sync(counter=5),)), (raw_id, ()), (0x123, ())]
    assert not tx[2].raw[0].is_extended_id and all(not c.raw[0].is_rx for c in tx)
    rx = [c for c in caps if c.direction == "rx"]
    echoes = [e for c in rx for e in c.echoes]
    assert sorted(echoes) == sorted([(to_can(Sync(counter=5)).arbitration_id, to_can(Sync(counter=5)).data),
                                     (raw_id, bytes(8)), (0x123, b"\x01\x02")])
    assert sum(len(c.raw) for c in rx) == 5  # the wire: three echoes and the chip's two frames
    kept = [f.arbitration_id for c in rx for f in c.frames()]
    assert kept == [to_can(Sample(9, 5, 1, 2, 3, 0)).arbitration_id, to_can(Status(9, 3, 0, 0, 0, 1)).arbitration_id]


def test_slcan_capture_expands_frame_blocks_into_the_frames_of_the_wire(pty_pair):
    """The SLCAN bus hands runs of SAMPLE lines over as `FrameBlock` arrays; a capture subscriber
    gets them row by row (`Capture.frames`) as the frames python-can would have made."""
    master, path = pty_pair
    msgs = [Sample(k + 1, 40, k, -k, 1024, 0) for k in range(30)] + [Ack(2, MsgType.START, 0)]
    msgs += [Sample(k + 1, 41, 1, 1, 1, 0) for k in range(10)]
    lines = b"".join(f"T{to_can(m).arbitration_id:08X}{len(to_can(m).data)}{to_can(m).data.hex().upper()}\r".encode()
                     for m in msgs)
    t = CanTransport(f"slcan:{path}", bitrate=1_000_000, sleep_after_open=0, drain_quiet_s=0.02)
    caps: list[Capture] = []
    t.begin_capture(caps.append)
    try:
        time.sleep(0.1)
        os.write(master, lines)
        events = receive_all(t, lambda ev: len(flat(ev)) >= len(msgs))
    finally:
        t.close()
    assert flat(events) == msgs
    rx = [c for c in caps if c.direction == "rx"]
    assert any(isinstance(f, FrameBlock) for c in rx for f in c.raw)  # the fast path was taken
    frames = [f for c in rx for f in c.frames()]
    assert [(f.arbitration_id, bytes(f.data)) for f in frames] == [(to_can(m).arbitration_id, to_can(m).data)
                                                                   for m in msgs]
    assert all(isinstance(f, (RawFrame, can.Message)) and f.is_extended_id and not f.is_fd for f in frames)
