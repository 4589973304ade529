"""Host transports on real parts: pyserial on loop:// and on real ptys, python-can's virtual and slcan
interfaces (slcan on a pty, with a minimal Lawicel peer), the in-memory link; errors by stage;
reconnection."""

from __future__ import annotations

import os
import threading
import time
import tty

import numpy as np
import pytest

from host.transport.ports import (CanTransport, MemoryTransport, SerialTransport, TransportCapabilities,
                            TransportError, TransportInitError, TransportOperationError, open_transport,
                            READ_TIMEOUTS_S, parse_can_spec, read_timeout_for)
from protocol import DecodeError, SampleBatch, Snapshot, encode, to_can
from protocol.messages import Ack, Announce, MsgType, Sample, Sync
from virtual_sheet.memport import memory_link

can = pytest.importorskip("can")


def collect(t, n_samples=0, n_msgs=0, timeout_s=3.0):
    """Receive until ``n_samples`` samples and ``n_msgs`` other events arrived (or timeout)."""
    samples, msgs = [], []
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and (sum(len(b) for b in samples) < n_samples or len(msgs) < n_msgs):
        for ev in t.recv(0.05):
            (samples if isinstance(ev, SampleBatch) else msgs).append(ev)
    return samples, msgs


def samples_wire(n, counter=0):
    return b"".join(encode(Sample(k + 1, counter, k, -k, 1024, 0)) for k in range(n))


# --------------------------------------------------------------------------------------------- serial

def test_loop_url_round_trip_and_capabilities():
    t = open_transport("serial", "loop://", baudrate=115200)
    try:
        caps = t.capabilities
        assert caps == TransportCapabilities("serial", 1018, False, 115200, None, "loop://")
        import dataclasses
        with pytest.raises(dataclasses.FrozenInstanceError):
            caps.mtu = 8  # frozen
        t.send(Sync(counter=0xFFFF))
        t.send(Sample(3, 0xFFFF, 1, 2, 3, 0))
        samples, msgs = collect(t, 1, 1)
        assert msgs == [Sync(counter=0xFFFF)]
        assert samples[0].messages() == [Sample(3, 0xFFFF, 1, 2, 3, 0)]
        assert t.stats.frames_out == 2 and t.stats.frames_in == 2
    finally:
        t.close()
    with pytest.raises(TransportOperationError):
        t.recv(0)


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    tty.setraw(master)
    path = os.ttyname(slave)
    yield master, slave, path
    for fd in (master, slave):
        try:
            os.close(fd)
        except OSError:
            pass


def test_pty_serial_receives_batches_and_counts_damage(pty_pair):
    master, _slave, path = pty_pair
    t = SerialTransport(path, baudrate=3_000_000)
    try:
        good = samples_wire(200)
        damaged = bytearray(encode(Ack(5, MsgType.START, 0)))
        damaged[3] ^= 0x40
        os.write(master, good[:990] + bytes(damaged) + good[990:])
        samples, msgs = collect(t, 200)
        assert sum(len(b) for b in samples) == 200
        assert t.stats.error_count == 1
        t.send(Sync(counter=7))
        time.sleep(0.05)
        assert os.read(master, 100) == encode(Sync(counter=7))
        assert t.capabilities.kind == "serial" and t.capabilities.bitrate == 3_000_000
    finally:
        t.close()


def test_pty_serial_sets_the_read_timeout_only_when_it_changes(pty_pair):
    """pyserial reconfigures the port (tcsetattr) at every ``timeout`` set: a streaming port sets
    it once, not at every read, and what is written still arrives whole."""
    master, _slave, path = pty_pair
    t = SerialTransport(path, baudrate=3_000_000, read_size=512)  # small reads: many of them
    try:
        def receive(n_samples, timeout_s):
            got, reads = [], 0
            while sum(len(b) for b in got) < n_samples:
                got += [ev for ev in t.recv(timeout_s) if isinstance(ev, SampleBatch)]
                reads += 1
                assert reads < 10_000
            return got, reads

        os.write(master, samples_wire(300))
        first, reads = receive(300, None)
        assert sum(len(b) for b in first) == 300 and reads > 5
        assert [t.recv(0) for _ in range(20)] == [[]] * 20  # nothing more: polls
        os.write(master, samples_wire(300))
        second, _ = receive(300, None)
        assert np.array_equal(np.concatenate([b.node for b in second]), np.concatenate([b.node for b in first]))
        assert set(t.read_timeouts) == {0.1, 0.0} and t.read_timeouts[0.0] == 20
        assert t.read_timeout_sets == 3  # 0.1 s, 0 for the polls, 0.1 s again
        assert t._port.timeout == 0.1  # what pyserial holds is what the transport thinks it set
        assert {read_timeout_for(r) for r in (0.05, 0.0499, 0.03, 0.011, 0.0004)} <= set(READ_TIMEOUTS_S)
    finally:
        t.close()


