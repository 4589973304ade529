"""Virtual devices: a `VirtualSheet` reachable exactly as hardware is, each in a background thread.

=================== ========================================================================
`MemoryDevice`      in-memory byte link (`memport`): ``device.port`` is the host's pyserial-like end
`PtyDevice`         a pseudo-terminal: ``device.path`` is a stable symlink to the slave
                    (``device.tty`` the slave itself); open it with ``serial.Serial(path)``
`CanDevice`         python-can buses (``virtual`` by default, any interface python-can knows):
                    ``device.channels`` are the channel names to open, one per bus
`SlcanDevice`       an SLCAN (Lawicel) adapter on a pty (`virtual_sheet.slcan`): open it with
                    ``can.Bus(interface="slcan", channel=device.path)``
`MultiPtyDevice`    several serial gateways of one sheet, each on its own pty with a contiguous
                    block of the links (``device.paths``); gateway 0 leads the SYNC line
`MultiMemoryDevice` the same on in-memory links (``device.ports``): a multi-gateway sheet on a
                    simulated clock
=================== ========================================================================

The two devices with a pty per gateway or bus (`MultiPtyDevice`, `SlcanDevice`) are
`PtyGroupDevice` s: one `PtyGroup` of `PtyPort` s, served by one ``select``.

Each is a context manager: ``with PtyDevice(sheet) as dev: ...`` starts the thread and stops it
(joined, ports closed) on exit; `start` / `stop` do the same by hand. The clock is
``time.monotonic()`` from `start` (``device.now()``); the chips are powered on at start.

**An idle sheet sleeps** (the pty devices): the thread waits for host input until the next thing
it has to do — a gateway's SYNC, a chip's heartbeat or re-announce, a frame due on the wire
(`Gateway.next_deadline`), the next outage — and is woken at once by a `call` and by `stop` (a pipe
in its ``select``). An idle 3x3 sheet on a pty wakes about once a second (its chips' re-announces
or heartbeats) instead of every 10 ms. The devices whose wait cannot be woken (python-can's
``recv``, the memory links' reads) still wait at most `_POLL_WAIT_S` at a time.

**Manual mode** (``clock=`` a callable): no thread; the caller runs the device with
``device.step()`` at the clock's time (a simulated clock: the in-process back-to-back tests run
host and sheet in one thread, deterministically, whatever the machine's load).

**A bus that goes away** (faults ``outage_at_s``/``outage_s``/``outage_every_s``): a pty slave
path cannot be reused once its master is closed, so the pty devices publish a stable symlink
(``device.path``, in a private temporary directory unless ``symlink_path`` is given). At an
outage the device closes the pty's master (the host's reads fail as on an unplugged USB adapter),
keeps its slave side open so that no other process takes the pty's number meanwhile, and removes
the symlink; when the bus comes back it lets the number go and asks for it at once, waiting up to a
second for a host that still holds it (as an adapter plugged back in keeps its number: a host
reconnects only to the same device, host/transport/portlock.py), then re-points the symlink
atomically, so a host that reopens the same path reconnects. On CAN the device stops answering
for the outage (frames sent to it are lost), after signalling an error frame.

**Whose path it is** (`claim_symlink`): a symlink path given by the caller may already hold
something. A folder is never touched; a file, or a symlink nobody here made, is replaced only when
the caller says so; a symlink a capsheet device published is replaced only when it is stale: every
published symlink is recorded (`SYMLINK_RECORDS`: the path, where it points, the publishing
process), and one is ours to replace when it still points where the record says and that process
is gone (a sheet killed with SIGKILL leaves its symlink behind). A device removes its symlink at
stop only while it still points to its own pty.
"""

from __future__ import annotations

import os
import select
import threading
import time
from typing import Any

from .faults import ERROR_FRAME
from .gateway import Gateway
from .memport import memory_link
from .pty import SYMLINK_RECORDS, PtyEndpoint, PtyGroup, PtyPort, claim_symlink, open_pty

__all__ = ["Device", "MemoryDevice", "PtyDevice", "MultiPtyDevice", "MultiMemoryDevice", "CanDevice", "PtyPort", "PtyGroup", "PtyGroupDevice", "open_pty", "claim_symlink",
           "SYMLINK_RECORDS"]

#: the longest wait for input of a device that cannot be woken by `Device.call` or `Device.stop`
_POLL_WAIT_S = 0.02
#: the longest wait of one that can (a guard: the deadlines and the wake-ups say when to wake)
_WAKEABLE_WAIT_S = 1.0


