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
=================== ========================================================================

The two devices with a pty per gateway or bus (`MultiPtyDevice`, `SlcanDevice`) are
`PtyGroupDevice` s: one `PtyGroup` of `PtyPort` s, served by one ``select``.

Each is a context manager: ``with PtyDevice(sheet) as dev: ...`` starts the thread and stops it
(joined, ports closed) on exit; `start` / `stop` do the same by hand. The clock is
``time.monotonic()`` from `start` (``device.now()``); the chips are powered on at start.

**Manual mode** (``clock=`` a callable): no thread; the caller runs the device with
``device.step()`` at the clock's time (a simulated clock: the in-process back-to-back tests run
host and sheet in one thread, deterministically, whatever the machine's load).

**A bus that goes away** (faults ``outage_at_s``/``outage_s``/``outage_every_s``): a pty slave
path cannot be reused once its master is closed, so the pty devices publish a stable symlink
(``device.path``, in a private temporary directory unless ``symlink_path`` is given). At an
outage the device closes the pty (the host's reads fail as on an unplugged USB adapter) and
removes the symlink; when the bus comes back it opens a pty with the same number if that comes
free within a second (as an adapter plugged back in keeps its number: a host reconnects only to
the same device, host/transport/portlock.py) and re-points the symlink atomically, so a host that
reopens the same path reconnects. On CAN the device stops answering
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

import hashlib
import json
import os
import select
import tempfile
import threading
import time
import tty
from pathlib import Path
from typing import Any, Callable

from .faults import ERROR_FRAME
from .gateway import Gateway
from .memport import memory_link

__all__ = ["Device", "MemoryDevice", "PtyDevice", "MultiPtyDevice", "CanDevice", "PtyPort", "PtyGroup", "PtyGroupDevice", "open_pty", "claim_symlink",
           "SYMLINK_RECORDS"]

_IDLE_WAIT_S = 0.005


class Device:
    """Base of every virtual device: a thread running `_run` between `start` and `stop`.

    Subclasses implement ``_open()``, ``_serve(timeout_s)`` (wait at most ``timeout_s`` for host
    input, handle it) and ``_close()``; `_outage` hooks the bus-away fault.
    """

    name = "device"

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
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout_s)
            if t.is_alive():
                raise RuntimeError(f"{self.name}: thread did not stop within {timeout_s} s")
        self._thread = None
        self._close()

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
            deadline = min(gw.next_deadline() for gw in self.gateways)
            self._serve(min(max(0.0, deadline - now), 0.02))
            now = self.now()
            self._given = now  # the chips' clock is here now: no later input is taken before it
            for gw in self.gateways:
                gw.poll(now)
            self._flush(now)

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


#: where the record of every symlink a device publishes is kept (one small JSON file per path)
SYMLINK_RECORDS = os.path.join(os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir(),
                               f"capsheet-symlinks-{os.getuid()}")


def _record_file(path: str) -> str:
    return os.path.join(SYMLINK_RECORDS, hashlib.sha256(os.path.abspath(path).encode()).hexdigest()[:24] + ".json")


def _read_record(path: str) -> dict | None:
    try:
        with open(_record_file(path)) as fh:
            rec = json.load(fh)
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) and rec.get("path") == os.path.abspath(path) else None


def _write_record(path: str, target: str) -> None:
    os.makedirs(SYMLINK_RECORDS, mode=0o700, exist_ok=True)
    tmp = _record_file(path) + f".{os.getpid()}"
    with open(tmp, "w") as fh:
        json.dump({"path": os.path.abspath(path), "target": target, "pid": os.getpid()}, fh)
    os.replace(tmp, _record_file(path))


def _drop_record(path: str) -> None:
    rec = _read_record(path)
    if rec is not None and rec.get("pid") == os.getpid():
        try:
            os.unlink(_record_file(path))
        except FileNotFoundError:
            pass


