"""host/transport/slcan.py's SLCAN bus (python-can interface ``capsheet_slcan``) on real ptys, against python-can's
own slcan interface: every frame delivered whatever the chunking (whole stream, byte by byte, seeded
random chunks), parsed as python-can parses it; damaged lines counted and skipped with every valid
frame around them kept; stale input an adapter left in the port drained at open; found by name
through python-can's entry point, from ``can.Bus`` and from a python-can configuration file. And
`CanTransport`'s batch decode equals decoding one frame per call, over python-can's virtual bus."""

from __future__ import annotations

import os
import select
import threading
import time
import tty

import numpy as np
import pytest

can = pytest.importorskip("can")

from can.interfaces.slcan import slcanBus  # noqa: E402

from host.transport.slcan import MAX_LINE, SlcanBus  # noqa: E402
from host.transport.ports import CanTransport, FrameBlock  # noqa: E402
from protocol import DecodeError, SampleBatch, to_can  # noqa: E402
from protocol.can import decode_can, make_id  # noqa: E402
from protocol.messages import Ack, MsgType, Sample, Status, Sync  # noqa: E402


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    yield master, os.ttyname(slave)
    for fd in (master, slave):
        try:
            os.close(fd)
        except OSError:
            pass


def t_line(msg) -> bytes:
    f = to_can(msg)
    return f"T{f.arbitration_id:08X}{len(f.data)}{f.data.hex().upper()}\r".encode()


#: one of each line python-can reads (frames of every kind, a Z1 timestamp, replies, an error reply)
VALID_LINES = [
    t_line(Sample(7, 0x1234, -2048, 2047, 1024, 0xF)),
    b"T1FFFFFFF0\r",  # extended, no data, the largest identifier
    b"t7FF8DEADBEEF01020304\r",
    b"t1230\r",
    b"T0101000023412ABCD\r",  # with the 4-digit timestamp of the Z1 mode
    b"x0101000023412\r",  # CANDapter's extended frame
    b"r1234\r",
    b"R123456788\r",
    b"d123F" + b"AB" * 64 + b"\r",
    b"D0101000093412" + b"00" * 10 + b"\r",  # FD DLC 9: 12 bytes
    b"b0002" + b"0102" + b"\r",
    b"B1ABCDEF0C" + b"5A" * 24 + b"\r",
    b"\r",  # OK
    b"z\r", b"Z\r",  # transmit acknowledged
    b"\a",  # error reply
    b"V1013\r", b"NCS01\r", b"F00\r",
]


def stream(n_samples: int = 60) -> tuple[bytes, int]:
    """The valid lines, then ``n_samples`` SAMPLE frames among replies: (bytes, frames in it)."""
    rng = np.random.Generator(np.random.MT19937(11))
    lines = list(VALID_LINES)
    for k in range(n_samples):
        x, y, z = (int(v) for v in rng.integers(-2048, 2048, 3))
        lines.append(t_line(Sample(int(rng.integers(1, 400)), k, x, y, z, int(rng.integers(0, 16)))))
        if k % 7 == 0:
            lines.append(b"\r")
    data = b"".join(lines)
    n_frames = sum(1 for line in lines if line[:1] in b"TtxrRdDbB")
    return data, n_frames


def as_messages(items: list) -> list:
    """`drain_blocks` output as `can.Message` objects (a FrameBlock row by row)."""
    out = []
    for it in items:
        if isinstance(it, FrameBlock):
            out += [can.Message(arbitration_id=int(i), is_extended_id=True, dlc=7, data=bytearray(d.tobytes()))
                    for i, d in zip(it.arbitration_id, it.data)]
        else:
            out.append(it)
    return out


