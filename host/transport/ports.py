"""Host transports: pluggable back ends that move capsheet frames between the host and a sheet.

A transport turns wire input into protocol events and messages into wire output. Three back ends,
chosen by name (`open_transport`) and imported lazily, so a host without python-can still talks
serial:

* ``serial`` — `SerialTransport`: pyserial, any URL or device path (a pty, ``loop://``,
  ``/dev/ttyUSB0``, ``socket://host:port``); taken exclusively, one session per port, and
  reconnects when the port goes away and comes back, only to the same device
  (`host.transport.portlock`).
* ``can`` — `CanTransport`: python-can, any interface it knows, given as ``interface:channel``
  (``virtual:bus0``, ``slcan:/dev/pts/5``, ``socketcan:can0``); classic CAN or CAN FD.
* ``memory`` — `MemoryTransport`: one end of ``virtual_sheet.memport.memory_link()`` (no OS).

The python-can pattern: the public `Transport.recv` runs the timeout loop and the bookkeeping;
a back end implements only ``_recv_internal`` (and ``_send_internal``, ``_close_internal``).
Only override the hooks, never `recv` / `send` directly.

Events returned by `Transport.recv` are what the protocol decoders produce, in wire order:
`protocol.Message` instances, `protocol.SampleBatch` (runs of SAMPLE, the fast path) and
`protocol.DecodeError` (damage, counted in `TransportStats.errors`). Wire input never raises. A
transport only moves bytes and frames: the decoding is the sans-I/O `protocol.framing.StreamDecoder`
(serial) or `protocol.can.CanDecoder` (CAN), the same objects replay and the tests use.

**Capture** (pycyphal's ``Transport.begin_capture``): `Transport.begin_capture(handler)` hands the
handler every unit of traffic from then on as a `Capture`, in both directions, raw and decoded: what
a receive read (serial bytes, or the CAN frames the bus delivered) with the events decoded from it,
and what a send wrote (bytes or a frame) with the message it carried. The recorder, ``--can-log``
and the conformance audit are capture handlers; nothing reaches into a transport. **Raw sends**
for tools that must put frames a conforming host never sends on the wire: `SerialTransport.send_bytes`
and `CanTransport.send_frame`; they are captured too (``events`` empty), and a CAN frame sent raw is
known to the echo filter like any other.
"""

from __future__ import annotations

import importlib
import sys
import logging
import threading
import time
from abc import ABC, abstractmethod
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Callable

from protocol.can import CAN_CLASSIC_MTU, CAN_FD_MTU, CanDecoder, EchoFilter, FrameBlock, to_can
from protocol.framing import MAX_PAYLOAD_SIZE, DecodeError, StreamDecoder, encode
from protocol.messages import ImuBatch, Message, SampleBatch, SnapshotFrames, StatusBatch

from host.transport.portlock import PortBusy, identify, in_use_message, is_device_path, open_exclusive, refusal
from host.transport.portlock import holders as lock_holders

__all__ = ["TransportError", "TransportInitError", "PortInUseError", "TransportOperationError", "TransportTimeoutError",
           "TransportCapabilities", "TransportStats", "Capture", "RawFrame", "Transport", "SerialTransport", "MemoryTransport",
           "CanTransport", "FrameBlock", "BACKENDS", "open_transport", "parse_can_spec", "feed_can"]

log = logging.getLogger("capsheet.host.transport")

#: the python-can interface name ``--can slcan:PORT`` opens (`host.transport.slcan.SlcanBus`, registered
#: by the ``can.interface`` entry point in pyproject.toml)
SLCAN_INTERFACE = "capsheet_slcan"
#: python-can's udp_multicast hearing its own group only (host/transport/udp_multicast.py)
UDP_MULTICAST_INTERFACE = "capsheet_udp_multicast"


# --------------------------------------------------------------------------------------------
# Errors by stage (python-can: CanError > CanInitializationError / CanOperationError / ...)
# --------------------------------------------------------------------------------------------

class TransportError(Exception):
    """Base of every transport error. ``port`` names the port or bus the error is about."""

    def __init__(self, message: str, port: str | None = None) -> None:
        super().__init__(message)
        self.port = port


class TransportInitError(TransportError):
    """The back end could not be imported, or the port/bus could not be opened or configured."""


class TransportOperationError(TransportError):
    """A send or receive failed on an open port (and reconnecting, if enabled, has not helped)."""


class PortInUseError(TransportInitError):
    """The port is held by another session (`host.transport.portlock`: one session per port); the
    message names the holding process where the system says."""


class TransportTimeoutError(TransportError, TimeoutError):
    """An operation did not finish within its timeout (e.g. a write that blocked).

    Also a `TimeoutError`, so ``except TimeoutError`` catches it as it catches the standard library's.
    """


