"""A recording written by a process of its own (`RecorderProcess`, docs/recording.md, "A writer
process"): the host's process hands the writer what it records, as it would hand it to a
`host.record.writer.Recorder`, and the writer process does the rest — the compact serial form, the
counts' coder, the protobuf messages and the zstd compression inside foxglove-sdk, whose calls keep
the interpreter lock while they compress.

On a 64x64 sheet at 145 Hz the host's process spent ~0.4-0.9 ms per SYNC in those calls with the
lock held, the lock its five receive threads and its SYNC thread wait for; here it spends the
writes into a pipe (a read's bytes as read, a snapshot's arrays as they are). The file is the one a
`Recorder` in the host's process writes (the same messages, in the same order, with the same times:
the writer process runs that `Recorder`), so a replay of it is exact as before.

The pipe: one message per call, ``<kind: u8><length: u32>`` then the body; raw serial input and
SYNCs packed with `struct`, everything else pickled (protocol 5). The writer answers on its stdout
with pickled messages: ``("ready", facts)`` or ``("error", type name, text)`` once started,
``("stopped", reason, paths)`` when the disk filled, ``("closed", state)`` at the end. A writer
whose host went away (end of file on its stdin) closes the file cleanly (its summary written).
"""

from __future__ import annotations

import fcntl
import os
import pickle
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import numpy as np

__all__ = ["RecorderProcess", "RAW", "SYNC", "CALL"]

RAW, SYNC, CALL = 1, 2, 3  #: message kinds
_HEAD = struct.Struct("<BI")  # kind, body length
_RAW = struct.Struct("<Bddq")  # bus, t, t_rx, log_time_ns (then the bytes)
_SYNC = struct.Struct("<Hd")  # counter, t
PIPE_SIZE = 1 << 20  #: the pipe to the writer, bytes (~0.15 s of a 64x64 sheet's input and snapshots)
_F_SETPIPE_SZ = 1031
#: seconds the host waits for the writer to open the file (it imports foxglove-sdk and numpy first)
START_TIMEOUT_S = 60.0


def _est_view(est, uncertainty: bool) -> SimpleNamespace:
    """What `Recorder.estimate` reads of an estimate, without the rest of it (its lazy parts: computed
    here only when the recording asks for them, as `Recorder.estimate` does)."""
    v = SimpleNamespace(joints=np.asarray(est.joints), valid=np.asarray(getattr(est, "valid")),
                        method=getattr(est, "method", ""), residual=getattr(est, "residual", np.nan),
                        iterations=getattr(est, "iterations", 0))
    for name in ("yaw_std", "joint_std"):
        if uncertainty or name in getattr(est, "__dict__", {}):
            val = getattr(est, name, None)
            if val is not None:
                setattr(v, name, np.asarray(val))
    return v