def _the_same_pty_again(name: str) -> tuple[int, int]:
    """A new pty pair whose slave is ``name`` again: the same device (number) coming back, the only
    one a reconnect takes. The kernel gives a new pty the lowest free number, so the one just freed,
    unless another process (a test running beside this one) took it meanwhile: then it is tried
    again until that process lets it go."""
    end = time.monotonic() + 20
    while time.monotonic() < end:
        m, s = os.openpty()
        if os.ttyname(s) == name:
            return m, s
        os.close(s)
        os.close(m)
        time.sleep(0.02)
    pytest.skip(f"{name} stayed held by another process for 20 s: the same device could not come back")


def test_pty_serial_reconnects_when_the_port_goes_away_and_comes_back(tmp_path):
    link = tmp_path / "sheet-port"
    m1, s1 = os.openpty()
    tty.setraw(m1)
    first = os.ttyname(s1)
    os.symlink(first, link)
    t = SerialTransport(str(link), reconnect_interval_s=0.05)
    m2 = s2 = None
    try:
        os.write(m1, samples_wire(3))
        assert sum(len(b) for b in collect(t, 3)[0]) == 3
        os.close(s1)
        os.close(m1)  # the port goes away (the reader sees EIO)
        end = time.monotonic() + 3
        while t.stats.disconnects == 0 and time.monotonic() < end:
            t.recv(0.05)
        assert t.stats.disconnects == 1 and not t.connected
        m2, s2 = _the_same_pty_again(first)  # ... and comes back under the same name
        tty.setraw(m2)
        os.unlink(link)
        os.symlink(os.ttyname(s2), link)
        end = time.monotonic() + 3
        while t.stats.reconnects == 0 and time.monotonic() < end:
            t.recv(0.05)
        assert t.stats.reconnects == 1 and t.connected
        os.write(m2, samples_wire(4, counter=9))
        batches, _ = collect(t, 4)
        assert [int(c) for b in batches for c in b.counter] == [9] * 4
    finally:
        t.close()
        for fd in (m2, s2):
            if fd is not None:
                os.close(fd)


def test_memory_transport_and_reopen_after_the_link_closes():
    ends = [memory_link("m0")]
    t = MemoryTransport(ends[0][0], reopen=lambda: ends.append(memory_link("m1")) or ends[-1][0])
    try:
        dev = ends[0][1]
        dev.write(samples_wire(10) + encode(Announce(0x8001, uid=0xABC)))
        samples, msgs = collect(t, 10, 1)
        assert msgs == [Announce(0x8001, uid=0xABC)] and t.capabilities.kind == "memory"
        dev.close()
        end = time.monotonic() + 2
        while t.stats.reconnects == 0 and time.monotonic() < end:
            t.recv(0.02)
        assert t.stats.disconnects == 1 and t.stats.reconnects == 1
        ends[-1][1].write(samples_wire(2))
        assert sum(len(b) for b in collect(t, 2)[0]) == 2
    finally:
        t.close()


# --------------------------------------------------------------------------------------------- CAN

def test_virtual_can_merges_samples_into_batches_and_sends_extended_ids():
    t = CanTransport("virtual:host_t1")
    peer = can.Bus(interface="virtual", channel="host_t1")
    try:
        assert t.capabilities == TransportCapabilities("can", 8, False, None, None, "virtual:host_t1")
        for k in range(50):
            f = to_can(Sample(k + 1, 0xFFFF, k, 0, 1024, 0))
            peer.send(can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True))
        peer.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))  # not ours
        samples, msgs = collect(t, 50, 1)
        assert sum(len(b) for b in samples) == 50
        assert isinstance(msgs[0], DecodeError) and t.stats.errors["BAD_FIELD"] == 1
        t.send(Sync(counter=3))
        m = peer.recv(1.0)
        assert m.is_extended_id and m.arbitration_id == to_can(Sync(counter=3)).arbitration_id
        assert bytes(m.data) == b"\x03\x00"
    finally:
        t.close()
        peer.shutdown()