# --------------------------------------------------------------------------------------------
# Capabilities and statistics
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class TransportCapabilities:
    """What a transport can carry. Frozen: a transport's capabilities do not change while it is open.

    Attributes
    ----------
    kind : str
        ``"serial"``, ``"can"`` or ``"memory"``. Example: ``"can"`` for ``virtual:bus0``.
    mtu : int
        Largest message payload (docs/protocol.md §4) one frame carries, in bytes.
        Examples: 8 on classic CAN, 64 on CAN FD, 1018 on serial (MAX_FRAME_SIZE 1024 minus header
        and CRC), so a serial SNAPSHOT carries up to 202 samples and a CAN FD one 11.
    fd : bool
        True if CAN FD frames can be sent and received (always False for serial/memory).
        Example: ``CanTransport("virtual:bus0", fd=True).capabilities.fd is True``.
    bitrate : int or None
        Line rate in bit/s if known: the baud rate of a serial port (e.g. 3_000_000), the nominal
        CAN bit rate (e.g. 1_000_000); None for a virtual bus or an in-memory link.
    data_bitrate : int or None
        CAN FD data-phase bit rate (e.g. 8_000_000), else None.
    name : str
        The port or bus as the user gave it, e.g. ``"/dev/pts/5"`` or ``"slcan:/dev/pts/6"``.
    """

    kind: str
    mtu: int
    fd: bool = False
    bitrate: int | None = None
    data_bitrate: int | None = None
    name: str = ""

    def __post_init__(self) -> None:
        if self.kind not in ("serial", "can", "memory"):
            raise ValueError(f"Invalid kind: {self.kind!r} (need 'serial', 'can' or 'memory')")
        if not isinstance(self.mtu, int) or self.mtu < 1:
            raise ValueError(f"Invalid mtu: {self.mtu!r} (need an integer >= 1)")


@dataclass
class TransportStats:
    """Counters of one transport (one bus). Updated by the transport's receive thread; read freely."""

    bytes_in: int = 0
    bytes_out: int = 0
    frames_in: int = 0  #: frames decoded (every SAMPLE of a batch counts)
    frames_out: int = 0
    errors: Counter = field(default_factory=Counter)  #: DecodeError reason name -> count
    disconnects: int = 0  #: times the port went away
    reconnects: int = 0  #: times it came back and was reopened
    send_failures: int = 0
    capture_errors: int = 0  #: exceptions a capture handler raised (the first of each handler is logged)
    refused_reopens: int = 0  #: reopens refused: another device at the port's path (`SerialTransport.refused`)

    @property
    def error_count(self) -> int:
        return sum(self.errors.values())

    def as_dict(self) -> dict:
        return {"bytes_in": self.bytes_in, "bytes_out": self.bytes_out, "frames_in": self.frames_in,
                "frames_out": self.frames_out, "errors": dict(self.errors), "disconnects": self.disconnects,
                "reconnects": self.reconnects, "send_failures": self.send_failures,
                "capture_errors": self.capture_errors, "refused_reopens": self.refused_reopens}


# Capture (host/transport/capture.py): what a transport received and sent, for whoever subscribes
from host.transport.capture import Capture, RawFrame  # noqa: E402  (re-exported: their names here stay)


# --------------------------------------------------------------------------------------------
# Base class
# --------------------------------------------------------------------------------------------