class RecorderProcess:
    """`host.record.writer.Recorder`'s interface for a session, with the writing in a process of its own.

    Parameters are `Recorder` 's (``path`` required; no ``live_port``: a live view shares the host's
    foxglove context, so a session with one records with a `Recorder` in the host's process,
    `host.record.recording.open_recorder`). Raises what `Recorder` raises (ValueError: too little
    free space; OSError: an unwritable path), with its message. The writer process inherits no file
    of the host's (``close_fds``): never a port, so one session per port holds as before.

    Attributes
    ----------
    path, paths, stopped, not_recorded, counts, estimates_cut, scene_cut
        As `Recorder` 's; ``paths``, ``counts`` and the cuts as the writer last reported them
        (``counts`` and the cuts at `close`).
    pid : int
        The writer process.
    """

    live = None  #: never a live view here (see above)

    def __init__(self, path, lattice, link_length: float, *, on_stop: Callable[[str], None] | None = None,
                 **kwargs) -> None:
        if path is None or kwargs.get("live_port") is not None:
            raise ValueError("RecorderProcess writes a file and no live view (give path, no live_port)")
        self.path = Path(path)
        self.lattice = lattice
        self.on_stop = on_stop
        self.paths: list[Path] = [self.path]
        self.stopped: str | None = None
        self.not_recorded = 0
        self.counts: dict[str, int] = {}
        self.estimates_cut = self.scene_cut = 0
        self._closed = False
        self._lock = threading.Lock()  # one message at a time into the pipe (from several threads)
        self._final = threading.Event()
        self._state: dict = {}
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            [str(Path(__file__).resolve().parents[2]), *filter(None, [os.environ.get("PYTHONPATH")])]))
        self._proc = subprocess.Popen([sys.executable, "-m", "host.record.writer_process"], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, env=env, close_fds=True)
        self.pid = self._proc.pid
        self._out = self._proc.stdin.fileno()
        try:
            fcntl.fcntl(self._out, _F_SETPIPE_SZ, PIPE_SIZE)
        except OSError:  # a lower pipe-max-size: the default 64 KB still works, with more waits
            pass
        self._send(CALL, pickle.dumps(("__init__", (str(path), lattice.rows, lattice.cols, float(link_length)),
                                       kwargs), protocol=5))
        reply = self._reply(START_TIMEOUT_S)
        if reply is None or reply[0] != "ready":
            self._proc.kill()
            self._proc.wait()
            if reply is None:
                raise OSError(f"the recording's writer process did not start within {START_TIMEOUT_S:g} s")
            _, kind, text = reply
            raise (ValueError if kind == "ValueError" else OSError)(text)
        self.compression_level = reply[1]["compression_level"]
        self.session = reply[1]["session"]
        self._reader = threading.Thread(target=self._replies, name="recorder-replies", daemon=True)
        self._reader.start()

    # -- the pipe --------------------------------------------------------------------------------
    def _send(self, kind: int, body, head: bytes = b"") -> None:
        data = _HEAD.pack(kind, len(head) + len(body)) + head
        with self._lock:
            try:
                if len(body) < 4096:
                    self._write_all(memoryview(data + bytes(body)))
                else:  # the body as it is, no copy of it
                    self._write_all(memoryview(data))
                    self._write_all(memoryview(body).cast("B"))
            except OSError:  # BrokenPipeError: the writer is gone
                self._writer_gone()

    def _write_all(self, v: memoryview) -> None:
        while v:
            v = v[os.write(self._out, v):]

    def _writer_gone(self) -> None:
        """The writer process ended (killed; its file is as far as it got): counted from then on."""
        if self.stopped is None:
            self.stopped = f"the writer process {self.pid} ended (exit {self._proc.poll()})"
            if self.on_stop is not None:
                self.on_stop(self.stopped)
        self.not_recorded += 1

    def _reply(self, timeout_s: float | None = None):
        f = self._proc.stdout
        if timeout_s is not None:
            import select
            r, _, _ = select.select([f], [], [], timeout_s)
            if not r:
                return None
        try:
            return pickle.load(f)
        except (EOFError, pickle.UnpicklingError, OSError):
            return None

    def _replies(self) -> None:
        while True:
            msg = self._reply()
            if msg is None:
                self._final.set()
                return
            if msg[0] == "stopped":
                self.stopped, self.paths = msg[1], [Path(p) for p in msg[2]]
                if self.on_stop is not None:
                    self.on_stop(msg[1])
            elif msg[0] == "closed":
                self._state = msg[1]
                self._final.set()
                return

    def _call(self, name: str, *args, **kwargs) -> None:
        if self._closed:
            return
        if self.stopped is not None and self._proc.poll() is not None:
            self.not_recorded += 1
            return
        self._send(CALL, pickle.dumps((name, args, kwargs), protocol=5))

    # -- what a session records (`Recorder` 's methods) --------------------------------------------
    def tap(self, transports, feed=None) -> None:
        """`Recorder.tap`: every transport's raw input, each chunk written when its events are ingested
        (stamped with the ``now`` the aggregator decides with), as `Recorder.tap` writes it."""
        from host.record.writer import InputTap
        self._tap = InputTap(transports, feed, self.raw)

    def raw(self, bus: int, kind: str, payload, port: str = "", t: float | None = None,
            log_time_ns: int | None = None, t_rx: float | None = None) -> None:
        """`Recorder.raw`: serial bytes go as they are; CAN frames as the recorder stores them."""
        if self._closed:
            return
        t = time.monotonic() if t is None else t
        t_rx = t if t_rx is None else t_rx
        if kind == "serial" and 0 <= bus < 256:
            self._send(RAW, payload, _RAW.pack(bus, t, t_rx, time.time_ns() if log_time_ns is None else log_time_ns))
            return
        if kind == "can":
            payload = [SimpleNamespace(arbitration_id=m.arbitration_id, is_extended_id=m.is_extended_id, is_fd=m.is_fd,
                                       is_error_frame=m.is_error_frame, is_remote_frame=m.is_remote_frame,
                                       bitrate_switch=getattr(m, "bitrate_switch", False), timestamp=m.timestamp,
                                       data=bytes(m.data)) for m in payload]
        self._call("raw", bus, kind, payload if kind == "can" else bytes(payload), port, t=t,
                   log_time_ns=log_time_ns, t_rx=t_rx)

    def sync(self, counter: int, t: float) -> None:
        if not self._closed:
            self._send(SYNC, b"", _SYNC.pack(int(counter) & 0xFFFF, float(t)))

    def tap_sync(self, feed) -> None:
        feed.add_open_listener(self.sync)

    def snapshot(self, snap) -> None:
        """`Recorder.snapshot`: the snapshot's arrays as they are (its readings only without counts)."""
        fields = {k: getattr(snap, k, None) for k in ("counter", "timestamp", "wall_time", "latency_s", "complete",
                                                      "valid", "status", "counts", "gyro", "mag", "sample_time_s")}
        if fields["counts"] is None:
            fields["readings"] = snap.readings
        self._call("snapshot", SimpleNamespace(**fields))

    def estimate(self, est, counter: int, timestamp: float, wall_time: float | None = None, *,
                 error_joint=None, error_pct_side=None, displacement=None, uncertainty: bool = False) -> None:
        self._call("estimate", _est_view(est, uncertainty), counter, timestamp,
                   time.time() if wall_time is None else wall_time, error_joint=error_joint,
                   error_pct_side=error_pct_side, displacement=displacement, uncertainty=uncertainty)

    def imu(self, snap, est=None) -> None:
        """The live view's channel: nothing here (no live view)."""

    def contacts(self, counter: int, timestamp: float, contacts: list[dict], wall_time: float | None = None) -> None:
        self._call("contacts", counter, timestamp, contacts, time.time() if wall_time is None else wall_time)

    def add_host_facts(self, host) -> None:
        """`Recorder.add_host_facts`: the facts are taken here (of the host) and written there."""
        from host.record.writer import Recorder
        session, layout, calibration = Recorder.session_facts(host)
        live_cal = host.calibration
        self._call("add_facts", session, layout, calibration, None if live_cal is None else live_cal.to_dict())

    def flush(self) -> None:
        self._call("flush")

    def close(self, stats: dict | None = None) -> None:
        """The pending input written, ``stats.json`` attached, the file closed by the writer; waits for
        it (its final counts). Idempotent."""
        if self._closed:
            return
        if getattr(self, "_tap", None) is not None:
            self._tap.flush()
        self._call("close", stats)
        self._closed = True
        try:
            self._proc.stdin.close()
        except OSError:
            pass
        self._final.wait(120.0)
        try:
            self._proc.wait(30.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        st = self._state
        if st:
            self.counts, self.paths = st["counts"], [Path(p) for p in st["paths"]]
            self.stopped = st["stopped"] or self.stopped
            self.not_recorded += st["not_recorded"]
            self.estimates_cut, self.scene_cut = st["estimates_cut"], st["scene_cut"]

    def __enter__(self) -> "RecorderProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ------------------------------------------------------------------------------------------------
# the writer process
# ------------------------------------------------------------------------------------------------

def _read_exact(f, n: int) -> bytes | None:
    b = f.read(n)
    return b if b is not None and len(b) == n else None


def serve(inp, out) -> int:
    """The writer: messages from ``inp`` (binary, blocking) into a `Recorder`; replies to ``out``."""
    from host.record.writer import Recorder
    from protocol.lattice import Lattice

    def reply(*msg) -> None:
        pickle.dump(msg, out, protocol=5)
        out.flush()

    head = _read_exact(inp, _HEAD.size)
    if head is None:
        return 1
    name, (path, rows, cols, link_length), kwargs = pickle.loads(_read_exact(inp, _HEAD.unpack(head)[1]))
    try:
        rec = Recorder(path, Lattice(rows, cols), link_length, **kwargs,
                       on_stop=lambda reason: reply("stopped", reason, [str(p) for p in rec.paths]))
    except (OSError, ValueError) as exc:
        reply("error", type(exc).__name__, str(exc))
        return 1
    reply("ready", {"compression_level": rec.compression_level, "session": rec.session})
    stats = None
    while True:
        head = _read_exact(inp, _HEAD.size)
        if head is None:
            break  # the host went away (or closed the pipe): close the file
        kind, n = _HEAD.unpack(head)
        body = _read_exact(inp, n)
        if body is None:
            break
        if kind == RAW:
            bus, t, t_rx, log_ns = _RAW.unpack_from(body)
            rec.raw(bus, "serial", body[_RAW.size:], t=t, log_time_ns=log_ns, t_rx=t_rx)
        elif kind == SYNC:
            rec.sync(*_SYNC.unpack(body))
        else:
            name, args, kw = pickle.loads(body)
            if name == "close":
                stats = args[0]
                break
            getattr(rec, name)(*args, **kw)
    rec.close(stats)
    reply("closed", {"counts": rec.counts, "paths": [str(p) for p in rec.paths], "stopped": rec.stopped,
                     "not_recorded": rec.not_recorded, "estimates_cut": rec.estimates_cut, "scene_cut": rec.scene_cut})
    return 0


if __name__ == "__main__":
    import signal
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the host: it closes us through the pipe
    replies = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # anything printed goes to stderr, never into the replies
    sys.exit(serve(sys.stdin.buffer, replies))