def receive(bus, master: int, chunks: list[bytes], n_frames: int, timeout_s: float = 5.0,
            method: str = "drain") -> list:
    """Write the chunks one by one, each read by the bus before the next is written (so the bus sees
    exactly these chunk boundaries, or finer ones), then collect ``n_frames`` frames with
    ``bus.drain`` or ``bus.drain_blocks``."""
    read = bus.drain if method == "drain" else (lambda t: as_messages(bus.drain_blocks(t)))
    out = []
    for chunk in chunks:
        os.write(master, chunk)
        end = time.monotonic() + timeout_s
        while bus.in_waiting == 0 and time.monotonic() < end:
            time.sleep(0.0005)
        while bus.in_waiting:
            out += read(0.0)
    end = time.monotonic() + timeout_s
    while len(out) < n_frames and time.monotonic() < end:
        out += read(0.05)
    return out


def feed(master: int, chunks) -> threading.Thread:
    """Write ``chunks`` to the pty's master side from a thread, each whole: a pty holds a few KB,
    so a writer in the reading thread blocks forever once the reader falls behind (a loaded
    machine hung the suite there)."""
    def run():
        for c in chunks:
            view = memoryview(c)
            while view:
                view = view[os.write(master, view):]
    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def reference(path: str, master: int, data: bytes, n_frames: int) -> list:
    """What python-can's own slcan interface makes of ``data`` (it reads one byte per call)."""
    ref = slcanBus(path, sleep_after_open=0)
    try:
        feed(master, [data])
        out = []
        end = time.monotonic() + 10
        while len(out) < n_frames and time.monotonic() < end:
            m = ref.recv(0.05)
            if m is not None:
                out.append(m)
        return out
    finally:
        ref.shutdown()


def same_frames(a: list, b: list) -> bool:
    return len(a) == len(b) and all(x.equals(y, timestamp_delta=None) for x, y in zip(a, b))


def open_bus(path: str, **kw) -> SlcanBus:
    return SlcanBus(path, sleep_after_open=0, drain_quiet_s=0.02, **kw)


def drain_master(master: int) -> None:
    while select.select([master], [], [], 0)[0]:
        os.read(master, 4096)


# --------------------------------------------------------------------------------------- chunking

@pytest.mark.parametrize("method", ["drain", "drain_blocks"])
@pytest.mark.parametrize("chunking", ["whole", "byte-by-byte", "random"])
def test_every_frame_arrives_as_python_can_parses_it_whatever_the_chunking(pty_pair, chunking, method):
    master, path = pty_pair
    data, n_frames = stream()
    expected = reference(path, master, data, n_frames)
    assert len(expected) == n_frames  # python-can itself reads all of it (slowly)
    drain_master(master)
    if chunking == "whole":
        chunks = [data]
    elif chunking == "byte-by-byte":
        chunks = [data[i:i + 1] for i in range(len(data))]
    else:
        rng = np.random.Generator(np.random.MT19937(5))
        cuts = np.sort(rng.choice(np.arange(1, len(data)), size=120, replace=False))
        chunks = [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)])]
    bus = open_bus(path)
    try:
        drain_master(master)
        got = receive(bus, master, chunks, n_frames, method=method)
        assert same_frames(got, expected)
        assert (bus.bad_lines, bus.nacks) == (0, 1)  # the one BEL of the stream
    finally:
        bus.shutdown()


def test_recv_and_get_version_go_through_the_same_lines(pty_pair):
    master, path = pty_pair
    bus = open_bus(path)
    try:
        drain_master(master)
        os.write(master, t_line(Ack(3, MsgType.START, 0))[:9])
        assert bus.recv(0.05) is None  # half a line: nothing yet
        os.write(master, t_line(Ack(3, MsgType.START, 0))[9:] + b"V1013\r")
        m = bus.recv(1.0)
        assert m is not None and m.arbitration_id == to_can(Ack(3, MsgType.START, 0)).arbitration_id
        assert bus.get_version(1.0) == (10, 13)  # python-can's own query, over the buffered lines
    finally:
        bus.shutdown()


# ------------------------------------------------------------------------------------ damaged lines

