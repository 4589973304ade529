"""Shape estimation in a process of its own (``capsheet host --estimate-process``, docs/host.md).

In one process the estimator shares the interpreter lock with the receive threads: at 64x64 a
warm estimate is ~3.5 ms of mostly Python-driven numpy, its sampled uncertainty (yaw_std,
joint_std) 1-2 s, and while the main thread holds the lock the receive threads fall behind and
frames arrive after their counter's deadline (13.9 % complete, 20 of 914 snapshots
estimated at 145 Hz). `EstimatorProcess` runs `host.analysis.estimator.estimate` in a child
process (``spawn``) and hands back `RemoteEstimate` s, in order:

* `submit` sends one snapshot's readings and mask (raw float64 bytes over a 1 MB pipe, no pickling
  of arrays); at most `max_in_flight` are outstanding, so a slow estimator costs queued snapshots
  (counted by the caller), never memory, and a send never blocks on a full pipe;
* `results` returns the estimates made since the last call, each with the counter it belongs to;
* the uncertainty is asked for with a snapshot (``uncertainty=True``) and made only when its last
  cost is under `UNCERTAINTY_SHARE` of the time since: at 14x14 (~0.1 s) once a second as in
  process, at 64x64 (~1.6 s) about once a minute, so it never starves the estimates.

**Links held.** A snapshot with a link missing has another mask of links, and a mask of its own
costs a structure and a factorisation: ~300 ms at 64x64 against ~4-6 ms warm, so one incomplete
snapshot at 145 Hz left the next ~45 unestimated (the requests in flight fill). The child keeps each
link's last valid reading: a link missing now but valid within the last `HOLD_SNAPSHOTS` snapshots
is estimated from that reading (the sheet moves little in 0.1 s) and the mask stays the held one.
The estimate's ``valid`` says which links it was made from, its ``held`` how many of those were
held readings (counted in `EstimatorProcess.held_links`); a link missing longer leaves the mask,
and that mask's structure is made once and kept while it lasts (a dead chip).

The child holds a `host.analysis.estimator.ShapeEstimator`: each estimate warm-starts from the
previous one (its yaws, its factorisation and the contraction measured on it), as the in-process
path's ``previous=`` chain does, with the same numbers. Before the first request it warms up (`WARMUP_COUNTER`): one estimate of a flat sheet
(the lattice's structure, ordering and factorisation built) and its uncertainty, whose cost starts
the rule above. A host makes the process before bring-up, so this happens while the chips are
brought up: the first snapshots' estimates no longer wait 1-2 s behind a 64x64 uncertainty, and
that CPU is not taken from the receive threads in the first seconds of streaming (the first
uncertainty of a 64x64 session then comes about a minute in).
"""

from __future__ import annotations

import multiprocessing as mp
import struct
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

__all__ = ["EstimatorProcess", "RemoteEstimate", "UNCERTAINTY_SHARE", "WARMUP_COUNTER", "PIPE_SIZE", "widen_pipe",
           "start_child", "end_child", "LinkHold", "HOLD_SNAPSHOTS"]

#: the uncertainty may take at most this share of the estimator's time (its cost / time since the last)
UNCERTAINTY_SHARE = 0.03
#: each pipe's buffer, bytes (Linux's default pipe-max-size): 4 requests of a 64x64 sheet
PIPE_SIZE = 1 << 20
#: request header: counter, n_links, flags (1 = uncertainty asked)
_REQ = struct.Struct("<qII")
#: answer header: counter, ok, iterations, residual, has_std, seconds spent, links held
_ANS = struct.Struct("<qIIdIdI")
#: a link missing from a snapshot but valid in one of the last this many is estimated from its
#: last reading (about 0.1 s at 145 Hz; module docstring, "Links held")
HOLD_SNAPSHOTS = 15
#: the counter of the child's warm-up answer (no snapshot has it: counters are 0..65535); its
#: seconds are the warm-up uncertainty's
WARMUP_COUNTER = -1


@dataclass(eq=False)
class RemoteEstimate:
    """An estimate made in the estimator process: what the recording, the live view and the
    publishers read of a `host.analysis.estimator.ShapeEstimate` (``joints``, ``valid``, ``method``,
    ``residual``, ``iterations``; ``yaw_std``/``joint_std`` only when the uncertainty was made,
    else absent from ``__dict__`` as a not-yet-computed cached property is)."""

    counter: int
    joints: np.ndarray
    valid: np.ndarray  #: the links the estimate was made from (held ones included)
    residual: float
    iterations: int
    method: str = "global"
    link_length: float = 0.01
    seconds: float = 0.0  #: the estimate's time in the child
    error: str = ""  #: why it could not be made (``joints`` is then empty)
    held: int = 0  #: links missing from the snapshot, estimated from their last reading
    extra: dict = field(default_factory=dict, repr=False)

    def __getattr__(self, name):  # yaw_std / joint_std when not computed: None, as asked
        if name in ("yaw_std", "joint_std"):
            return None
        raise AttributeError(name)