def _alive(pid) -> bool:
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError, ValueError, TypeError):
        return True  # it exists (another user's), or we cannot tell: do not take its path
    return True


def claim_symlink(path: str | os.PathLike, *, replace: bool = False) -> None:
    """Check that a device may publish its symlink at ``path`` (module docstring, "Whose path it
    is"): nothing there, or a stale symlink a capsheet device published (replaced when the device
    starts). ``replace`` (the user said so): a file or a foreign symlink there is removed now.

    Raises
    ------
    FileExistsError
        ``path`` is a folder, the live port of another running sheet, or (without ``replace``) a
        file or a symlink no capsheet device published. The message says which.
    """
    path = os.fspath(path)
    if not os.path.lexists(path):
        return
    if os.path.isdir(path) and not os.path.islink(path):
        raise FileExistsError(f"{path} is a folder: a port symlink cannot take its place (give another path)")
    if os.path.islink(path):
        target, rec = os.readlink(path), _read_record(path)
        if rec is not None and rec.get("target") == target:
            if rec.get("pid") != os.getpid() and _alive(rec.get("pid")):
                raise FileExistsError(f"{path} is the port of a running virtual sheet (pid {rec['pid']}): stop it "
                                      f"or give another path")
            return  # a stale symlink of ours (its sheet was killed): replaced at start
        what = f"a symlink to {target} that no capsheet sheet published"
    else:
        what = "a file"
    if not replace:
        raise FileExistsError(f"{path} is {what}: not replaced (--overwrite replaces it)")
    os.unlink(path)


def _pty_index(path: str) -> int:
    try:
        return int(os.path.basename(path))
    except ValueError:
        return -1


def open_pty(want: str | None = None, wait_s: float = 1.0) -> tuple[int, int, str]:
    """A raw pseudo-terminal: ``(master_fd, slave_fd, slave_path)``, master non-blocking.

    ``want``: the slave path a pty of this device had before (a bus back from an outage): the same
    one if it comes free within ``wait_s``, as a USB adapter plugged back in keeps its number (a
    host reconnects only to the same device, host/transport/portlock.py). The kernel hands out the
    lowest free number: lower ones are held while asking, a higher one means ``want`` is still
    held (by a host that has not closed it yet) and is asked again; after ``wait_s`` whatever came.
    """
    held: list[tuple[int, int]] = []
    end = time.monotonic() + wait_s
    try:
        while True:
            master, slave = os.openpty()
            name = os.ttyname(slave)
            if want is None or name == want or time.monotonic() >= end or len(held) >= 256:
                break
            if 0 <= _pty_index(name) < _pty_index(want):
                held.append((master, slave))  # a lower number is free: keep it while asking again
            else:
                os.close(slave)
                os.close(master)
                time.sleep(0.01)
    finally:
        for fds in held:
            for fd in fds:
                os.close(fd)
    tty.setraw(slave)
    os.set_blocking(master, False)
    return master, slave, name


