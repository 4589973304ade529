"""The fused estimator in a process of its own (``capsheet demo`` with 6/9-axis chips).

The fused estimator (`host.analysis.motion.MotionEstimator`) shapes every snapshot in order; in the
host's process it took the interpreter lock from the receive threads for ~1.5 ms of every 6.9 ms
SYNC period of a 14x14 sheet (about half the host's CPU). On a busy 2-core machine the receive
thread that lost the lock most fell behind its port: the frames of one gateway's links came after
their counter was given up, and a run of the README's 9-axis demo ended 78 % complete, the second
gateway's links late 34,027 times against the first's 3,833 (the same run with no estimate in the
host's process: 100 % complete, none late). `FusedProcess` runs `fused_update` in a child process
(``spawn``) and hands back the shapes, in order, as `FusedResult` s:

* `submit` sends one snapshot (its counter, time, mask, accelerometer, gyroscope, magnetometer
  and sample times: raw float64 bytes over a widened pipe, no pickling of arrays); at most
  `FusedProcess.max_in_flight` are outstanding, so a send never blocks on a full pipe, and a
  snapshot that finds no room waits with the caller (it must not be skipped: the estimator
  integrates the gyroscopes from one snapshot to the next);
* `results` returns the shapes made since the last call, each with the counter it belongs to;
* `wait_ready` waits for the child's start: its imports and one warm-up update of a still, level
  sheet (the estimator's structure built, then `reset`) take seconds on a busy machine, which a
  stream that has begun would spend queueing snapshots (a caller waits before it streams).

The child is the same code a caller runs in its own process (`fused_update` on a
`MotionEstimator`): the shapes are the same numbers (tests/host/workers/test_fused_worker.py).
"""

from __future__ import annotations

import struct
import time
from collections import deque
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from host.workers.estimate_worker import PIPE_SIZE, end_child, start_child

__all__ = ["FusedProcess", "FusedResult", "READY_COUNTER"]

#: request header: counter, timestamp (s), n_links, flags (`_GYRO`, `_MAG`, `_TIMES`)
_REQ = struct.Struct("<qdII")
_GYRO, _MAG, _TIMES = 1, 2, 4
#: answer header: counter, ok (a shape was made), the estimator's snapshot count, seconds spent
_ANS = struct.Struct("<qIId")
#: the counter of the child's answer once it is ready (no snapshot has it: counters are 0..65535)
READY_COUNTER = -1


@dataclass(eq=False)
class FusedResult:
    """A shape the fused estimator's process made: what the recording, the live view and the
    demo read of `host.analysis.motion.snapshots.FusedShape` (``joints``, ``valid``, ``method``;
    ``motion`` is None: the estimator's state stays in the child).

    ``joints`` is empty and ``error`` says why when the shape could not be made; ``ok`` False
    without an error is a snapshot `fused_update` leaves out (no IMU record, none newer)."""

    counter: int
    joints: np.ndarray
    valid: np.ndarray
    ok: bool
    seconds: float = 0.0  #: the update's time in the child
    snapshots: int = 0  #: the child estimator's count of snapshots (it restarts: it drops)
    error: str = ""
    method: str = "fused"
    motion: None = None


def _child(pipes, rows: int, cols: int, link_length: float, config, nice: int) -> None:
    """The fused estimator's process: every request, in order, until the pipe closes."""
    req, ans = pipes
    if nice:
        try:  # it yields to the receive path: a snapshot waits, a frame read late is lost
            import os
            os.nice(nice)
        except (AttributeError, OSError):
            pass
    from host.runtime import one_blas_thread
    one_blas_thread()
    from host.analysis.motion import MotionEstimator
    from host.analysis.motion.snapshots import fused_update

    fused = MotionEstimator(rows, cols, link_length, config=config)
    _warm_up(fused)
    ans.send_bytes(_ANS.pack(READY_COUNTER, 1, 0, 0.0))
    while True:
        try:
            buf = req.recv_bytes()
        except (EOFError, OSError):
            return
        counter, timestamp, n, flags = _REQ.unpack_from(buf, 0)
        off = _REQ.size

        def take(count: int, dtype, shape=None):
            nonlocal off
            a = np.frombuffer(buf, dtype=dtype, count=count, offset=off)
            off += a.nbytes
            return a if shape is None else a.reshape(shape)
        valid = take(n, np.bool_)
        readings = take(3 * n, "<f8", (n, 3))
        gyro = take(3 * n, "<f8", (n, 3)) if flags & _GYRO else None
        mag = take(3 * n, "<f8", (n, 3)) if flags & _MAG else None
        times = take(n, "<f8") if flags & _TIMES else np.full(n, np.nan)
        snap = SimpleNamespace(counter=counter, timestamp=timestamp, valid=valid, readings=readings, gyro=gyro,
                               mag=mag, sample_time_s=times)
        t0 = time.perf_counter()
        try:
            est = fused_update(fused, snap)
        except ValueError as exc:  # a snapshot the estimator refuses: said, not fatal
            ans.send_bytes(_ANS.pack(counter, 0, fused.snapshots, time.perf_counter() - t0)
                           + str(exc).encode()[:2000])
            continue
        secs = time.perf_counter() - t0
        if est is None:
            ans.send_bytes(_ANS.pack(counter, 0, fused.snapshots, secs))
            continue
        ans.send_bytes(b"".join((_ANS.pack(counter, 1, fused.snapshots, secs),
                                 np.ascontiguousarray(est.joints, dtype="<f8").tobytes(),
                                 np.ascontiguousarray(est.valid, dtype=np.bool_).tobytes())))