#: damaged lines, each counted once and skipped (python-can raises on most, or returns a short frame)
DAMAGED = [
    b"T0101000023G12\r",  # a character that is not hex in the data
    b"T01010000234\r",  # data shorter than its DLC
    b"T010100002341200\r",  # longer (and not a 4-digit timestamp)
    b"T0101000093412341234123412\r",  # classic DLC 9
    b"TG1010000\r",  # identifier not hex
    b"T2000000000\r",  # identifier over 29 bits
    b"t8000\r",  # standard identifier over 11 bits
    b"T01 1000023412\r",  # int(' 1', 16) would take the space
    b"T\xff\xfe\r",  # not ASCII
    b"T010\r",  # cut short
    b"Q123\r",  # no SLCAN line
    b"T01010000" + b"A" * (MAX_LINE + 40) + b"\r",  # over-long, its end arriving later
    b"T0101000023412\a",  # an error reply after text
    b"T01010000712345678G0ABCD\r",  # the SAMPLE line's length, a character that is not hex
    b"T3FFFFFFF700000000000000\r",  # ... an identifier over 29 bits
    b"T01010000812345678901234\r",  # ... DLC 8 with 7 bytes
]


@pytest.mark.parametrize("method", ["drain", "drain_blocks"])
def test_damaged_lines_are_counted_and_the_frames_around_them_kept(pty_pair, method):
    master, path = pty_pair
    good = [Sample(k + 1, 9, k, -k, 1024, k % 16) for k in range(len(DAMAGED) + 1)]
    data = bytearray(t_line(good[0]))
    for bad, msg in zip(DAMAGED, good[1:]):
        data += bad + t_line(msg)
    bus = open_bus(path)
    try:
        drain_master(master)
        rng = np.random.Generator(np.random.MT19937(3))
        cuts = np.sort(rng.choice(np.arange(1, len(data)), size=40, replace=False))
        got = receive(bus, master, [bytes(data[a:b]) for a, b in zip([0, *cuts], [*cuts, len(data)])], len(good),
                      method=method)
        assert [bytes(m.data) for m in got] == [to_can(s).data for s in good]
        assert bus.bad_lines == len(DAMAGED)
    finally:
        bus.shutdown()


def test_the_can_transport_reports_damaged_slcan_lines_as_transport_errors(pty_pair):
    master, path = pty_pair
    t = CanTransport(f"slcan:{path}", bitrate=1_000_000, sleep_after_open=0, drain_quiet_s=0.02)
    try:
        drain_master(master)
        good = [Sample(k + 1, 4, k, 0, 1024, 0) for k in range(5)]
        os.write(master, b"".join(t_line(s) + DAMAGED[k] for k, s in enumerate(good)) + t_line(Ack(2, MsgType.START, 0)))
        samples, msgs = [], []
        end = time.monotonic() + 5
        while (sum(map(len, samples)) < 5 or not msgs) and time.monotonic() < end:
            for ev in t.recv(0.05):
                (samples if isinstance(ev, SampleBatch) else msgs).append(ev)
        assert [m for b in samples for m in b.messages()] == good and msgs == [Ack(2, MsgType.START, 0)]
        assert t.stats.errors == {"SLCAN_BAD_LINE": 5} and t.stats.frames_in == 6
    finally:
        t.close()


# --------------------------------------------------------------------------------------- stale input

class StreamingAdapter:
    """A Lawicel adapter left open by a host that is gone: it streams frames into the port until it
    reads ``C``, then flushes the backlog it still holds (as virtual_sheet's pty does), answers
    commands with CR, and after ``O`` sends the fresh frames it is given."""

    def __init__(self, master: int, stale: bytes, backlog: bytes) -> None:
        self.master, self.stale, self.backlog = master, stale, backlog
        self.opened = threading.Event()
        self._stop = threading.Event()
        self._th = threading.Thread(target=self._run, daemon=True)
        self._th.start()

    def _run(self) -> None:
        closed, buf = False, b""
        while not self._stop.is_set():
            if not closed:
                os.write(self.master, self.stale)  # streaming on, faster than nobody reads
            r, _, _ = select.select([self.master], [], [], 0.002)
            if not r:
                continue
            buf += os.read(self.master, 4096)
            while b"\r" in buf:
                line, buf = buf.split(b"\r", 1)
                if line == b"C" and not closed:
                    closed = True
                    os.write(self.master, self.backlog)
                os.write(self.master, b"\r")
                if line == b"O":
                    self.opened.set()

    def stop(self) -> None:
        self._stop.set()
        self._th.join(2)