def test_virtual_can_fd_carries_snapshot_frames():
    t = CanTransport("virtual:host_fd", fd=True)
    peer = can.Bus(interface="virtual", channel="host_fd", fd=True)
    try:
        assert t.capabilities.fd and t.capabilities.mtu == 64
        snap = Snapshot.from_arrays(0, 9, 11, np.tile([1, 2, 1024], (11, 1)), np.zeros(11, dtype=int))
        f = to_can(snap)
        peer.send(can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True, is_fd=True))
        _, msgs = collect(t, 0, 1)
        assert msgs == [snap]
    finally:
        t.close()
        peer.shutdown()


class SlcanPeer:
    """A minimal Lawicel adapter on a pty master: answers commands with CR, forwards frames we push,
    records frames the host transmits."""

    def __init__(self, master: int) -> None:
        self.master = master
        self.sent: list[str] = []
        self._stop = threading.Event()
        self._th = threading.Thread(target=self._run, daemon=True)
        self._th.start()

    def _run(self) -> None:
        buf = b""
        import select
        while not self._stop.is_set():
            r, _, _ = select.select([self.master], [], [], 0.02)
            if not r:
                continue
            try:
                buf += os.read(self.master, 4096)
            except OSError:
                return
            while b"\r" in buf:
                line, buf = buf.split(b"\r", 1)
                if line[:1] in (b"T", b"t", b"D", b"d"):
                    self.sent.append(line.decode())
                os.write(self.master, b"\r")

    def push(self, msg) -> None:
        f = to_can(msg)
        os.write(self.master, f"T{f.arbitration_id:08X}{len(f.data)}{f.data.hex().upper()}\r".encode())

    def stop(self) -> None:
        self._stop.set()
        self._th.join(1)


def test_slcan_on_a_pty_through_python_cans_own_interface(pty_pair):
    master, _slave, path = pty_pair
    peer = SlcanPeer(master)
    t = CanTransport(f"slcan:{path}", bitrate=1_000_000, sleep_after_open=0)
    try:
        assert t.capabilities.bitrate == 1_000_000
        for k in range(20):
            peer.push(Sample(k + 1, 5, 0, 0, 1024, 0))
        peer.push(Ack(3, MsgType.START, 0))
        samples, msgs = collect(t, 20, 1)
        assert sum(len(b) for b in samples) == 20 and msgs == [Ack(3, MsgType.START, 0)]
        t.send(Sync(counter=0x1234))
        end = time.monotonic() + 2
        while not peer.sent and time.monotonic() < end:
            time.sleep(0.01)
        f = to_can(Sync(counter=0x1234))
        assert peer.sent == [f"T{f.arbitration_id:08X}2{f.data.hex().upper()}"]
    finally:
        t.close()
        peer.stop()


# --------------------------------------------------------------------------------------------- errors

def test_errors_name_the_port_and_chain_the_cause(tmp_path):
    missing = str(tmp_path / "no-such-tty")
    with pytest.raises(TransportInitError) as ei:
        open_transport("serial", missing)
    assert repr(missing) in str(ei.value) and ei.value.port == missing
    assert ei.value.__cause__ is not None and isinstance(ei.value, TransportError)
    with pytest.raises(TransportInitError, match="Unknown transport back end 'usb'"):
        open_transport("usb", "x")
    with pytest.raises(TransportInitError, match="INTERFACE:CHANNEL"):
        CanTransport("can0")
    with pytest.raises(TransportInitError, match="Cannot open CAN bus 'nosuchiface:x'") as ei:
        CanTransport("nosuchiface:x")
    assert ei.value.__cause__ is not None
    assert parse_can_spec("slcan:/dev/pts/5") == ("slcan", "/dev/pts/5")


def test_send_on_a_closed_memory_link_is_an_operation_error():
    a, b = memory_link()
    t = MemoryTransport(a)
    b.close()
    with pytest.raises(TransportOperationError, match="mem:host"):
        t.send(Sync(counter=1))
    assert t.stats.send_failures == 1
    t.close()


def test_a_write_timeout_is_a_transport_timeout_and_a_timeout_error():
    import serial

    from host.transport.ports import TransportError, TransportTimeoutError

    class BlockedPort:  # a port whose writes time out, as pyserial reports it
        name = "blocked"

        def write(self, data):
            raise serial.SerialTimeoutException("Write timeout")

        def close(self):
            pass

    t = SerialTransport(BlockedPort(), reconnect=False)
    with pytest.raises(TimeoutError) as info:
        t.send_bytes(b"\x01\x00")
    assert isinstance(info.value, TransportTimeoutError) and isinstance(info.value, TransportError)
    assert t.connected  # a timeout is not a lost port
