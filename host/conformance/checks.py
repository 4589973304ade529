"""``capsheet conformance``: hold one chip (real or virtual, or a gateway with chips) to the spec.

Runs numbered checks, one per clause of docs/protocol.md, through the real port — a serial port
(pyserial: a USB adapter, a pty) or a CAN interface (python-can) — and prints PASS/FAIL per check
with a summary; the exit status is 1 if any check failed. The device under test may be anything
that speaks capsheet v1: the Python chip model, the C reference firmware, or hardware.

The checks talk to ONE chip: the first that answers the broadcast GET_INFO (others on a gateway
are left alone: frames from other nodes are ignored). The chip is RESET first and last, and is
assigned ``--node`` for the run. Clause numbers are those of protocol/messages.py: §3 addressing,
§4.x messages, §5 sampling, §6 serial framing, §7 CAN, §8 state machine.

Timing (§5.1) is measured on the host, so it includes the host's and the port's own latency: the
SYNC->SAMPLE check passes when the median is within the 2 ms deadline plus ``--slack-ms``.

    capsheet conformance --port /dev/ttyUSB0
    capsheet conformance --can socketcan:can0
    capsheet conformance --can virtual:bus0 --only 4,5
"""

from __future__ import annotations

import queue
import statistics
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

from cobs import cobs

from protocol.can import CanFrame, decode_can, make_id, split_id, to_can
from protocol.crc import crc16_ccitt_false
from protocol.framing import HEADER, DecodeError, StreamDecoder, encode, encode_frame
from protocol.messages import (MESSAGE_TYPES, NODE_PROVISIONAL_MAX, NODE_PROVISIONAL_MIN, PROTOCOL_VERSION, Ack,
                               Announce, Assign, CalData, CalRead, CalWrite, ChipState, Config, Direction,
                               GetInfo, Info, Message, MsgType, Nack, NackReason, Reset, Sample, Start, Status,
                               StatusFlag, Stop, Sync, provisional_node)
from protocol.state import ANNOUNCE_PERIOD_S, SYNC_REPLY_DEADLINE_S

__all__ = ["run_checks", "summary", "CheckResult", "CHECKS", "SerialLink", "CanLink", "Link"]


# ---------------------------------------------------------------------------------------------
# Links: the port, a reader thread, decoded events with arrival times
# ---------------------------------------------------------------------------------------------