def test_stale_input_in_the_port_is_drained_at_open(pty_pair):
    master, path = pty_pair
    stale = b"".join(t_line(Sample(k + 1, 0xAAAA, 1, 1, 1, 0)) for k in range(40))
    backlog = stale * 8 + t_line(Sample(99, 0xAAAA, 1, 1, 1, 0))[:11]  # ends inside a line
    peer = StreamingAdapter(master, stale, backlog)
    try:
        bus = open_bus(path)
        try:
            assert peer.opened.wait(5)
            fresh = [Sample(k + 1, 0x0005, 2, 2, 2, 0) for k in range(10)]
            time.sleep(0.05)
            os.write(master, b"".join(t_line(s) for s in fresh))
            got = []
            end = time.monotonic() + 5
            while len(got) < len(fresh) and time.monotonic() < end:
                got += bus.drain(0.05)
            assert [bytes(m.data) for m in got] == [to_can(s).data for s in fresh]  # nothing stale
            assert bus.stale_bytes >= len(backlog) and bus.bad_lines == 0
        finally:
            bus.shutdown()
    finally:
        peer.stop()


# ------------------------------------------------------------------------ batch decode == one by one

def frame_mix(n: int, seed: int = 1) -> list:
    """python-can messages as a sheet's bus carries them, with every kind of damage mixed in."""
    rng = np.random.Generator(np.random.MT19937(seed))
    out = []

    def msg(f, **kw):
        return can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True, is_fd=f.is_fd, **kw)

    for k in range(n):
        kind = int(rng.integers(0, 20))
        node = int(rng.integers(1, 365))
        if kind < 12:  # runs of samples, extremes included
            x, y, z = (int(v) for v in rng.choice([-2048, -1, 0, 1, 2047, *rng.integers(-2048, 2048, 3)], 3))
            out.append(msg(to_can(Sample(node, int(rng.integers(0, 1 << 16)), x, y, z, int(rng.integers(0, 16))))))
        elif kind == 12:
            out.append(msg(to_can(Ack(node, MsgType.START, 0))))
        elif kind == 13:
            out.append(msg(to_can(Status(node, 3, 0, 0, 0, k))))
        elif kind == 14:  # a SAMPLE one byte short; from node 0xFFFF; on an 11-bit identifier
            f = to_can(Sample(node, k, 1, 2, 3, 0))
            out.append(can.Message(arbitration_id=f.arbitration_id, data=f.data[:6], is_extended_id=True))
            out.append(can.Message(arbitration_id=f.arbitration_id | 0xFFFF, data=f.data, is_extended_id=True))
            out.append(can.Message(arbitration_id=0x123, data=f.data, is_extended_id=False))
        elif kind == 15:  # another protocol version; an unknown type
            f = to_can(Sample(node, k, 1, 2, 3, 0))
            out.append(can.Message(arbitration_id=f.arbitration_id ^ (1 << 16), data=f.data, is_extended_id=True))
            out.append(can.Message(arbitration_id=make_id(0x3E, node, 7), data=b"\x01", is_extended_id=True))
        elif kind == 16:
            out.append(can.Message(is_error_frame=True))
        elif kind == 17:
            out.append(can.Message(arbitration_id=make_id(MsgType.SAMPLE, node), is_remote_frame=True, dlc=7))
        elif kind == 18:  # a CAN FD frame on a bus opened classic
            out.append(msg(to_can(Sample(node, k, 1, 2, 3, 0), fd=True)))
        else:  # the echo of the host's own SYNC
            out.append(msg(to_can(Sync(counter=k))))
    return out