def widen_pipe(conn) -> None:
    """Make a one-way pipe's buffer `PIPE_SIZE` (Linux; elsewhere it stays as it is)."""
    try:
        import fcntl
        fcntl.fcntl(conn.fileno(), 1031, PIPE_SIZE)  # F_SETPIPE_SZ
    except (ImportError, OSError):
        pass


def start_child(target, args: tuple, name: str):
    """A spawned daemon child ``target((requests, answers), *args)`` and the parent's ends of its two
    one-way pipes, each widened to `PIPE_SIZE`: a request is 32 bytes a link (a 64x64 snapshot
    200 KB), and on a duplex pipe (a socket pair, ~200 KB buffered) the second one in flight blocked
    the main thread until the child had finished the first. Returns ``(requests, answers, process)``."""
    ctx = mp.get_context("spawn")
    req_r, req_w = ctx.Pipe(duplex=False)
    ans_r, ans_w = ctx.Pipe(duplex=False)
    for c in (req_r, ans_w):
        widen_pipe(c)
    proc = ctx.Process(target=target, args=((req_r, ans_w), *args), name=name, daemon=True)
    proc.start()
    req_r.close()
    ans_w.close()
    return req_w, ans_r, proc


def end_child(req, ans, proc) -> None:
    """Close a `start_child` child's pipes (it ends at end of file) and wait for it; terminated if
    it has not ended within 2 s."""
    req.close()
    ans.close()
    proc.join(2.0)
    if proc.is_alive():
        proc.terminate()
        proc.join(2.0)