class Device:
    """Base of every virtual device: a thread running `_run` between `start` and `stop`.

    Subclasses implement ``_open()``, ``_serve(timeout_s)`` (wait at most ``timeout_s`` for host
    input, handle it) and ``_close()``; `_outage` hooks the bus-away fault.
    """

    name = "device"
    #: the longest single wait for input (`_POLL_WAIT_S` unless the device's wait is woken by
    #: `_wake`: then only a guard, the deadlines decide)
    max_wait_s = _POLL_WAIT_S
    #: the wait is a ``select`` (`_wait_on`): a pipe among its descriptors wakes it (`_wake`)
    wake_by_pipe = False
    _wake_r = _wake_w = -1

    def __init__(self, sheet, *, packed: bool = False, sync_rate_hz: float | None = None,
                 verbose: Any = None, clock=None, gateway_node: bool | None = None,
                 gateway_class: type | None = None) -> None:
        self.clock = clock  # manual mode when given: seconds, the device's `now`
        #: the gateways are nodes on the wire (None: when they pack or drive SYNC, as the spec requires;
        #: False: a protocol 1.0 gateway that does not announce itself)
        self.gateway_node = gateway_node
        #: what the gateways are made with (a subclass of `Gateway`: the conformance suite's broken gateways)
        self.gateway_class = gateway_class or Gateway
        self._outage_end: float | None = None
        self.sheet = sheet
        self.packed = packed
        self.sync_rate_hz = sync_rate_hz
        self.verbose = verbose  # callable(direction, frame) or None
        self.fault_stats = sheet.fault_stats
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._t0 = 0.0
        self.error: BaseException | None = None
        self.down = False
        self._calls: list = []  # (fn, done Event, result box) run in the device thread
        #: the latest time the device thread gave its chips (a poll, a call, a frame): a frame
        #: taken at its time on the bus is never taken before it (the chips' clock never goes back)
        self._given = float("-inf")
        self._calls_lock = threading.Lock()
        self._outages = sheet.faults.outage_windows()
        self._next_outage = next(self._outages, None)

    # ------------------------------------------------------------------ life cycle
    def now(self) -> float:
        """Seconds since `start` (the chips' clock); in manual mode the clock's time."""
        if self.clock is not None:
            return self.clock()
        return time.monotonic() - self._t0

    def start(self, *, power_on: bool = True) -> "Device":
        """Open the ports and start the thread (manual mode: no thread). ``power_on=False`` leaves
        the chips off until `power_on` (a sheet plugged in after the host opened its port)."""
        if self._thread is not None:
            raise RuntimeError(f"{self.name} already started")
        self._stop.clear()
        self._open()
        if self.wake_by_pipe and self.clock is None and self._wake_r < 0:
            self._wake_r, self._wake_w = os.pipe()
            os.set_blocking(self._wake_r, False)
            os.set_blocking(self._wake_w, False)
        self._t0 = time.monotonic()
        self._given = float("-inf")  # the chips' clock begins again
        if power_on:
            for gw in self.gateways:
                gw.power_on(self.now() if self.clock is not None else 0.0)
        if self.clock is not None:
            self._started = True
            return self
        self._thread = threading.Thread(target=self._run_guarded, name=f"capsheet-{self.name}", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the thread and close the ports (idempotent)."""
        self._stop.set()
        self._started = False
        self._wake()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout_s)
            if t.is_alive():
                raise RuntimeError(f"{self.name}: thread did not stop within {timeout_s} s")
        self._thread = None
        self._close()
        fds, (self._wake_r, self._wake_w) = (self._wake_r, self._wake_w), (-1, -1)
        for fd in fds:
            if fd >= 0:
                os.close(fd)

    close = stop

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def step(self) -> None:
        """Manual mode: one pass of the device loop at ``clock()`` — the bus-away fault, host
        input, the chips' timers, output due. Never waits."""
        if self.clock is None:
            raise RuntimeError(f"{self.name}: step() is for manual mode (a device built with clock=)")
        if not getattr(self, "_started", False):
            return
        now = self.now()
        if self._calls:
            self._run_calls()
        if self.down:
            if now < self._outage_end:
                self._drain_while_down(0.0)
                return
            self._come_back()
            self.down = False
        if self._next_outage is not None and now >= self._next_outage[0]:
            _start, self._outage_end = self._next_outage
            self._next_outage = next(self._outages, None)
            self.fault_stats.outages += 1
            self.down = True
            self._go_down()
            return
        self._serve(0.0)
        for gw in self.gateways:
            gw.poll(now)
        self._flush(now)

    def call(self, fn, timeout_s: float = 5.0):
        """Run ``fn(now_s)`` in the device thread (the chips are not thread-safe) and return its
        result; called directly when the device is not running."""
        if not self.running:
            return fn(self.now())
        done, box = threading.Event(), []
        with self._calls_lock:
            self._calls.append((fn, done, box))
        self._wake()
        if not done.wait(timeout_s):
            raise TimeoutError(f"{self.name}: the device thread did not run the call within {timeout_s} s")
        if box and isinstance(box[0], BaseException):
            raise box[0]
        return box[0] if box else None

    def power_on(self) -> None:
        """Power every chip now (after ``start(power_on=False)``)."""
        def do(now_s):
            for gw in self.gateways:
                gw.power_on(now_s)
        self.call(do)

    def commission(self, *, start: bool = True) -> None:
        """Assign every chip its physical link (node = link + 1) and START them, through frames,
        as a host would (`Gateway.commission`): a shortcut for demos and benchmarks."""
        def do(now_s):
            for gw in self.gateways:
                gw.commission(now_s, start=start)
        self.call(do)

    def _run_calls(self) -> None:
        with self._calls_lock:
            calls, self._calls = self._calls, []
        for fn, done, box in calls:
            try:
                self._given = now = self.now()
                box.append(fn(now))
            except BaseException as exc:  # handed to the caller
                box.append(exc)
            done.set()

    # ------------------------------------------------------------------ loop
    def _run_guarded(self) -> None:
        try:
            self._run()
        except BaseException as exc:  # surfaced by `error` and re-raised nowhere: a thread
            self.error = exc
            raise

    def _run(self) -> None:
        while not self._stop.is_set():
            if self._calls:
                self._run_calls()
            now = self.now()
            if self._next_outage is not None and now >= self._next_outage[0]:
                start, end = self._next_outage
                self._next_outage = next(self._outages, None)
                self.fault_stats.outages += 1
                self.down = True
                self._go_down()
                while not self._stop.is_set() and self.now() < end:
                    self._drain_while_down(min(0.01, max(0.0, end - self.now())))
                if self._stop.is_set():
                    return
                self._come_back()
                self.down = False
                continue
            self._serve(min(max(0.0, self._next_deadline() - now), self.max_wait_s))
            now = self.now()
            self._given = now  # the chips' clock is here now: no later input is taken before it
            for gw in self.gateways:
                gw.poll(now)
            self._flush(now)

    def _next_deadline(self) -> float:
        """When the loop next has something to do without input: a gateway's timer or output
        (`Gateway.next_deadline`), or the next outage."""
        t = min(gw.next_deadline() for gw in self.gateways)
        if self._next_outage is not None:
            t = min(t, self._next_outage[0])
        return t

    def _flush(self, now: float) -> None:
        wire = getattr(self, "_send_wire", None)
        for i, gw in enumerate(self.gateways):
            if wire is not None and self.verbose is None:  # serial: the due frames as one write
                data, n = gw.pop_wire(now)
                if n:
                    wire(i, data, n)
                continue
            out = gw.pop_output(now)
            if out:
                if self.verbose is not None:
                    for f in out:
                        self.verbose("tx", f)
                self._send(i, out)

    # hooks --------------------------------------------------------------
    gateways: list[Gateway]

    def _open(self) -> None: ...
    def _close(self) -> None: ...
    def _serve(self, timeout_s: float) -> None: ...
    def _send(self, bus: int, frames: list) -> None: ...

    def _wake(self) -> None:
        """Cut the thread's current wait short (a `call` or `stop` waits for it): a byte into the
        wake pipe (``wake_by_pipe``); a device that waits otherwise says how."""
        fd = self._wake_w
        if fd >= 0:
            try:
                os.write(fd, b"w")
            except OSError:  # full (it is awake already) or closed by `stop`
                pass

    def _wait_on(self, rfds: list, wfds: list, timeout_s: float) -> None:
        """Wait at most ``timeout_s`` until a descriptor of ``rfds`` is readable or of ``wfds``
        writable, or `_wake` is called; what is ready is for the caller to take (without waiting)."""
        if timeout_s <= 0:
            return
        if self._wake_r < 0:  # not started as a thread
            select.select(rfds, wfds, [], timeout_s)
            return
        r, _w, _x = select.select([*rfds, self._wake_r], wfds, [], timeout_s)
        if self._wake_r in r:
            try:
                while os.read(self._wake_r, 4096):
                    pass
            except BlockingIOError:
                pass

    def _go_down(self) -> None:
        pass

    def _drain_while_down(self, timeout_s: float) -> None:
        if timeout_s > 0:
            time.sleep(timeout_s)

    def _come_back(self) -> None:
        pass

    def describe(self) -> str:
        return self.name


# ---------------------------------------------------------------------------------------------
# serial: memory link and pty
# ---------------------------------------------------------------------------------------------

class _SerialDevice(Device):
    def __init__(self, sheet, **kw) -> None:
        if sheet.transport != "serial":
            raise ValueError(f"{type(self).__name__} needs a sheet with transport='serial', "
                             f"got {sheet.transport!r}")
        super().__init__(sheet, **kw)
        self.gateway = self.gateway_class(sheet, packed=self.packed, sync_rate_hz=self.sync_rate_hz, as_node=self.gateway_node)
        self.gateways = [self.gateway]

    def _handle_input(self, data: bytes) -> None:
        if self.verbose is not None:
            self.verbose("rx", data)
        self.gateway.feed(data, self.now())


class MemoryDevice(_SerialDevice):
    """The sheet behind an in-memory link. ``device.port`` is the host's end (pyserial subset:
    ``read``, ``write``, ``in_waiting``, ``timeout``, ``close``)."""

    name = "memory"

    def __init__(self, sheet, **kw) -> None:
        super().__init__(sheet, **kw)
        self.port, self._end = memory_link("capsheet", timeout=0.1)

    def _serve(self, timeout_s: float) -> None:
        self._end.timeout = timeout_s
        try:
            data = self._end.read(65536)
        except OSError:  # the host closed its end: nothing more to do but wait for stop
            self._stop.wait(0.05)
            return
        if data:
            self._handle_input(data)

    def _send_wire(self, bus: int, data: bytes, n_frames: int) -> None:
        self._send(bus, [data])

    def _send(self, bus: int, frames: list) -> None:
        try:
            self._end.write(b"".join(frames))
        except OSError:
            pass

    def _close(self) -> None:
        self._end.close()

    def _drain_while_down(self, timeout_s: float) -> None:
        """The link is gone: what the host sends meanwhile is lost (not served after the outage)."""
        self._end.timeout = 0
        try:
            while self._end.read(65536):
                pass
        except OSError:
            pass
        if timeout_s > 0:
            time.sleep(timeout_s)

    def describe(self) -> str:
        return "in-memory link (use device.port)"


class PtyDevice(PtyEndpoint, _SerialDevice):
    """The sheet's gateway on a pseudo-terminal serial port.

    ``device.path``: stable symlink to open (``serial.Serial(device.path)``); ``device.tty``:
    the current ``/dev/pts/N``. Baud rate settings are accepted and ignored (a pty has none).
    """

    name = "pty"

    def __init__(self, sheet, *, symlink_path: str | os.PathLike | None = None, **kw) -> None:
        super().__init__(sheet, **kw)
        self.pty_init(symlink_path)

    def _open(self) -> None:
        self.pty_open()

    def _close(self) -> None:
        self.pty_cleanup()

    wake_by_pipe = True
    max_wait_s = _WAKEABLE_WAIT_S

    def _serve(self, timeout_s: float) -> None:
        if self.master < 0:  # no pty right now: pty_read sleeps, and nothing would wake it
            timeout_s = min(timeout_s, _POLL_WAIT_S)
        else:
            self._wait_on([self.master], [self.master] if self.has_pending else [], timeout_s)
            timeout_s = 0.0
        data = self.pty_read(timeout_s)
        if data:
            self._handle_input(data)

    def _send(self, bus: int, frames: list) -> None:
        self.pty_write(b"".join(frames), len(frames))

    def _send_wire(self, bus: int, data: bytes, n_frames: int) -> None:
        self.pty_write(data, n_frames)

    def _go_down(self) -> None:
        self.pty_close()

    def _come_back(self) -> None:
        self.pty_open()

    def describe(self) -> str:
        return f"serial port {self.path} (-> {self.tty})"


class PtyGroupDevice(Device):
    """A device that serves its host through several ptys, one `PtyGroup`: opened, served, closed
    in an outage and re-opened together. A subclass sets ``self.ports`` (and ``paths``/``path``)
    and says what a port's bytes do (`_received`)."""

    ports: PtyGroup

    @property
    def tx_overflow_frames(self) -> int:
        return self.ports.tx_overflow_frames

    def _open(self) -> None:
        self.ports.open()

    def _close(self) -> None:
        self.ports.cleanup()

    wake_by_pipe = True
    max_wait_s = _WAKEABLE_WAIT_S

    def _serve(self, timeout_s: float) -> None:
        ports = [p for p in self.ports if p.master >= 0]
        if not ports:  # no pty right now: serve sleeps, and nothing would wake it
            self.ports.serve(min(timeout_s, _POLL_WAIT_S), self._received, self.now)
            return
        self._wait_on([p.master for p in ports], [p.master for p in ports if p.has_pending], timeout_s)
        self.ports.serve(0.0, self._received, self.now)

    def _received(self, b: int, data: bytes, t: float) -> None:
        """Port ``b`` received ``data`` at device time ``t``."""
        raise NotImplementedError

    def _go_down(self) -> None:
        self.ports.close()

    def _come_back(self) -> None:
        self.ports.open()


def split_into_gateways(device, sheet, n_gateways: int) -> None:
    """``device.blocks`` and ``device.gateways``: the sheet's links in ``n_gateways`` contiguous
    blocks (`VirtualSheet.split`), one serial gateway each; gateway 0 drives SYNC (at
    ``sync_rate_hz`` when set) and passes it to the others, its followers."""
    device.blocks = sheet.split(n_gateways)
    device.gateways = [device.gateway_class(sheet, blk, packed=device.packed,
                                            sync_rate_hz=device.sync_rate_hz if b == 0 else None, stream=b,
                                            as_node=device.gateway_node)
                       for b, blk in enumerate(device.blocks)]
    device.gateways[0].followers = device.gateways[1:]


class MultiPtyDevice(PtyGroupDevice):
    """One sheet behind ``n_gateways`` serial gateways, each on its own pty: a sheet too big for one
    UART (1,984 links at 145 Hz exceed a 12 Mbaud link even packed, docs/protocol.md §10) split in
    contiguous link blocks (`VirtualSheet.split`), as CAN buses are. The host opens every port and
    merges them into one lattice (``capsheet host --port P0 --port P1``).

    SYNC: a driving host sends SYNC on every port; each gateway passes it to its own chips. With
    ``sync_rate_hz`` gateway 0 is the SYNC source and the others follow it over a SYNC line
    (`Gateway.followers`): the same counter at the same instant on every port.

    ``device.paths``: one stable symlink per gateway (``symlink_paths``, else in a private
    temporary directory); ``device.path`` is the first. An outage closes every port.
    """

    name = "pty-gateways"

    def __init__(self, sheet, *, n_gateways: int = 2, symlink_paths: list[str] | None = None, **kw) -> None:
        if sheet.transport != "serial":
            raise ValueError(f"MultiPtyDevice needs a sheet with transport='serial', got {sheet.transport!r}")
        if symlink_paths is not None and len(symlink_paths) != n_gateways:
            raise ValueError(f"{n_gateways} gateways need {n_gateways} symlink paths, got {len(symlink_paths)}")
        if symlink_paths is not None and len({os.path.abspath(p) for p in symlink_paths}) != n_gateways:
            raise ValueError(f"the gateways' symlink paths must differ: {symlink_paths}")
        super().__init__(sheet, **kw)
        split_into_gateways(self, sheet, n_gateways)
        self.ports = PtyGroup("pty", n_gateways, symlink_paths)
        self.paths = self.ports.paths
        self.path = self.paths[0]

    def _received(self, b: int, data: bytes, t: float) -> None:
        if self.verbose is not None:
            self.verbose("rx", data)
        self.gateways[b].feed(data, t)  # when it was read: the chips sample at their SYNC's arrival

    def _send(self, bus: int, frames: list) -> None:
        self.ports[bus].write(b"".join(frames), len(frames))

    def describe(self) -> str:
        return (f"{len(self.ports)} serial gateways: "
                + ", ".join(f"{p.path} (-> {p.tty}, links {blk.start}..{blk.stop - 1})"
                            for p, blk in zip(self.ports, self.blocks)))


class MultiMemoryDevice(Device):
    """`MultiPtyDevice` over in-memory links: one sheet behind ``n_gateways`` serial gateways, each
    with a contiguous block of the links (`VirtualSheet.split`) on its own `memory_link`
    (``device.ports[b]`` is the host's end of gateway ``b``). With ``clock=`` it runs in manual
    mode, so a host on the same simulated clock (`host.session.core.Host` with ``driver=``) meets
    a multi-gateway sheet with exact counts, whatever the machine's load.

    Every port's input is read before any gateway is fed, as `PtyGroup.serve` does, and each
    port's read is handed to its gateway whole: after a stall the first gateway takes every SYNC
    of its read before the second takes its copies (`arrival.SyncArrival` keeps them together).

    ``device.stalled``: the gateways not served now (a set of indices; a test's seam for a
    gateway whose process is starved): what the host sends them waits in their link, and what
    their chips made waits in their queue, until they are served again.
    """

    name = "memory-gateways"

    def __init__(self, sheet, *, n_gateways: int = 2, **kw) -> None:
        if sheet.transport != "serial":
            raise ValueError(f"MultiMemoryDevice needs a sheet with transport='serial', got {sheet.transport!r}")
        super().__init__(sheet, **kw)
        split_into_gateways(self, sheet, n_gateways)
        links = [memory_link(f"capsheet-gw{b}", timeout=0.1) for b in range(n_gateways)]
        self.ports = [host_end for host_end, _dev in links]
        self._ends = [dev for _host, dev in links]
        self.stalled: set[int] = set()

    def _serve(self, timeout_s: float) -> None:
        got = []
        for b, end in enumerate(self._ends):
            if b in self.stalled:
                continue
            end.timeout = 0.0
            try:
                data = end.read(1 << 20)
            except OSError:  # the host closed its end
                continue
            if data:
                got.append((b, data, self.now()))
        if not got:
            if timeout_s > 0:
                self._stop.wait(timeout_s)
            return
        for b, data, t in got:
            if self.verbose is not None:
                self.verbose("rx", data)
            self.gateways[b].feed(data, t)

    def _flush(self, now: float) -> None:
        for b, gw in enumerate(self.gateways):
            if b in self.stalled:  # its output stays queued
                continue
            if self.verbose is None:  # the due frames as one write
                data, n = gw.pop_wire(now)
                if n:
                    self._send_wire(b, data, n)
                continue
            out = gw.pop_output(now)
            if out:
                for f in out:
                    self.verbose("tx", f)
                self._send(b, out)

    def _send_wire(self, bus: int, data: bytes, n_frames: int) -> None:
        self._send(bus, [data])

    def _send(self, bus: int, frames: list) -> None:
        try:
            self._ends[bus].write(b"".join(frames))
        except OSError:
            pass

    def _close(self) -> None:
        for end in self._ends:
            end.close()

    def describe(self) -> str:
        return (f"{len(self._ends)} serial gateways on in-memory links: "
                + ", ".join(f"links {blk.start}..{blk.stop - 1}" for blk in self.blocks))


# ---------------------------------------------------------------------------------------------
# python-can
# ---------------------------------------------------------------------------------------------

#: a bus timestamp older than this is from another clock (an adapter's own): the read time is taken
_MAX_FRAME_AGE_S = 1.0


def _frame_age(msg) -> float:
    """How long ago python-can says frame ``msg`` was on the bus (its ``timestamp``, ``time.time()``
    seconds: the sender's clock on ``virtual``, the kernel's receive time on ``udp_multicast``), 0
    when it says nothing usable. The chips answer — and sample a SYNC — when a frame was on the
    wire, not when this process got round to reading it (a loaded machine: tens of ms later)."""
    ts = msg.timestamp
    if not ts:
        return 0.0
    age = time.time() - float(ts)
    return age if 0.0 < age < _MAX_FRAME_AGE_S else 0.0


class CanDevice(Device):
    """The sheet's chips on one or several python-can buses.

    Parameters
    ----------
    sheet : VirtualSheet
        With ``transport="can"``.
    n_buses : int
        Chips are split in contiguous link blocks, one per bus (`VirtualSheet.split`).
    interface : str
        python-can interface (``virtual``: in this process only; ``udp_multicast``,
        ``socketcan`` ... to reach another process).
    channels : list of str, optional
        One channel per bus; default ``capsheet0``, ``capsheet1``, ... (``virtual``).
    bus_kwargs : dict
        Passed to ``can.Bus`` for every bus.
    """

    name = "can"

    def __init__(self, sheet, *, n_buses: int = 1, interface: str = "virtual",
                 channels: list[str] | None = None, bus_kwargs: dict | None = None, **kw) -> None:
        if sheet.transport != "can":
            raise ValueError(f"CanDevice needs a sheet with transport='can', got {sheet.transport!r}")
        super().__init__(sheet, **kw)
        self.interface = interface
        #: the python-can interface opened: ``udp_multicast`` is python-can's bus isolated to its
        #: group (``capsheet_udp_multicast``, host/transport/udp_multicast.py, found by name): two sheets on
        #: distinct groups on one machine do not hear each other
        self.bus_interface = "capsheet_udp_multicast" if interface == "udp_multicast" else interface
        self.channels = channels or [f"capsheet{b}" for b in range(n_buses)]
        if len(self.channels) != n_buses and channels is not None:
            n_buses = len(self.channels)
        self.blocks = sheet.split(n_buses)
        self.gateways = [self.gateway_class(sheet, blk, packed=self.packed, sync_rate_hz=self.sync_rate_hz, stream=b,
                                 as_node=self.gateway_node)
                         for b, blk in enumerate(self.blocks)]
        self.bus_kwargs = dict(bus_kwargs or {})
        self.buses: list = []
        self.foreign_frames = 0
        # udp_multicast hands a sender its own frames back: recognise and drop them
        from protocol.can import EchoFilter
        self._echo = [EchoFilter(4096) for _ in self.channels] if interface == "udp_multicast" else None

    def _open(self) -> None:
        import can
        self._can = can
        try:
            for ch in self.channels:
                self.buses.append(can.Bus(interface=self.bus_interface, channel=ch, fd=self.sheet.fd,
                                          receive_own_messages=False, **self.bus_kwargs))
        except Exception as exc:
            self._close()
            raise can.CanInitializationError(
                f"Cannot open python-can interface {self.interface!r} channel {ch!r}: {exc}") from exc

    def _close(self) -> None:
        for b in self.buses:
            try:
                b.shutdown()
            except Exception:
                pass
        self.buses = []

    def _serve(self, timeout_s: float) -> None:
        # one thread serves every bus: wait on the first, then drain them all
        got = False
        per = timeout_s / max(1, len(self.buses))
        for i, bus in enumerate(self.buses):
            msg = bus.recv(per if not got else 0.0)
            while msg is not None:
                got = True
                self._on_msg(i, msg)
                msg = bus.recv(0.0)

    def _on_msg(self, i: int, msg) -> None:
        from protocol.can import CanFrame
        if msg.is_error_frame or msg.is_remote_frame or not msg.is_extended_id:
            self.foreign_frames += 1  # not capsheet traffic (capsheet uses 29-bit data frames)
            return
        if self._echo is not None and self._echo[i].is_echo(msg.arbitration_id, msg.data):
            return
        frame = CanFrame(msg.arbitration_id, bytes(msg.data), msg.is_fd)
        if self.verbose is not None:
            self.verbose("rx", frame)
        t = self.now()
        if self.clock is None:  # at its time on the bus, never before what the chips were given already
            t = self._given = max(self._given, t - _frame_age(msg))
        self.gateways[i].receive(frame, t)

    def _send(self, bus: int, frames: list) -> None:
        can = self._can
        b = self.buses[bus]
        for f in frames:
            if f is ERROR_FRAME:
                m = can.Message(is_error_frame=True, is_extended_id=True, arbitration_id=0, dlc=0,
                                channel=self.channels[bus])
            else:
                m = can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True,
                                is_fd=f.is_fd, bitrate_switch=f.is_fd, check=False)
                if self._echo is not None:
                    self._echo[bus].sent(f.arbitration_id, f.data)
            try:
                b.send(m)
            except can.CanError:
                pass

    def _go_down(self) -> None:
        for i in range(len(self.buses)):
            self._send(i, [ERROR_FRAME])

    def _drain_while_down(self, timeout_s: float) -> None:
        for bus in self.buses:
            while bus.recv(0.0) is not None:
                pass
        if timeout_s > 0:
            time.sleep(timeout_s)

    def describe(self) -> str:
        return (f"python-can interface {self.interface!r}, channels {', '.join(self.channels)}"
                f"{' (CAN FD)' if self.sheet.fd else ''}")