def _warm_up(fused) -> None:
    """One update of a still, level sheet with Earth's field along x, then `reset`: what the first
    snapshot would build (the structure, the accelerometer-only start) is built before any comes."""
    from protocol.constants import G0

    n = fused.n_links
    accel, field = np.zeros((n, 3)), np.zeros((n, 3))
    accel[:, 2], field[:, 0], field[:, 2] = G0, 20e-6, -40e-6
    try:
        fused.update(0.0, accel, np.zeros((n, 3)), field)
    finally:
        fused.reset()


class FusedProcess:
    """`fused_update` on a `MotionEstimator` of one lattice, in a child process (module docstring).

    Parameters
    ----------
    rows, cols : int
        Joints.
    link_length : float
        Metres.
    config : host.analysis.motion.FusedConfig, optional
    max_in_flight : int, optional
        Snapshots sent and not yet answered, at most (default: what the request pipe holds, 2..64).
    nice : int
        The child's niceness added (Unix; default 0): on a busy machine an estimator that
        can catch up yields the processor to the receive threads, which cannot.
    """

    def __init__(self, rows: int, cols: int, link_length: float, *, config=None,
                 max_in_flight: int | None = None, nice: int = 0) -> None:
        self.rows, self.cols, self.link_length = int(rows), int(cols), float(link_length)
        self.n_links = self.rows * (self.cols - 1) + self.cols * (self.rows - 1)
        request = _REQ.size + 81 * self.n_links
        #: default: as many as the request pipe holds (a send never blocks), 2..64 (14x14: 35)
        self.max_in_flight = int(max_in_flight) if max_in_flight else max(2, min(64, PIPE_SIZE // request))
        self._req, self._ans, self._proc = start_child(
            _child, (self.rows, self.cols, self.link_length, config, int(nice)), "capsheet-fused")
        self._in_flight = 0
        self.ready = False  #: the child answered `READY_COUNTER` (`wait_ready`)
        self.submitted = 0
        self.made = 0  #: shapes returned
        self.left_out = 0  #: snapshots `fused_update` left out (no IMU record, none newer)
        self.failed = 0  #: snapshots the estimator refused (`FusedResult.error`)
        self.busy_s = 0.0  #: seconds the child spent in `fused_update`

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    def wait_ready(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for the child to be ready (module docstring); whether it is."""
        t_end = time.monotonic() + timeout_s
        while not self.ready:
            left = t_end - time.monotonic()
            if left <= 0 or not self._proc.is_alive() and not self._ans.poll(0):
                break
            if self._ans.poll(min(0.1, left)):
                self._take(self._ans.recv_bytes())
        return self.ready

    @property
    def free(self) -> bool:
        """Another snapshot may be sent now."""
        return self._in_flight < self.max_in_flight

    def submit(self, snap) -> None:
        """Send ``snap`` (a `host.snapshots.snapshot.LatticeSnapshot` of 6/9-axis chips); needs `free`."""
        n = self.n_links
        valid = np.ascontiguousarray(snap.valid, dtype=np.bool_)
        readings = np.ascontiguousarray(snap.readings, dtype="<f8")
        if valid.shape != (n,) or readings.shape != (n, 3):
            raise ValueError(f"snapshot of {readings.shape} readings for a lattice of {n} links")
        flags, parts = 0, [valid.tobytes(), readings.tobytes()]
        for bit, a in ((_GYRO, snap.gyro), (_MAG, snap.mag)):
            if a is not None:
                flags |= bit
                parts.append(np.ascontiguousarray(a, dtype="<f8").tobytes())
        if snap.sample_time_s is not None:
            flags |= _TIMES
            parts.append(np.ascontiguousarray(snap.sample_time_s, dtype="<f8").tobytes())
        self._req.send_bytes(_REQ.pack(int(snap.counter), float(snap.timestamp), n, flags) + b"".join(parts))
        self._in_flight += 1
        self.submitted += 1

    def results(self, timeout_s: float = 0.0) -> list[FusedResult]:
        """Shapes made since the last call, in order (waiting up to ``timeout_s`` for the first)."""
        out: list[FusedResult] = []
        while (self._in_flight or not self.ready) and self._ans.poll(timeout_s if not out else 0.0):
            try:
                buf = self._ans.recv_bytes()
            except (EOFError, OSError):
                self._in_flight = 0
                break
            r = self._take(buf)
            if r is not None:
                out.append(r)
        return out

    def _take(self, buf: bytes) -> FusedResult | None:
        """One answer of the child: a `FusedResult`, or None for its ready message."""
        counter, ok, count, secs = _ANS.unpack_from(buf, 0)
        if counter == READY_COUNTER:
            self.ready = True
            return None
        n, rc = self.n_links, (self.rows, self.cols, 3)
        self._in_flight -= 1
        self.busy_s += secs
        if not ok:
            err = buf[_ANS.size:].decode(errors="replace")
            if err:
                self.failed += 1
            else:
                self.left_out += 1
            return FusedResult(counter, np.empty((0,)), np.zeros(n, bool), False, secs, count, err)
        off = _ANS.size
        joints = np.frombuffer(buf, "<f8", count=3 * self.rows * self.cols, offset=off).reshape(rc)
        valid = np.frombuffer(buf, np.bool_, count=n, offset=off + joints.nbytes)
        self.made += 1
        return FusedResult(counter, joints, valid, True, secs, count)

    def close(self, timeout_s: float = 5.0) -> list[FusedResult]:
        """Collect what is in flight (up to ``timeout_s``), then end the child. Returns those shapes."""
        out: list[FusedResult] = []
        t_end = time.monotonic() + timeout_s
        while self._in_flight and time.monotonic() < t_end:
            out += self.results(min(0.1, max(0.0, t_end - time.monotonic())))
        end_child(self._req, self._ans, self._proc)
        return out