class _PtyMixin:
    """A pty with a stable symlink, re-created after an outage (module docstring)."""

    def _pty_init(self, symlink_path: str | os.PathLike | None) -> None:
        self._tmpdir = None
        if symlink_path is None:
            self._tmpdir = tempfile.mkdtemp(prefix="capsheet-")
            symlink_path = os.path.join(self._tmpdir, self.name)
        else:
            claim_symlink(symlink_path)  # nothing there but (at most) a stale symlink of ours
        self.path = str(symlink_path)
        self.tty: str | None = None
        self._master = self._slave = -1
        self._pending = bytearray()
        self.tx_overflow_bytes = 0
        self.tx_overflow_frames = 0  #: frames dropped whole because the host did not read (counted)
        # what a gateway holds for a host that does not read: a real adapter's buffer is small, and
        # a bounded one lets a host that fell behind see fresh frames again (newest wins)
        self.max_pending = 256 << 10

    def _pty_open(self) -> None:
        # back from an outage: the same pty number if it comes free (open_pty)
        self._master, self._slave, self.tty = open_pty(self.tty)
        claim_symlink(self.path)  # still nothing but (at most) a stale symlink of ours there
        # a name of our own beside it, then one atomic rename: a host reopening the path never
        # finds it missing, and nothing else's file is touched
        tmp = os.path.join(os.path.dirname(os.path.abspath(self.path)),
                           f".{os.path.basename(self.path)}.capsheet-{os.getpid()}-{id(self):x}")
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(self.tty, tmp)
        os.replace(tmp, self.path)
        if self._tmpdir is None:
            _write_record(self.path, self.tty)

    def _pty_close(self, remove_link: bool = True) -> None:
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1
        self._pending.clear()
        if remove_link:
            try:
                if self.tty is not None and os.readlink(self.path) == self.tty:  # still ours
                    os.unlink(self.path)
            except OSError:  # gone, or no longer a symlink: someone else's now
                pass
            if self._tmpdir is None:
                _drop_record(self.path)

    def _pty_read(self, timeout_s: float) -> bytes:
        if self._master < 0:
            time.sleep(timeout_s)
            return b""
        wl = [self._master] if self._pending else []
        r, w, _ = select.select([self._master], wl, [], timeout_s)
        if w:
            self._pty_write(b"")
        if not r:
            return b""
        try:
            return os.read(self._master, 65536)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:  # EIO: no slave open right now
            time.sleep(min(timeout_s, 0.005))
            return b""

    def _pty_write(self, data: bytes, n_frames: int = 0) -> None:
        if self._master < 0:
            return
        if data:
            if len(self._pending) + len(data) > self.max_pending:
                self.tx_overflow_bytes += len(data)  # nobody reads: the frames fall on the floor whole
                self.tx_overflow_frames += n_frames
                return
            self._pending += data
        while self._pending:
            try:
                n = os.write(self._master, self._pending)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.tx_overflow_bytes += len(self._pending)
                self._pending.clear()
                return
            del self._pending[:n]

    def _pty_cleanup(self) -> None:
        self._pty_close()
        if self._tmpdir is not None:
            try:
                os.rmdir(self._tmpdir)
            except OSError:
                pass


class PtyPort(_PtyMixin):
    """One pseudo-terminal with a stable symlink, re-created after an outage: for a device that
    serves several of its own (the SLCAN adapters of virtual_sheet/slcan.py)."""

    def __init__(self, name: str, symlink_path: str | os.PathLike | None = None) -> None:
        self.name = name
        self._pty_init(symlink_path)

    @property
    def master(self) -> int:
        """The master side's file descriptor (-1 while closed)."""
        return self._master

    @property
    def has_pending(self) -> bool:
        """Bytes wait for the host to read them (write again when the master is writable)."""
        return bool(self._pending)

    def open(self) -> None:
        self._pty_open()

    def close(self, remove_link: bool = True) -> None:
        self._pty_close(remove_link)

    def cleanup(self) -> None:
        self._pty_cleanup()

    def write(self, data: bytes, n_frames: int = 0) -> None:
        """Queue ``data`` (``n_frames`` frames) for the host and write what the pty takes."""
        self._pty_write(data, n_frames)