def flat(events: list) -> list:
    return [m for ev in events for m in (ev.messages() if isinstance(ev, SampleBatch) else [ev])]


def test_batch_decode_equals_one_frame_per_call_over_a_virtual_bus():
    channel = f"capsheet-batch-{os.getpid()}"
    frames = frame_mix(1500)
    batched = CanTransport(f"virtual:{channel}")
    single = CanTransport(f"virtual:{channel}", max_batch=1)
    sender = can.Bus(interface="virtual", channel=channel)
    try:
        for t in (batched, single):
            for f in frames:
                if f.arbitration_id == to_can(Sync(0)).arbitration_id:
                    t.echo.sent(f.arbitration_id, f.data)  # as if it had sent that SYNC itself
        for f in frames:
            sender.send(f)
        out = {}
        for name, t in (("batched", batched), ("single", single)):
            events = []
            while got := t.recv(0.2):  # everything was sent before: [] means all of it was read
                events += got
            out[name] = events
        b_events, s_events = out["batched"], out["single"]
        assert flat(b_events) == flat(s_events)
        # and both are what decode_can makes of each frame the transport keeps (an independent rule)
        sync_id = to_can(Sync(0)).arbitration_id
        kept = [f for f in frames if not (f.is_error_frame or f.is_remote_frame or f.is_fd or f.arbitration_id == sync_id)]
        assert flat(s_events) == [decode_can(f.arbitration_id, f.data, is_extended_id=f.is_extended_id) for f in kept]
        assert batched.stats.as_dict() == single.stats.as_dict()
        assert batched.echo.echoes == single.echo.echoes > 0
        errors = [ev for ev in s_events if isinstance(ev, DecodeError)]
        assert {e.reason.name for e in errors} == {"BAD_LENGTH", "BAD_FIELD", "BAD_VERSION", "UNKNOWN_TYPE"}
        assert set(batched.stats.errors) >= {"CAN_ERROR_FRAME", "FD_ON_CLASSIC", "BAD_LENGTH"}
        # batched: one SampleBatch per run of samples between other events (all frames were
        # queued before the first call, and fit in one drain), not one per frame
        runs = sum(1 for a, b in zip([None, *s_events], s_events)
                   if isinstance(b, SampleBatch) and not isinstance(a, SampleBatch))
        assert sum(isinstance(ev, SampleBatch) for ev in b_events) == runs < len(flat(s_events)) // 2
    finally:
        for t in (batched, single):
            t.close()
        sender.shutdown()


def slcan_line(f) -> bytes:
    """A python-can message as the adapter's line (classic frames only)."""
    if f.is_remote_frame:
        return (f"R{f.arbitration_id:08X}{f.dlc}" if f.is_extended_id else f"r{f.arbitration_id:03X}{f.dlc}").encode() + b"\r"
    head = f"T{f.arbitration_id:08X}" if f.is_extended_id else f"t{f.arbitration_id:03X}"
    return f"{head}{len(f.data)}{bytes(f.data).hex().upper()}\r".encode()