class Transport(ABC):
    """Base of every transport. Thread model: one thread receives, any thread may send (sends are
    serialised by a lock).

    Subclasses implement ``_recv_internal(timeout_s) -> list`` (events, possibly empty; may return
    early), ``_send_internal(msg) -> raw`` (what was written: bytes, or the CAN frame) and
    ``_close_internal()``, and set ``capabilities``. A back end hands what it reads to
    `emit_capture` (the base class captures what `send` writes).
    """

    capabilities: TransportCapabilities
    #: what a log line calls this transport ("serial port", "CAN bus")
    label = "port"

    def __init__(self, name: str, *, reconnect: bool = False, reconnect_interval_s: float = 0.2) -> None:
        self.name = name
        self.stats = TransportStats()
        self._send_lock = threading.Lock()
        self._closed = False
        self.reconnect = reconnect
        self.reconnect_interval_s = reconnect_interval_s
        self._last_attempt = float("-inf")
        self._captures: tuple = ()  # capture handlers (a tuple: iterated without a lock)
        self._capture_failed: set = set()  # handlers whose failure was logged once
        #: what the device was when first opened (`host.transport.portlock.DeviceIdentity`; None for
        #: a URL, an object or a bus with no device file): a reopen goes only to the same device
        self.identity = None
        #: the last reopen refused (another device at the path), one line; None once reopened
        self.refused: str | None = None

    # -- capture (pycyphal: Transport.begin_capture) -------------------------------------------
    def begin_capture(self, handler: Callable[[Capture], None]) -> None:
        """Hand ``handler`` every `Capture` from now on: each receive (raw input and the events
        decoded from it) and each send (the raw output and the message, ``events`` empty for a
        raw send), in wire order per direction.

        The handler runs in the thread that moved the traffic: for rx inside `recv`, before the
        events are returned (so it sees the input before anyone acts on it); for tx inside the send
        lock, after the write. It must be quick, must not modify what it is given, and must not call
        this transport's `send` or `recv`. An exception it raises is counted in
        ``stats.capture_errors`` (the first of each handler logged with its traceback) and does not
        reach the receive or send. Several handlers may be registered; `end_capture` removes one.
        """
        if not callable(handler):
            raise TypeError(f"Invalid capture handler: {handler!r} (need a callable taking a Capture)")
        self._captures = (*self._captures, handler)

    def end_capture(self, handler: Callable[[Capture], None]) -> None:
        """Stop handing captures to ``handler`` (registered by `begin_capture`); no error if it is not."""
        self._captures = tuple(h for h in self._captures if h != handler)  # == : bound methods are new objects

    @property
    def capturing(self) -> bool:
        """True while at least one capture handler is registered (a back end may skip the work)."""
        return bool(self._captures)

    def emit_capture(self, direction: str, raw: Any, events=(), echoes=()) -> None:
        """For back ends: hand one unit of traffic (`Capture`'s fields) to every capture handler
        now; nothing to do without handlers."""
        handlers = self._captures
        if not handlers:
            return
        cap = Capture(self, direction, time.monotonic(), time.time(), self.capabilities.kind
                      if self.capabilities.kind != "memory" else "serial", raw, tuple(events), tuple(echoes))
        for h in handlers:
            try:
                h(cap)
            except Exception:  # noqa: BLE001 - a subscriber's bug must not stop the traffic
                self.stats.capture_errors += 1
                if id(h) not in self._capture_failed:
                    self._capture_failed.add(id(h))
                    log.exception("capture handler %r of %s %r failed (further failures are counted in "
                                  "stats.capture_errors)", h, self.label, self.name)

    # -- reconnect, written once for every back end ----------------------------------------------
    def _lost(self, exc: BaseException) -> None:
        """The port or bus failed: count it (once per loss), release it, and let `_try_reopen` bring
        it back later (if ``reconnect``)."""
        if self.connected:
            log.warning("%s %r went away: %s", self.label, self.name, exc)
            self.stats.disconnects += 1
            try:
                self._release_internal()
            except Exception:  # noqa: BLE001 - it is gone already
                pass
        self._forget_internal()

    def _try_reopen(self) -> bool:
        """Reopen a lost port, at most once per ``reconnect_interval_s``; True if it is back."""
        if not (self.reconnect and self._can_reopen()):
            return False
        now = time.monotonic()
        if now - self._last_attempt < self.reconnect_interval_s:
            return False
        self._last_attempt = now
        try:
            self._reopen_internal()
        except Exception as exc:  # noqa: BLE001 - still away; try again later
            log.debug("reopen %r failed: %s", self.name, exc)
            return False
        self.stats.reconnects += 1
        log.warning("%s %r is back (reconnect #%d)", self.label, self.name, self.stats.reconnects)
        return True

    @property
    def connected(self) -> bool:
        """True while the port or bus is open (False after a loss, until reopened)."""
        return True

    def _can_reopen(self) -> bool:
        return True

    def _release_internal(self) -> None:
        """Close the lost port's handle (errors ignored)."""

    def _forget_internal(self) -> None:
        """Drop the handle and any partial input."""

    def _reopen_internal(self) -> None:
        """Open the port again; raise if it is still away."""
        raise TransportInitError(f"{self.name!r} cannot be reopened", self.name)

    def _refuse(self, msg: str | None) -> None:
        """Refuse this reopen (another device at the path, ``msg`` from `portlock.refusal`): counted,
        kept in `refused` for the session to report once; nothing when ``msg`` is None."""
        if msg is None:
            return
        self.stats.refused_reopens += 1
        if msg != self.refused:  # the session reports it (a `not_a_sheet` event): logged here at info
            log.info("%s", msg)
        self.refused = msg
        raise TransportInitError(msg, self.name)

    # -- public API ------------------------------------------------------------------------
    def recv(self, timeout_s: float | None = 0.1) -> list:
        """Events received within ``timeout_s`` (None: wait until there is at least one).

        Returns as soon as at least one event is available; an empty list on timeout.
        Raises `TransportOperationError` only if the transport is closed.
        """
        if self._closed:
            raise TransportOperationError(f"Transport {self.name!r} is closed", self.name)
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            events = self._recv_internal(remaining)
            if events:
                for ev in events:
                    if isinstance(ev, DecodeError):
                        self.stats.errors[ev.reason.name] += 1
                    elif isinstance(ev, (SampleBatch, ImuBatch, StatusBatch, SnapshotFrames)):
                        self.stats.frames_in += len(ev)
                    else:
                        self.stats.frames_in += 1
                return events
            if self._closed:
                raise TransportOperationError(f"Transport {self.name!r} is closed", self.name)
            if deadline is not None and time.monotonic() >= deadline:
                return []

    def send(self, msg: Message) -> None:
        """Send one message. Raises `TransportOperationError` (or `TransportTimeoutError`) naming
        the port if the back end fails; the cause is chained."""
        if self._closed:
            raise TransportOperationError(f"Transport {self.name!r} is closed", self.name)
        with self._send_lock:
            try:
                raw = self._send_internal(msg)
            except TransportError:
                self.stats.send_failures += 1
                raise
            except Exception as exc:  # noqa: BLE001 - back ends raise many kinds; re-raise by stage
                self.stats.send_failures += 1
                raise TransportOperationError(
                    f"Cannot send {msg.TYPE.name} on {self.name!r}: {exc}", self.name) from exc
            self.stats.frames_out += 1
            if self._captures:
                self.emit_capture("tx", raw, (msg,))

    def close(self) -> None:
        """Close the port. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._close_internal()
        except Exception as exc:  # noqa: BLE001
            log.debug("closing %s: %s", self.name, exc)

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> "Transport":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"

    # -- hooks -----------------------------------------------------------------------------
    @abstractmethod
    def _recv_internal(self, timeout_s: float | None) -> list:
        """Events available within ``timeout_s``; [] if none. Never raises on wire input."""

    @abstractmethod
    def _send_internal(self, msg: Message) -> Any:
        """Put one message on the wire; return what was written, as `Capture.raw` holds it (bytes,
        or a tuple of the CAN frame)."""

    def _close_internal(self) -> None:
        pass


# --------------------------------------------------------------------------------------------
# Serial (pyserial) and in-memory
# --------------------------------------------------------------------------------------------

def _import(module: str, what: str, port: str):
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise TransportInitError(f"Cannot import module {module} for {what} {port!r}: {exc}", port) from exc


#: the timeouts a serial read waits with, longest first (seconds)
READ_TIMEOUTS_S = (0.1, 0.05, 0.02, 0.01, 0.005, 0.002, 0.001)


def read_timeout_for(timeout_s: float | None) -> float:
    """The read timeout for a receive with ``timeout_s`` left: 0.1 s for None (wait), 0 for a
    poll, else the largest of `READ_TIMEOUTS_S` not over it (1 ms at least): `Transport.recv`
    reads again until its own deadline, so a shorter read costs an iteration, not an event.

    >>> read_timeout_for(None), read_timeout_for(0), read_timeout_for(0.0499), read_timeout_for(0.0003)
    (0.1, 0.0, 0.02, 0.001)
    """
    if timeout_s is None:
        return READ_TIMEOUTS_S[0]
    if timeout_s <= 0:
        return 0.0
    for v in READ_TIMEOUTS_S:
        if v <= timeout_s:
            return v
    return READ_TIMEOUTS_S[-1]


class SerialTransport(Transport):
    """The serial back end: COBS frames (docs §6) over anything with pyserial's API.

    Parameters
    ----------
    port : str or file-like
        A pyserial URL or device path (``/dev/pts/5``, ``loop://``, ``/dev/ttyUSB0``), opened with
        ``serial.serial_for_url``; or an already open object with pyserial's ``read``/``write``/
        ``timeout``/``in_waiting``/``close`` (e.g. a ``memory_link`` end).
    baudrate : int
        Line rate for real UARTs (ignored by ptys and ``loop://``).
    reconnect : bool
        When the port goes away (read/write raises), keep trying to reopen it every
        ``reconnect_interval_s`` and resume; `TransportStats.disconnects`/``reconnects`` count it.
        Only for ports given by name (an object cannot be reopened unless ``reopen`` is given).
    reopen : callable, optional
        Returns a fresh port object; used instead of reopening by name.
    read_size : int
        Largest read per call; large reads keep the batch decoder on its fast path.
    reader_process : bool
        Read the port (given by name) through a process of its own (`host.transport.portreader.ReaderPort`:
        a tty gives 4 KB a read; the reader drains it into a 1 MB pipe the host reads in 64 KB).

    Reads wait on pyserial's ``timeout``, and setting it costs pyserial a termios reconfiguration
    (``tcsetattr``) every time, whatever the value. So a read's timeout is taken from a few fixed
    values (`read_timeout_for`: the largest of 100, 50, 20, 10, 5, 2, 1 ms not over what is left,
    0 for a poll) and set only when it differs from the port's current one: a streaming port sets
    it once. ``read_timeouts`` counts the reads made per timeout value and ``read_timeout_sets``
    the times it was set.
    """

    def __init__(self, port: Any, baudrate: int = 3_000_000, *, reconnect: bool = True,
                 reconnect_interval_s: float = 0.2, reopen: Callable[[], Any] | None = None,
                 read_size: int = 1 << 16, kind: str = "serial", reader_process: bool = False) -> None:
        self._url = port if isinstance(port, str) else None
        self.reader_process = bool(reader_process) and self._url is not None
        name = self._url if self._url is not None else str(getattr(port, "name", None) or getattr(port, "port", None) or port)
        super().__init__(name, reconnect=reconnect, reconnect_interval_s=reconnect_interval_s)
        self.baudrate = baudrate
        self._reopen = reopen
        self._read_size = read_size
        self.decoder = StreamDecoder(batch_samples=True)
        self._read_timeout: float | None = None  # the port's timeout as last set; None: unknown
        self.read_timeouts: Counter = Counter()  #: read timeout (s) -> reads made with it
        self.read_timeout_sets = 0  #: times the port's timeout was set (a termios call each)
        self._opened = None
        if self._url is not None:
            self._serial_mod = _import("serial", "serial port", self._url)
            self._port = self._open()
            self.identity = self._opened
        else:
            self._serial_mod = None
            self._port = port
        self.capabilities = TransportCapabilities(
            kind=kind, mtu=MAX_PAYLOAD_SIZE, fd=False,
            bitrate=baudrate if (self._url is not None and kind == "serial") else None, name=name)

    def _open(self):
        """Open the port for this session alone (`host.transport.portlock.open_exclusive`: a port
        another session holds is `PortInUseError`, naming the holder); what was opened is kept in
        ``_opened`` (its `DeviceIdentity`)."""
        serial = self._serial_mod
        try:
            port, self._opened = open_exclusive(lambda excl: serial.serial_for_url(
                self._url, baudrate=self.baudrate, timeout=0.05, write_timeout=1.0, exclusive=excl), self._url)
        except PortBusy as exc:
            raise PortInUseError(str(exc), self._url) from exc
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportInitError(f"Cannot open serial port {self._url!r}: {exc}", self._url) from exc
        if not self.reader_process:
            return port
        from host.transport.portreader import ReaderPort
        try:
            return ReaderPort(port)
        except (AttributeError, OSError, ValueError) as exc:  # e.g. loop:// has no file descriptor
            port.close()
            raise TransportInitError(f"Cannot read {self._url!r} through a reader process: {exc}", self._url) from exc

    # reconnect (the logic is `Transport._lost` / `_try_reopen`) ------------------------------
    label = "serial port"

    @property
    def connected(self) -> bool:
        return self._port is not None

    def _can_reopen(self) -> bool:
        return self._url is not None or self._reopen is not None

    def _release_internal(self) -> None:
        self._port.close()

    def _forget_internal(self) -> None:
        self._port = None
        self._read_timeout = None
        self.decoder.reset()

    def _reopen_internal(self) -> None:
        if self._reopen is not None:
            self._port = self._reopen()
        else:
            # the same device only (`host.transport.portlock`): what the path leads to now is
            # compared before it is opened, and what was opened once more (the path may change between)
            if self.identity is not None:
                self._refuse(refusal(self.name, self.identity, identify(self._url)))
            port = self._open()
            if self.identity is not None:
                try:
                    self._refuse(refusal(self.name, self.identity, self._opened))
                except TransportInitError:
                    port.close()
                    raise
            self._port = port
        self.refused = None
        self._read_timeout = None

    # hooks -------------------------------------------------------------------------------
    def _recv_internal(self, timeout_s: float | None) -> list:
        port = self._port
        if port is None:
            if not self._try_reopen():
                time.sleep(min(0.05, timeout_s if timeout_s is not None else 0.05))
                return []
            port = self._port
        try:
            rt = read_timeout_for(timeout_s)
            if rt != self._read_timeout:
                port.timeout = rt
                self._read_timeout = rt
                self.read_timeout_sets += 1
            self.read_timeouts[rt] += 1
            waiting = port.in_waiting
            data = port.read(min(max(1, waiting), self._read_size))
            if data and waiting == 0:
                more = port.in_waiting
                if more:
                    data += port.read(min(more, self._read_size))
        except Exception as exc:  # noqa: BLE001 - SerialException, OSError, memport's OSError
            self._lost(exc)
            return []
        if not data:
            return []
        self.stats.bytes_in += len(data)
        events = self.decoder.feed(data)
        if self._captures:
            self.emit_capture("rx", data, events)
        return events

    def _send_internal(self, msg: Message) -> bytes:
        data = encode(msg)
        self._write(data)
        return data

    def send_bytes(self, data: bytes) -> None:
        """Raw send: wire bytes as they are (already framed, or deliberately not: a conformance
        check's junk), under the send lock, captured (``events`` empty). Raises as `send` does."""
        if self._closed:
            raise TransportOperationError(f"Transport {self.name!r} is closed", self.name)
        data = bytes(data)
        with self._send_lock:
            try:
                self._write(data)
            except TransportError:
                self.stats.send_failures += 1
                raise
            if self._captures:
                self.emit_capture("tx", data)

    def _write(self, data: bytes) -> None:
        port = self._port
        if port is None:
            raise TransportOperationError(f"Serial port {self.name!r} is not connected", self.name)
        try:
            port.write(data)
        except Exception as exc:  # noqa: BLE001
            # pyserial's class, if pyserial is loaded at all (a port object may come from elsewhere)
            serial_timeout = getattr(sys.modules.get("serial"), "SerialTimeoutException", None)
            if serial_timeout is not None and isinstance(exc, serial_timeout):
                raise TransportTimeoutError(f"Write to serial port {self.name!r} timed out: {exc}",
                                            self.name) from exc
            self._lost(exc)
            raise TransportOperationError(f"Cannot write to serial port {self.name!r}: {exc}", self.name) from exc
        self.stats.bytes_out += len(data)

    def _close_internal(self) -> None:
        if self._port is not None:
            self._port.close()
            self._port = None


class MemoryTransport(SerialTransport):
    """The serial framing over one end of ``virtual_sheet.memport.memory_link()`` (fast unit tests).

    ``reopen`` (optional) returns a new end after the link was closed, to exercise reconnection.
    """

    def __init__(self, end: Any, *, reopen: Callable[[], Any] | None = None) -> None:
        super().__init__(end, reconnect=reopen is not None, reopen=reopen, kind="memory",
                         reconnect_interval_s=0.02)


# --------------------------------------------------------------------------------------------
# CAN (python-can)
# --------------------------------------------------------------------------------------------

def feed_can(decoder: CanDecoder, frames, stats: TransportStats, echoes: list | None = None) -> list:
    """``decoder.feed(frames)``, with what the decoder took in and dropped without an event added
    to a transport's ``stats``: data bytes to ``bytes_in``, error frames to
    ``errors["CAN_ERROR_FRAME"]``, CAN FD frames on a classic bus to ``errors["FD_ON_CLASSIC"]``
    (`Transport.recv` counts the `DecodeError` events). ``echoes``: `CanDecoder.feed`'s. `CanTransport`
    and `host.record.replay.ReplayTransport` receive through it."""
    st = decoder.stats
    b0, e0, f0 = st.bytes_in, st.error_frames, st.fd_on_classic
    events = decoder.feed(frames, echoes)
    stats.bytes_in += st.bytes_in - b0
    if st.error_frames != e0:
        stats.errors["CAN_ERROR_FRAME"] += st.error_frames - e0
    if st.fd_on_classic != f0:
        stats.errors["FD_ON_CLASSIC"] += st.fd_on_classic - f0
    return events


def parse_can_spec(spec: str) -> tuple[str, str]:
    """``"interface:channel"`` -> ``(interface, channel)``; the channel may contain ':'.

    >>> parse_can_spec("slcan:/dev/pts/5")
    ('slcan', '/dev/pts/5')
    >>> parse_can_spec("virtual:bus0")
    ('virtual', 'bus0')
    """
    interface, sep, channel = spec.partition(":")
    if not sep or not interface or not channel:
        raise ValueError(f"Invalid CAN bus {spec!r}: expected INTERFACE:CHANNEL, e.g. virtual:bus0, "
                         f"slcan:/dev/pts/5 or socketcan:can0")
    return interface, channel


class CanTransport(Transport):
    """The CAN back end: one python-can bus, 29-bit identifiers (docs §7).

    Parameters
    ----------
    spec : str
        ``interface:channel`` as python-can names them (``virtual:bus0``, ``slcan:/dev/pts/5``,
        ``socketcan:can0``, ``pcan:PCAN_USBBUS1``, ...).
    fd : bool
        Open the bus for CAN FD (needed to receive SNAPSHOT frames from a concentrator).
    bitrate, data_bitrate : int, optional
        Nominal and FD data-phase bit rates, passed to python-can.
    reconnect : bool
        Reopen the bus after an operation error (an SLCAN adapter that was unplugged).
    max_batch : int
        At most this many frames drained per receive call; consecutive SAMPLE frames come out
        as one `SampleBatch`.
    **bus_kwargs
        Passed to ``can.Bus`` (e.g. ``sleep_after_open=0`` for slcan on a pty).

    The ``slcan`` interface is opened as python-can's ``capsheet_slcan`` (`host.transport.slcan.SlcanBus`:
    read in chunks, stale input drained at open, runs of SAMPLE lines handed over as arrays by its
    ``drain_blocks``); the SLCAN lines it skips as damaged are counted in
    ``stats.errors["SLCAN_BAD_LINE"]``. Any other interface is python-can's ``can.Bus`` of that name.
    """

    def __init__(self, spec: str, *, fd: bool = False, bitrate: int | None = None,
                 data_bitrate: int | None = None, reconnect: bool = True, reconnect_interval_s: float = 0.5,
                 max_batch: int = 4096, **bus_kwargs: Any) -> None:
        super().__init__(spec, reconnect=reconnect, reconnect_interval_s=reconnect_interval_s)
        try:
            self.interface, self.channel = parse_can_spec(spec)
        except ValueError as exc:
            raise TransportInitError(str(exc), spec) from exc
        self._can = _import("can", f"CAN interface '{self.interface}' on", spec)
        self.fd = fd
        self._bus_kwargs = dict(bus_kwargs)
        if bitrate is not None:
            self._bus_kwargs["bitrate"] = bitrate
        if data_bitrate is not None:
            self._bus_kwargs["data_bitrate"] = data_bitrate
        self._max_batch = max_batch
        #: our own frames handed back (udp_multicast does): dropped, counted in ``echo.echoes``
        self.echo = EchoFilter()
        #: the sans-I/O receiver (`protocol.can.CanDecoder`): frames in, events out
        self.decoder = CanDecoder(fd=fd, echo=self.echo)
        self._bus = self._open()
        # an SLCAN adapter is a device file (`host.transport.slcan.SlcanBus.identity`): a reopen goes
        # only to the same adapter, as a serial gateway's port does
        self.identity = getattr(self._bus, "identity", None)
        self.capabilities = TransportCapabilities(
            kind="can", mtu=CAN_FD_MTU if fd else CAN_CLASSIC_MTU, fd=fd, bitrate=bitrate,
            data_bitrate=data_bitrate if fd else None, name=spec)

    def _open(self):
        can = self._can
        # slcan: capsheet's own SLCAN bus, a python-can interface found by name (host/transport/slcan.py)
        # udp_multicast: python-can's, isolated to its group (host/transport/udp_multicast.py)
        interface = {"slcan": SLCAN_INTERFACE, "udp_multicast": UDP_MULTICAST_INTERFACE}.get(
            self.interface, self.interface)
        if interface == SLCAN_INTERFACE:  # an adapter on a tty: one session per port (portlock)
            tty = self.channel.rpartition("@")[0] if "@" in self.channel else self.channel
            found = lock_holders(tty) if is_device_path(tty) else []
            if found:
                raise PortInUseError(in_use_message(tty, found), self.name)
        try:
            return can.Bus(interface=interface, channel=self.channel, fd=self.fd, **self._bus_kwargs)
        except Exception as exc:  # noqa: BLE001 - CanInitializationError, ImportError, OSError, ValueError
            raise TransportInitError(f"Cannot open CAN bus {self.name!r}: {exc}", self.name) from exc

    label = "CAN bus"

    @property
    def connected(self) -> bool:
        return self._bus is not None

    def _release_internal(self) -> None:
        self._bus.shutdown()

    def _forget_internal(self) -> None:
        self._bus = None

    def _reopen_internal(self) -> None:
        if self.identity is None:
            self._bus = self._open()
            self.refused = None
            return
        # the same adapter only: what the tty's path leads to now is compared before it is opened
        # (never written to, never switched to raw mode), and what was opened once more
        tty = self.channel.rpartition("@")[0] if "@" in self.channel else self.channel
        self._refuse(refusal(self.name, self.identity, identify(tty)))
        bus = self._open()
        try:
            self._refuse(refusal(self.name, self.identity, getattr(bus, "identity", None)))
        except TransportInitError:
            bus.shutdown()
            raise
        self._bus = bus
        self.refused = None

    def _recv_internal(self, timeout_s: float | None) -> list:
        bus = self._bus
        if bus is None:
            self._try_reopen()
            time.sleep(min(0.05, timeout_s if timeout_s is not None else 0.05))
            return []
        wait = min(timeout_s, 0.1) if timeout_s is not None else 0.1
        try:
            drain = getattr(bus, "drain_blocks", None)
            if drain is not None:  # host.slcan.SlcanBus: every buffered line parsed in one pass
                frames = drain(wait, max_lines=self._max_batch)
                bad = bus.take_bad_lines()
                if bad:
                    self.stats.errors["SLCAN_BAD_LINE"] += bad
            else:
                first = bus.recv(wait)
                if first is None:
                    return []
                frames = [first]
                while len(frames) < self._max_batch:
                    m = bus.recv(0)
                    if m is None:
                        break
                    frames.append(m)
        except Exception as exc:  # noqa: BLE001 - CanOperationError etc.
            self._lost(exc)
            return []
        if not frames:
            return []
        if not self._captures:
            return feed_can(self.decoder, frames, self.stats)
        echoes: list = []
        events = feed_can(self.decoder, frames, self.stats, echoes)
        self.emit_capture("rx", tuple(frames), events, echoes)
        return events

    def _send_internal(self, msg: Message):
        frame = to_can(msg, fd=True if (self.fd and len(msg.payload()) > CAN_CLASSIC_MTU) else None)
        return (self._put(frame.arbitration_id, frame.data, True, frame.is_fd),)

    def send_frame(self, arbitration_id: int, data: bytes, *, extended: bool = True, fd: bool = False) -> None:
        """Raw send: one CAN frame as given, whatever it holds (an undefined type, another protocol
        version, a standard 11-bit identifier: what a conformance check sends), under the send lock.
        Captured (``events`` empty) and known to the echo filter like every frame this host sends.
        Raises `TransportOperationError` / `TransportTimeoutError` as `send` does."""
        if self._closed:
            raise TransportOperationError(f"Transport {self.name!r} is closed", self.name)
        with self._send_lock:
            try:
                m = self._put(int(arbitration_id), bytes(data), bool(extended), bool(fd))
            except TransportError:
                self.stats.send_failures += 1
                raise
            except Exception as exc:  # noqa: BLE001 - python-can rejects a malformed frame by ValueError etc.
                self.stats.send_failures += 1
                raise TransportOperationError(f"Cannot send frame 0x{arbitration_id:X} on {self.name!r}: {exc}",
                                              self.name) from exc
            if self._captures:
                self.emit_capture("tx", (m,))

    def _put(self, arbitration_id: int, data: bytes, extended: bool, fd: bool):
        """Write one frame; returns the python-can message written (``is_rx`` False, stamped with
        the wall clock as python-can stamps received frames)."""
        bus = self._bus
        if bus is None:
            raise TransportOperationError(f"CAN bus {self.name!r} is not connected", self.name)
        m = self._can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=extended, is_fd=fd)
        self.echo.sent(arbitration_id, data)
        try:
            bus.send(m, timeout=1.0)
        except Exception as exc:  # noqa: BLE001
            if isinstance(exc, self._can.CanTimeoutError):
                raise TransportTimeoutError(f"Send on CAN bus {self.name!r} timed out: {exc}", self.name) from exc
            self._lost(exc)
            raise TransportOperationError(f"Cannot send on CAN bus {self.name!r}: {exc}", self.name) from exc
        self.stats.bytes_out += len(data)
        m.timestamp, m.is_rx = time.time(), False
        return m

    def _close_internal(self) -> None:
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None


# --------------------------------------------------------------------------------------------
# Back ends by name
# --------------------------------------------------------------------------------------------

#: back-end name -> (module, class); imported when first asked for
BACKENDS: dict[str, tuple[str, str]] = {
    "serial": ("host.transport.ports", "SerialTransport"),
    "can": ("host.transport.ports", "CanTransport"),
    "memory": ("host.transport.ports", "MemoryTransport"),
}


def open_transport(backend: str, *args: Any, **kwargs: Any) -> Transport:
    """Open a transport by back-end name.

    >>> t = open_transport("serial", "loop://")
    >>> t.capabilities.kind, t.capabilities.mtu
    ('serial', 1018)
    >>> t.close()

    ``open_transport("can", "virtual:bus0", fd=True)``; ``open_transport("memory", end)``.
    """
    try:
        module_name, cls_name = BACKENDS[backend]
    except KeyError:
        raise TransportInitError(f"Unknown transport back end {backend!r} (known: {', '.join(BACKENDS)})",
                                 None) from None
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise TransportInitError(f"Cannot import module {module_name} for transport '{backend}': {exc}",
                                 None) from exc
    return getattr(module, cls_name)(*args, **kwargs)