class Link:
    """One port to the device: ``send`` wire frames, ``events()`` gives what arrived, in order."""

    transport = "?"

    def __init__(self) -> None:
        self._q: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.rx_errors: list[DecodeError] = []  # frames from the device that did not decode
        self.rx_frames = 0
        self.bad_ids: list[str] = []  # §7.1 violations seen on CAN

    def start(self) -> "Link":
        self._thread = threading.Thread(target=self._reader, name=f"conformance-{self.transport}", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._close()

    def _put(self, ev) -> None:
        t = time.monotonic()
        if isinstance(ev, DecodeError):
            self.rx_errors.append(ev)
        else:
            self.rx_frames += 1
        self._q.put((t, ev))

    def get(self, timeout_s: float):
        """The next ``(arrival_time, Message | DecodeError)`` or None after ``timeout_s``."""
        try:
            return self._q.get(timeout=max(0.0, timeout_s))
        except queue.Empty:
            return None

    def drain(self) -> None:
        while True:
            try:
                self._q.get_nowait()
            except queue.Empty:
                return

    def send(self, msg: Message) -> float:
        raise NotImplementedError

    def _reader(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError


class SerialLink(Link):
    """pyserial port (``serial_for_url``: device paths, ``loop://``, ``socket://`` ...)."""

    transport = "serial"

    def __init__(self, port: str, baudrate: int = 3_000_000) -> None:
        super().__init__()
        import serial  # lazy: the protocol core never imports pyserial

        try:
            self.port = serial.serial_for_url(port, baudrate=baudrate, timeout=0.02)
        except (serial.SerialException, OSError) as exc:
            raise ConnectionError(f"Cannot open serial port {port!r}: {exc}") from exc
        self._dec = StreamDecoder()
        self._wlock = threading.Lock()

    def _reader(self) -> None:
        while not self._stop.is_set():
            try:
                # one byte with the timeout (returns as soon as one is there), then what is waiting
                data = self.port.read(1)
                if data:
                    data += self.port.read(self.port.in_waiting)
            except Exception:  # noqa: BLE001 - a port that went away ends the reader
                return
            if data:
                for ev in self._dec.feed(data):
                    self._put(ev)

    def send_bytes(self, data: bytes) -> float:
        with self._wlock:
            self.port.write(data)
            self.port.flush()
        return time.monotonic()

    def send(self, msg: Message) -> float:
        return self.send_bytes(encode(msg))

    def send_raw(self, type_code: int, node: int, payload: bytes, version: int = PROTOCOL_VERSION) -> float:
        return self.send_bytes(encode_frame(type_code, node, payload, version=version))

    def _close(self) -> None:
        try:
            self.port.close()
        except Exception:  # noqa: BLE001
            pass


class CanLink(Link):
    """python-can bus, ``IFACE:CHANNEL`` (``socketcan:can0``, ``virtual:bus0``, ``slcan:/dev/ttyACM0``)."""

    transport = "can"

    def __init__(self, spec: str, *, fd: bool = False, bitrate: int | None = None) -> None:
        super().__init__()
        try:
            import can
        except ImportError as exc:  # pragma: no cover
            raise ConnectionError(f"Cannot import python-can for --can {spec!r}: {exc}") from exc
        iface, _, channel = spec.partition(":")
        if not iface or not channel:
            raise ConnectionError(f"Invalid --can {spec!r} (expected IFACE:CHANNEL, e.g. socketcan:can0)")
        kw = {"fd": True} if fd else {}
        if bitrate:
            kw["bitrate"] = bitrate
        try:
            self.bus = can.Bus(interface=iface, channel=channel, **kw)
        except Exception as exc:  # noqa: BLE001 - python-can raises many kinds
            raise ConnectionError(f"Cannot open CAN interface '{iface}' channel {channel!r}: {exc}") from exc
        self._can = can

    def _reader(self) -> None:
        while not self._stop.is_set():
            try:
                m = self.bus.recv(0.02)
            except Exception:  # noqa: BLE001
                return
            if m is None or m.is_error_frame or m.is_remote_frame:
                continue
            ev = decode_can(m.arbitration_id, bytes(m.data), is_extended_id=m.is_extended_id, is_fd=m.is_fd)
            if isinstance(ev, Message) and ev.DIRECTION == Direction.CHIP_TO_HOST:
                prio, _t, _v, _n = split_id(m.arbitration_id)
                if prio != ev.PRIORITY:
                    self.bad_ids.append(f"{ev.TYPE.name} sent with priority {prio}, table says {ev.PRIORITY}")
                if m.is_fd and len(ev.payload()) <= 8:
                    self.bad_ids.append(f"{ev.TYPE.name} sent as CAN FD though it fits classic CAN")
            self._put(ev)

    def send_frame(self, f: CanFrame, *, extended: bool = True) -> float:
        msg = self._can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=extended,
                                is_fd=f.is_fd)
        self.bus.send(msg)
        return time.monotonic()

    def send(self, msg: Message) -> float:
        return self.send_frame(to_can(msg))

    def send_raw(self, type_code: int, node: int, payload: bytes, version: int = PROTOCOL_VERSION) -> float:
        return self.send_frame(CanFrame(make_id(type_code, node, priority=4, version=version), payload, False))

    def _close(self) -> None:
        try:
            self.bus.shutdown()
        except Exception:  # noqa: BLE001
            pass


# ---------------------------------------------------------------------------------------------
# The session: one chip, tracked through its node id
# ---------------------------------------------------------------------------------------------

class CheckFailed(AssertionError):
    pass


class Skip(Exception):
    pass


def require(cond: bool, what: str) -> None:
    if not cond:
        raise CheckFailed(what)


@dataclass
class Session:
    link: Link
    timeout_s: float = 0.5
    node: int = 42  #: the node id assigned for the run
    slack_ms: float = 10.0
    uid: int | None = None
    cur: int | None = None  #: the chip's current node id
    info: Info | None = None
    notes: list[str] = field(default_factory=list)

    # ---- receiving
    def mine(self, m) -> bool:
        if not isinstance(m, Message) or m.DIRECTION != Direction.CHIP_TO_HOST:
            return False
        if isinstance(m, Announce):
            return self.uid is None or m.uid == self.uid
        # its current node, or the node this run assigns (an ACK to ASSIGN comes from the new id)
        return m.node == self.cur or m.node == self.node

    def collect(self, duration_s: float, stop: Callable[[list], bool] | None = None) -> list:
        """This chip's messages (with arrival times) for ``duration_s`` or until ``stop(msgs)``."""
        out: list = []
        end = time.monotonic() + duration_s
        while True:
            left = end - time.monotonic()
            if left <= 0:
                return out
            item = self.link.get(min(left, 0.05))
            if item is None:
                continue
            t, m = item
            if isinstance(m, Announce) and self.mine(m):
                self.cur = m.node  # a re-announce may come from a new provisional id
            if self.mine(m):
                out.append((t, m))
                if stop is not None and stop([x for _, x in out]):
                    return out

    def request(self, msg: Message, n: int = 1, timeout_s: float | None = None) -> list[Message]:
        """Send and return this chip's first ``n`` answers (fewer on timeout)."""
        self.link.drain()
        self.link.send(msg)
        got = self.collect(timeout_s or self.timeout_s, lambda ms: len(ms) >= n)
        return [m for _, m in got]

    def raw(self, type_code: int, node: int, payload: bytes, version: int = PROTOCOL_VERSION,
            n: int = 1, timeout_s: float | None = None) -> list[Message]:
        self.link.drain()
        self.link.send_raw(type_code, node, payload, version)
        return [m for _, m in self.collect(timeout_s or self.timeout_s, lambda ms: len(ms) >= n)]

    def silent(self, msg_or_send, duration_s: float | None = None) -> list[Message]:
        """Send and return everything this chip says within the timeout (should be nothing)."""
        self.link.drain()
        if isinstance(msg_or_send, Message):
            self.link.send(msg_or_send)
        else:
            msg_or_send()
        return [m for _, m in self.collect(duration_s or self.timeout_s)
                if not isinstance(m, (Status, Announce, Info))]  # heartbeats and re-announces are not answers

    def status(self) -> Status:
        """The next STATUS heartbeat (CONFIG sets the period to 100 ms for the run)."""
        self.link.drain()
        got = self.collect(max(1.5, 3 * self.timeout_s), lambda ms: any(isinstance(m, Status) for m in ms))
        st = [m for _, m in got if isinstance(m, Status)]
        require(bool(st), "no STATUS heartbeat within 1.5 s")
        return st[-1]

    # ---- getting the chip to a known state
    def to_boot(self) -> None:
        ans = self.request(Reset(self.cur), 3)
        require(len(ans) == 3 and ans[0] == Ack(ans[0].node, MsgType.RESET, 0),
                f"RESET not answered ACK, ANNOUNCE, INFO: {ans}")
        self.cur = ans[1].node

    def refresh_node(self) -> None:
        """An unassigned chip changes its provisional id as it re-announces: ask where it is now."""
        self.link.drain()
        self.link.send(GetInfo(0))
        self.collect(self.timeout_s, lambda ms: any(isinstance(m, Info) for m in ms))

    def to_idle(self) -> None:
        if self.info is None or self.cur is None:
            raise Skip("no chip found")
        self.to_boot()
        ans = self.request(Assign(self.cur, new_node=self.node, link=0, uid_low=self.uid & 0xFFFFFFFF))
        require(ans == [Ack(self.node, MsgType.ASSIGN, 0)], f"ASSIGN answered {ans}")
        self.cur = self.node
        ans = self.request(Config(self.node, rate_hz=145, range=0, filter=0, heartbeat_ms=100))
        require(ans == [Ack(self.node, MsgType.CONFIG, 0)], f"CONFIG answered {ans}")

    def to_streaming(self) -> None:
        self.to_idle()
        ans = self.request(Start(self.node))
        require(ans == [Ack(self.node, MsgType.START, 0)], f"START answered {ans}")


# ---------------------------------------------------------------------------------------------
# The checks
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Check:
    number: int
    clause: str
    title: str
    fn: Callable[[Session], str | None]
    transport: str | None = None  # only on this transport


CHECKS: list[Check] = []


def check(clause: str, title: str, transport: str | None = None):
    def deco(fn):
        CHECKS.append(Check(len(CHECKS) + 1, clause, title, fn, transport))
        return fn
    return deco


@check("§4.13", "GET_INFO (broadcast) is answered with ANNOUNCE then INFO")
def c_discover(s: Session):
    s.link.drain()
    s.link.send(GetInfo(0))
    # the first chip to announce is the one under test
    end = time.monotonic() + max(1.5, 3 * s.timeout_s)
    ann = None
    while time.monotonic() < end and ann is None:
        item = s.link.get(0.05)
        if item is not None and isinstance(item[1], Announce):
            ann = item[1]
    require(ann is not None, "no ANNOUNCE in answer to a broadcast GET_INFO")
    s.uid, s.cur = ann.uid, ann.node
    got = s.collect(s.timeout_s, lambda ms: any(isinstance(m, Info) for m in ms))
    infos = [m for _, m in got if isinstance(m, Info)]
    require(bool(infos), f"ANNOUNCE from node 0x{ann.node:04X} not followed by INFO")
    s.info = infos[0]
    return f"uid 0x{s.uid:016X}, node 0x{s.cur:04X}, state {s.info.state.name}"


@check("§4.2", "INFO: protocol version 1, 12-bit ADC, a defined state")
def c_info(s: Session):
    if s.info is None:
        raise Skip("no chip found")
    require(s.info.protocol_version == PROTOCOL_VERSION, f"protocol_version {s.info.protocol_version}")
    require(s.info.adc_bits == 12, f"adc_bits {s.info.adc_bits}")
    return (f"firmware {s.info.fw_major}.{s.info.fw_minor}.{s.info.fw_patch}, "
            f"capabilities {s.info.capabilities!r}")


@check("§4.14", "RESET: ACK from the current node, then ANNOUNCE + INFO in BOOT")
def c_reset(s: Session):
    if s.info is None:
        raise Skip("no chip found")
    before = s.cur
    ans = s.request(Reset(s.cur), 3)
    require(len(ans) == 3, f"expected ACK, ANNOUNCE, INFO; got {ans}")
    require(ans[0] == Ack(before, MsgType.RESET, 0), f"first answer {ans[0]}")
    require(isinstance(ans[1], Announce) and ans[1].uid == s.uid, f"second answer {ans[1]}")
    require(isinstance(ans[2], Info) and ans[2].state == ChipState.BOOT, f"third answer {ans[2]}")
    s.cur = ans[1].node


@check("§3.2", "an unassigned chip speaks from a provisional node id (0x8000..0xFFFE)")
def c_provisional(s: Session):
    if s.cur is None:
        raise Skip("no chip found")
    require(NODE_PROVISIONAL_MIN <= s.cur <= NODE_PROVISIONAL_MAX, f"node 0x{s.cur:04X}")
    rec = provisional_node(s.uid, 0)
    return "the recommended provisional_node(uid, 0)" if s.cur == rec else \
        f"0x{s.cur:04X} (not the recommended 0x{rec:04X}; allowed)"


@check("§3.2", "an unassigned chip repeats ANNOUNCE + INFO every second")
def c_reannounce(s: Session):
    if s.cur is None:
        raise Skip("no chip found")
    s.link.drain()
    t0 = time.monotonic()
    got = s.collect(ANNOUNCE_PERIOD_S * 2.5, lambda ms: sum(isinstance(m, Announce) for m in ms) >= 2)
    times = [t for t, m in got if isinstance(m, Announce)]
    require(len(times) >= 2, f"{len(times)} ANNOUNCE in {ANNOUNCE_PERIOD_S * 2.5:.1f} s")
    period = times[1] - times[0]
    require(0.5 * ANNOUNCE_PERIOD_S <= period <= 1.5 * ANNOUNCE_PERIOD_S, f"period {period:.3f} s")
    infos = [m for _, m in got if isinstance(m, Info)]
    require(bool(infos), "re-ANNOUNCE without INFO")
    return f"period {period:.3f} s (first after {times[0] - t0:.3f} s)"


@check("§8", "a command not allowed in BOOT is refused: NACK BAD_STATE")
def c_bad_state_boot(s: Session):
    if s.cur is None:
        raise Skip("no chip found")
    ans = s.request(Start(s.cur))
    require(ans == [Nack(s.cur, MsgType.START, NackReason.BAD_STATE)], f"START in BOOT answered {ans}")


@check("§4.10", "ASSIGN whose uid_low is another chip's is ignored silently")
def c_assign_wrong_uid(s: Session):
    if s.cur is None:
        raise Skip("no chip found")
    other = (s.uid ^ 0x5A5A5A5A) & 0xFFFFFFFF
    ans = s.silent(Assign(s.cur, new_node=s.node, link=0, uid_low=other))
    require(ans == [], f"answered {ans}")


@check("§4.10", "ASSIGN: ACK from the new node id; the chip is IDLE")
def c_assign(s: Session):
    if s.cur is None:
        raise Skip("no chip found")
    s.refresh_node()
    ans = s.request(Assign(s.cur, new_node=s.node, link=3, uid_low=s.uid & 0xFFFFFFFF))
    require(ans == [Ack(s.node, MsgType.ASSIGN, 0)], f"answered {ans}")
    s.cur = s.node
    ans = s.request(GetInfo(s.node), 2)
    require(len(ans) == 2 and isinstance(ans[1], Info) and ans[1].state == ChipState.IDLE, f"GET_INFO: {ans}")


@check("§4.11", "CONFIG (valid) is acknowledged")
def c_config(s: Session):
    if s.cur != s.node:
        s.to_idle()
    ans = s.request(Config(s.node, rate_hz=145, range=0, filter=0, heartbeat_ms=100))
    require(ans == [Ack(s.node, MsgType.CONFIG, 0)], f"answered {ans}")


@check("§4.6", "CONFIG with a value out of range: NACK BAD_VALUE")
def c_config_bad_value(s: Session):
    if s.cur != s.node:
        s.to_idle()
    for cfg in (Config(s.node, range=7), Config(s.node, rate_hz=0)):
        ans = s.request(cfg)
        require(ans == [Nack(s.node, MsgType.CONFIG, NackReason.BAD_VALUE)], f"{cfg} answered {ans}")


@check("§4.6", "an undefined type addressed to the chip: NACK UNKNOWN_COMMAND")
def c_unknown(s: Session):
    if s.cur != s.node:
        s.to_idle()
    ans = s.raw(0x3F, s.node, b"")
    require(ans == [Nack(s.node, 0x3F, NackReason.UNKNOWN_COMMAND)], f"answered {ans}")


@check("§4.6", "a payload of the wrong length: NACK BAD_LENGTH")
def c_bad_length(s: Session):
    if s.cur != s.node:
        s.to_idle()
    ans = s.raw(MsgType.START, s.node, b"\x01")
    require(ans == [Nack(s.node, MsgType.START, NackReason.BAD_LENGTH)], f"answered {ans}")


@check("§4.6", "a frame of another protocol version: NACK BAD_VERSION")
def c_bad_version(s: Session):
    if s.cur != s.node:
        s.to_idle()
    ans = s.raw(MsgType.GET_INFO, s.node, b"", version=PROTOCOL_VERSION + 1)
    require(ans == [Nack(s.node, MsgType.GET_INFO, NackReason.BAD_VERSION)], f"answered {ans}")


@check("§4.6", "a field the decoder rejects (CAL_READ axis 3): NACK BAD_VALUE")
def c_bad_field(s: Session):
    if s.cur != s.node:
        s.to_idle()
    ans = s.raw(MsgType.CAL_READ, s.node, b"\x03")
    require(ans == [Nack(s.node, MsgType.CAL_READ, NackReason.BAD_VALUE)], f"answered {ans}")


@check("§4.15", "CAL_WRITE then CAL_READ gives back the calibration (CAL_DATA)")
def c_calibration(s: Session):
    if s.cur != s.node:
        s.to_idle()
    ans = s.request(CalWrite(s.node, axis=1, flags=0, offset_q4=-21, sensitivity=1003.5))
    require(ans == [Ack(s.node, MsgType.CAL_WRITE, 0)], f"CAL_WRITE answered {ans}")
    ans = s.request(CalRead(s.node, axis=1))
    require(ans == [CalData(s.node, axis=1, flags=0, offset_q4=-21, sensitivity=1003.5)], f"CAL_READ answered {ans}")


@check("§4.4", "STATUS heartbeat at the CONFIG period, state IDLE, CONFIGURED flag")
def c_heartbeat(s: Session):
    if s.cur != s.node:
        s.to_idle()
    s.link.drain()
    got = s.collect(0.75, lambda ms: sum(isinstance(m, Status) for m in ms) >= 4)
    st = [(t, m) for t, m in got if isinstance(m, Status)]
    require(len(st) >= 3, f"{len(st)} STATUS in 0.75 s at heartbeat_ms=100")
    period = (st[-1][0] - st[0][0]) / (len(st) - 1)
    require(0.05 <= period <= 0.2, f"period {period * 1000:.0f} ms")
    m = st[-1][1]
    require(m.state == ChipState.IDLE, f"state {m.state.name}")
    require(bool(m.flags & StatusFlag.CONFIGURED), f"flags {m.flags!r}")
    return f"period {period * 1000:.0f} ms, rx_errors {m.rx_errors}"


@check("§6.4", "damaged serial input is dropped silently, counted in rx_errors, and the chip recovers",
       transport="serial")
def c_bad_input_serial(s: Session):
    if s.cur != s.node:
        s.to_idle()
    before = s.status().rx_errors
    body = HEADER.pack(PROTOCOL_VERSION, MsgType.GET_INFO, s.node)
    bad_crc = cobs.encode(body + ((crc16_ccitt_false(body) ^ 0x0100).to_bytes(2, "big"))) + b"\x00"
    junk = [b"\x05\x01\x02\x03\x00", bad_crc, b"\x01" * 1100 + b"\x00", b"\x03\x01\x02\x00"]
    link: SerialLink = s.link  # type: ignore[assignment]
    ans = s.silent(lambda: [link.send_bytes(j) for j in junk])
    require(ans == [], f"answered damaged input with {ans}")
    after = s.status().rx_errors
    require(after - before == len(junk) or after == 255, f"rx_errors {before} -> {after}, expected +{len(junk)}")
    ans = s.request(GetInfo(s.node), 2)
    require(len(ans) == 2, f"no answer to GET_INFO after the damage: {ans}")
    return f"rx_errors {before} -> {after}"


@check("§7", "frames that are not capsheet frames are not answered, and the chip recovers", transport="can")
def c_bad_input_can(s: Session):
    if s.cur != s.node:
        s.to_idle()
    link: CanLink = s.link  # type: ignore[assignment]
    ans = s.silent(lambda: link.send_frame(CanFrame(0x123, b"\x01\x02", False), extended=False))
    require(ans == [], f"answered a standard-identifier frame with {ans}")
    ans = s.request(GetInfo(s.node), 2)
    require(len(ans) == 2, f"no answer to GET_INFO afterwards: {ans}")


@check("§4.12", "START: ACK, the chip is STREAMING")
def c_start(s: Session):
    if s.cur != s.node:
        s.to_idle()
    ans = s.request(Start(s.node))
    require(ans == [Ack(s.node, MsgType.START, 0)], f"answered {ans}")
    ans = s.request(GetInfo(s.node), 2)
    require(len(ans) == 2 and ans[1].state == ChipState.STREAMING, f"GET_INFO: {ans}")


@check("§5.1", "SYNC -> one SAMPLE with the SYNC's counter, within the deadline")
def c_sync(s: Session):
    s.to_streaming()
    lat = []
    for c in range(100, 130):
        s.link.drain()
        t0 = s.link.send(Sync(counter=c))
        got = s.collect(s.timeout_s, lambda ms: any(isinstance(m, Sample) for m in ms))
        smp = [(t, m) for t, m in got if isinstance(m, Sample)]
        require(len(smp) == 1, f"SYNC {c}: {len(smp)} SAMPLE")
        require(smp[0][1].counter == c, f"SYNC {c} answered with counter {smp[0][1].counter}")
        lat.append(smp[0][0] - t0)
    med = statistics.median(lat) * 1000
    limit = SYNC_REPLY_DEADLINE_S * 1000 + s.slack_ms
    require(med <= limit, f"median SYNC->SAMPLE {med:.2f} ms > {limit:.1f} ms")
    return f"median {med:.2f} ms, max {max(lat) * 1000:.2f} ms (host-measured)"


@check("§5.2", "SAMPLE words: 12-bit counts, 4 status bits, steady stream")
def c_sample_word(s: Session):
    s.to_streaming()
    seen = []
    for c in range(200, 210):
        ans = s.request(Sync(counter=c))
        require(len(ans) == 1 and isinstance(ans[0], Sample), f"SYNC {c}: {ans}")
        seen.append(ans[0])
    # decoding already enforces the ranges; a chip that streams zeros everywhere is suspicious
    require(all(-2048 <= v <= 2047 for m in seen for v in (m.x, m.y, m.z)), "counts out of range")
    return f"last {seen[-1].x, seen[-1].y, seen[-1].z} status 0x{seen[-1].status:X}"


@check("§4.9", "SYNC counter wraparound 0xFFFF -> 0 is not a miss; a gap is counted in missed_syncs")
def c_wraparound(s: Session):
    s.to_streaming()
    for c in (0xFFFD, 0xFFFE, 0xFFFF, 0, 1):
        ans = s.request(Sync(counter=c))
        require([m.counter for m in ans if isinstance(m, Sample)] == [c], f"SYNC {c}: {ans}")
    base = s.status().missed_syncs
    require(base == 0, f"missed_syncs {base} after a wraparound without gaps")
    for c in (2, 5):  # 3 and 4 missed
        s.request(Sync(counter=c))
    after = s.status().missed_syncs
    require(after == 2, f"missed_syncs {after} after skipping 2 counters")


@check("§8", "CONFIG while STREAMING: NACK BAD_STATE")
def c_bad_state_streaming(s: Session):
    s.to_streaming()
    ans = s.request(Config(s.node))
    require(ans == [Nack(s.node, MsgType.CONFIG, NackReason.BAD_STATE)], f"answered {ans}")


@check("§4.12", "STOP: ACK, back to IDLE, SYNC no longer answered")
def c_stop(s: Session):
    s.to_streaming()
    ans = s.request(Stop(s.node))
    require(ans == [Ack(s.node, MsgType.STOP, 0)], f"answered {ans}")
    ans = s.silent(Sync(counter=7))
    require(ans == [], f"SYNC after STOP answered {ans}")


@check("§3", "broadcast frames get no NACK (START broadcast in BOOT is ignored)")
def c_broadcast_silent(s: Session):
    if s.info is None:
        raise Skip("no chip found")
    s.to_boot()
    ans = s.silent(Start(0))
    require(ans == [], f"answered {ans}")


@check("§6.2" + "/§7.1", "every frame from the chip decoded (COBS, CRC / identifier layout, priorities)")
def c_framing(s: Session):
    require(s.link.rx_frames > 0, "nothing received")
    require(not s.link.rx_errors, f"{len(s.link.rx_errors)} frames did not decode, first: {s.link.rx_errors[:1]}")
    require(not s.link.bad_ids, "; ".join(s.link.bad_ids[:3]))
    return f"{s.link.rx_frames} frames"


# ---------------------------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CheckResult:
    number: int
    clause: str
    title: str
    outcome: str  # PASS, FAIL, SKIP
    detail: str = ""


def run_checks(link: Link, *, timeout_s: float = 0.5, node: int = 42, slack_ms: float = 10.0,
               only: list[str] | None = None, out=None) -> list[CheckResult]:
    """Run every check (or those whose number or clause starts with one of ``only``) in order."""
    s = Session(link, timeout_s=timeout_s, node=node, slack_ms=slack_ms)
    results = []
    for c in CHECKS:
        if c.transport and c.transport != link.transport:
            continue
        if only and c.number > 1 and not any(str(c.number) == o or c.clause.lstrip("§").startswith(o.lstrip("§"))
                                             for o in only):
            continue  # the discovery check always runs: the others need its chip
        try:
            detail = c.fn(s) or ""
            r = CheckResult(c.number, c.clause, c.title, "PASS", detail)
        except Skip as exc:
            r = CheckResult(c.number, c.clause, c.title, "SKIP", str(exc))
        except CheckFailed as exc:
            r = CheckResult(c.number, c.clause, c.title, "FAIL", str(exc))
        except Exception as exc:  # noqa: BLE001 - a broken device must not stop the battery
            r = CheckResult(c.number, c.clause, c.title, "FAIL", f"{type(exc).__name__}: {exc}")
        results.append(r)
        if out is not None:
            print(f"{r.outcome:4}  {r.number:2d}  {r.clause:10} {r.title}" + (f"  [{r.detail}]" if r.detail else ""),
                  file=out, flush=True)
    if s.cur is not None and s.info is not None:
        try:  # leave the chip unassigned, as a fresh one
            s.to_boot()
        except Exception:  # noqa: BLE001
            pass
    return results


def summary(results: list[CheckResult]) -> str:
    n = {k: sum(r.outcome == k for r in results) for k in ("PASS", "FAIL", "SKIP")}
    return f"conformance: {n['PASS']} checks passed, {n['FAIL']} failed, {n['SKIP']} skipped"
