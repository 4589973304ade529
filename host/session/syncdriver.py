"""The SYNC driver: who drives SYNC (the host, or another source it follows), when the host sends it
(`SyncSchedule`, sans-I/O: a fixed grid that never bursts), and the step the SYNC thread runs
(`SyncDriver`: SYNC, emit what is due, watchdog).
"""

from __future__ import annotations

import threading

import numpy as np

from protocol.messages import Sync

from host.snapshots.counter_trust import SyncCopies
from host.session.errors import SyncConflictError

__all__ = ["SyncSchedule", "SyncDriver", "SYNC_LISTEN_S", "POLL_WAIT_S", "EMIT_EVERY_S"]

#: how long (s) a driving host listens for another SYNC source before START (`SyncDriver.check_source`)
SYNC_LISTEN_S = 0.25
#: the SYNC step emits what passed its deadline when the feed is free; after this long (s)
#: without, it waits for the feed (a receive thread holds it across a read). With threads, the
#: emitting thread waits for the feed this often instead, and the SYNC thread never waits for it
POLL_WAIT_S = 0.02
#: how often (s) the emitting thread emits what passed its deadline
EMIT_EVERY_S = 0.005


class SyncSchedule:
    """SYNC slots on a fixed grid ``t0 + k / rate_hz`` that never bursts.

    `due` is asked with the current time; it answers True at most once per slot, and when the
    caller was late by several slots it sends only one SYNC (the newest slot) and counts the
    others as ``missed``: the chips see SYNC at the rate or below it, never faster.

    >>> s = SyncSchedule(100.0, t0=0.0)
    >>> [s.due(t) for t in (0.0, 0.001, 0.010, 0.0105)]
    [True, False, True, False]
    >>> s.due(0.055), s.missed, s.sent        # slots 0.02..0.05 due at once: one SYNC, 3 missed
    (True, 3, 3)
    >>> round(s.next_t, 3)
    0.06
    """

    __slots__ = ("period", "t0", "slot", "sent", "missed", "late_s", "max_late_s")

    def __init__(self, rate_hz: float, t0: float) -> None:
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"Invalid rate_hz: {rate_hz!r} (need a finite value > 0)")
        self.period = 1.0 / float(rate_hz)
        self.t0 = float(t0)
        self.slot = 0  #: index of the next slot to send
        self.sent = 0
        self.missed = 0  #: slots skipped because the caller came too late for them
        self.late_s = 0.0  #: how late the last SYNC left after its slot (s)
        self.max_late_s = 0.0

    @property
    def next_t(self) -> float:
        """Time of the next slot."""
        return self.t0 + self.slot * self.period

    def due(self, now: float) -> bool:
        """True if a SYNC is to be sent now (then the slot is consumed)."""
        k = int(np.floor((now - self.t0) / self.period + 1e-9))
        if k < self.slot:
            return False
        self.missed += k - self.slot
        self.late_s = max(0.0, now - (self.t0 + k * self.period))
        self.max_late_s = max(self.max_late_s, self.late_s)
        self.slot = k + 1
        self.sent += 1
        return True