class PtyGroup:
    """Several `PtyPort` s served as one: one ``select`` over their masters, each port's bytes
    handed on with its index. What a device with a pty per gateway (`MultiPtyDevice`) or per CAN
    bus (virtual_sheet/slcan.py's `SlcanDevice`) serves its host through.

    ``group[b]`` is port ``b``; ``group.paths`` their stable symlinks (``symlink_paths``, else
    each in a private temporary directory, named ``f"{prefix}{b}"``).
    """

    def __init__(self, prefix: str, n: int, symlink_paths: list[str] | None = None) -> None:
        self.ports = [PtyPort(f"{prefix}{b}", symlink_paths[b] if symlink_paths else None) for b in range(n)]
        self.paths = [p.path for p in self.ports]

    def __len__(self) -> int:
        return len(self.ports)

    def __getitem__(self, b: int) -> PtyPort:
        return self.ports[b]

    def __iter__(self):
        return iter(self.ports)

    @property
    def tx_overflow_frames(self) -> int:
        """Frames dropped whole, over every port, because the host did not read (counted)."""
        return sum(p.tx_overflow_frames for p in self.ports)

    def open(self) -> None:
        for p in self.ports:
            p.open()

    def close(self) -> None:
        """Close every port (an outage): the symlinks go until `open`."""
        for p in self.ports:
            p.close()

    def cleanup(self) -> None:
        for p in self.ports:
            p.cleanup()

    def serve(self, timeout_s: float, on_data: Callable[[int, bytes, float], None],
              clock: Callable[[], float]) -> None:
        """Wait at most ``timeout_s`` for the host: write what waits where a port takes it, and
        hand what a port received to ``on_data(index, data, t)``, ``t`` the ``clock`` when it was read.

        Every ready port is read (and stamped) before any ``on_data``: the host writes a SYNC to
        every port at once, and a port's bytes arrive when they are read, not after the other
        ports' answers were made (a chip samples when its SYNC arrives, docs/motion.md)."""
        fds = {p.master: b for b, p in enumerate(self.ports) if p.master >= 0}
        if not fds:
            time.sleep(timeout_s)
            return
        wl = [p.master for p in self.ports if p.has_pending and p.master >= 0]
        r, w, _ = select.select(list(fds), wl, [], timeout_s)
        for fd in w:
            self.ports[fds[fd]].write(b"")
        got = []
        for fd in r:
            try:
                data = os.read(fd, 65536)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:  # EIO: no slave open right now
                continue
            if data:
                got.append((fds[fd], data, clock()))
        for b, data, t in got:
            on_data(b, data, t)


class PtyDevice(_PtyMixin, _SerialDevice):
    """The sheet's gateway on a pseudo-terminal serial port.

    ``device.path``: stable symlink to open (``serial.Serial(device.path)``); ``device.tty``:
    the current ``/dev/pts/N``. Baud rate settings are accepted and ignored (a pty has none).
    """

    name = "pty"

    def __init__(self, sheet, *, symlink_path: str | os.PathLike | None = None, **kw) -> None:
        super().__init__(sheet, **kw)
        self._pty_init(symlink_path)

    def _open(self) -> None:
        self._pty_open()

    def _close(self) -> None:
        self._pty_cleanup()

    def _serve(self, timeout_s: float) -> None:
        data = self._pty_read(timeout_s)
        if data:
            self._handle_input(data)

    def _send(self, bus: int, frames: list) -> None:
        self._pty_write(b"".join(frames), len(frames))

    def _send_wire(self, bus: int, data: bytes, n_frames: int) -> None:
        self._pty_write(data, n_frames)

    def _go_down(self) -> None:
        self._pty_close()

    def _come_back(self) -> None:
        self._pty_open()

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

    def _serve(self, timeout_s: float) -> None:
        self.ports.serve(timeout_s, self._received, self.now)

    def _received(self, b: int, data: bytes, t: float) -> None:
        """Port ``b`` received ``data`` at device time ``t``."""
        raise NotImplementedError

    def _go_down(self) -> None:
        self.ports.close()

    def _come_back(self) -> None:
        self.ports.open()


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
        self.blocks = sheet.split(n_gateways)
        self.gateways = [self.gateway_class(sheet, blk, packed=self.packed,
                                 sync_rate_hz=self.sync_rate_hz if b == 0 else None, stream=b,
                                 as_node=self.gateway_node)
                         for b, blk in enumerate(self.blocks)]
        self.gateways[0].followers = self.gateways[1:]
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