class LinkHold:
    """Each link's last valid reading and its age in snapshots (module docstring, "Links held").

    >>> h = LinkHold(3, hold=2)
    >>> r = np.array([[0.0, 0.0, 9.8], [0.1, 0.0, 9.8], [0.2, 0.0, 9.8]])
    >>> _ = h.fill(r, np.ones(3, bool))
    >>> gone = r.copy(); gone[1] = np.nan
    >>> out, used, held = h.fill(gone, np.array([True, False, True]))
    >>> used.tolist(), held, out[1].tolist()    # link 1 from its last reading
    ([True, True, True], 1, [0.1, 0.0, 9.8])
    >>> _ = h.fill(gone, np.array([True, False, True]))
    >>> h.fill(gone, np.array([True, False, True]))[1].tolist()   # missing 3 snapshots: out
    [True, False, True]
    """

    def __init__(self, n_links: int, hold: int = HOLD_SNAPSHOTS) -> None:
        self.hold = int(hold)
        self.last = np.full((int(n_links), 3), np.nan)
        self.age = np.full(int(n_links), np.iinfo(np.int64).max // 2, dtype=np.int64)

    def fill(self, readings: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """``(readings, used, held)``: the snapshot's readings with the held links' last ones put
        in, the links to estimate from, and how many of them were held."""
        r = np.asarray(readings)
        # all three finite, column by column (numpy's reduction over an axis of three: ~0.3 ms)
        ok = (np.asarray(valid, dtype=bool) & np.isfinite(r[:, 0]) & np.isfinite(r[:, 1])
              & np.isfinite(r[:, 2]))
        self.age += 1
        if ok.all():  # the common case: every link (a boolean gather and scatter cost ~0.5 ms at 64x64)
            self.age[:] = 0
            self.last[...] = r
        else:
            self.age[ok] = 0
            self.last[ok] = r[ok]
        used = ok | (self.age <= self.hold)
        held = int(np.count_nonzero(used & ~ok))
        if not held:
            return readings, ok, 0
        out = np.array(readings, dtype=float)
        fill = used & ~ok
        out[fill] = self.last[fill]
        return out, used, held


def _child(pipes, rows: int, cols: int, link_length: float, hold_snapshots: int = HOLD_SNAPSHOTS) -> None:
    """The estimator process: estimate every request in order until the pipe closes."""
    req, ans = pipes
    from host.runtime import one_blas_thread
    one_blas_thread()
    from host.analysis.estimator import ShapeEstimator, estimate

    n = rows * (cols - 1) + cols * (rows - 1)
    _warm_up(ans, estimate, rows, cols, link_length, n)
    chain = ShapeEstimator(rows, cols, link_length, bad_readings="mask")
    hold = LinkHold(n, hold_snapshots)
    while True:
        try:
            buf = req.recv_bytes()
        except (EOFError, OSError):
            return
        counter, n_links, flags = _REQ.unpack_from(buf, 0)
        off = _REQ.size
        readings = np.frombuffer(buf, dtype="<f8", count=3 * n, offset=off).reshape(n, 3)
        valid = np.frombuffer(buf, dtype=np.bool_, count=n, offset=off + 24 * n)
        t0 = time.perf_counter()
        readings, used, held = hold.fill(readings, valid)
        try:
            est = chain.update(readings, valid=used)
        except ValueError as exc:  # every valid link's reading bad: said, not fatal (the warm start is kept)
            err = str(exc).encode()[:2000]
            ans.send_bytes(_ANS.pack(counter, 0, 0, float("nan"), 0, time.perf_counter() - t0, 0) + err)
            continue
        parts = [np.ascontiguousarray(est.joints, dtype="<f8").tobytes(),
                 np.ascontiguousarray(est.valid, dtype=np.bool_).tobytes()]
        has_std = 0
        if flags & 1:
            parts += [np.ascontiguousarray(est.yaw_std, dtype="<f8").tobytes(),
                      np.ascontiguousarray(est.joint_std, dtype="<f8").tobytes()]
            has_std = 1
        head = _ANS.pack(counter, 1, int(est.iterations), float(est.residual), has_std, time.perf_counter() - t0,
                         held)
        ans.send_bytes(head + est.method.encode().ljust(16, b"\0") + b"".join(parts))


def _warm_up(ans, estimate, rows: int, cols: int, link_length: float, n: int) -> None:
    """Estimate a flat sheet and its uncertainty once; answer `WARMUP_COUNTER` with the
    uncertainty's seconds (ok 0 and the reason if it failed: the requests are served anyway)."""
    from protocol.constants import G0

    flat = np.zeros((n, 3))
    flat[:, 2] = G0
    try:
        est = estimate(flat, rows, cols, link_length, valid=np.ones(n, dtype=bool), bad_readings="mask")
        t0 = time.perf_counter()
        _ = (est.yaw_std, est.joint_std)  # cached properties: made now
        ans.send_bytes(_ANS.pack(WARMUP_COUNTER, 1, 0, 0.0, 1, time.perf_counter() - t0, 0))
    except Exception as exc:  # noqa: BLE001 (a warm-up that fails costs nothing but itself)
        ans.send_bytes(_ANS.pack(WARMUP_COUNTER, 0, 0, 0.0, 0, 0.0, 0) + repr(exc).encode()[:2000])


class EstimatorProcess:
    """Shape estimates of one lattice made in a child process (module docstring).

    Parameters
    ----------
    rows, cols : int
        Joints.
    link_length : float
        Metres.
    max_in_flight : int, optional
        Snapshots sent and not yet answered, at most (default: what the request pipe holds, 2..16).
    hold_snapshots : int, optional
        A missing link valid within this many snapshots is estimated from its last reading
        (default `HOLD_SNAPSHOTS`; 0: never, every new mask gets its own structure).
    """

    def __init__(self, rows: int, cols: int, link_length: float, *, max_in_flight: int | None = None,
                 hold_snapshots: int = HOLD_SNAPSHOTS) -> None:
        if int(hold_snapshots) < 0:
            raise ValueError(f"Invalid hold_snapshots: {hold_snapshots!r} (need >= 0)")
        self.rows, self.cols, self.link_length = int(rows), int(cols), float(link_length)
        self.n_links = self.rows * (self.cols - 1) + self.cols * (self.rows - 1)
        request = _REQ.size + 25 * self.n_links
        #: default: as many as the request pipe holds (a send never blocks), 2..16 (64x64: 5)
        self.max_in_flight = int(max_in_flight) if max_in_flight else max(2, min(16, PIPE_SIZE // request))
        self._req, self._ans, self._proc = start_child(_child, (self.rows, self.cols, self.link_length,
                                                                int(hold_snapshots)), "capsheet-estimator")
        self._in_flight: deque[float] = deque([time.monotonic()])  # send times; the warm-up's first
        self.warm = False  #: the child's warm-up answered (`WARMUP_COUNTER`)
        self.warmup_error = ""  #: why the warm-up failed, if it did
        self.submitted = 0
        self.made = 0  #: estimates returned
        self.failed = 0  #: snapshots the estimator could not estimate (`RemoteEstimate.error`)
        self.busy_s = 0.0  #: seconds the child spent estimating
        self.held_links = 0  #: links estimated from their last reading, over every estimate ("Links held")
        self.held_estimates = 0  #: estimates with at least one such link
        self.uncertainties = 0
        self._unc_cost = 0.0
        self._last_unc = -np.inf

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    @property
    def alive(self) -> bool:
        """The child is running (one that died, e.g. killed, never answers again)."""
        return self._proc.is_alive()

    @property
    def uncertainty_cost_s(self) -> float:
        """The last uncertainty's seconds in the child (the warm-up's until one is made)."""
        return self._unc_cost

    @property
    def last_uncertainty_t(self) -> float:
        """When the last uncertainty was asked for (the warm-up: when it was answered), monotonic s."""
        return self._last_unc

    @property
    def free(self) -> bool:
        """Another snapshot may be sent now."""
        return len(self._in_flight) < self.max_in_flight

    def uncertainty_due(self, now: float, period_s: float) -> bool:
        """The uncertainty may be asked for at ``now``: the child warmed up, ``period_s`` passed since
        the last and its last cost is under `UNCERTAINTY_SHARE` of the time since."""
        if not self.warm:  # the warm-up's own uncertainty first: its cost starts the rule
            return False
        since = now - self._last_unc
        return since >= period_s and self._unc_cost <= UNCERTAINTY_SHARE * since

    def submit(self, snap, *, uncertainty: bool = False) -> None:
        """Send ``snap`` (readings, valid, counter) for estimation; needs `free`."""
        readings = np.ascontiguousarray(snap.readings, dtype="<f8")
        valid = np.ascontiguousarray(snap.valid, dtype=np.bool_)
        if readings.shape != (self.n_links, 3) or valid.shape != (self.n_links,):
            raise ValueError(f"snapshot of {readings.shape} readings for a lattice of {self.n_links} links")
        if uncertainty:
            self._last_unc = time.monotonic()
        self._req.send_bytes(b"".join((_REQ.pack(int(snap.counter), self.n_links, 1 if uncertainty else 0),
                                        readings.tobytes(), valid.tobytes())))
        self._in_flight.append(time.monotonic())
        self.submitted += 1

    def results(self, timeout_s: float = 0.0) -> list[RemoteEstimate]:
        """Estimates made since the last call (waiting up to ``timeout_s`` for the first)."""
        out: list[RemoteEstimate] = []
        n, rc = self.n_links, (self.rows, self.cols, 3)
        while self._in_flight and self._ans.poll(timeout_s if not out else 0.0):
            try:
                buf = self._ans.recv_bytes()
            except (EOFError, OSError):
                self._in_flight.clear()
                break
            self._in_flight.popleft()
            counter, ok, iterations, residual, has_std, secs, held = _ANS.unpack_from(buf, 0)
            if counter == WARMUP_COUNTER:  # its uncertainty's cost starts the rule
                self.warm = True
                if ok:
                    self._unc_cost, self._last_unc = secs, time.monotonic()
                else:
                    self.warmup_error = buf[_ANS.size:].decode(errors="replace")
                continue
            self.busy_s += secs
            if not ok:
                self.failed += 1
                out.append(RemoteEstimate(counter, np.empty((0,)), np.zeros(n, bool), residual, 0, seconds=secs,
                                          error=buf[_ANS.size:].decode(errors="replace")))
                continue
            off = _ANS.size
            method = buf[off:off + 16].rstrip(b"\0").decode()
            off += 16
            joints = np.frombuffer(buf, "<f8", count=3 * self.rows * self.cols, offset=off).reshape(rc)
            off += 24 * self.rows * self.cols
            valid = np.frombuffer(buf, np.bool_, count=n, offset=off)
            off += n
            est = RemoteEstimate(counter, joints, valid, residual, iterations, method, self.link_length, secs,
                                 held=held)
            self.held_links += held
            self.held_estimates += bool(held)
            if has_std:
                est.yaw_std = np.frombuffer(buf, "<f8", count=n, offset=off)
                est.joint_std = np.frombuffer(buf, "<f8", count=self.rows * self.cols,
                                              offset=off + 8 * n).reshape(self.rows, self.cols)
                self.uncertainties += 1
                self._unc_cost = secs
            self.made += 1
            out.append(est)
        return out

    def close(self, timeout_s: float = 5.0) -> list[RemoteEstimate]:
        """Collect what is in flight (up to ``timeout_s``), then end the child. Returns those estimates."""
        out: list[RemoteEstimate] = []
        t_end = time.monotonic() + timeout_s
        while self._in_flight and time.monotonic() < t_end:
            out += self.results(min(0.1, max(0.0, t_end - time.monotonic())))
        end_child(self._req, self._ans, self._proc)
        return out
