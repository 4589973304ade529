"""The conformance session: one chip under test, reached through a host transport.

`Port` runs one reader thread over a `host.transport.ports.Transport` (`SerialTransport` or
`CanTransport`) and timestamps what arrives; every wait is event-driven (a condition variable,
woken by each arrival) with an explicit timeout. `Session` tracks the chip under test (its uid,
its current node id, its state as last seen) and gives the checks their few verbs:

============== ====================================================================================
``request``    send, then wait for this chip's answers: until ``n`` arrived or ``timeout_s``
``silent``     send, then everything this chip answered within ``timeout_s`` (should be nothing)
``statuses``   STATUS heartbeats of this chip, until ``n`` arrived or a timeout
``fresh_boot`` RESET and its ACK + ANNOUNCE + INFO: the chip is in BOOT for the next 1 s
``to_idle``    fresh boot, ASSIGN to the run's node id, CONFIG (heartbeat 100 ms)
============== ====================================================================================

Tolerated, never taken as an answer: STATUS heartbeats, and ANNOUNCE/INFO when the request does not
ask for them (an unassigned chip re-announces every second; a gateway may forward other chips').
Frames from other nodes are ignored.

Timeouts (from ``timeout_s``, the ``--timeout`` option, default 0.5 s): an expected answer
``max(1 s, 3 timeout_s)`` (`Session.answer_s`; the wait ends when it arrives); a window in which
the chip must stay silent ``timeout_s``; a heartbeat ``max(1.5 s, 3 timeout_s)``; a re-announce 3.6 s.

The port's own losses are kept apart from the chip's faults: every `DecodeError` the transport
delivers (a damaged frame) and every CAN error frame counts in `Port.damaged`. A check during which
the port lost frames and that failed is retried (`runner`); see `Port.lossy`.

Transport errors (the port went away, a send failed) are raised as the transport raises them
(`host.transport.ports.TransportError`): they end the run.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Callable

from host.session.gateways import GatewayRecord
from host.transport.ports import CanTransport, Transport, TransportError, TransportOperationError
from protocol.can import decode_can, split_id
from protocol.can import INCOMPLETE_IMU
from protocol.framing import DecodeError
from protocol.messages import ImuBatch, SampleBatch
from protocol.messages import (LINK_NONE, MSG_TYPE_CODES, NODE_MAX_ASSIGNED, Ack, Announce, Assign, Capability, ChipState, Config,
                               Direction, GatewayFlag, GatewayInfo, GetInfo, ImuSample, Info, Message, MsgType, Reset,
                               Sample, Snapshot, SnapshotImu, Start, Status, Stop, Sync, is_node_to_host_type)


__all__ = ["Port", "SimulatedClock", "SimulatedPort", "Session", "CheckFailed", "Skip", "PortLost", "RunAborted", "require", "acked", "AuditedCanTransport",
           "FrameAudit", "HEARTBEAT_MS", "SAMPLES"]

#: STATUS period the run configures (CONFIG heartbeat_ms), ms
HEARTBEAT_MS = 100
#: what answers a SYNC for the chip under test, whatever record format reaches the host: its SAMPLE or
#: IMU_SAMPLE (classic CAN's IMU frames assembled), or its link in a gateway's SNAPSHOT or SNAPSHOT_IMU
#: (`Session.collect` turns those into the SAMPLE or IMU_SAMPLE they stand for)
SAMPLES = (Sample, ImuSample)


class CheckFailed(AssertionError):
    """The chip under test violated the clause; the message says how."""


class Skip(Exception):
    """The check cannot run (no chip found, or a broadcast check without --allow-broadcast)."""


def acked(ans: list, node: int, command: int) -> bool:
    """``ans`` is exactly one ACK of ``command`` from ``node`` (its ``detail`` is check 31's business)."""
    return len(ans) == 1 and isinstance(ans[0], Ack) and ans[0].node == node and ans[0].command == command


class RunAborted(Exception):
    """The run cannot go on for a reason that is not the chip's (e.g. ``--node`` is another chip's)."""


class PortLost(Exception):
    """The port lost frames during the check: inconclusive, not a chip violation."""


def require(cond: bool, what: str) -> None:
    if not cond:
        raise CheckFailed(what)


# ---------------------------------------------------------------------------------------------
# Raw-frame audits: capture handlers on the host transports (`Transport.begin_capture`)
# ---------------------------------------------------------------------------------------------

class FrameAudit:
    """A capture handler (`host.transport.ports.Transport.begin_capture`) that keeps every frame the port
    received, raw, and audits CAN identifiers (§7.1: the priority the table gives the type, no CAN
    FD for a payload that fits classic CAN).

    ``raw``: serial — each run of bytes between delimiters, with its 0x00 (what the chip sent,
    for the §2/§9 comparison with the reference encoding); CAN — ``(arbitration_id, data, is_fd)``
    of every extended data frame, the echoes of the host's own frames left out (a bus that hands
    them back, python-can's ``udp_multicast``, must not make the suite blame the chip for them).
    At most ``keep``, newest last. ``bad_ids``: one line per identifier the audit rejects.
    """

    def __init__(self, keep: int = 4096) -> None:
        self.raw: deque = deque(maxlen=keep)
        self.bad_ids: list[str] = []
        self._run = bytearray()  # serial: the start of a run not yet delimited

    def __call__(self, cap) -> None:
        if cap.direction != "rx":
            return
        if cap.kind == "serial":
            self._serial(cap.raw)
            return
        for f in cap.frames():
            if f.is_error_frame or f.is_remote_frame or not f.is_extended_id:
                continue
            data = bytes(f.data)
            self.raw.append((f.arbitration_id, data, bool(f.is_fd)))
            ev = decode_can(f.arbitration_id, data, is_extended_id=True, is_fd=f.is_fd)
            if isinstance(ev, Message) and ev.DIRECTION == Direction.CHIP_TO_HOST:
                prio = split_id(f.arbitration_id)[0]
                if prio != ev.PRIORITY:
                    self.bad_ids.append(f"{ev.TYPE.name} sent with priority {prio}, the table says {ev.PRIORITY}")
                if f.is_fd and len(ev.payload()) <= 8:
                    self.bad_ids.append(f"{ev.TYPE.name} sent as CAN FD though it fits classic CAN")

    def _serial(self, data: bytes) -> None:
        parts = bytes(data).split(b"\x00")
        for p in parts[:-1]:
            run = bytes(self._run) + p
            self._run.clear()
            if run:
                self.raw.append(run + b"\x00")
        self._run += parts[-1]
        if len(self._run) > 2048:
            self._run.clear()


class _AuditView:
    """``raw`` and ``bad_ids`` of the object's ``audit`` (a `FrameAudit`)."""

    audit: FrameAudit

    @property
    def raw(self) -> deque:
        """Every frame received, raw (`FrameAudit.raw`: serial byte runs, or CAN ``(id, data, fd)``)."""
        return self.audit.raw

    @property
    def bad_ids(self) -> list[str]:
        """CAN identifiers the audit rejected (`FrameAudit.bad_ids`)."""
        return self.audit.bad_ids


class AuditedCanTransport(_AuditView, CanTransport):
    """A `CanTransport` with a `FrameAudit` subscribed to its capture from the start: ``raw`` and
    ``bad_ids`` are the audit's. Raw frames (undefined types, another version, standard ids) go
    out through the transport's own `CanTransport.send_frame`."""

    def __init__(self, *args, **kw) -> None:
        super().__init__(*args, **kw)
        self.audit = FrameAudit()
        self.begin_capture(self.audit)


# ---------------------------------------------------------------------------------------------
# The port: a reader thread, arrival times, event-driven waits
# ---------------------------------------------------------------------------------------------

class Port(_AuditView):
    """The transport to the device, read by one thread; ``next(deadline)`` blocks on arrivals.

    Parameters
    ----------
    transport : Transport
        An open `SerialTransport` (any pyserial URL: a pty, ``socket://`` to QEMU, a USB adapter)
        or `CanTransport`. The port subscribes a `FrameAudit` to its capture (an
        `AuditedCanTransport` has one already), so the checks see every frame received, raw.
    """

    def __init__(self, transport: Transport) -> None:
        self.transport = transport
        kind = transport.capabilities.kind
        self.kind = "can" if kind == "can" else "serial"
        #: every frame received, raw, and the CAN identifier audit (`FrameAudit`)
        self.audit = transport.audit if isinstance(transport, AuditedCanTransport) else FrameAudit()
        if not isinstance(transport, AuditedCanTransport):
            transport.begin_capture(self.audit)
        self._q: deque = deque()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self.error: BaseException | None = None
        self.frames = 0  #: messages decoded
        self.damaged = 0  #: frames that arrived damaged (DecodeError) plus CAN error frames
        self.incomplete_imu = 0  #: classic CAN IMU frames that made no record (docs/protocol.md §16.4)
        self.damage: Counter = Counter()  #: reason -> count
        self._err_base = transport.stats.errors.get("CAN_ERROR_FRAME", 0)
        self._disc_base = transport.stats.disconnects
        self._thread: threading.Thread | None = None
        self._start_reader()

    # -- the clock: every time the session and the checks read or wait on is the port's
    def now(self) -> float:
        """The port's clock, seconds: `time.monotonic` here (`host.conformance.simulated.SimulatedPort`:
        the simulated clock). Arrival and send times, deadlines and the checks' own waits all read it."""
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` of the port's clock pass (what arrives meanwhile is queued for `next`)."""
        if seconds > 0:
            time.sleep(seconds)

    # -- the reader
    def _start_reader(self) -> None:
        self._thread = threading.Thread(target=self._reader, name="conformance-port", daemon=True)
        self._thread.start()

    def _went_away(self) -> bool:
        """The transport lost its device (a disconnect counted): `error` says so."""
        if self.transport.stats.disconnects > self._disc_base:
            self.error = TransportOperationError(f"The port {self.transport.name!r} went away during the run",
                                                 self.transport.name)
            return True
        return False

    def _reader(self) -> None:
        while not self._stop.is_set():
            try:
                events = self.transport.recv(0.05)
            except TransportError as exc:
                if not self._stop.is_set():
                    self.error = exc
                with self._cond:
                    self._cond.notify_all()
                return
            if self._went_away():
                with self._cond:
                    self._cond.notify_all()
                return
            if not events:
                continue
            t = self.now()
            with self._cond:
                self._take(events, t)
                self._cond.notify_all()

    def _take(self, events: list, t: float) -> None:
        """Queue what the transport delivered at ``t`` (and count it); the caller holds ``_cond``."""
        for ev in events:
            if isinstance(ev, (SampleBatch, ImuBatch)):
                for m in ev.messages():
                    self.frames += 1
                    self._q.append((t, m))
            elif isinstance(ev, DecodeError) and ev.detail.startswith(INCOMPLETE_IMU):
                # classic CAN frames of an IMU record that do not make one (§16.4): every frame
                # arrived intact, so the node sent them so; the §16 checks see no record
                self.incomplete_imu += 1
            elif isinstance(ev, DecodeError):
                self.damaged += 1
                self.damage[ev.reason.name] += 1
                self._q.append((t, ev))
            else:
                self.frames += 1
                self._q.append((t, ev))

    def _error_frames(self) -> int:
        return self.transport.stats.errors.get("CAN_ERROR_FRAME", 0) - self._err_base

    @property
    def lost(self) -> int:
        """Frames damaged on the port so far (decode errors and CAN error frames)."""
        return self.damaged + self._error_frames()

    @property
    def lossy(self) -> bool:
        """The port damages some frames but delivers most intact (a noisy port, not a broken chip:
        a chip whose every frame is damaged, e.g. a wrong CRC, is the chip's fault, §6.2)."""
        return self.lost > 0 and self.frames >= 2 * self.lost

    def next(self, deadline: float):
        """The next ``(arrival_time, Message | DecodeError)``, or None at ``deadline`` (the port's clock, `now`).

        Raises the transport's error if the port went away."""
        with self._cond:
            while not self._q:
                if self.error is not None:
                    raise self.error
                left = deadline - self.now()
                if left <= 0:
                    return None
                self._cond.wait(left)
            return self._q.popleft()

    def drain(self) -> None:
        with self._cond:
            self._q.clear()

    # -- sending (TransportError propagates)
    def send(self, msg: Message) -> float:
        if self.error is not None:
            raise self.error
        self.transport.send(msg)
        return self.now()

    def send_raw(self, type_code: int, node: int, payload: bytes, *, version: int | None = None) -> float:
        """A frame a conforming host never sends (undefined type, wrong length or version)."""
        from protocol.can import make_id
        from protocol.framing import encode_frame
        from protocol.messages import PROTOCOL_VERSION
        v = PROTOCOL_VERSION if version is None else version
        if self.kind == "serial":
            self.transport.send_bytes(encode_frame(type_code, node, payload, version=v))
        else:
            self._can_raw(make_id(type_code, node, priority=4, version=v), payload)
        return self.now()

    def send_bytes(self, data: bytes) -> float:
        self.transport.send_bytes(data)
        return self.now()

    def _can_raw(self, arbitration_id: int, data: bytes, extended: bool = True) -> None:
        if not isinstance(self.transport, CanTransport):
            raise Skip("raw CAN frames need a CAN transport")
        self.transport.send_frame(arbitration_id, data, extended=extended)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.transport.end_capture(self.audit)


# ---------------------------------------------------------------------------------------------
# The port on a simulated clock (host/conformance/simulated.py says what it is for)
# ---------------------------------------------------------------------------------------------

#: when the device names no later event (it is down in an outage), time moves on by its loop's poll period
_IDLE_STEP_S = 0.01


class SimulatedClock:
    """Seconds that move only when the run moves them (`advance_to`); call it for the time.

    Pass the same clock to the device (``clock=``) and to `SimulatedPort`."""

    def __init__(self, start_s: float = 0.0) -> None:
        self.t = float(start_s)

    def __call__(self) -> float:
        return self.t

    def advance_to(self, t: float) -> None:
        """Move to ``t`` (never back: an earlier ``t`` leaves the clock where it is)."""
        if t > self.t:
            self.t = float(t)

    def __repr__(self) -> str:
        return f"SimulatedClock({self.t:.6f})"


class SimulatedPort(Port):
    """A `Port` on a simulated clock, over the host's end of an in-process device in manual mode.

    Parameters
    ----------
    transport : Transport
        The host's end of ``device``: a `MemoryTransport` over ``device.port`` (serial), or an
        `AuditedCanTransport` on the device's python-can ``virtual`` channel. Read without waiting.
    device : virtual_sheet.devices.Device
        Built with ``clock=`` ``clock`` and started (manual mode: no thread; the port runs it with
        ``device.step()``).
    clock : SimulatedClock, optional
        Default: ``device.clock``, which must then be a `SimulatedClock`.

    ``steps``: how many times the port stepped the device (a run's cost, the same on every run).
    """

    def __init__(self, transport: Transport, device, clock: SimulatedClock | None = None) -> None:
        clock = device.clock if clock is None else clock
        if not isinstance(clock, SimulatedClock):
            raise ValueError(f"Invalid clock {clock!r}: a SimulatedPort needs a SimulatedClock (the device's, "
                             f"given as clock= when it was built)")
        if device.clock is not clock:
            raise ValueError("the device runs on another clock: build it with clock= the port's SimulatedClock")
        self.clock = clock
        self.device = device
        self.steps = 0
        super().__init__(transport)

    def _start_reader(self) -> None:  # the caller's thread reads, in `_pump`
        pass

    def now(self) -> float:
        return self.clock.t

    def _pump(self) -> None:
        """Step the device at the clock's time (it reads what the host sent, serves its timers, sends
        what is due) and queue everything the transport then holds, as arrived now."""
        self.device.step()
        self.steps += 1
        while True:
            events = self.transport.recv(0.0)  # TransportError propagates, as the reader thread's does
            if self._went_away():
                raise self.error
            if not events:
                return
            self._take(events, self.clock.t)

    def _next_event(self) -> float:
        """When the device next has something to do (after the clock's time)."""
        now = self.clock.t
        t = min(gw.next_deadline() for gw in self.device.gateways)
        return t if t > now else now + _IDLE_STEP_S

    def next(self, deadline: float):
        """The next ``(arrival_time, Message | DecodeError)``, or None at ``deadline``: the device runs
        from one event to the next until something arrives or the clock reaches ``deadline``."""
        while True:
            if self.error is not None:
                raise self.error
            self._pump()
            if self._q:
                return self._q.popleft()
            if self.clock.t >= deadline:
                return None
            self.clock.advance_to(min(deadline, self._next_event()))

    def sleep(self, seconds: float) -> None:
        """Run the device for ``seconds`` of the clock; what arrives meanwhile is queued, at its time."""
        end = self.clock.t + max(0.0, seconds)
        while True:
            self._pump()
            if self.clock.t >= end:
                return
            self.clock.advance_to(min(end, self._next_event()))

    def drain(self) -> None:
        """Discard what has arrived by now (the device stepped at the clock's time first, as a reader
        thread would have read it by now)."""
        self._pump()
        self._q.clear()

    def close(self) -> None:
        """End the port's capture (the device and the transport are the caller's to close)."""
        self._stop.set()
        self.transport.end_capture(self.audit)


# ---------------------------------------------------------------------------------------------
# The session: one chip, tracked through its node id
# ---------------------------------------------------------------------------------------------

#: never taken as the answer to a command: heartbeats, (re-)announces, and samples or IMU records — a streaming chip
#: behind a gateway that drives SYNC answers that SYNC all the time (a SYNC check collects them itself)
_TOLERATED = (Status, Announce, Info, GatewayInfo, Sample, ImuSample)


def _cobs_head(encoded: bytes, n: int = 4) -> bytes | None:
    """The first ``n`` bytes of a COBS run (a damaged frame's excerpt), or None."""
    out = bytearray()
    i = 0
    while i < len(encoded) and len(out) < n:
        code = encoded[i]
        if code == 0:
            return None
        out += encoded[i + 1:i + code]
        i += code
        if i < len(encoded) and code != 0xFF:
            out.append(0)
    return bytes(out[:n]) if len(out) >= n else None


@dataclass
class Session:
    """The chip under test and the run's settings. See the module docstring."""

    port: Port
    timeout_s: float = 0.5
    node: int | None = None  #: the node id assigned for the run (None: pick a free one)
    slack_ms: float = 10.0
    uid: int | None = None  #: the chip under test (None: the first to answer)
    allow_broadcast: bool = False
    cur: int | None = None  #: the chip's current node id
    info: Info | None = None
    first_info: Info | None = None  #: INFO as found at discovery
    nodes_seen: dict = field(default_factory=dict)  #: node id -> uid (or None) of every chip heard
    boot_t: float = 0.0  #: when the chip last entered BOOT (its ANNOUNCE arrived)
    my_nodes: set = field(default_factory=set)  #: every node id the chip under test spoke from
    acks: list = field(default_factory=list)  #: every ACK the chip under test sent (§4.5 detail)
    profile: str = "chip"  #: "chip" or "gateway": which kind of node is under test (§11)
    link: int = 0  #: the link the run assigns the chip (a packing gateway's first link, if there is one)
    gateways: dict = field(default_factory=dict)  #: uid -> host.gateways.GatewayRecord of every gateway heard
    uids_heard: dict = field(default_factory=dict)  #: uid -> "chip" / "gateway" / None (INFO not yet seen)
    #: (type, intact?) -> frames of the node under test by type: a type whose every frame fails its CRC
    #: while others arrive intact is the node's encoding, not the port (§6.2; `systematic_damage`)
    by_type: Counter = field(default_factory=Counter)
    _last_announce: dict = field(default_factory=dict)  #: node -> the uid of its last ANNOUNCE
    node_of_uid: dict = field(default_factory=dict)  #: uid -> the node id of its last ANNOUNCE
    #: SYNC counter -> when the suite sent it or last heard it (a SYNC-source gateway's, forwarded): an answer
    #: with that counter arriving later answers that SYNC (a packing gateway's up to 10 ms later, §13.2)
    syncs_heard: dict = field(default_factory=dict)

    @property
    def answer_s(self) -> float:
        """How long to wait for an expected answer: ``max(1 s, 3 timeout_s)``. The wait ends as soon as
        the answer is there, so this costs time only when the chip does not answer; the windows in
        which a chip must stay silent are ``timeout_s``."""
        return max(1.0, 3 * self.timeout_s)

    # ---- receiving
    def mine(self, m) -> bool:
        if not isinstance(m, Message) or m.DIRECTION != Direction.CHIP_TO_HOST:
            return False
        if isinstance(m, Announce):
            return self.uid is None or m.uid == self.uid
        # its current node, or the node this run assigns (the ACK to ASSIGN comes from the new id)
        return m.node == self.cur or (self.node is not None and m.node == self.node)

    def packing_gateway_for_any(self) -> GatewayRecord | None:
        """The first gateway heard that packs some links (the run then gives the chip one of them)."""
        for g in self.gateways.values():
            if g.flags & GatewayFlag.PACKING and g.first_link() is not None:
                return g
        return None

    @property
    def packing_gateway(self) -> GatewayRecord | None:
        """A gateway that packs the link the run gives the chip (its SAMPLEs come in SNAPSHOTs)."""
        if self.profile != "chip":
            return None
        for g in self.gateways.values():
            if g.flags & GatewayFlag.PACKING and g.covers(self.link):
                return g
        return None

    @property
    def sync_gateway(self) -> GatewayRecord | None:
        """A gateway that is its segment's SYNC source: SYNC from this suite does not reach the chip."""
        if self.profile != "chip":
            return None
        for g in self.gateways.values():
            if g.flags & GatewayFlag.SYNC_SOURCE:
                return g
        return None

    def _from_snapshot(self, m: Snapshot | SnapshotImu) -> Sample | ImuSample | None:
        """The chip under test's sample in a SNAPSHOT or SNAPSHOT_IMU (a packing gateway's), as the SAMPLE
        or IMU_SAMPLE it stands for: a chip is reached by whichever record format its gateway packs
        (§13.2, §16.5), and every check of its samples reads them from any of them."""
        if self.profile != "chip" or self.node is None or self.cur != self.node \
                or not (m.first_link <= self.link < m.first_link + m.count):
            return None
        k = self.link - m.first_link
        if isinstance(m, SnapshotImu):
            counts, status, t_us, gyro, mag = m.arrays()
            mg = (None, None, None) if mag is None else tuple(mag[k].tolist())
            return ImuSample(self.node, m.counter, *counts[k].tolist(), int(status[k]), int(t_us[k]),
                             *gyro[k].tolist(), *mg)
        (x, y, z), st = m.counts[k].tolist(), int(m.status[k])
        return Sample(self.node, m.counter, x, y, z, st)

    def note(self, t: float, m) -> None:
        """Bookkeeping of every frame heard: node ids in use, uids, gateways, the node's frames by type."""
        if isinstance(m, Sync):
            self.syncs_heard[m.counter] = t
            return
        if isinstance(m, DecodeError):
            hdr = _cobs_head(m.excerpt) if m.reason.name == "BAD_CRC" else None
            if hdr is not None and hdr[0] == 1 and is_node_to_host_type(hdr[1]) and \
                    int.from_bytes(hdr[2:4], "little") in (self.my_nodes | {self.cur, self.node}):
                self.by_type[(hdr[1], False)] += 1
            return
        if not isinstance(m, Message) or m.DIRECTION != Direction.CHIP_TO_HOST:
            return
        self.nodes_seen.setdefault(m.node, m.uid if isinstance(m, Announce) else None)
        if isinstance(m, Announce):
            self._last_announce[m.node] = m.uid
            self.node_of_uid[m.uid] = m.node
            self.uids_heard.setdefault(m.uid, None)
            if m.uid in self.gateways:
                self.gateways[m.uid].node = m.node
        elif isinstance(m, Info) and m.node in self._last_announce:
            uid = self._last_announce[m.node]
            kind = "gateway" if m.capabilities & Capability.GATEWAY else "chip"
            self.uids_heard[uid] = kind
            if kind == "gateway":
                g = self.gateways.setdefault(uid, GatewayRecord(uid, m.node, bus=0))
                g.node, g.info = m.node, m
        elif isinstance(m, GatewayInfo):
            for g in self.gateways.values():
                if g.node == m.node:
                    g.runs[m.first_link] = m
        if m.node in self.my_nodes or m.node in (self.cur, self.node):
            self.by_type[(int(m.TYPE), True)] += 1

    def systematic_damage(self) -> str | None:
        """A message type every frame of which, from the node under test, failed its CRC (at least 3)
        while its other types arrived intact: the node's encoding (§6.2), not a lossy port."""
        intact_any = sum(v for (t, ok), v in self.by_type.items() if ok)
        for (t, ok), bad in self.by_type.items():
            if ok or bad < 3 or self.by_type.get((t, True), 0) or not intact_any:
                continue
            name = MsgType(t).name if t in MSG_TYPE_CODES else f"type 0x{t:02X}"
            return (f"§6.2: every {name} frame from the node ({bad} of {bad}) fails its CRC while its other "
                    f"frames ({intact_any}) arrive intact: the node's CRC, not the port")
        return None

    def collect(self, duration_s: float, stop: Callable[[list], bool] | None = None, *,
                syncs: bool = False) -> list:
        """This node's messages, ``[(arrival_time, msg)]``, for ``duration_s`` or until ``stop(msgs)``.

        A packing gateway's SNAPSHOT that covers the chip's link counts as the SAMPLE it carries for
        the chip; with ``syncs`` the SYNC frames heard (a gateway's, forwarded) are kept too. Every
        frame heard updates the bookkeeping (`note`), and ``stop`` is asked after each."""
        out: list = []
        deadline = self.port.now() + duration_s
        while True:
            item = self.port.next(deadline)
            if item is None:
                return out
            t, m = item
            self.note(t, m)
            if syncs and isinstance(m, Sync):
                pass
            elif isinstance(m, (Snapshot, SnapshotImu)):
                m = self._from_snapshot(m)
            elif not self.mine(m):
                m = None
            if m is not None:
                if isinstance(m, Announce):
                    self.cur = m.node  # a re-announce comes from a new provisional id
                    self.boot_t = t
                if not isinstance(m, Sync):
                    self.my_nodes.add(m.node)
                if isinstance(m, Ack):
                    self.acks.append(m)
                    if m.command == MsgType.ASSIGN:
                        self.cur = m.node  # assigned (even by an ASSIGN it should have ignored)
                out.append((t, m))
            if stop is not None and stop([x for _, x in out]):
                return out

    def drain(self) -> None:
        """Consume what has arrived (keeping track of the chip's node id), before a new request."""
        self.collect(0.0)

    @staticmethod
    def answers(got: list, keep: tuple = ()) -> list[Message]:
        """Drop what is tolerated (heartbeats, re-announces) unless its type is in ``keep``."""
        return [m for _, m in got if not isinstance(m, _TOLERATED) or isinstance(m, keep)]

    def request(self, msg: Message, n: int = 1, timeout_s: float | None = None, keep: tuple = ()) -> list[Message]:
        """Send ``msg`` and return this chip's first ``n`` answers (fewer on timeout)."""
        self.drain()
        self.port.send(msg)
        got = self.collect(timeout_s or self.answer_s, lambda ms: len(self._ans(ms, keep)) >= n)
        return self.answers(got, keep)

    def _ans(self, ms: list, keep: tuple) -> list:
        return [m for m in ms if not isinstance(m, _TOLERATED) or isinstance(m, keep)]

    def request_info(self, node: int) -> list[Message]:
        """GET_INFO to ``node``: the ANNOUNCE + INFO answer."""
        return self.request(GetInfo(node), 2, keep=(Announce, Info))

    def raw(self, type_code: int, node: int, payload: bytes, version: int | None = None, n: int = 1,
            timeout_s: float | None = None) -> list[Message]:
        self.drain()
        self.port.send_raw(type_code, node, payload, version=version)
        got = self.collect(timeout_s or self.answer_s, lambda ms: len(self._ans(ms, ())) >= n)
        return self.answers(got)

    def silent(self, send: Message | Callable[[], object], duration_s: float | None = None) -> list[Message]:
        """Send and return everything this chip answered within the timeout (should be nothing); a
        SAMPLE counts as an answer here (a SYNC that should go unanswered)."""
        self.drain()
        if isinstance(send, Message):
            self.port.send(send)
        else:
            send()
        return self.answers(self.collect(duration_s or self.timeout_s), keep=(Sample,))

    def statuses(self, n: int, timeout_s: float | None = None) -> list:
        """``[(arrival_time, Status)]``: this chip's next ``n`` heartbeats (fewer on timeout)."""
        got = self.collect(timeout_s or max(1.5, 3 * self.timeout_s),
                           lambda ms: sum(isinstance(m, Status) for m in ms) >= n)
        return [(t, m) for t, m in got if isinstance(m, Status)]

    def status(self) -> Status:
        """The next STATUS heartbeat."""
        self.drain()
        st = self.statuses(1)
        require(bool(st), f"no STATUS heartbeat within {max(1.5, 3 * self.timeout_s):.1f} s")
        return st[-1][1]

    # ---- getting the chip to a known state
    def need_chip(self) -> None:
        if self.info is None or self.cur is None:
            raise Skip("no chip found")

    def relocate(self) -> None:
        """Broadcast GET_INFO (read-only) and take the chip's node id from its ANNOUNCE."""
        self.drain()
        self.port.send(GetInfo(0))
        self.collect(self.answer_s, lambda ms: any(isinstance(m, Announce) for m in ms))

    def fresh_boot(self) -> None:
        """RESET: ACK, ANNOUNCE, INFO (a gateway: and GATEWAY_INFO). The node then stays at this
        provisional id for 1 s."""
        self.need_chip()
        n = 4 if self.profile == "gateway" else 3
        keep = (Announce, Info, GatewayInfo)
        ans = self.request(Reset(self.cur), n, keep=keep)
        if not (ans and isinstance(ans[0], Ack)):
            # it moved: a re-announce we did not hear (lost on the port), or a chip in BOOT took its
            # next provisional id (every 1 s, §3.2) before the RESET reached it — then what came is
            # that re-announce alone, and the RESET went to the old id: find it, once
            self.relocate()
            ans = self.request(Reset(self.cur), n, keep=keep)
        require(len(ans) >= 3 and isinstance(ans[0], Ack) and ans[0].command == MsgType.RESET and isinstance(ans[1], Announce)
                and isinstance(ans[2], Info), f"RESET not answered ACK, ANNOUNCE, INFO: {ans}")
        self.cur = ans[1].node

    def assign_without_reset(self, heartbeat_ms: int = HEARTBEAT_MS) -> None:
        """ASSIGN (and CONFIG) the chip where it is, without a RESET: IDLE at ``self.node``."""
        self.need_chip()
        ans = self.request_info(self.cur)  # where it is now (an unassigned chip moves every second)
        if len(ans) < 2:
            self.relocate()
            ans = self.request_info(self.cur)
        if len(ans) == 2 and isinstance(ans[1], Info) and ans[1].state == ChipState.STREAMING:
            self.request(Stop(self.cur))
        ans = self.request(Assign(self.cur, new_node=self.node, link=self.link, uid_low=self.uid & 0xFFFFFFFF))
        require(acked(ans, self.node, MsgType.ASSIGN), f"ASSIGN answered {ans}")
        self.cur = self.node
        ans = self.request(Config(self.node, rate_hz=145, range=0, filter=0, heartbeat_ms=heartbeat_ms))
        require(acked(ans, self.node, MsgType.CONFIG), f"CONFIG answered {ans}")

    def to_idle(self, heartbeat_ms: int = HEARTBEAT_MS) -> None:
        """Fresh boot, ASSIGN to the run's node id, CONFIG: the chip is IDLE at ``self.node``."""
        self.fresh_boot()
        ans = self.request(Assign(self.cur, new_node=self.node, link=self.link, uid_low=self.uid & 0xFFFFFFFF))
        require(acked(ans, self.node, MsgType.ASSIGN), f"ASSIGN answered {ans}")
        self.cur = self.node
        ans = self.request(Config(self.node, rate_hz=145, range=0, filter=0, heartbeat_ms=heartbeat_ms))
        require(acked(ans, self.node, MsgType.CONFIG), f"CONFIG answered {ans}")

    def ensure_idle(self) -> None:
        """IDLE at the run's node (without a RESET when it already is)."""
        self.need_chip()
        if self.cur == self.node:
            ans = self.request_info(self.node)
            if len(ans) == 2 and isinstance(ans[1], Info) and ans[1].state == ChipState.IDLE:
                return
            if len(ans) == 2 and isinstance(ans[1], Info) and ans[1].state == ChipState.STREAMING:
                if acked(self.request(Stop(self.node)), self.node, MsgType.STOP):
                    return
        self.to_idle()

    def ensure_node(self) -> None:
        """The node under test assigned at the run's node id: IDLE (a chip, configured) or a gateway."""
        if self.profile == "gateway":
            self.assign_gateway()
        else:
            self.ensure_idle()

    def to_streaming(self) -> None:
        self.ensure_idle()
        ans = self.request(Start(self.node))
        require(acked(ans, self.node, MsgType.START), f"START answered {ans}")

    # ---- SYNC, wherever it comes from
    @property
    def gateway_sync_wait_s(self) -> float:
        g = self.sync_gateway
        rate = g.sync_rate_hz if g is not None else 0
        return max(self.answer_s, 3.0 / rate) if rate else self.answer_s

    def sync_round(self, counter: int) -> tuple[int, float, list]:
        """One SYNC and the chip's answers to it: ``(counter, time of the SYNC, [(time, Sample or ImuSample)])``.

        The suite sends SYNC ``counter`` — or, behind a gateway that is its segment's SYNC source
        (§13.3, which passes no SYNC from this suite), takes that gateway's next SYNC and its counter.
        A packing gateway's SNAPSHOT counts as the chip's SAMPLE (`collect`). Waits until a sample
        with the counter arrived, at most `answer_s`."""
        self.drain()
        g = self.sync_gateway
        if g is None:
            t0 = self.port.send(Sync(counter=counter))
            c = counter
            self.syncs_heard[c] = t0
        else:
            got = self.collect(self.gateway_sync_wait_s, lambda ms: any(isinstance(m, Sync) for m in ms), syncs=True)
            syn = [(t, m) for t, m in got if isinstance(m, Sync)]
            if not syn:
                raise Skip(f"{g.label()} is the segment's SYNC source and sent no SYNC within "
                           f"{self.gateway_sync_wait_s:.1f} s")
            t0, c = syn[-1][0], syn[-1][1].counter
        got = self.collect(self.answer_s, lambda ms: any(isinstance(m, SAMPLES) and m.counter == c for m in ms))
        return c, t0, [(t, m) for t, m in got if isinstance(m, SAMPLES)]

    def assign_gateway(self) -> None:
        """The gateway under test: ASSIGN where it is (link 0xFFFF): IDLE at ``self.node``."""
        self.need_chip()
        if self.cur == self.node:
            return
        ans = self.request(Assign(self.cur, new_node=self.node, link=LINK_NONE, uid_low=self.uid & 0xFFFFFFFF))
        if not ans:
            self.relocate()
            ans = self.request(Assign(self.cur, new_node=self.node, link=LINK_NONE, uid_low=self.uid & 0xFFFFFFFF))
        require(acked(ans, self.node, MsgType.ASSIGN), f"ASSIGN answered {ans}")
        self.cur = self.node

    def pick_node(self) -> int:
        """The highest assigned node id no chip was heard from (so a full sheet is not disturbed)."""
        for n in range(NODE_MAX_ASSIGNED, 0, -1):
            if n not in self.nodes_seen:
                return n
        raise Skip("no free node id")  # pragma: no cover - 32767 chips on one port
