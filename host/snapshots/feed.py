"""`SnapshotFeed`: the aggregator for threads, and the one place every consumer reads snapshots from.

`host.snapshots.aggregator.Aggregator` is sans-I/O: it takes ``now`` in every call and holds no lock. A host
feeds it from several threads (one receive thread per bus, the SYNC thread) while consumers wait
for snapshots in others; `SnapshotFeed` is the small piece between them:

* **the lock and the clock**: every call into the aggregator runs under one lock, at ``now`` read
  from the feed's clock under that lock (a simulated clock in tests);
* **the correction, in one place**: each emitted snapshot passes the feed's ``correction``
  (``readings -> readings``; `host.session.core.Host.set_calibration` installs a per-chip calibration)
  exactly once, when it is emitted, before anyone sees it;
* **listeners**: then every listener (`add_listener`: the recorder, the host's health check, a
  user's ``on_snapshot``) is called with the corrected snapshot, in emission order, in the thread
  that caused the emission, under the lock (quick work only);
* **the queue**: then it is queued for the consumers that wait (`get`, `latest`, `drain`): newest
  wins, a consumer slower than the sheet loses the oldest, counted in the aggregator's
  ``stats.dropped``.

So ``capsheet host``, ``demo``, ``tactile``, ``calibrate``, the live view and the recorder all see
the same, corrected snapshots, and none can read past the correction. `add_open_listener` and
`add_ingest_listener` observe the inputs (a SYNC opening a counter; events ingested at ``now``) at
the moment they are applied, under the lock, so a recording of them replays alike.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
import time
from collections import deque
from typing import Callable, Iterable

import numpy as np

from host.snapshots.aggregator import Aggregator
from host.snapshots.snapshot import LatticeSnapshot

__all__ = ["SnapshotFeed", "corrected"]

#: while a consumer waits, the feed emits what passed its deadline at least this often (s)
_WAIT_POLL_S = 0.05


def corrected(snap: LatticeSnapshot, correction: Callable[[np.ndarray], np.ndarray]) -> LatticeSnapshot:
    """``snap`` with ``correction(readings)`` as its readings (read-only, float64): what the feed
    does to every snapshot it emits, and what a consumer that makes snapshots without a host (the
    virtual tactile sheet) does to its own."""
    readings = np.asarray(correction(snap.readings), dtype=np.float64)
    readings.setflags(write=False)
    return dataclasses.replace(snap, readings=readings)


class SnapshotFeed:
    """A thread-safe `Aggregator` with its correction, listeners and output queue (module docstring).

    Parameters
    ----------
    aggregator : Aggregator
        The sans-I/O core, without an ``on_snapshot`` of its own (give listeners to the feed: they
        get corrected snapshots); from now on called only through this feed, which drains its
        buffer after every call.
    clock : callable
        ``() -> seconds``, monotonic: the ``now`` of every call (default ``time.monotonic``).
    queue_size : int
        Snapshots kept for `get` / `latest` / `drain` (newest wins).
    wall_clock : callable
        ``() -> Unix seconds``, for the snapshots' ``wall_time`` (default ``time.time``).
    """

    def __init__(self, aggregator: Aggregator, *, clock: Callable[[], float] = time.monotonic,
                 queue_size: int = 64, wall_clock: Callable[[], float] = time.time) -> None:
        if queue_size < 1:
            raise ValueError(f"Invalid queue_size: {queue_size!r} (need >= 1)")
        if aggregator.on_snapshot is not None:
            raise ValueError("The aggregator of a SnapshotFeed has no on_snapshot of its own: give it to "
                             "SnapshotFeed.add_listener (listeners get the corrected snapshots)")
        self.aggregator = aggregator
        self.clock = clock
        self.wall_clock = wall_clock
        self.queue_size = int(queue_size)
        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._out: deque[LatticeSnapshot] = deque()
        self._correction: Callable[[np.ndarray], np.ndarray] | None = None
        self._listeners: tuple = ()
        self._open_listeners: tuple = ()
        self._ingest_listeners: tuple = ()
        self._posted: deque[tuple[int, float, bool]] = deque()  # `post_open`s not yet applied
        self._depth = 0  # how deep the lock is held (by its one holder): posts apply at the outermost

    # -- what consumers get ----------------------------------------------------------------------
    def set_correction(self, correction: Callable[[np.ndarray], np.ndarray] | None) -> None:
        """``readings (n_links, 3) -> readings``, applied once to every snapshot emitted from now
        on (NaN rows stay NaN); None: none. The one place a calibration is applied."""
        with self._lock:
            self._correction = correction

    @property
    def correction(self) -> Callable[[np.ndarray], np.ndarray] | None:
        return self._correction

    def add_listener(self, fn: Callable[[LatticeSnapshot], None]) -> None:
        """Call ``fn(snapshot)`` with every snapshot emitted from now on, corrected, in emission
        order, in the emitting thread, under the feed's lock (recorders, checks, callbacks)."""
        with self._lock:
            self._listeners = (*self._listeners, fn)

    def add_open_listener(self, fn: Callable[[int, float], None]) -> None:
        """Call ``fn(counter, now)`` for every `open_counter`, under the lock, before it is applied."""
        with self._lock:
            self._open_listeners = (*self._open_listeners, fn)

    def add_ingest_listener(self, fn: Callable[[int, float], None]) -> None:
        """Call ``fn(bus, now)`` for every `ingest`, under the lock, before it is applied: ``now``
        is the arrival time the aggregator decides with."""
        with self._lock:
            self._ingest_listeners = (*self._ingest_listeners, fn)

    def get(self, timeout_s: float | None = None) -> LatticeSnapshot | None:
        """The oldest queued snapshot, waiting up to ``timeout_s`` (None: forever); None on timeout.
        While it waits, counters whose deadline passes are emitted (at least every 50 ms)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while not self._out:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._cond.wait(_WAIT_POLL_S if remaining is None else min(remaining, _WAIT_POLL_S))
                if not self._out:
                    self.poll()
            return self._out.popleft()

    def latest(self, timeout_s: float | None = None) -> LatticeSnapshot | None:
        """Newest wins: the newest queued snapshot (waiting up to ``timeout_s`` for one); the older
        ones queued are skipped and counted in the aggregator's ``stats.dropped``. None on timeout."""
        snap = self.get(timeout_s)
        if snap is None:
            return None
        with self._lock:
            if self._out:  # `snap` and all but the newest queued are skipped
                self.aggregator.stats.dropped += len(self._out)
                snap = self._out.pop()
                self._out.clear()
        return snap

    def drain(self) -> list[LatticeSnapshot]:
        """Every queued snapshot, oldest first, without waiting."""
        with self._lock:
            out = list(self._out)
            self._out.clear()
            return out

    @property
    def pending(self) -> int:
        """Snapshots queued for `get`."""
        return len(self._out)

    # -- what producers do (each under the lock, at the feed's ``now``) --------------------------
    @contextlib.contextmanager
    def _locked(self):
        """The feed's lock; the outermost holder first applies the opens posted meanwhile."""
        with self._lock:
            self._depth += 1
            try:
                if self._depth == 1 and self._posted:
                    self._apply_posted()
                yield
            finally:
                self._depth -= 1

    @contextlib.contextmanager
    def _locked_if_free(self, wait: bool):
        """`_locked` if the lock is free (or ``wait``); yields whether it is held."""
        if not self._lock.acquire(blocking=wait):
            yield False
            return
        try:
            with self._locked():
                yield True
        finally:
            self._lock.release()

    def _apply_posted(self) -> None:
        while self._posted:
            counter, now, restart = self._posted.popleft()
            self._open(counter, now, restart)

    def _now(self, now: float | None) -> float:
        return self.clock() if now is None else now

    def _deliver(self) -> None:
        """Everything the core emitted during the call: corrected, to the listeners, queued."""
        emitted = self.aggregator.drain()
        if not emitted:
            return
        fix, agg = self._correction, self.aggregator
        for snap in emitted:
            if fix is not None:
                snap = corrected(snap, fix)
            for fn in self._listeners:
                fn(snap)
            if len(self._out) >= self.queue_size:
                self._out.popleft()
                agg.stats.dropped += 1
            self._out.append(snap)
        self._cond.notify_all()

    def ingest(self, events: Iterable, bus: int = 0, now: float | None = None) -> float:
        """`Aggregator.ingest` at ``now`` (default: the clock, read under the lock); returns ``now``."""
        with self._locked():
            now = self._now(now)
            for fn in self._ingest_listeners:
                fn(bus, now)
            self.aggregator.wall_offset = self.wall_clock() - self.clock()  # a frame may open a counter
            self.aggregator.ingest(events, bus, now=now)
            self._deliver()
            return now

    @contextlib.contextmanager
    def one_read(self):
        """Hold the feed across everything one read of a bus brings (its data ingested in parts
        around the control frames between them): no other thread emits in between. A recording
        writes the read once, at its first `ingest` (`add_ingest_listener`), and a replay ingests
        it whole at that time; a counter emitted by the SYNC thread between two parts would take
        the first part live and both in the replay (2 of 198 snapshots of a loaded 6-axis
        run replayed different)."""
        with self._locked():
            yield

    def open_counter(self, counter: int, now: float | None = None, *, restart: bool = False) -> bool:
        """`Aggregator.open_counter` at ``now`` (default: the clock)."""
        with self._locked():
            return self._open(counter, self._now(now), restart)

    def _open(self, counter: int, now: float, restart: bool) -> bool:
        for fn in self._open_listeners:
            fn(counter, now)
        self.aggregator.wall_offset = self.wall_clock() - self.clock()
        ok = self.aggregator.open_counter(counter, now, restart=restart)
        self._deliver()
        return ok

    def post_open(self, counter: int, now: float, *, restart: bool = False) -> bool:
        """`open_counter` without waiting for the lock (the SYNC thread, right before it writes the
        SYNC): applied now if the lock is free, else by the next call that takes the lock, before
        that call's own work; the counter's time is ``now`` either way. Every frame answering the
        SYNC is read after it was written, so after this post, and is ingested after the open (a
        read held across `one_read` began before the post and applies it when it ends). Returns
        True if it was applied now.

        A receive thread holds the lock across a whole read's ingest; waiting for it put the SYNC
        out 1.4 ms late at the median and 17 ms at p99 on a 64x64 sheet on five gateways, and the
        slots it overran were missed."""
        self._posted.append((int(counter), float(now), bool(restart)))
        with self._locked_if_free(False) as held:  # inside a read (`one_read`): applied when it ends
            return held and self._depth == 1

    def poll(self, now: float | None = None, *, wait: bool = True) -> bool:
        """`Aggregator.poll`: emit what passed its deadline. ``wait=False``: only if the lock is
        free (returns False, nothing done, if another thread holds it)."""
        with self._locked_if_free(wait) as held:
            if held:
                self.aggregator.poll(self._now(now))
                self._deliver()
            return held

    def input_idle(self, bus: int, now: float | None = None) -> None:
        """`Aggregator.input_idle`: bus ``bus`` had nothing more to read at ``now``."""
        with self._locked():
            self.aggregator.input_idle(bus, self._now(now))
            self._deliver()

    def flush(self, now: float | None = None) -> None:
        """`Aggregator.flush`: emit every open counter, masked where incomplete."""
        with self._locked():
            self.aggregator.flush(self._now(now))
            self._deliver()

    def emit_through(self, counter: int, now: float | None = None) -> None:
        """`Aggregator.emit_through` (what a replay does where the recording says the host emitted)."""
        with self._locked():
            self.aggregator.emit_through(counter, self._now(now))
            self._deliver()

    def restart(self, now: float | None = None) -> None:
        """`Aggregator.restart`: a new counter sequence."""
        with self._locked():
            self.aggregator.restart(self._now(now))
            self._deliver()

    def mark_silent(self, link: int, silent: bool = True, now: float | None = None) -> None:
        with self._locked():
            self.aggregator.mark_silent(link, silent, self._now(now))
            self._deliver()

    def set_map(self, node_to_link, unassigned, now: float | None = None) -> None:
        """`Aggregator.set_node_map` and `Aggregator.set_unassigned` together (a new assignment)."""
        with self._locked():
            self.aggregator.set_node_map(node_to_link)
            self.aggregator.set_unassigned(unassigned, self._now(now))
            self._deliver()

    def set_calibration(self, offset=None, sensitivity=None) -> None:
        """`Aggregator.set_calibration`: the chips' own (CAL_DATA), what counts are converted with."""
        with self._locked():
            self.aggregator.set_calibration(offset, sensitivity)

    def set_trust(self, trust: str) -> None:
        with self._locked():
            self.aggregator.set_trust(trust)

    def streaming_from(self, now: float | None = None) -> None:
        """The host (re)starts streaming: every link counts as seen at ``now``, nobody as missing."""
        with self._locked():
            self.aggregator.stats.link_last_seen[:] = self._now(now)
            self.aggregator.reset_miss_runs()

    @property
    def n_open(self) -> int:
        return self.aggregator.n_open
