"""Chip management and the `Host`: discover, assign, configure, calibrate, stream (docs/host.md).

`Host` is the Python API a program (the demo, the CLI) uses to run a sheet::

    from host.session import Host, Layout
    from host.transport import open_transport
    with Host([open_transport("serial", "/dev/pts/5")], "14x14", layout=Layout.load("sheet.csv"),
              rate_hz=100) as host:
        host.discover(); host.assign(); host.configure(); host.read_calibration(); host.start()
        for snap in host.snapshots(duration_s=10):
            print(snap.counter, snap.completeness)
        host.stop()

or ``host.bring_up()`` for discover + assign + configure + read_calibration + start.

Node ids: the chip on link ``k`` gets node id ``k + 1`` (1..0x7FFF), so node ids are dense, stable
across runs and the aggregator's lookup is a fixed table.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

from protocol.constants import Range, nominal_sensitivity
from protocol.framing import DecodeError, ImuBatch, SampleBatch
from protocol.lattice import Lattice
from protocol.layout import LayoutDoc, LayoutError, load_layout, save_layout
from protocol.capacity import bus_load
from protocol.messages import (NODE_MAX_ASSIGNED, Ack, Announce, Assign, CalData, CalRead, ChipState, Config,
                               ConfigImu, GetInfo, ImuSample, Info, Message, MsgType, Nack, NackReason, Reset, Sample, Snapshot, SnapshotImu, Start,
                               Status, Stop, Sync)

from .aggregator import Aggregator, LatticeSnapshot
from .feed import SnapshotFeed
from .gateways import GatewayNodes
from .transport import Transport, TransportError

#: events that are data for the aggregator (IMU records of 6/9-axis chips too, docs/protocol.md §16)
_DATA = (SampleBatch, Snapshot, Sample, DecodeError, ImuSample, SnapshotImu, ImuBatch)

__all__ = ["Layout", "LayoutError", "ChipRecord", "HostEvent", "Host", "SyncSchedule", "node_for_link",
           "SessionError", "MismatchError", "CapacityError", "SyncConflictError", "link_ranges", "capacity_remedy"]

log = logging.getLogger("capsheet.host")

#: how long (s) a driving host listens for another SYNC source before START (`Host.check_sync_source`)
SYNC_LISTEN_S = 0.25
#: bounds of what a host keeps for a run of days (issue 34); what goes is counted
EVENTS_KEPT = 10_000
RX_ERRORS_KEPT = 64
RECOVERIES_KEPT = 1_000


def node_for_link(link: int) -> int:
    """Node id the host assigns to the chip on ``link``: ``link + 1``."""
    if not 0 <= link < NODE_MAX_ASSIGNED:
        raise ValueError(f"Invalid link {link}: node ids cover links 0..{NODE_MAX_ASSIGNED - 1}")
    return link + 1


def link_ranges(links, limit: int = 12) -> str:
    """Links as compact ranges, for one log line per incident; past ``limit`` ranges the rest is
    counted, not listed (a 128x128 sheet's incident stays one readable line).

    >>> link_ranges([0, 1, 2, 3, 7, 9, 10])
    '0–3, 7, 9–10'
    >>> link_ranges([0, 2, 4, 6, 8], limit=2)
    '0, 2 and 3 more (5 links in all)'
    """
    out, run = [], []
    ks = sorted(set(int(x) for x in links))
    for k in ks:
        if run and k == run[-1] + 1:
            run.append(k)
            continue
        if run:
            out.append(f"{run[0]}–{run[-1]}" if len(run) > 1 else f"{run[0]}")
        run = [k]
    if run:
        out.append(f"{run[0]}–{run[-1]}" if len(run) > 1 else f"{run[0]}")
    if len(out) > limit:
        return f"{', '.join(out[:limit])} and {len(out) - limit} more ({len(ks)} links in all)"
    return ", ".join(out)


class SessionError(Exception):
    """The session cannot go on as asked; the message says why and what to do (one line)."""


class MismatchError(SessionError, ValueError):
    """What the host was told (layout, lattice, --fd, ...) does not match the sheet it found."""


class CapacityError(MismatchError):
    """The traffic asked for does not fit a bus (docs/protocol.md §10)."""


def capacity_remedy(kind: str, load: float, rate_hz: float, *, packed: bool, fd: bool = False,
                    bitrate: int | None = None, split: str | None = None, pack: str | None = None,
                    faster: bool = True) -> str:
    """What takes a bus at ``load`` (1.0 = full) back under its capacity, for what is already set:
    packing where it is not on (``pack``: how the command says so, e.g. with the gateways packing
    needs), more gateways or buses (``split``), a faster link (``faster``), or the highest rate
    that fits.

    >>> capacity_remedy("serial", 2.5, 145.0, packed=True, bitrate=12_000_000)
    'use more gateways (a --port each; at least 3), a link faster than 12 Mbaud (--baud), or --rate 58 or lower'
    """
    ways = []
    k = int(np.ceil(load - 1e-9))
    if kind == "serial":
        if not packed:
            ways.append(pack or "--packed (SNAPSHOT frames from the gateway)")
        ways.append(split or f"more gateways (a --port each; at least {k})")
        if faster:
            ways.append("a link faster than " + (f"{bitrate / 1e6:g} Mbaud" if bitrate else "this one") + " (--baud)")
    else:
        if not (fd and packed):
            ways.append(pack or "CAN FD with packed frames (--fd --packed)")
        ways.append(split or f"more buses (a --can each; at least {k})")
    ways.append(f"--rate {int(rate_hz / load):d} or lower")
    return "use " + ", ".join(ways[:-1]) + ", or " + ways[-1]


class SyncConflictError(SessionError):
    """Another SYNC source drives the sheet while the host was asked to drive it."""


# --------------------------------------------------------------------------------------------
# Layout files
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Layout:
    """Which chip (64-bit uid) sits on which link (lattice address, docs/design.md link order).

    The file format (CSV or JSON, uids in hex) is `protocol.layout`'s, shared with the virtual
    sheet; `load` and `save` are its thin wrappers. ``lattice`` is ``"ROWSxCOLS"`` when the file
    gives one (JSON), else None.
    """

    links: dict  # uid -> link
    lattice: str | None = None
    is_auto: bool = False  #: made by `Layout.auto`: positions are arbitrary

    def __post_init__(self) -> None:
        rows = cols = None
        if self.lattice is not None:
            r, _, c = str(self.lattice).lower().partition("x")
            if not (r.isdigit() and c.isdigit()):
                raise ValueError(f"Invalid lattice: {self.lattice!r} (need 'ROWSxCOLS')")
            rows, cols = int(r), int(c)
        LayoutDoc(dict(self.links), rows, cols)  # validates uids, links, duplicates

    @classmethod
    def load(cls, path) -> "Layout":
        """Read a layout file; raises `protocol.layout.LayoutError` (a ValueError) naming the problem."""
        doc = load_layout(path)
        return cls(dict(doc.links), doc.lattice)

    def save(self, path) -> None:
        rows = cols = None
        if self.lattice:
            r, c = self.lattice.lower().split("x")
            rows, cols = int(r), int(c)
        save_layout(path, self.links, rows, cols)

    @classmethod
    def auto(cls, uids: Sequence[int], lattice: Lattice) -> "Layout":
        """Auto-assign: chips in ascending uid order take links 0, 1, 2, ... The positions are then
        arbitrary (a shape estimate is meaningless until a real layout is given); a warning says so."""
        uids = sorted(set(int(u) for u in uids))
        if len(uids) > lattice.n_links:
            log.warning("auto-assign: %d chips for %d links; the extra chips stay unassigned", len(uids),
                        lattice.n_links)
        log.warning("auto-assign: %d chips placed on links in uid order; positions are arbitrary "
                    "(give a layout file for a meaningful shape)", min(len(uids), lattice.n_links))
        return cls({u: k for k, u in enumerate(uids[:lattice.n_links])}, f"{lattice.rows}x{lattice.cols}", is_auto=True)


# --------------------------------------------------------------------------------------------
# Chip records and host events
# --------------------------------------------------------------------------------------------

@dataclass
class ChipRecord:
    """What the host knows about one chip."""

    uid: int
    node: int  #: the node id it speaks from now (provisional until assigned)
    bus: int  #: index of the transport it was heard on
    info: Info | None = None
    link: int | None = None
    assigned: bool = False
    configured: bool = False
    started: bool = False
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))  #: counts (at the configured range)
    sensitivity: np.ndarray = field(default_factory=lambda: np.full(3, nominal_sensitivity()))  #: counts/g
    calibrated: bool = False  #: CAL_DATA read for all three axes
    last_status: Status | None = None
    nacks: list = field(default_factory=list)  #: (command name, reason name), the last `MAX_NACKS` kept
    started_at: float = float("-inf")  #: host time of its START ACK

    MAX_NACKS = 16


@dataclass(frozen=True, slots=True)
class HostEvent:
    """Something the host reports: ``kind`` in {"silent", "recovered" (a silent link speaks again),
    "nack", "no_ack", "unknown_chip", "missing_chip", "announce" (a chip rebooted), "recovery" (rebooted
    chips streaming again), "reconnect", "not_a_sheet", "sync", "resync", "stray", and `host.health`'s
    "health_magnitude", "health_magnitude_ok", "health_bias_shift"}; ``link``/``node``/``uid`` where known;
    ``detail`` text."""

    t: float
    kind: str
    detail: str
    link: int | None = None
    node: int | None = None
    uid: int | None = None


# --------------------------------------------------------------------------------------------
# The SYNC schedule (sans-I/O)
# --------------------------------------------------------------------------------------------

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


# --------------------------------------------------------------------------------------------
# The host
# --------------------------------------------------------------------------------------------

class Host:
    """Run a sheet over one or more transports (several CAN buses merge into one lattice).

    Parameters
    ----------
    transports : Transport or sequence of Transport
        Open transports (`host.transport.open_transport`). Bus index = position in this list.
    lattice : Lattice or str
        e.g. ``"14x14"`` (joints).
    layout : Layout or path, optional
        uid -> link; None: auto-assign in uid order (`Layout.auto`).
    rate_hz : float
        SYNC rate when ``sync="drive"``; also sent to the chips in CONFIG.
    sync : {"drive", "follow"}
        ``drive``: the host sends SYNC on every bus. ``follow``: a gateway drives SYNC; the host
        opens a counter when it sees that SYNC (or, without SYNC in the stream, on the first frame).
    deadline_s : float, optional
        How long a counter waits for missing links; default ``max(2 / rate_hz, 0.05)``.
    watchdog_s : float, optional
        A link silent this long is reported and marked missing; default ``max(0.5, 20 / rate_hz)``.
    range_code, filter_code, heartbeat_ms : int
        CONFIG fields.
    timeout_s, retries : float, int
        Per command round: wait ``timeout_s`` for ACKs, resend what is unanswered, ``retries`` times.
    on_snapshot : callable, optional
        Called (in a receive or SYNC thread) with every emitted `LatticeSnapshot`, corrected as
        every consumer gets it (`feed`).
    queue_size : int
        Snapshots kept for `snapshots` / `get` / `latest`; older ones are dropped when the consumer is slow.
    clock : callable, optional
        ``() -> seconds``, monotonic (default ``time.monotonic``). Every time the host uses comes
        from it, so a test can run the host on a simulated clock.
    driver : callable, optional
        Manual mode (a simulated clock): no thread is started; whenever the host waits ``dt``
        seconds it calls ``driver(dt)`` (which advances ``clock`` by ``dt`` and runs the world
        for that long) and then does its receive / SYNC / watchdog work in `service`.
    tick_s : float
        Manual mode: the longest step the host hands to ``driver`` at once (default 1 ms).
    """

    def __init__(self, transports: Transport | Sequence[Transport], lattice: Lattice | str, *,
                 layout: Layout | str | Path | None = None, rate_hz: float = 100.0, sync: str = "drive",
                 deadline_s: float | None = None, watchdog_s: float | None = None, range_code: int = Range.G2,
                 filter_code: int = 0, heartbeat_ms: int = 1000, timeout_s: float = 0.25, retries: int = 4,
                 on_snapshot: Callable[[LatticeSnapshot], None] | None = None, queue_size: int = 64,
                 start_counter: int = 0, clock: Callable[[], float] | None = None,
                 driver: Callable[[float], None] | None = None, tick_s: float = 0.001) -> None:
        self.clock: Callable[[], float] = clock if clock is not None else time.monotonic
        self._driver = driver
        if not (np.isfinite(tick_s) and tick_s > 0):
            raise ValueError(f"Invalid tick_s: {tick_s!r} (need a finite value > 0 s)")
        self.tick_s = float(tick_s)
        self.transports: list[Transport] = [transports] if isinstance(transports, Transport) else list(transports)
        if not self.transports:
            raise ValueError("Host needs at least one transport")
        self.lattice = Lattice.parse(lattice) if isinstance(lattice, str) else lattice
        if isinstance(layout, (str, Path)):
            layout = Layout.load(layout)
        self.layout: Layout | None = layout
        if sync not in ("drive", "follow", "auto"):
            raise ValueError(f"Invalid sync: {sync!r} (need 'drive', 'follow' or 'auto')")
        if not (isinstance(rate_hz, (int, float)) and np.isfinite(rate_hz) and 0 < rate_hz <= 4000):
            raise ValueError(f"Invalid rate_hz: {rate_hz!r} (need 0 < rate <= 4000)")
        self.rate_hz = float(rate_hz)
        self.sync_policy = sync  #: as asked: "drive", "follow" or "auto" (drive unless another source)
        self.sync_mode = "follow" if sync == "follow" else "drive"  #: what the host does now
        if self.layout is not None:
            far = {u: k for u, k in self.layout.links.items() if k >= self.lattice.n_links}
            if far:
                u, k = min(far.items(), key=lambda kv: kv[1])
                raise MismatchError(f"the layout puts {len(far)} chip(s) beyond lattice {self.lattice.rows}x"
                                    f"{self.lattice.cols} ({self.lattice.n_links} links), e.g. 0x{u:016X} on link {k}")
        self.range_code = Range(range_code)
        #: CONFIG_IMU for 6/9-axis chips (docs/protocol.md §16.2), sent by `bring_up` after CONFIG
        #: when set: a `protocol.messages.ConfigImu`'s fields (format, gyro_range, mag_range, flags)
        self.imu_config: tuple[int, int, int, int] | None = None
        self.filter_code = filter_code
        self.heartbeat_ms = heartbeat_ms
        self.timeout_s = timeout_s
        self.retries = retries
        self.watchdog_s = watchdog_s if watchdog_s is not None else max(0.5, 20.0 / self.rate_hz)
        n = self.lattice.n_links
        # completion deadline: a fixed one if given, else adapted to the measured SYNC -> sample
        # latency within [1.5 periods, max(0.25 s, 8 periods)] (host/aggregator.py, "Adaptive deadline")
        period = 1.0 / self.rate_hz
        if deadline_s is not None:
            dl = dict(deadline_s=deadline_s)
        else:
            dl = dict(deadline_s=max(2.0 * period, 0.05), min_deadline_s=max(1.5 * period, 0.004),
                      max_deadline_s=max(0.25, 8.0 * period))
        #: the sans-I/O aggregator: its configuration and statistics (read them freely; it is
        #: driven only through `feed`)
        self.aggregator = Aggregator(n, node_to_link=None, n_buses=len(self.transports),
                                     trust="sent" if self.sync_mode == "drive" else "follow", **dl)
        #: the one place snapshots come from (`host.feed.SnapshotFeed`): what `get`, `latest`,
        #: `snapshots`, `drain` and every listener (``on_snapshot``, a recorder, `health`) see,
        #: corrected by `set_calibration` once
        self.feed = SnapshotFeed(self.aggregator, clock=self.clock, queue_size=queue_size)
        self.feed.add_listener(self._check_health)
        if on_snapshot is not None:
            self.feed.add_listener(on_snapshot)
        self.chips: dict[int, ChipRecord] = {}  # uid -> record
        self._node_uid: dict[tuple[int, int], int] = {}  # (bus, node) -> uid
        self.events: list[HostEvent] = []  #: the newest events (bounded: `_keep_event`)
        self.events_cut = 0
        self._events_lock = threading.Lock()
        self._inbox: queue.Queue = queue.Queue(maxsize=100_000)
        self._lock = threading.RLock()
        # held for one whole `_sync_step` (SYNC sent and its counter opened together): `stop` takes
        # it, so no SYNC goes out after stop has looked at what is open
        self._step_lock = threading.Lock()
        self._stop = threading.Event()
        self._rx_threads: list[threading.Thread] = []
        self._sync_thread: threading.Thread | None = None
        self._streaming = threading.Event()
        self.counter = start_counter & 0xFFFF
        self.syncs_sent = 0
        self.syncs_seen = 0
        self._status_seen = np.full(n, -np.inf)
        self._silent_reported = np.zeros(n, dtype=bool)
        self._rx_errors: list[str] = []  #: the newest RX_ERRORS_KEPT receive errors (`_rx_error`)
        self.rx_errors_total = 0  #: every receive error (the list keeps the newest)
        self.unknown_chips: set[int] = set()
        self._send_failing: set[int] = set()
        self._host_calibration = None  # as given to `set_calibration`
        self._live_calibration = None  # ... rebased to the chips' own calibration
        self.calibration_reads = 0  #: `read_calibration` calls completed
        #: a `host.health.HealthChecker` fed every emitted snapshot (corrected); its findings are host events
        self.health = None
        # SYNC schedule, loop lag and the lag-free watchdog clock (see _sync_step / _watchdog)
        self.sync_schedule: SyncSchedule | None = None
        self._syncs_missed_before = 0  #: SYNC slots missed by earlier schedules (earlier starts)
        self.loop_lag_s = 0.0  #: EWMA of how late the SYNC loop woke (s)
        self.max_loop_lag_s = 0.0
        self._service_s = 0.0  #: host time with its own stalls removed (the watchdog's clock)
        self._last_service: float | None = None
        self._seen_service = np.zeros(n)  #: per link, _service_s when a frame was last seen
        self._seen_real = np.full(n, -np.inf)
        self._next_wd = -np.inf
        self._reconnects = [0] * len(self.transports)
        self._disconnects = [t.stats.disconnects for t in self.transports]
        self._init_sessions()

    # -- lifetime ----------------------------------------------------------------------------
    def open(self) -> "Host":
        """Start the receive threads (one per transport). Idempotent; done by every other step."""
        if self._rx_threads or self._driver is not None:
            return self
        self._stop.clear()
        for bus, t in enumerate(self.transports):
            th = threading.Thread(target=self._rx_loop, args=(bus, t), name=f"capsheet-rx-{bus}", daemon=True)
            th.start()
            self._rx_threads.append(th)
        return self

    def close(self) -> None:
        """Stop streaming (best effort), stop every thread, close the transports."""
        if self._streaming.is_set():
            try:
                self.stop()
            except TransportError as exc:
                log.warning("stop on close: %s", exc)
        self._stop.set()
        self._recover_event.set()
        for th in self._rx_threads + [t for t in (self._sync_thread, self._recover_thread) if t]:
            th.join(timeout=2.0)
        self._rx_threads = []
        self._sync_thread = None
        self._recover_thread = None
        for t in self.transports:
            t.close()

    def __enter__(self) -> "Host":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def _rx_error(self, text: str) -> None:
        """A receive error: counted, the newest RX_ERRORS_KEPT kept."""
        self.rx_errors_total += 1
        self._rx_errors.append(text)
        if len(self._rx_errors) > RX_ERRORS_KEPT:
            del self._rx_errors[0]

    def _keep_event(self, ev) -> None:
        """``events`` keeps at most `EVENTS_KEPT` (the oldest half goes when full; ``events_cut``
        counts them; ``event_counts`` counts every event by kind)."""
        with self._events_lock:
            self.events.append(ev)
            if len(self.events) > EVENTS_KEPT:
                del self.events[:EVENTS_KEPT // 2]
                self.events_cut += EVENTS_KEPT // 2

    def _report(self, kind: str, detail: str, *, quiet: bool = False, **kw) -> None:
        """Record an event (bounded) and log it, unless ``quiet`` (the caller logs the incident once)."""
        self.event_counts[kind] += 1
        if quiet:
            ev = HostEvent(self._now(), kind, detail, **kw)
            self._keep_event(ev)
            return
        ev = HostEvent(self._now(), kind, detail, **kw)
        self._keep_event(ev)
        (log.warning if kind in ("silent", "nack", "no_ack", "recovery", "reconnect", "not_a_sheet", "sync",
                                  "resync", "mismatch", "stray", "health_magnitude", "health_bias_shift")
         else log.info)("%s: %s", kind, detail)

    # -- receive path ------------------------------------------------------------------------
    def _rx_loop(self, bus: int, t: Transport) -> None:
        while not self._stop.is_set():
            if self._rx_once(bus, t, 0.05) is None:
                return

    def _rx_once(self, bus: int, t: Transport, timeout_s: float) -> bool | None:
        """One receive from transport ``bus``: ingest samples, handle control frames. Returns
        whether anything arrived, None when the transport is closed for good."""
        feed = self.feed
        try:
            events = t.recv(timeout_s)
        except TransportError as exc:
            if self._stop.is_set() or t.closed:
                return None
            self._rx_error(str(exc))
            self._idle(0.05)
            return False
        except Exception as exc:  # noqa: BLE001 - never let the receive thread die silently
            log.exception("receive thread %d", bus)
            self._rx_error(repr(exc))
            self._idle(0.05)
            return False
        if t.stats.disconnects != self._disconnects[bus]:
            self._port_lost(bus)
        if t.stats.reconnects != self._reconnects[bus]:
            self._reconnects[bus] = t.stats.reconnects
            self._report("reconnect", f"{t.name} is back (reconnect #{t.stats.reconnects})")
            self._on_reconnect(bus, t)
        if events and self._discarding:
            self._count_stale(events)
            return True
        if not events:
            if self._driver is None:
                feed.poll()
            return False
        if self.gateway_nodes.unreadable:  # a gateway packs words this host cannot read (§4.16)
            events = self.gateway_nodes.drop_unreadable(bus, events)
        control = False
        for ev in events:
            if not isinstance(ev, _DATA):
                control = True
                break
        if not control:
            feed.ingest(events, bus)
            return True
        # in wire order: a SYNC opens its counter before the samples that answer it are ingested
        data: list = []
        for ev in events:
            if isinstance(ev, _DATA):
                data.append(ev)
                continue
            if data:
                feed.ingest(data, bus)
                data = []
            self._on_control(bus, ev)
        if data:
            feed.ingest(data, bus)
        return True

    def _on_control(self, bus: int, msg: Message) -> None:
        if self.gateway_nodes.observe(bus, msg):  # a gateway node's frame (docs/protocol.md §13)
            return
        if isinstance(msg, Announce):
            if bus in self.unproven and not self._prove(bus, msg.uid):
                return  # a chip that was never on this port: not ours to drive (reported)
            with self._lock:
                rec = self.chips.get(msg.uid)
                if rec is None:
                    if len(self.chips) >= self.max_chips:  # an ANNOUNCE flood: bounded, counted
                        self.chips_dropped += 1
                        if self.chips_dropped == 1:
                            log.warning("more than %d chips announce: further uids are counted, not kept "
                                        "(a babbling bus or a foreign device?)", self.max_chips)
                        return
                    rec = self.chips[msg.uid] = ChipRecord(msg.uid, msg.node, bus)
                else:
                    if rec.assigned and msg.node != rec.node and msg.node >= 0x8000:
                        # the chip rebooted (RESET, power loss): it must be assigned again
                        was_started = rec.started
                        rec.assigned = rec.configured = rec.started = False
                        self._report("announce", f"chip 0x{msg.uid:016X} rebooted (link {rec.link})",
                                     quiet=True, link=rec.link, node=msg.node, uid=msg.uid)
                        if was_started and self._streaming.is_set():
                            self._queue_recovery(msg.uid, "rebooted")
                    if rec.bus != bus and len(self.cross_bus_uids) < self.max_chips:
                        self.cross_bus_uids.setdefault(msg.uid, {rec.bus}).add(bus)
                    rec.node, rec.bus = msg.node, bus
                self._node_uid[(bus, msg.node)] = msg.uid
        elif isinstance(msg, Info):
            with self._lock:
                uid = self._node_uid.get((bus, msg.node))
                if uid is not None:
                    self.chips[uid].info = msg
        elif isinstance(msg, Status):
            link = self.aggregator.link_of(msg.node)
            if link >= 0:
                self._status_seen[link] = self._now()
            uid = self._node_uid.get((bus, msg.node))
            if uid is not None:
                rec = self.chips[uid]
                rec.last_status = msg
                # a started chip that says it is not streaming (it lost its START: a brown-out
                # into IDLE, a STOP from elsewhere): bring it back
                if (rec.started and rec.assigned and self._streaming.is_set() and msg.state == ChipState.IDLE
                        and self._now() - rec.started_at > max(2 * self.timeout_s, 0.2)):
                    rec.started = False
                    self._queue_recovery(uid, "not streaming")
        elif isinstance(msg, Sync):
            self.syncs_seen += 1
            if self.sync_mode == "drive":
                self._foreign_sync(bus, msg)
            elif self.sync_mode == "follow" and self._streaming.is_set():
                self.feed.open_counter(msg.counter)
        elif isinstance(msg, (Ack, Nack, CalData)):
            if isinstance(msg, Nack):
                uid = self._node_uid.get((bus, msg.node))
                name = MsgType(msg.command).name if msg.command in MsgType._value2member_map_ else str(msg.command)
                if uid is not None:
                    nacks = self.chips[uid].nacks
                    nacks.append((name, msg.reason.name))
                    if len(nacks) > ChipRecord.MAX_NACKS:
                        del nacks[0]
                key = (name, msg.reason.name)
                self.nack_counts[key] += 1
                first = key not in self._nack_logged
                self._nack_logged.add(key)
                self._report("nack", f"node {msg.node} refused {name}: {msg.reason.name}"
                             + (" (further NACKs of this kind in this round are counted, not logged)" if first else ""),
                             quiet=not first, node=msg.node, uid=uid)
            try:
                self._inbox.put_nowait((bus, msg))
            except queue.Full:
                self.inbox_dropped += 1

    # -- command rounds ------------------------------------------------------------------------
    def _send(self, bus: int, msg: Message) -> None:
        t = self.transports[bus]
        if t.stats.disconnects != self._disconnects[bus]:
            self._port_lost(bus)
        if bus in self.unproven and not isinstance(msg, GetInfo):
            self.muted_sends += 1  # a port that came back drives nothing before it answers as the sheet
            return
        t.send(msg)

    def _broadcast(self, msg: Message) -> None:
        for bus in range(len(self.transports)):
            try:
                self._send(bus, msg)
                self._send_failing.discard(bus)
            except TransportError as exc:
                if bus not in self._send_failing:  # once per failure spell, not once per SYNC
                    self._send_failing.add(bus)
                    log.warning("%s", exc)

    # ---- what the gateway nodes (host/gateways.py) ask of the host, and nothing else reads
    def report(self, kind: str, detail: str, **kw) -> None:
        """Record an incident (`events`, `event_counts`) and log it."""
        self._report(kind, detail, **kw)

    def command_round(self, requests: dict, build: Callable[[object, int], list[tuple[int, Message]]],
                      match: Callable[[int, Message], object | None], what: str) -> tuple[dict, list]:
        """One command round with retries, as the bring-up's own (ASSIGN, CONFIG, ...): see `_round`."""
        return self._round(requests, build, match, what)

    def uid_at(self, bus: int, node: int) -> int | None:
        """The uid whose ANNOUNCE last came from ``node`` on transport ``bus`` (None: none heard)."""
        with self._lock:
            return self._node_uid.get((bus, node))

    def drop_chip(self, bus: int, node: int, uid: int) -> None:
        """Forget the chip record an ANNOUNCE made of ``uid`` at ``node``: it is a gateway node (its INFO
        says so), which the host does not drive as a chip."""
        with self._lock:
            self.chips.pop(uid, None)
            self._node_uid.pop((bus, node), None)

    def node_ids_in_use(self) -> set[int]:
        """Node ids the chips hold or will be given: assigned chips and every link of the layout."""
        with self._lock:
            used = {rec.node for rec in self.chips.values() if rec.assigned}
            if self.layout is not None:
                used |= {k + 1 for k in self.layout.links.values()}
            return used

    def _round(self, requests: dict, build: Callable[[object, int], list[tuple[int, Message]]],
               match: Callable[[int, Message], object | None], what: str) -> tuple[dict, list]:
        """Send every request, collect answers, resend the unanswered; ``retries`` times.

        ``requests``: key -> anything; ``build(key, attempt)`` -> [(bus, message), ...];
        ``match(bus, msg)`` -> key answered (by an ACK, NACK or CAL_DATA) or None.
        Returns ``(answers: key -> message, unanswered keys)``.
        """
        self.open()
        with self._round_lock:
            return self._round_locked(requests, build, match, what)

    def _round_locked(self, requests, build, match, what) -> tuple[dict, list]:
        answers: dict = {}
        pending = set(requests)
        self._nack_logged = set()  # one log line per (command, reason) per round
        while True:  # drop stale answers
            try:
                self._inbox.get_nowait()
            except queue.Empty:
                break
        for attempt in range(self.retries + 1):
            if not pending:
                break
            send_failed = 0
            for key in list(pending):
                for bus, msg in build(key, attempt):
                    try:
                        self._send(bus, msg)
                    except TransportError as exc:
                        send_failed += 1
                        if send_failed == 1:
                            log.warning("%s: %s", what, exc)
            deadline = self._now() + self.timeout_s * (1 + 0.5 * attempt)
            while pending:
                remaining = deadline - self._now()
                if remaining <= 0:
                    break
                try:
                    bus, msg = self._inbox_get(remaining)
                except queue.Empty:
                    break
                key = match(bus, msg)
                if key is not None and key in pending:
                    answers[key] = msg
                    pending.discard(key)
        for key in pending:
            self._report("no_ack", f"{what}: no answer from {self._key_name(key)} after {self.retries + 1} "
                                   f"attempts", quiet=True)
        if pending:  # one line per round, not one per chip
            names = sorted(self._key_name(k) for k in pending)
            log.warning("%s: no answer from %d chip(s) after %d attempts: %s%s", what, len(pending),
                        self.retries + 1, ", ".join(names[:6]), " ..." if len(names) > 6 else "")
        return answers, sorted(pending, key=repr)

    def _key_name(self, key) -> str:
        """A round's key (a uid, or (bus, node)) as 'link L (uid 0x..)' where known."""
        rec = self.chips.get(key) if isinstance(key, int) else None
        if rec is None and isinstance(key, tuple):
            uid = self._node_uid.get(key)
            rec = self.chips.get(uid) if uid is not None else None
        if rec is None:
            return repr(key)
        return f"link {rec.link} (uid 0x{rec.uid:016X})" if rec.link is not None else f"uid 0x{rec.uid:016X}"

    # -- steps ---------------------------------------------------------------------------------
    def discover(self, timeout_s: float = 0.5, rounds: int = 2) -> dict[int, ChipRecord]:
        """Broadcast GET_INFO on every bus and collect ANNOUNCE + INFO for ``timeout_s`` per round."""
        self.open()
        for _ in range(rounds):
            self._broadcast(GetInfo(0))
            deadline = self._now() + timeout_s
            while self._now() < deadline:
                self._idle(0.01)
                with self._lock:
                    expect = len(self.layout.links) if self.layout is not None else None
                    if expect is not None and all(u in self.chips and self.chips[u].info is not None
                                                  for u in self.layout.links):
                        return dict(self.chips)
        with self._lock:
            return dict(self.chips)

    def assign(self, layout: Layout | None = None, uids=None) -> dict[int, ChipRecord]:
        """ASSIGN every discovered chip to its link: node id ``link + 1``. Chips the layout does not
        name are reported (``unknown_chip``) and left unassigned; layout chips not found are links
        marked UNASSIGNED."""
        if layout is not None:
            self.layout = layout
        with self._lock:
            if self.layout is None:
                self.layout = Layout.auto(list(self.chips), self.lattice)
            links = self.layout.links
            todo = {}
            for uid, rec in self.chips.items():
                if uids is not None and uid not in uids:
                    continue
                link = links.get(uid)
                if link is None:
                    if uid not in self.unknown_chips:
                        self.unknown_chips.add(uid)
                        self._report("unknown_chip", f"chip 0x{uid:016X} is not in the layout", uid=uid,
                                     quiet=len(self.unknown_chips) > 1)
                    continue
                if link >= self.lattice.n_links:
                    raise ValueError(f"Layout puts chip 0x{uid:016X} on link {link}, but lattice "
                                     f"{self.lattice.rows}x{self.lattice.cols} has {self.lattice.n_links} links")
                rec.link = link
                todo[uid] = link

        def build(uid, attempt):
            rec = self.chips[uid]
            new = node_for_link(rec.link)
            msgs = [(rec.bus, Assign(rec.node, new_node=new, link=rec.link, uid_low=uid & 0xFFFFFFFF))]
            if attempt and rec.node != new:  # the ACK may have been lost: ask the new node too
                msgs.append((rec.bus, Assign(new, new_node=new, link=rec.link, uid_low=uid & 0xFFFFFFFF)))
            return msgs

        by_new = {node_for_link(link): uid for uid, link in todo.items()}

        def match(bus, msg):
            if msg.command != MsgType.ASSIGN:
                return None
            if isinstance(msg, Ack):
                return by_new.get(msg.node)
            return self._node_uid.get((bus, msg.node))

        answers, _ = self._round(todo, build, match, "ASSIGN")
        with self._lock:
            for uid, msg in answers.items():
                rec = self.chips[uid]
                if isinstance(msg, Ack):
                    rec.node = msg.node
                    rec.assigned = True
                    self._node_uid[(rec.bus, rec.node)] = uid
            self._apply_map()
        return dict(self.chips)

    def _assigned(self) -> list[ChipRecord]:
        return [r for r in self.chips.values() if r.assigned and r.link is not None]

    def _apply_map(self) -> None:
        n = self.lattice.n_links
        lut = np.full(1 << 16, -1, dtype=np.int64)
        unassigned = np.ones(n, dtype=bool)
        for rec in self._assigned():
            lut[rec.node] = rec.link
            unassigned[rec.link] = False
        self.feed.set_map(lut, unassigned)
        self._apply_calibration()

    def _apply_calibration(self) -> None:
        """The chips' own calibration (CAL_DATA) to the aggregator's conversion of counts, and the
        host's calibration (`set_calibration`) rebased to it, to the feed's correction."""
        n = self.lattice.n_links
        off = np.zeros((n, 3))
        sens = np.full((n, 3), nominal_sensitivity(self.range_code))
        for rec in self._assigned():
            off[rec.link] = rec.offset
            sens[rec.link] = rec.sensitivity
        self.feed.set_calibration(off, sens)
        cal = self._host_calibration
        live = None if cal is None else cal.rebased(*self.chip_calibration())
        self._live_calibration = live
        self.feed.set_correction(None if live is None else live.apply)

    def set_calibration(self, calibration) -> None:
        """Correct every snapshot with ``calibration`` (a `host.analysis.calibration.Calibration`
        of this lattice: ``capsheet calibrate``'s file) from now on, or none (None). It is rebased
        to the calibration the chips report whenever the host reads it (`read_calibration`), so a
        file works whether or not it was written to the chips; applied once, where every consumer
        reads (`feed`). Set it before bring-up so the first snapshot streamed is corrected too."""
        if calibration is not None and calibration.n_links != self.lattice.n_links:
            raise MismatchError(f"the calibration is for {calibration.rows}x{calibration.cols} joints "
                                f"({calibration.n_links} links), the lattice has {self.lattice.n_links} links")
        self._host_calibration = calibration
        self._apply_calibration()

    @property
    def calibration(self):
        """The host calibration applied now, rebased to the chips' own (what a recording attaches
        for its replay), or None."""
        return self._live_calibration

    def chip_calibration(self) -> tuple[np.ndarray, np.ndarray]:
        """The calibration the chips report (CAL_DATA, nominal where they did not answer), in ±2 g
        counts: ``(offset_counts (n_links, 3), sensitivity (n_links, 3))``; links without a chip
        nominal."""
        n = self.lattice.n_links
        scale = float(1 << int(self.range_code))
        off, sens = np.zeros((n, 3)), np.full((n, 3), nominal_sensitivity())
        for rec in self._assigned():
            off[rec.link] = np.asarray(rec.offset) * scale
            sens[rec.link] = np.asarray(rec.sensitivity) * scale
        return off, sens

    def assigned_chips(self) -> list[ChipRecord]:
        """The chips assigned to a link."""
        return self._assigned()

    def chips_by_node(self, uids=None) -> dict[tuple[int, int], ChipRecord]:
        """``(bus, node) -> ChipRecord`` of the assigned chips (of ``uids``, if given): the keys a
        `command_round` addresses chips by."""
        return self._by_node(uids)

    def command_round(self, requests: dict, build, match, what: str) -> tuple[dict, list]:
        """One command round, as every bring-up step runs it: send each request, collect the
        answers, resend the unanswered, `retries` times (a tool's own command: ``capsheet calibrate``'s
        CAL_WRITE). ``build(key, attempt) -> [(bus, message), ...]``; ``match(bus, message) -> key``
        answered (by an ACK, NACK or CAL_DATA) or None. Returns ``(answers, unanswered keys)``."""
        return self._round(requests, build, match, what)

    def _check_health(self, snap: LatticeSnapshot) -> None:
        """Feed listener: every emitted snapshot, corrected, to `health` (if set)."""
        health = self.health
        if health is not None:
            for ev in health.update(snap.readings, snap.valid, snap.timestamp):
                self._report(ev.kind, ev.detail, link=ev.link)

    def _by_node(self, uids=None) -> dict[tuple[int, int], ChipRecord]:
        return {(r.bus, r.node): r for r in self._assigned() if uids is None or r.uid in uids}

    def _simple_round(self, make: Callable[[ChipRecord], Message], command: MsgType, what: str,
                      uids=None) -> list[ChipRecord]:
        chips = self._by_node(uids)

        def match(bus, msg):
            return (bus, msg.node) if isinstance(msg, (Ack, Nack)) and msg.command == command else None

        answers, _ = self._round(chips, lambda key, _a: [(key[0], make(chips[key]))], match, what)
        return [chips[k] for k, m in answers.items() if isinstance(m, Ack)]

    def configure(self, uids=None) -> int:
        """CONFIG every assigned chip (or those of ``uids``): rate, range, filter, heartbeat. Returns
        how many ACKed."""
        ok = self._simple_round(lambda r: Config(r.node, rate_hz=max(1, min(4000, round(self.rate_hz))),
                                                 range=self.range_code, filter=self.filter_code,
                                                 heartbeat_ms=self.heartbeat_ms), MsgType.CONFIG, "CONFIG", uids)
        for rec in ok:
            rec.configured = True
        return len(ok)

    def configure_imu(self, uids=None) -> int:
        """CONFIG_IMU every assigned chip (docs §16.2) with `imu_config`; the aggregator converts the
        records at those ranges. Returns how many ACKed (a chip without the sensors NACKs UNSUPPORTED)."""
        fmt, gr, mr, fl = self.imu_config
        ok = self._simple_round(lambda r: ConfigImu(r.node, fmt, gr, mr, fl), MsgType.CONFIG_IMU, "CONFIG_IMU", uids)
        self.aggregator.gyro_range, self.aggregator.mag_range = gr, mr
        return len(ok)

    def read_calibration(self, uids=None) -> int:
        """CAL_READ the three axes of every assigned chip; chips that do not answer keep nominal
        values (reported). CAL_DATA refers to ±2 g counts; they are scaled to the configured range.
        Returns the number of chips fully calibrated (of ``uids``, if given)."""
        chips = self._by_node(uids)
        got: dict[tuple[int, int], dict[int, CalData]] = {k: {} for k in chips}
        scale = float(1 << int(self.range_code))
        for axis in range(3):
            def match(bus, msg, axis=axis):
                if isinstance(msg, CalData) and msg.axis == axis:
                    return (bus, msg.node)
                if isinstance(msg, Nack) and msg.command == MsgType.CAL_READ:
                    return (bus, msg.node)
                return None
            answers, _ = self._round(chips, lambda key, _a, axis=axis: [(key[0], CalRead(key[1], axis))],
                                     match, f"CAL_READ axis {axis}")
            for key, msg in answers.items():
                if isinstance(msg, CalData):
                    got[key][axis] = msg
        n_ok = 0
        with self._lock:
            for key, axes in got.items():
                rec = chips[key]
                for axis, cal in axes.items():
                    rec.offset[axis] = cal.offset_q4 / 16.0 / scale
                    rec.sensitivity[axis] = cal.sensitivity / scale
                rec.calibrated = len(axes) == 3
                n_ok += rec.calibrated
            self._apply_calibration()
            self.calibration_reads += 1
        return n_ok

    def calibration_summary(self) -> dict:
        """Of the assigned chips whose calibration was read, ``{"own": n, "nominal": m}``: those whose
        CAL_DATA differs from the nominal values on some axis, and those reporting the nominal values
        on all three (what a chip with no stored calibration reports, docs/protocol.md §4.7)."""
        nominal = nominal_sensitivity(self.range_code)
        own = nom = 0
        for rec in self._assigned():
            if not rec.calibrated:
                continue
            plain = bool(np.all(np.asarray(rec.offset) == 0) and np.allclose(rec.sensitivity, nominal, rtol=1e-6))
            nom += plain
            own += not plain
        return {"own": own, "nominal": nom}

    def start(self, uids=None) -> int:
        """START every assigned chip, then drive SYNC (or follow the gateway's). Returns ACK count.

        With ``uids`` (recovery) only those chips are started; the stream goes on undisturbed."""
        if uids is None:
            self.check_sync_source()
        ok = self._simple_round(lambda r: Start(r.node), MsgType.START, "START", uids)
        t_ack = self._now()
        for rec in ok:
            rec.started = True
            rec.started_at = t_ack
        if uids is not None:
            return len(ok)
        now = self._now()
        self.feed.streaming_from(now)
        self._seen_real[:] = now
        self._seen_service[:] = self._service_s
        self._silent_reported[:] = False
        if self.sync_schedule is not None:
            self._syncs_missed_before += self.sync_schedule.missed
        self.sync_schedule = None
        self._streaming.set()
        if self.sync_mode == "follow":
            self.feed.restart()
        if self._sync_thread is None and self._driver is None:
            self._sync_thread = threading.Thread(target=self._sync_loop, name="capsheet-sync", daemon=True)
            self._sync_thread.start()
        if self._recover_thread is None and self._driver is None:
            self._recover_thread = threading.Thread(target=self._recovery_loop, name="capsheet-recover",
                                                    daemon=True)
            self._recover_thread.start()
        return len(ok)

    def stop(self) -> None:
        """Stop driving SYNC, STOP every chip (broadcast, best effort), emit what is open."""
        with self._step_lock:  # a SYNC step in flight finishes first: its counter is then open
            self._streaming.clear()
        # let the counters in flight complete (up to their deadline) before masking them
        end = self._now() + self.aggregator.deadline_s + 0.02
        while self.feed.n_open and self._now() < end:
            self._idle(0.005)
            self.feed.poll()
        self._broadcast(Stop(0))
        self.feed.flush()

    def bring_up(self, discover_timeout_s: float = 0.5, discover_rounds: int = 3, *, reset: bool = True,
                 strict: bool = False, capacity: str = "refuse", packed: bool = False) -> dict:
        """From any state to streaming: `quiesce` (STOP, drain, RESET), discover, check what was found
        (`check_discovery`), assign, configure, read_calibration, `check_capacity`, start.

        Parameters
        ----------
        reset : bool
            Bring every chip to BOOT first (a sheet left streaming by a killed host, chips assigned by
            another session). False: only STOP and drain, then discover.
        strict : bool
            Layout chips that never answer, or announcing chips the layout does not name, are a
            `MismatchError` (else they are reported and the session goes on without them).
        capacity : {"refuse", "warn", "off"}
            What a bus over 100 % of its capacity does (`check_capacity`); over 80 % always warns.
        packed : bool
            Check capacity for SNAPSHOT frames on every port, whatever the gateways say (an override:
            a port whose gateway node says it packs, GATEWAY_INFO, is checked for SNAPSHOTs anyway).

        Returns a summary dict (counts of each step).
        """
        if reset:
            self.quiesce()
        found = self.discover(discover_timeout_s, discover_rounds)
        self.check_discovery(strict=strict)
        self.gateway_nodes.assign()
        self.assign()
        n_cfg = self.configure()
        if self.imu_config is not None:
            self.configure_imu()
        n_cal = self.read_calibration()
        self.capacity_report = self.check_capacity(capacity, packed=packed)
        n_start = self.start()
        return {"discovered": len(found), "assigned": len(self._assigned()), "configured": n_cfg,
                "calibrated": n_cal, "started": n_start, "gateways": len(self.gateway_nodes.by_uid)}

    # -- sessions that survive real life (issue 12) ----------------------------------------------
    def _init_sessions(self) -> None:
        n = self.lattice.n_links
        #: at most this many chip records (an ANNOUNCE flood with new uids is counted, not kept)
        self.max_chips = max(4 * n, 64)
        self.chips_dropped = 0
        self.inbox_dropped = 0
        self.stale_frames = 0  #: frames drained (discarded) by `quiesce`
        self.event_counts: Counter = Counter()  #: HostEvent kind -> count (never capped)
        self.nack_counts: Counter = Counter()  #: (command, reason) -> NACKs
        self._nack_logged: set = set()
        self._round_lock = threading.RLock()
        self._discarding = False
        self._stale_chip_frames = 0
        self.foreign_syncs = 0  #: SYNCs seen while driving (another SYNC source)
        #: before START a driving host listens this long (s, from the end of `quiesce`) for another
        #: SYNC source: a source slower than 1 / sync_listen_s may be caught only once streaming
        self.sync_listen_s = SYNC_LISTEN_S
        self._listen_since: float | None = None
        self.sync_conflict: str | None = None  #: set when a foreign SYNC source stopped a driving host
        self.mismatch: str | None = None  #: a mismatch found only once streaming (e.g. FD SNAPSHOTs on classic)
        self.recoveries = 0  #: incidents recovered (a reboot wave, a reconnect)
        self.recovered_chips = 0
        #: per incident, the newest RECOVERIES_KEPT: first report -> chips started again
        self.recovery_times_s: deque[float] = deque(maxlen=RECOVERIES_KEPT)
        self.not_a_sheet: dict[int, str] = {}  #: bus -> why (after a reconnect nothing sheet-like answered)
        self.capacity_report: list[dict] = []
        #: the gateway nodes heard (host/gateways.py): they say whether a port packs, who drives SYNC
        self.gateway_nodes = GatewayNodes(self, lock=self._lock)
        self._recover_queue: dict[int, str] = {}  # uid -> why
        self._recover_since: float | None = None
        self._recover_event = threading.Event()
        self._recover_thread: threading.Thread | None = None
        self._in_recovery = False
        self._probes: dict[int, dict] = {}  # bus -> reconnect probe state
        #: bus -> the uids it must answer with after a reconnect (empty: any chip). Until one of them
        #: ANNOUNCEs, nothing but GET_INFO is sent there (`_send`): the path may lead elsewhere now
        self.unproven: dict[int, set[int]] = {}
        self.muted_sends = 0  #: frames not sent to a port that had not yet answered as the sheet
        #: uid -> the buses it announced on, for uids heard on more than one (the same chips behind
        #: two ports: one gateway named twice, or two sheets with the same uids); bounded by max_chips
        self.cross_bus_uids: dict[int, set[int]] = {}
        self._resyncs_reported = 0
        self._stray_reported = 0

    def _count_stale(self, events: list) -> None:
        for ev in events:
            k = len(ev) if isinstance(ev, (SampleBatch, ImuBatch)) else 1
            self.stale_frames += k
            if not isinstance(ev, (Sync, DecodeError)):
                self._stale_chip_frames += k

    def quiesce(self, quiet_s: float = 0.1, max_s: float = 3.0, reset: bool = True) -> int:
        """Bring every chip to a known state whatever a previous session left: broadcast STOP, drain
        the stale input (samples, answers, a previous session's backlog) until nothing but SYNC came for
        ``quiet_s`` (at most ``max_s``), then broadcast RESET (every chip to BOOT; calibration is
        kept, docs/protocol.md §4.14) and forget what the host knew. Returns the frames drained."""
        self.open()
        self._streaming.clear()
        before = self.stale_frames
        self._discarding = True
        try:
            for _ in range(2):  # STOP twice: a frame lost to a full buffer does not leave a chip streaming
                self._broadcast(Stop(0))
                self._idle(0.01)
            t_end = self._now() + max_s
            last_n, last_t = self._stale_chip_frames, self._now()
            while self._now() < t_end:
                self._idle(min(0.01, quiet_s / 4))
                if self._stale_chip_frames != last_n:
                    last_n, last_t = self._stale_chip_frames, self._now()
                elif self._now() - last_t >= quiet_s:
                    break
            while True:
                try:
                    self._inbox.get_nowait()
                except queue.Empty:
                    break
        finally:
            self._discarding = False
            self._listen_since = self._now()  # what is heard from here on counts (check_sync_source)
        if reset:
            with self._lock:
                self.chips.clear()
                self._node_uid.clear()
                self.unknown_chips.clear()
            self.gateway_nodes.forget()
            self._broadcast(Reset(0))
        drained = self.stale_frames - before
        if drained:
            log.info("bring-up: drained %d stale frames left by a previous session", drained)
        return drained

    def check_discovery(self, strict: bool = True) -> None:
        """Mismatches between what the host was told and what answered, before anything streams.

        Always an error: CAN FD frames on a bus opened for classic CAN ("add --fd"). With ``strict``
        also: layout chips that never answered and announcing chips the layout does not name (each
        named by uid and link). Otherwise those are reported (events) and the session goes on."""
        for bus, t in enumerate(self.transports):
            n_fd = t.stats.errors.get("FD_ON_CLASSIC", 0)
            if n_fd:
                raise MismatchError(f"{t.name} carries CAN FD frames ({n_fd} seen) but was opened for classic "
                                    f"CAN: add --fd")
        if self.cross_bus_uids:
            # a chip sits behind one gateway: the same uids on two ports are one gateway opened twice
            # (or two sheets whose uids collide), never one lattice
            uid, buses = min(self.cross_bus_uids.items())
            names = " and ".join(self.transports[b].name for b in sorted(buses))
            raise MismatchError(f"{len(self.cross_bus_uids)} chip(s) answer on more than one port, e.g. uid "
                                f"0x{uid:016X} on {names}: the ports reach the same chips (one gateway "
                                f"named twice?); give each gateway of the sheet once")
        if self.layout is None or not self.chips:
            return  # no chip answered at all: the port (or the sheet's power), not the layout: the caller says so
        with self._lock:
            found = set(self.chips)
            missing = sorted(((k, u) for u, k in self.layout.links.items() if u not in found))
            unknown = sorted(found - set(self.layout.links))
        # a port none of whose chips is in the layout: a gateway of another sheet (or a layout
        # for another lattice): said beside whichever mismatch is raised
        hint = ""
        if unknown and len(self.transports) > 1:
            with self._lock:
                per_port = Counter(self.chips[u].bus for u in unknown)
                alien = [self.transports[b].name for b, c in sorted(per_port.items())
                         if c == sum(1 for r in self.chips.values() if r.bus == b)]
            if alien:
                hint = (f"; none of the chips on {', '.join(alien)} is in the layout (a gateway of another "
                        f"sheet, or a layout for another lattice?)")
        for k, u in missing:
            self._report("missing_chip", f"layout chip 0x{u:016X} (link {k}) did not answer", quiet=True,
                         link=k, uid=u)
        if missing:
            names = ", ".join(f"link {k} (uid 0x{u:016X})" for k, u in missing[:5])
            more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
            msg = f"{len(missing)} layout chip(s) never answered: {names}{more}{hint}"
            if strict:
                raise MismatchError(msg + " (check the layout file; --allow-missing streams without them)")
            log.warning("%s", msg)
        if unknown:
            names = ", ".join(f"uid 0x{u:016X} (on {self.transports[self.chips[u].bus].name}, node "
                              f"0x{self.chips[u].node:04X})" for u in unknown[:5])
            more = f" and {len(unknown) - 5} more" if len(unknown) > 5 else ""
            msg = f"{len(unknown)} announcing chip(s) are not in the layout: {names}{more}{hint}"
            if strict:
                raise MismatchError(msg + " (wrong layout file? --allow-missing streams without them)")
            log.warning("%s", msg)

    def check_capacity(self, action: str = "refuse", packed: bool = False) -> list[dict]:
        """The load each bus would carry at ``rate_hz`` (docs/protocol.md §10, `protocol.capacity`),
        in SNAPSHOT frames where a gateway node says it packs (or everywhere with ``packed``).

        Over 100 %: `CapacityError` naming the remedy (``action="refuse"``), else a warning; over
        80 %: a warning. A bus whose bit rate is unknown and that has no wire (a memory link, the
        in-process python-can ``virtual`` bus) is not checked; other CAN buses without ``--bitrate``
        are checked at 1 Mbit/s (CAN FD: 1/8 Mbit/s). Returns one dict per bus."""
        imu_fmt = self.imu_config[0] if self.imu_config is not None else 0  # IMU records: larger (§16)
        if action not in ("refuse", "warn", "off"):
            raise ValueError(f"Invalid capacity action: {action!r} (need 'refuse', 'warn' or 'off')")
        report = []
        if action == "off":
            return report
        per_bus = Counter(r.bus for r in self._assigned())
        packed_any = packed
        for bus, t in enumerate(self.transports):
            cap = t.capabilities
            n = per_bus.get(bus, 0)
            packed = packed_any or self.gateway_nodes.packing(bus)
            if n == 0:
                continue
            if cap.kind == "memory" or (cap.kind == "can" and cap.bitrate is None
                                        and getattr(t, "interface", "") == "virtual"):
                continue
            if cap.kind == "serial":
                load = bus_load(n, self.rate_hz, kind="serial", bitrate=cap.bitrate or 3_000_000, packed=packed,
                                fmt=imu_fmt)
            else:
                load = bus_load(n, self.rate_hz, kind="can", bitrate=cap.bitrate or 1_000_000, fd=cap.fd,
                                data_bitrate=cap.data_bitrate or 8_000_000, packed=packed, fmt=imu_fmt)
            row = {"bus": t.name, "chips": n, "load_pct": round(100 * load, 1)}
            report.append(row)
            what = (f"{t.name}: {n} chips at {self.rate_hz:g} Hz need {100 * load:.0f} % of the bus "
                    f"({'packed SNAPSHOT' if packed else 'per-chip SAMPLE'} frames)")
            if load > 1.0:
                remedy = capacity_remedy(cap.kind, load, self.rate_hz, packed=packed, fd=bool(cap.fd),
                                         bitrate=cap.bitrate)
                if action == "refuse":
                    raise CapacityError(f"over capacity: {what}; {remedy}")
                log.warning("over capacity: %s; %s", what, remedy)
            elif load > 0.8:
                log.warning("near capacity: %s", what)
        return report

    def check_sync_source(self) -> None:
        """Before START: in drive mode, another SYNC source already on the bus is a conflict —
        ``sync="auto"`` follows it, ``sync="drive"`` raises `SyncConflictError`.

        The host listens for at least `sync_listen_s` after the bus was drained (`quiesce`) before
        it decides: a bring-up is shorter than one period of a slow source (3x3 chips: 20-40 ms),
        so without the wait a gateway's SYNC was caught only once streaming (exit 1, not 2)."""
        if self.sync_mode != "drive":
            return
        sources = self.gateway_nodes.sync_sources()  # a gateway that said so (GATEWAY_INFO, §13.3)
        if sources:
            what = "; ".join(r.describe() for r in sources)
            if self.sync_policy == "auto":
                self._switch_to_follow(what)
                return
            raise SyncConflictError(f"{what}: it passes no SYNC from this host to its chips; use --sync follow "
                                    f"(or --sync auto)")
        now = self._now()
        since = self._listen_since if self._listen_since is not None else now
        while not self.syncs_seen and self._now() - since < self.sync_listen_s:
            self._idle(min(0.01, self.sync_listen_s))
        if not self.syncs_seen:
            return
        if self.sync_policy == "auto":
            self._switch_to_follow(f"{self.syncs_seen} SYNC frames from another source")
            return
        raise SyncConflictError(f"another device drives SYNC on this sheet ({self.syncs_seen} SYNC frames seen "
                                f"that this host did not send): use --sync follow (or --sync auto)")

    def _switch_to_follow(self, why: str) -> None:
        self.sync_mode = "follow"
        self.feed.set_trust("follow")
        self.feed.restart()
        self._report("sync", f"{why}: following that SYNC source (--sync auto)")

    def _foreign_sync(self, bus: int, msg: Sync) -> None:
        """A SYNC this host did not send while it drives SYNC (it never hears its own)."""
        self.foreign_syncs += 1
        if not self._streaming.is_set():
            return  # before START: `check_sync_source` decides
        if self.sync_policy == "auto":
            self._switch_to_follow(f"SYNC from another source on {self.transports[bus].name}")
            self.feed.open_counter(msg.counter)
        elif self.sync_conflict is None:
            self.sync_conflict = (f"another device drives SYNC on {self.transports[bus].name} while this host "
                                  f"does: stopped (use --sync follow or --sync auto)")
            self.sync_mode = "none"  # `_sync_step` sends no more SYNC
            self._report("sync", self.sync_conflict)

    # recovery --------------------------------------------------------------------------------
    def _queue_recovery(self, uid: int, why: str) -> None:
        with self._lock:
            if not self._recover_queue:
                self._recover_since = self._now()
            self._recover_queue[uid] = why
        self._recover_event.set()

    def _port_lost(self, bus: int) -> None:
        """A port went away: from now on it must prove it leads to this sheet again (`_prove`) before
        anything but GET_INFO is sent there. Marked at the loss, not at the reconnect: the transport
        reopens the path in its receive thread, and a SYNC sent between the reopen and the host
        hearing of it would already reach whatever the path leads to then."""
        with self._lock:
            t = self.transports[bus]
            if t.stats.disconnects == self._disconnects[bus]:
                return
            self._disconnects[bus] = t.stats.disconnects
            self.unproven[bus] = {u for u, r in self.chips.items() if r.bus == bus}

    def _on_reconnect(self, bus: int, t: Transport) -> None:
        """The port came back: drive nothing there until it proves to lead to this sheet (`_prove`:
        one of the chips known on it ANNOUNCEs); ask every chip who it is (a rebooted chip answers
        from a provisional node id and is recovered) and report a port where none answers."""
        with self._lock:
            self.unproven[bus] = {u for u, r in self.chips.items() if r.bus == bus}
        self._probes[bus] = {"t": self._now(), "frames": t.stats.frames_in, "bytes": t.stats.bytes_in,
                             "errors": t.stats.error_count, "asks": 0, "next": self._now()}
        self._recover_event.set()

    def _prove(self, bus: int, uid: int) -> bool:
        """A chip ANNOUNCEd on a port that came back: the port leads to this sheet again if the chip
        is one of those known on it (any chip when none was known yet). Returns whether it is."""
        expected = self.unproven.get(bus)
        if expected is None:
            return True
        t = self.transports[bus]
        if expected and uid not in expected:
            if bus not in self.not_a_sheet:
                why = (f"{t.name} came back but chip 0x{uid:016X} answers there, which was never on it "
                       f"(another sheet on this path?): nothing is driven there")
                self.not_a_sheet[bus] = why
                self._report("not_a_sheet", why)
            return False
        self.unproven.pop(bus, None)
        self._probes.pop(bus, None)
        self.not_a_sheet.pop(bus, None)
        self._report("reconnect", f"{t.name} answers as the sheet (chip 0x{uid:016X}): driven again", quiet=True)
        return True

    def _check_probes(self, now: float) -> None:
        for bus, pr in list(self._probes.items()):
            t = self.transports[bus]
            if bus not in self.unproven:  # proven by an ANNOUNCE (`_prove`)
                del self._probes[bus]
                continue
            if now >= pr["next"] and pr["asks"] < 6:
                pr["asks"] += 1
                pr["next"] = now + 0.3
                try:
                    self._send(bus, GetInfo(0))
                except TransportError:
                    pass
            if now - pr["t"] > 2.0 and bus not in self.not_a_sheet:
                why = (f"{t.name} came back but answers nothing like a sheet: {t.stats.bytes_in - pr['bytes']} "
                       f"bytes, {t.stats.error_count - pr['errors']} undecodable, no chip of it announced in "
                       f"{now - pr['t']:.1f} s (a stale symlink to another device?): nothing is driven there")
                self.not_a_sheet[bus] = why
                self._report("not_a_sheet", why)
            if now - pr["t"] > 30.0:
                del self._probes[bus]  # stop asking; the port stays muted until a chip of it announces

    def _recovery_loop(self) -> None:
        while not self._stop.is_set():
            self._recover_event.wait(0.1)
            self._recover_event.clear()
            try:
                self._maybe_recover()
            except Exception:  # noqa: BLE001 - never let recovery die silently
                log.exception("recovery")

    def _maybe_recover(self) -> None:
        """Recovery work, if any is due (the recovery thread; `service` in manual mode)."""
        if self._in_recovery or not self._streaming.is_set():
            return
        now = self._now()
        if self._probes:
            self._check_probes(now)
        self._report_stream_incidents()
        if self._recover_queue and now - (self._recover_since or now) >= 0.05:  # gather a reboot wave
            self.recover()

    def _report_stream_incidents(self) -> None:
        if self.mismatch is None:
            for t in self.transports:
                n_fd = t.stats.errors.get("FD_ON_CLASSIC", 0)
                if n_fd:
                    self.mismatch = (f"{t.name} carries CAN FD frames ({n_fd} seen) but was opened for classic "
                                     f"CAN: add --fd")
                    self._report("mismatch", self.mismatch)
                    break
        st = self.aggregator.stats
        if st.resyncs != self._resyncs_reported:
            self._resyncs_reported = st.resyncs
            ev = self.aggregator.resync_events[-1] if self.aggregator.resync_events else None
            self._report("resync", f"the SYNC counter restarted or jumped ({ev[0]} -> {ev[1]}): resynchronised "
                                   f"(resync #{st.resyncs})" if ev else f"resync #{st.resyncs}")
        if st.stray and st.stray >= 2 * self._stray_reported + 1:  # at 1, 3, 7, 15, ...: log lines grow as log2
            self._stray_reported = st.stray
            self._report("stray", f"{st.stray} frame(s) for counters this host did not expect dropped "
                                  f"(each costs at most its own sample)")

    def recover(self) -> int:
        """Bring the queued chips back into the stream: ASSIGN, CONFIG, CAL_READ, START (only those;
        the others keep streaming). One report per incident. Returns the chips streaming again."""
        with self._lock:
            queued, self._recover_queue = self._recover_queue, {}
            since = self._recover_since if self._recover_since is not None else self._now()
            self._recover_since = None
        uids = {u for u in queued if u in self.chips and self.chips[u].link is not None}
        if not uids:
            return 0
        self._in_recovery = True
        try:
            links = [self.chips[u].link for u in uids]
            whys = Counter(queued[u] for u in uids)
            log.warning("recovering %d chip(s) (%s) on links %s", len(uids),
                        ", ".join(f"{k}: {v}" for k, v in whys.items()), link_ranges(links))
            self.assign(uids=uids)
            self.configure(uids)
            self.read_calibration(uids)
            self.start(uids)
        finally:
            self._in_recovery = False
        ok = [u for u in uids if self.chips[u].started]
        dt = self._now() - since
        self.recoveries += 1
        self.recovered_chips += len(ok)
        self.recovery_times_s.append(dt)
        left = sorted(self.chips[u].link for u in uids if not self.chips[u].started)
        self._report("recovery", f"{len(ok)} of {len(uids)} chip(s) streaming again after {dt:.2f} s"
                     + (f"; still out: links {link_ranges(left)}" if left else ""))
        return len(ok)

    def summary(self) -> dict:
        """The end-of-run account: completeness, missing links (index and uid), errors by kind,
        reconnects, recoveries, stray frames and resyncs."""
        agg = self.aggregator.stats
        n = self.lattice.n_links
        uid_of = {rec.link: rec.uid for rec in self.chips.values() if rec.link is not None}
        if self.layout is not None:
            uid_of.update({k: u for u, k in self.layout.links.items()})
        emitted = agg.emitted
        valid = agg.valid_links
        frac = valid / (emitted * n) if emitted else 0.0
        assigned = {r.link for r in self._assigned()}
        never = sorted(set(range(n)) - assigned)
        missing = np.flatnonzero(agg.link_missing > 0.5 * max(1, emitted)).tolist() if emitted else []
        missing = sorted(set(missing) | set(self.silent_links))
        errors: Counter = Counter()
        for t in self.transports:
            errors.update(t.stats.errors)
        for key, c in self.nack_counts.items():
            errors[f"NACK {key[0]} {key[1]}"] += c
        for kind in ("no_ack", "not_a_sheet"):
            if self.event_counts.get(kind):
                errors[kind] += self.event_counts[kind]
        return {"snapshots": emitted, "complete_snapshots": agg.complete,
                # completeness by snapshot and by valid link, over the same emitted snapshots
                "complete_snapshots_pct": round(100 * agg.complete / emitted, 2) if emitted else 0.0,
                "valid_links_pct": round(100 * frac, 2),
                "links": n, "assigned": len(assigned),
                "unassigned_links": [{"link": k, "uid": f"0x{uid_of[k]:016X}" if k in uid_of else None}
                                     for k in never],
                "missing_links": [{"link": k, "uid": f"0x{uid_of[k]:016X}" if k in uid_of else None}
                                  for k in missing],
                "errors": dict(errors),
                "reconnects": sum(t.stats.reconnects for t in self.transports),
                "recoveries": self.recoveries, "recovered_chips": self.recovered_chips,
                "stray_frames": agg.stray, "resyncs": agg.resyncs, "late": agg.late,
                "foreign_syncs": self.foreign_syncs, "sync_mode": self.sync_mode,
                "sync_conflict": self.sync_conflict, "not_a_sheet": list(self.not_a_sheet.values()),
                # ports that came back but never answered as the sheet, and what was not sent there
                "unproven_ports": [self.transports[b].name for b in sorted(self.unproven)],
                "muted_sends": self.muted_sends,
                "mismatch": self.mismatch, "gateways": self.gateway_nodes.summary(),
                "chips_dropped": self.chips_dropped, "stale_frames_drained": self.stale_frames,
                "events_cut": self.events_cut, "rx_errors": self.rx_errors_total,
                "incidents": [{"t": e.t, "kind": e.kind, "detail": e.detail} for e in list(self.events)
                              if e.kind in ("recovery", "reconnect", "resync", "not_a_sheet", "sync")][-100:]}

    # -- SYNC and watchdog --------------------------------------------------------------------
    def _sync_loop(self) -> None:
        """The SYNC thread: `_sync_step` on the fixed schedule, measuring how late it wakes."""
        wake = self._now()
        while not self._stop.is_set():
            now = self._now()
            lag = max(0.0, now - wake)
            self.loop_lag_s += 0.05 * (lag - self.loop_lag_s)
            self.max_loop_lag_s = max(self.max_loop_lag_s, lag)
            with self._step_lock:
                self._sync_step(now)
            if not self._streaming.is_set():
                wake = now + 0.01
            else:
                nxt = self.sync_schedule.next_t if (self.sync_mode == "drive" and self.sync_schedule) else now + 0.005
                wake = min(nxt, self._next_wd, now + 0.01)
            wait = wake - self._now()
            if wait > 0:
                self._stop.wait(wait)
            else:
                wake = self._now()

    def _sync_step(self, now: float) -> None:
        """SYNC if a slot is due (never a burst: missed slots are counted, not caught up), emit
        what is complete or past its deadline, and run the watchdog."""
        step = now - self._last_service if self._last_service is not None else 0.0
        self._last_service = now
        # the watchdog's clock: host time with the host's own stalls cut to two periods
        self._service_s += min(max(step, 0.0), max(2.0 / self.rate_hz, 0.02))
        if not self._streaming.is_set():
            if self.sync_schedule is not None:
                self._syncs_missed_before += self.sync_schedule.missed
                self.sync_schedule = None
            return
        if self.sync_mode == "drive":
            sched = self.sync_schedule
            first = sched is None
            if first:
                sched = self.sync_schedule = SyncSchedule(self.rate_hz, now)
            if sched.due(now):
                c = self.counter
                self.feed.open_counter(c, now, restart=first)
                self._broadcast(Sync(counter=c))
                self.syncs_sent += 1
                self.counter = (c + 1) & 0xFFFF
        self.feed.poll(now)
        if now >= self._next_wd:
            self._watchdog(now)
            self._next_wd = now + min(0.05, self.watchdog_s / 4)

    def service(self, now: float | None = None) -> None:
        """Manual mode: read whatever every transport has, then `_sync_step`. The threads do the
        same when the host runs on the real clock."""
        for bus, t in enumerate(self.transports):
            if t.closed:
                continue
            for _ in range(1000):  # everything that is there, bounded
                if not self._rx_once(bus, t, 0.0):
                    break
        with self._step_lock:
            self._sync_step(self._now() if now is None else now)
        self._maybe_recover()

    def _now(self) -> float:
        return self.clock()

    def _idle(self, dt: float) -> None:
        """Let ``dt`` seconds pass: sleep (threads do the work), or in manual mode run the world
        and the host's own work in steps of at most ``tick_s``."""
        if self._driver is None:
            if dt > 0:
                time.sleep(dt)
            return
        end = self._now() + dt
        while True:
            left = end - self._now()
            if left <= 1e-12:
                return
            self._driver(min(left, self.tick_s))
            self.service()

    def _inbox_get(self, timeout_s: float):
        """The next command answer, waiting at most ``timeout_s``; raises queue.Empty."""
        if self._driver is None:
            return self._inbox.get(timeout=timeout_s)
        end = self._now() + timeout_s
        while True:
            try:
                return self._inbox.get_nowait()
            except queue.Empty:
                if self._now() >= end:
                    raise
                self._idle(min(self.tick_s, end - self._now()))

    def _watchdog(self, now: float) -> None:
        """Mark silent the links whose chip stopped answering, never for the host's own lag:

        * a link missing from ``n`` consecutive snapshots in which most other expected links
          arrived (its neighbours' frames for the same counters came, its did not), ``n`` =
          ``watchdog_s`` worth of SYNCs (at least 3); or
        * no frame from it for ``watchdog_s`` of the host's *stall-free* time (`_sync_step`):
          the whole sheet or bus fell silent while the host kept running.
        """
        agg = self.aggregator
        assigned = ~agg.unassigned
        seen = np.maximum(agg.stats.link_last_seen, self._status_seen)
        fresh = seen > self._seen_real
        self._seen_real = np.where(fresh, seen, self._seen_real)
        self._seen_service[fresh] = self._service_s
        quiet = self._service_s - self._seen_service
        n_runs = max(3, int(np.ceil(self.watchdog_s * self.rate_hz)))
        silent = assigned & ((agg.miss_run >= n_runs) | (quiet > self.watchdog_s))
        newly = silent & ~self._silent_reported
        back = self._silent_reported & ~silent
        for link in np.flatnonzero(newly).tolist():
            self.feed.mark_silent(link, True)
            self._report("silent", f"link {link} (node {node_for_link(link)}) silent "
                                   f"({int(agg.miss_run[link])} snapshots without it, "
                                   f"{quiet[link]:.2f} s host time): marked missing",
                         link=link, node=node_for_link(link), quiet=True)
        for link in np.flatnonzero(back).tolist():
            self.feed.mark_silent(link, False)
            self._report("recovered", f"link {link} (node {node_for_link(link)}) speaks again",
                         link=link, node=node_for_link(link), quiet=True)
        if newly.any():  # one log line per incident, not one per link
            log.warning("silent: links %s marked missing (no frame while their neighbours' came, or "
                        "none for %.2f s)", link_ranges(np.flatnonzero(newly)), self.watchdog_s)
        if back.any():
            log.info("links %s speak again", link_ranges(np.flatnonzero(back)))
        self._silent_reported = silent

    # -- output -------------------------------------------------------------------------------
    def get(self, timeout_s: float | None = None) -> LatticeSnapshot | None:
        """The next snapshot (oldest queued), or None after ``timeout_s`` (`feed`)."""
        return self.feed.get(timeout_s)

    def latest(self, timeout_s: float | None = None) -> LatticeSnapshot | None:
        """Newest wins: the newest queued snapshot, the older ones skipped (counted in the
        aggregator's ``stats.dropped``), or None after ``timeout_s`` (`feed`)."""
        return self.feed.latest(timeout_s)

    def drain(self) -> list[LatticeSnapshot]:
        """Every queued snapshot, oldest first, without waiting (`feed`)."""
        return self.feed.drain()

    def snapshots(self, duration_s: float | None = None, count: int | None = None,
                  timeout_s: float = 1.0) -> Iterator[LatticeSnapshot]:
        """Iterate over snapshots until ``duration_s`` passed, ``count`` were given, or none came
        for ``timeout_s``."""
        if self._driver is not None:
            yield from self._snapshots_manual(duration_s, count, timeout_s)
            return
        end = None if duration_s is None else time.monotonic() + duration_s
        n = 0
        while count is None or n < count:
            wait = timeout_s if end is None else min(timeout_s, end - time.monotonic())
            if wait <= 0:
                return
            snap = self.get(wait)
            if snap is None:
                if end is not None and time.monotonic() < end:
                    continue
                return
            n += 1
            yield snap

    def _snapshots_manual(self, duration_s, count, timeout_s) -> Iterator[LatticeSnapshot]:
        end = None if duration_s is None else self._now() + duration_s
        n, quiet_since = 0, self._now()
        while count is None or n < count:
            for snap in self.feed.drain():
                n += 1
                quiet_since = self._now()
                yield snap
                if count is not None and n >= count:
                    return
            now = self._now()
            if (end is not None and now >= end) or now - quiet_since >= timeout_s:
                return
            self._idle(self.tick_s)

    @property
    def silent_links(self) -> list[int]:
        return np.flatnonzero(self._silent_reported).tolist()

    @property
    def stats(self) -> dict:
        """Everything counted, as plain numbers: per bus, per chip (link), the aggregator's totals."""
        agg = self.aggregator.stats
        buses = []
        for i, t in enumerate(self.transports):
            d = {"name": t.name, "kind": t.capabilities.kind, **t.stats.as_dict(),
                 "samples": int(agg.bus_frames[i]), "late": int(agg.bus_late[i]),
                 "duplicates": int(agg.bus_duplicates[i]), "unknown": int(agg.bus_unknown[i])}
            buses.append(d)
        chips = {}
        for rec in self._assigned():
            k = rec.link
            chips[k] = {"uid": f"0x{rec.uid:016X}", "node": rec.node, "bus": rec.bus,
                        "frames": int(agg.link_frames[k]), "late": int(agg.link_late[k]),
                        "duplicates": int(agg.link_duplicates[k]), "missing": int(agg.link_missing[k]),
                        "latency_s": float(agg.link_latency_s[k]), "silent": bool(self._silent_reported[k]),
                        "calibrated": rec.calibrated,
                        "missed_syncs": rec.last_status.missed_syncs if rec.last_status else None,
                        "rx_errors": rec.last_status.rx_errors if rec.last_status else None}
        sched = self.sync_schedule
        live = {"loop_lag_s": round(self.loop_lag_s, 6), "max_loop_lag_s": round(self.max_loop_lag_s, 6),
                "syncs_missed": self._syncs_missed_before + (sched.missed if sched else 0),
                "sync_late_s": round(sched.max_late_s, 6) if sched else 0.0,
                "deadline_s": round(self.aggregator.deadline_s, 6), **self.aggregator.completeness()}
        return {"aggregator": agg.summary(), "live": live, "buses": buses, "chips": chips,
                "syncs_sent": self.syncs_sent,
                "syncs_seen": self.syncs_seen, "silent_links": self.silent_links,
                "unknown_nodes": dict(agg.unknown_nodes), "unknown_chips": [f"0x{u:016X}" for u in self.unknown_chips]}