def test_the_slcan_transport_decodes_blocks_as_decode_can_does_frame_by_frame(pty_pair):
    master, path = pty_pair
    frames = [f for f in frame_mix(1200, seed=2) if not (f.is_error_frame or f.is_fd)]
    t = CanTransport(f"slcan:{path}", bitrate=1_000_000, sleep_after_open=0, drain_quiet_s=0.02)
    try:
        drain_master(master)
        sync_id = to_can(Sync(0)).arbitration_id
        for f in frames:
            if f.arbitration_id == sync_id:
                t.echo.sent(f.arbitration_id, f.data)
        echoed = next(f for f in frames[50:] if len(f.data) == 7 and not f.is_remote_frame
                      and (f.arbitration_id >> 20) & 0x3F == MsgType.SAMPLE)
        t.echo.sent(echoed.arbitration_id, echoed.data)  # one SAMPLE the host "sent": its echo is dropped
        data = b"".join(slcan_line(f) for f in frames)
        events = []
        rng = np.random.Generator(np.random.MT19937(8))
        cuts = np.sort(rng.choice(np.arange(1, len(data)), size=60, replace=False))
        writer = feed(master, [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)])])
        while writer.is_alive():
            events += t.recv(0.01)
        while got := t.recv(0.3):
            events += got
        kept = [f for f in frames if not (f.is_remote_frame or f.arbitration_id == sync_id)]
        kept.remove(echoed)
        assert flat(events) == [decode_can(f.arbitration_id, f.data, is_extended_id=f.is_extended_id) for f in kept]
        assert t.echo.echoes == 1 + sum(f.arbitration_id == sync_id for f in frames)
        assert t.stats.bytes_in == sum(len(f.data) for f in frames if not f.is_remote_frame)
        assert "SLCAN_BAD_LINE" not in t.stats.errors
    finally:
        t.close()


# ------------------------------------------------------------------------- a python-can interface

def test_slcan_bus_implements_python_cans_hooks_and_nothing_else_of_busabc():
    """A back end implements the documented hooks (python-can: "only override _recv_internal"),
    never ``recv`` or the filtering: whatever of `can.BusABC` it defines is one of these."""
    overridden = {name for name in vars(SlcanBus) if name in vars(can.BusABC) and callable(vars(SlcanBus)[name])}
    assert overridden <= {"__init__", "_recv_internal", "send", "shutdown", "fileno"}
    assert {"_recv_internal", "send"} <= overridden
    assert not issubclass(SlcanBus, slcanBus)


def test_can_bus_opens_it_by_name_through_the_entry_point(pty_pair):
    master, path = pty_pair
    assert can.interfaces.BACKENDS["capsheet_slcan"] == ("host.transport.slcan", "SlcanBus")
    bus = can.Bus(interface="capsheet_slcan", channel=path, bitrate=1_000_000, sleep_after_open=0, drain_quiet_s=0.02)
    try:
        assert isinstance(bus, SlcanBus)
        os.write(master, t_line(Ack(4, MsgType.START, 0)))
        m = bus.recv(2.0)
        assert (m.arbitration_id, bytes(m.data)) == (to_can(Ack(4, MsgType.START, 0)).arbitration_id,
                                                     to_can(Ack(4, MsgType.START, 0)).data)
        bus.send(can.Message(arbitration_id=0x1010000, data=b"\x34\x12", is_extended_id=True))
        time.sleep(0.05)
        wrote = os.read(master, 4096)
        assert wrote == b"C\rS8\rO\rT010100002" + b"3412\r"  # bring-up, then the frame, as python-can writes it
    finally:
        bus.shutdown()


def test_a_python_can_configuration_file_opens_it(pty_pair, tmp_path):
    """``interface = capsheet_slcan`` in python-can's configuration file (``~/can.conf``): any
    python-can program opens capsheet's SLCAN bus without naming it in code."""
    import subprocess
    import sys
    master, path = pty_pair
    (tmp_path / "can.conf").write_text(f"[default]\ninterface = capsheet_slcan\nchannel = {path}\n"
                                       f"bitrate = 500000\nsleep_after_open = 0\ndrain_quiet_s = 0\n")
    code = ("import can; b = can.Bus(); print(type(b).__name__, flush=True); m = b.recv(10); "
            "print(hex(m.arbitration_id), bytes(m.data).hex()); b.shutdown()")
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env=dict(os.environ, HOME=str(tmp_path)))
    try:
        assert p.stdout.readline().strip() == "SlcanBus", p.stderr.read()
        os.write(master, t_line(Sample(9, 77, 1, 2, 3, 0)))
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, err
    f = to_can(Sample(9, 77, 1, 2, 3, 0))
    assert out.split() == [hex(f.arbitration_id), f.data.hex()]
    assert os.read(master, 4096).startswith(b"C\rS6\rO\r")  # 500 kbit/s from the file