class SyncDriver:
    """Who drives SYNC, and the SYNC step the host runs on its schedule (`step`, in the SYNC thread
    or `Host.service`): send SYNC when a slot is due and open its counter, emit what is complete or
    past its deadline, run the watchdog.

    Parameters
    ----------
    host : Host
    sync : {"drive", "follow", "auto"}
        As asked (``sync_policy``); ``sync_mode`` is what the host does now: "drive", "follow", or
        "none" (a driving host stopped by another SYNC source: ``sync_conflict`` says why).
    start_counter : int
        The first SYNC counter sent.

    Attributes
    ----------
    step_lock : Lock
        Held for one whole `step` (SYNC sent and its counter opened together): `Host.stop` takes
        it, so no SYNC goes out after stop has looked at what is open.
    service_s : float
        Host time with the host's own stalls cut to two periods: the watchdog's clock.
    loop_lag_s, max_loop_lag_s : float
        EWMA and maximum of how late the SYNC thread woke (s).
    """

    def __init__(self, host, sync: str, start_counter: int = 0) -> None:
        if sync not in ("drive", "follow", "auto"):
            raise ValueError(f"Invalid sync: {sync!r} (need 'drive', 'follow' or 'auto')")
        self.host = host
        self.sync_policy = sync  #: as asked: "drive", "follow" or "auto" (drive unless another source)
        self.sync_mode = "follow" if sync == "follow" else "drive"  #: what the host does now
        self.counter = start_counter & 0xFFFF  #: the next SYNC counter to send
        self.syncs_sent = 0
        self.syncs_seen = 0  #: SYNCs heard (a driving host never hears its own)
        self.foreign_syncs = 0  #: SYNCs seen while driving (another SYNC source)
        #: before START a driving host listens this long (s, from the end of `quiesce`) for another
        #: SYNC source: a source slower than 1 / sync_listen_s may be caught only once streaming
        self.sync_listen_s = SYNC_LISTEN_S
        self.sync_conflict: str | None = None  #: set when a foreign SYNC source stopped a driving host
        self.sync_schedule: SyncSchedule | None = None  #: the schedule of this stream (drive)
        self.step_lock = threading.Lock()
        #: follow: each port's SYNCs, and the copies of SYNCs already heard on another port
        self.copies = SyncCopies()
        self.service_s = 0.0
        self.loop_lag_s = 0.0
        self.max_loop_lag_s = 0.0
        self._listen_since: float | None = None
        self._missed_before = 0  # SYNC slots missed by earlier schedules (earlier starts)
        self._last_step: float | None = None
        self._last_poll = float("-inf")  # when the SYNC step last emitted what was due
        #: the SYNC step also emits what passed its deadline (manual mode: `Host.service`); False
        #: when `emit_loop` runs in a thread of its own
        self.emits = True

    @property
    def syncs_missed(self) -> int:
        """SYNC slots missed since the host was made (every schedule's)."""
        return self._missed_before + (self.sync_schedule.missed if self.sync_schedule else 0)

    def listen_from(self, now: float) -> None:
        """What is heard from ``now`` on counts for `check_source` (the bus was just drained)."""
        self._listen_since = now

    def end_schedule(self) -> None:
        """The stream (re)starts or stopped: the next SYNC starts a new schedule."""
        if self.sync_schedule is not None:
            self._missed_before += self.sync_schedule.missed
        self.sync_schedule = None

    # -- the step and its thread -----------------------------------------------------------
    def step(self, now: float) -> None:
        """SYNC if a slot is due (never a burst: missed slots are counted, not caught up), emit
        what is complete or past its deadline, and run the watchdog. Callers hold `step_lock`."""
        host = self.host
        step = now - self._last_step if self._last_step is not None else 0.0
        self._last_step = now
        # the watchdog's clock: host time with the host's own stalls cut to two periods
        self.service_s += min(max(step, 0.0), max(2.0 / host.rate_hz, 0.02))
        if not host.streaming.is_set():
            self.end_schedule()
            return
        if self.sync_mode == "drive":
            sched = self.sync_schedule
            first = sched is None
            if first:
                sched = self.sync_schedule = SyncSchedule(host.rate_hz, now)
            if sched.due(now):
                c = self.counter
                # the counter's time is read right before the SYNC is written (the chips sample
                # when it arrives), and the SYNC thread does not wait for the feed's lock, which a
                # receive thread holds across a read: the open is posted, applied before any frame
                # answering it is ingested (`SnapshotFeed.post_open`)
                host.feed.post_open(c, host.now(), restart=first)
                host.commands.broadcast(Sync(counter=c))
                self.syncs_sent += 1
                self.counter = (c + 1) & 0xFFFF
        # what passed its deadline: emitted now if the feed is free, else by the next step; never
        # later than `POLL_WAIT_S` after the last poll (the step then waits for the feed)
        if self.emits and host.feed.poll(now, wait=now - self._last_poll >= POLL_WAIT_S):
            self._last_poll = now
        host.watchdog.tick(now, self.service_s)

    def emit_loop(self, stop: threading.Event) -> None:
        """The emitting thread: every `EMIT_EVERY_S`, emit what passed its deadline, waiting for the
        feed as long as a receive thread holds it — so the SYNC thread never waits for it."""
        host = self.host
        while not stop.wait(EMIT_EVERY_S):
            if host.streaming.is_set():
                host.feed.poll(host.now(), wait=True)

    def loop(self, stop: threading.Event) -> None:
        """The SYNC thread: `step` on the fixed schedule, measuring how late it wakes, until ``stop``."""
        host = self.host
        wake = host.now()
        while not stop.is_set():
            now = host.now()
            lag = max(0.0, now - wake)
            self.loop_lag_s += 0.05 * (lag - self.loop_lag_s)
            self.max_loop_lag_s = max(self.max_loop_lag_s, lag)
            with self.step_lock:
                self.step(now)
            if not host.streaming.is_set():
                wake = now + 0.01
            else:
                nxt = self.sync_schedule.next_t if (self.sync_mode == "drive" and self.sync_schedule) else now + 0.005
                wake = min(nxt, host.watchdog.next_check, now + 0.01)
            wait = wake - host.now()
            if wait > 0:
                stop.wait(wait)
            else:
                wake = host.now()

    # -- another SYNC source ---------------------------------------------------------------
    def heard(self, bus: int, msg: Sync) -> None:
        """A SYNC on ``bus`` (the receive path): while driving, another source; while following,
        the counter to open."""
        self.syncs_seen += 1
        if self.sync_mode == "drive":
            self._foreign_sync(bus, msg)
        elif self.sync_mode == "follow" and self.host.streaming.is_set():
            # (under the feed's lock: a SYNC is a control frame, handled inside `one_read`)
            if self.copies.fresh(bus, msg.counter, self.host.aggregator.newest):
                self.host.feed.open_counter(msg.counter)

    def check_source(self) -> None:
        """Before START: in drive mode, another SYNC source already on the bus is a conflict —
        ``sync="auto"`` follows it, ``sync="drive"`` raises `SyncConflictError`.

        The host listens for at least `sync_listen_s` after the bus was drained (`quiesce`) before
        it decides: a bring-up is shorter than one period of a slow source (3x3 chips: 20-40 ms),
        so without the wait a gateway's SYNC was caught only once streaming (exit 1, not 2)."""
        if self.sync_mode != "drive":
            return
        host = self.host
        sources = host.gateway_nodes.sync_sources()  # a gateway that said so (GATEWAY_INFO, §13.3)
        if sources:
            what = "; ".join(r.describe() for r in sources)
            if self.sync_policy == "auto":
                self.switch_to_follow(what)
                return
            raise SyncConflictError(f"{what}: it passes no SYNC from this host to its chips; use --sync follow "
                                    f"(or --sync auto)")
        now = host.now()
        since = self._listen_since if self._listen_since is not None else now
        while not self.syncs_seen and host.now() - since < self.sync_listen_s:
            host.idle(min(0.01, self.sync_listen_s))
        if not self.syncs_seen:
            return
        if self.sync_policy == "auto":
            self.switch_to_follow(f"{self.syncs_seen} SYNC frames from another source")
            return
        raise SyncConflictError(f"another device drives SYNC on this sheet ({self.syncs_seen} SYNC frames seen "
                                f"that this host did not send): use --sync follow (or --sync auto)")

    def switch_to_follow(self, why: str) -> None:
        """Follow the other SYNC source from now on (``sync="auto"``)."""
        self.sync_mode = "follow"
        self.host.feed.set_trust("follow")
        self.host.feed.restart()
        self.host.report("sync", f"{why}: following that SYNC source (--sync auto)")

    def _foreign_sync(self, bus: int, msg: Sync) -> None:
        """A SYNC this host did not send while it drives SYNC (it never hears its own)."""
        host = self.host
        self.foreign_syncs += 1
        if not host.streaming.is_set():
            return  # before START: `check_source` decides
        if self.sync_policy == "auto":
            self.switch_to_follow(f"SYNC from another source on {host.transports[bus].name}")
            host.feed.open_counter(msg.counter)
        elif self.sync_conflict is None:
            self.sync_conflict = (f"another device drives SYNC on {host.transports[bus].name} while this host "
                                  f"does: stopped (use --sync follow or --sync auto)")
            self.sync_mode = "none"  # `step` sends no more SYNC
            host.report("sync", self.sync_conflict)
