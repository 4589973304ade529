"""The `Host`: discover, assign, configure, calibrate, stream (docs/host.md).

`Host` is the Python API a program (the demo, the CLI) uses to run a sheet::

    from host.session.core import Host, Layout
    from host.transport.ports import open_transport
    with Host([open_transport("serial", "/dev/pts/5")], "14x14", layout=Layout.load("sheet.csv"),
              rate_hz=100) as host:
        host.discover(); host.assign(); host.configure(); host.read_calibration(); host.start()
        for snap in host.snapshots(duration_s=10):
            print(snap.counter, snap.completeness)
        host.stop()

or ``host.bring_up()`` for discover + assign + configure + read_calibration + start.

`Host` is a façade: it holds the configuration, the threads and the receive path, and hands the
work to its parts, each in its own module with its own state:

* ``host.session.registry`` (`host.session.registry.ChipRegistry`): the chips heard, the layout, node ids;
* ``host.session.commands`` (`host.session.commands.CommandRounds`): sending, command rounds with retries, NACKs;
* ``host.session.bringup`` (`host.session.bringup.BringUp`): quiesce, discover, assign, configure, calibrate,
  capacity; the calibration applied to the feed;
* ``host.sync_driver`` (`host.session.syncdriver.SyncDriver`): drive or follow SYNC, the SYNC step;
* ``host.session.watchdog`` (`host.session.watchdog.Watchdog`): links fallen silent;
* ``host.session.recovery`` (`host.session.recovery.Recovery`): rebooted chips, ports that come back, incidents;
* ``host.event_log`` (`host.session.report.EventLog`): events, counts, receive errors (and `summary`,
  `stats`: `host.session.report`);
* ``host.snapshots.feed`` (`host.snapshots.feed.SnapshotFeed`): the aggregator for threads, what consumers read;
* ``host.receiver`` (`host.session.receive.Receiver`): the receive path, each event to the part that owns it.

What they share they reach through each other's public names. The attributes a `Host` has always
had (``host.chips``, ``host.syncs_sent``, ``host.events``, ...) read and write the part's.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

from protocol.constants import Range
from protocol.framing import StreamDecoder
from protocol.lattice import Lattice
from protocol.layout import LayoutError
from protocol.messages import Stop

from host.snapshots.aggregator import INPUT_HOLD_S, Aggregator
from host.snapshots.snapshot import LatticeSnapshot
from host.session.bringup import BringUp, capacity_remedy
from host.session.commands import ACK_TIMEOUT_S, RETRIES, CommandRounds
from host.session.errors import CapacityError, MismatchError, SessionError, SyncConflictError
from host.snapshots.feed import SnapshotFeed
from host.session.gateways import GatewayNodes
from host.session.recovery import RECOVERIES_KEPT, Recovery
from host.session.registry import ChipRecord, ChipRegistry, Layout, node_for_link
from host.session.report import EVENTS_KEPT, RX_ERRORS_KEPT, EventLog, HostEvent, link_ranges, run_stats, run_summary
from host.session.syncdriver import SYNC_LISTEN_S, SyncDriver, SyncSchedule
from host.transport.ports import Transport, TransportError
from host.session.receive import Receiver
from host.session.watchdog import Watchdog

__all__ = ["Layout", "LayoutError", "ChipRecord", "HostEvent", "Host", "SyncSchedule", "node_for_link",
           "SessionError", "MismatchError", "CapacityError", "SyncConflictError", "link_ranges", "capacity_remedy",
           "EVENTS_KEPT", "RX_ERRORS_KEPT", "RECOVERIES_KEPT", "SYNC_LISTEN_S"]

log = logging.getLogger("capsheet.host")

#: the most counters a host keeps open at once (`Host`: as many as its deadline and input hold may
#: wait for, up to this: 16 MB of buffers for a 64x64 sheet)
MAX_OPEN_CAP = 128


class _InPart:
    """A `Host` attribute that lives in one of its parts: ``host.<name>`` reads and sets
    ``host.<part>.<name>``."""

    def __init__(self, part: str) -> None:
        self.part = part
        self.name = ""

    def __set_name__(self, owner, name: str) -> None:
        self.name = name

    def __get__(self, host, owner=None):
        if host is None:
            return self
        return getattr(getattr(host, self.part), self.name)

    def __set__(self, host, value) -> None:
        setattr(getattr(host, self.part), self.name, value)


class Host:
    """Run a sheet over one or more transports (several CAN buses merge into one lattice).

    Parameters
    ----------
    transports : Transport or sequence of Transport
        Open transports (`host.transport.ports.open_transport`). Bus index = position in this list.
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
        How long a counter waits for missing links; default: adapted to the measured latency, starting
        at ``max(2 / rate_hz, 0.05)`` (`host.snapshots.deadline`).
    watchdog_s : float, optional
        A link silent this long is reported and marked missing; default ``max(0.5, 20 / rate_hz,
        deadline_s)`` (a fixed deadline the host waits for a link is not cut short by its watchdog).
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

    # -- the attributes a Host has always had, kept by its parts ----------------------------
    chips = _InPart("registry")  #: uid -> `ChipRecord`
    layout = _InPart("registry")
    unknown_chips = _InPart("registry")
    max_chips = _InPart("registry")
    chips_dropped = _InPart("registry")
    cross_bus_uids = _InPart("registry")
    nack_counts = _InPart("commands")
    inbox_dropped = _InPart("commands")
    muted_sends = _InPart("commands")
    stale_frames = _InPart("bringup")
    calibration_reads = _InPart("bringup")
    capacity_report = _InPart("bringup")
    sync_policy = _InPart("sync_driver")
    sync_mode = _InPart("sync_driver")
    counter = _InPart("sync_driver")
    syncs_sent = _InPart("sync_driver")
    syncs_seen = _InPart("sync_driver")
    foreign_syncs = _InPart("sync_driver")
    sync_listen_s = _InPart("sync_driver")
    sync_conflict = _InPart("sync_driver")
    sync_schedule = _InPart("sync_driver")
    loop_lag_s = _InPart("sync_driver")
    max_loop_lag_s = _InPart("sync_driver")
    watchdog_s = _InPart("watchdog")
    silent_links = _InPart("watchdog")
    recoveries = _InPart("recovery")
    recovered_chips = _InPart("recovery")
    recovery_times_s = _InPart("recovery")
    not_a_sheet = _InPart("recovery")
    unproven = _InPart("recovery")
    mismatch = _InPart("recovery")
    events = _InPart("event_log")
    events_cut = _InPart("event_log")
    event_counts = _InPart("event_log")
    rx_errors_total = _InPart("event_log")
    frames_before_start = _InPart("receiver")  #: a following host's sample frames before it streamed

    def __init__(self, transports: Transport | Sequence[Transport], lattice: Lattice | str, *,
                 layout: Layout | str | Path | None = None, rate_hz: float = 100.0, sync: str = "drive",
                 deadline_s: float | None = None, watchdog_s: float | None = None, range_code: int = Range.G2,
                 filter_code: int = 0, heartbeat_ms: int = 1000, timeout_s: float = ACK_TIMEOUT_S, retries: int = RETRIES,
                 on_snapshot: Callable[[LatticeSnapshot], None] | None = None, queue_size: int = 64,
                 start_counter: int = 0, clock: Callable[[], float] | None = None,
                 driver: Callable[[float], None] | None = None, tick_s: float = 0.001) -> None:
        self.clock: Callable[[], float] = clock if clock is not None else time.monotonic
        self._driver = driver
        if not (np.isfinite(tick_s) and tick_s > 0):
            raise ValueError(f"Invalid tick_s: {tick_s!r} (need a finite value > 0 s)")
        self.tick_s = float(tick_s)
        self.transports: list[Transport] = [transports] if isinstance(transports, Transport) else list(transports)
        for t in self.transports:  # serial heartbeats and SNAPSHOTs in runs, taken at once
            if isinstance(getattr(t, "decoder", None), StreamDecoder):  # (`Receiver.on_heartbeats`, the aggregator)
                t.decoder.batch_status = True
                t.decoder.batch_snapshots = True
        if not self.transports:
            raise ValueError("Host needs at least one transport")
        self.lattice = Lattice.parse(lattice) if isinstance(lattice, str) else lattice
        if isinstance(layout, (str, Path)):
            layout = Layout.load(layout)
        #: who drives SYNC, the SYNC step and its thread (`host.session.syncdriver`)
        self.sync_driver = SyncDriver(self, sync, start_counter)
        if not (isinstance(rate_hz, (int, float)) and np.isfinite(rate_hz) and 0 < rate_hz <= 4000):
            raise ValueError(f"Invalid rate_hz: {rate_hz!r} (need 0 < rate <= 4000)")
        self.rate_hz = float(rate_hz)
        self._lock = threading.RLock()  # the chip records' (shared by the registry and the gateway nodes)
        #: the chips heard and the layout (`host.session.registry`)
        self.registry = ChipRegistry(self.lattice, layout, self._lock)
        self.range_code = Range(range_code)
        #: CONFIG_IMU for 6/9-axis chips (docs/protocol.md §16.2), sent by `bring_up` after CONFIG
        #: when set: a `protocol.messages.ConfigImu`'s fields (format, gyro_range, mag_range, flags)
        self.imu_config: tuple[int, int, int, int] | None = None
        self.filter_code = filter_code
        self.heartbeat_ms = heartbeat_ms
        if not (isinstance(timeout_s, (int, float)) and np.isfinite(timeout_s) and timeout_s > 0):
            raise ValueError(f"Invalid timeout_s: {timeout_s!r} (need a finite value > 0 s)")
        self.timeout_s = float(timeout_s)
        self.retries = retries
        n = self.lattice.n_links
        # completion deadline: a fixed one if given, else adapted to the measured SYNC -> sample
        # latency within [1.5 periods, max(0.25 s, 8 periods)] (host/snapshots/deadline.py)
        period = 1.0 / self.rate_hz
        if deadline_s is not None:
            dl = dict(deadline_s=deadline_s)
        else:
            dl = dict(deadline_s=max(2.0 * period, 0.05), min_deadline_s=max(1.5 * period, 0.004),
                      max_deadline_s=max(0.25, 8.0 * period))
        #: the sans-I/O aggregator: its configuration and statistics (read them freely; it is
        #: driven only through `feed`)
        # hold_for_input: a counter past its deadline waits until its bus was read past it, so a
        # host that was not scheduled for a while reads the frames waiting for it before it gives
        # their counters up (host.snapshots.aggregator, "Input watermark")
        # room for every counter that may still be waited for: its deadline and the input hold after
        # it (the default 32 was 0.22 s at 145 Hz, under the 0.5 s a counter may wait: on a busy
        # machine the counters whose frames were still unread were emitted incomplete to make room)
        longest = dl.get("max_deadline_s", dl["deadline_s"]) + INPUT_HOLD_S
        max_open = max(32, min(MAX_OPEN_CAP, int(np.ceil(longest * self.rate_hz)) + 2))
        self.aggregator = Aggregator(n, node_to_link=None, n_buses=len(self.transports),
                                     trust="sent" if self.sync_driver.sync_mode == "drive" else "follow",
                                     hold_for_input=True, max_open=max_open, **dl)
        #: the one place snapshots come from (`host.snapshots.feed.SnapshotFeed`): what `get`, `latest`,
        #: `snapshots`, `drain` and every listener (``on_snapshot``, a recorder, `health`) see,
        #: corrected by `set_calibration` once
        self.feed = SnapshotFeed(self.aggregator, clock=self.clock, queue_size=queue_size)
        self.feed.add_listener(self._check_health)
        if on_snapshot is not None:
            self.feed.add_listener(on_snapshot)
        #: what the host reports: events, counts, receive errors (`host.session.report`)
        self.event_log = EventLog(self.clock)
        #: sending and command rounds (`host.session.commands`)
        self.commands = CommandRounds(self)
        #: the steps to streaming, the calibration applied (`host.session.bringup`)
        self.bringup = BringUp(self)
        #: links fallen silent (`host.session.watchdog`)
        # a link is marked silent after watchdog_s without a frame: by default not before a fixed
        # completion deadline has passed either (a host told to wait 2 s for a link's frame that
        # gave the link up after 0.5 s would cut every snapshot a slow sheet sends)
        if watchdog_s is None:
            watchdog_s = max(0.5, 20.0 / self.rate_hz, deadline_s or 0.0)
        elif not (isinstance(watchdog_s, (int, float)) and np.isfinite(watchdog_s) and watchdog_s > 0):
            raise ValueError(f"Invalid watchdog_s: {watchdog_s!r} (need a finite value > 0 s)")
        self.watchdog = Watchdog(self, float(watchdog_s))
        #: rebooted chips, ports that come back, stream incidents (`host.session.recovery`)
        self.recovery = Recovery(self)
        #: the gateway nodes heard (host/session/gateways.py): they say whether a port packs, who drives SYNC
        self.gateway_nodes = GatewayNodes(self, lock=self._lock)
        #: the receive path: every event from a transport to the part that owns it (`host.session.receive`)
        self.receiver = Receiver(self)
        #: a `host.snapshots.health.HealthChecker` fed every emitted snapshot (corrected); its findings are host events
        self.health = None
        #: set while the host streams (between `start` and `stop`)
        self.streaming = threading.Event()
        #: from the bring-up (`quiesce`) until `start` has set `streaming`; not while `stop` lets
        #: the counters in flight complete
        self.awaiting_stream = True
        self._stop = threading.Event()
        self._rx_threads: list[threading.Thread] = []
        self._sync_thread: threading.Thread | None = None
        self._recover_thread: threading.Thread | None = None
        self._emit_thread: threading.Thread | None = None

    # -- time ------------------------------------------------------------------------------
    @property
    def manual(self) -> bool:
        """Manual mode (a ``driver`` was given): no threads; `idle` runs the world and `service`."""
        return self._driver is not None

    def now(self) -> float:
        """The host's time (its ``clock``)."""
        return self.clock()

    def idle(self, dt: float) -> None:
        """Let ``dt`` seconds pass: sleep (threads do the work), or in manual mode run the world
        and the host's own work in steps of at most ``tick_s``."""
        if self._driver is None:
            if dt > 0:
                time.sleep(dt)
            return
        end = self.now() + dt
        while True:
            left = end - self.now()
            if left <= 1e-12:
                return
            self._driver(min(left, self.tick_s))
            self.service()

    def service(self, now: float | None = None) -> None:
        """Manual mode: read whatever every transport has, then the SYNC step and the recovery work.
        The threads do the same when the host runs on the real clock."""
        for bus, t in enumerate(self.transports):
            if t.closed:
                continue
            for _ in range(1000):  # everything that is there, bounded
                if not self.receiver.receive(bus, t, 0.0):
                    break
        with self.sync_driver.step_lock:
            self.sync_driver.step(self.now() if now is None else now)
        self.recovery.maybe_recover()

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
        if self.streaming.is_set():
            try:
                self.stop()
            except TransportError as exc:
                log.warning("stop on close: %s", exc)
        self._stop.set()
        self.recovery.wake.set()
        for th in self._rx_threads + [t for t in (self._sync_thread, self._emit_thread, self._recover_thread) if t]:
            th.join(timeout=2.0)
        self._rx_threads = []
        self._sync_thread = None
        self._emit_thread = None
        self._recover_thread = None
        for t in self.transports:
            t.close()

    def __enter__(self) -> "Host":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self, uids=None) -> int:
        """START every assigned chip, then drive SYNC (or follow the gateway's). Returns ACK count.

        With ``uids`` (recovery) only those chips are started; the stream goes on undisturbed."""
        if uids is None:
            self.sync_driver.check_source()
        n_ok = self.bringup.start_chips(uids)
        if uids is not None:
            return n_ok
        now = self.now()
        self.feed.streaming_from(now)
        self.watchdog.restart(now, self.sync_driver.service_s)
        self.sync_driver.end_schedule()
        self.streaming.set()
        self.awaiting_stream = False
        # following a gateway's SYNC, no new counter sequence begins here: the gateway's goes on,
        # and what is open completes as usual. (A restart here — emit what is open, forget the
        # order — let another port's copy of a SYNC just emitted, or a frame for it, open that
        # counter a second time: counters [69, 69, 70, ...] behind two gateways under load.)
        if self._sync_thread is None and self._driver is None:
            # what passed its deadline is emitted by a thread of its own: emitting waits for the
            # feed, which a receive thread holds across a whole read, and the SYNC thread waiting
            # there missed SYNC slots (a 64x64 sheet on five ports: ~10 % of them)
            self.sync_driver.emits = False
            self._emit_thread = threading.Thread(target=self.sync_driver.emit_loop, args=(self._stop,),
                                                 name="capsheet-emit", daemon=True)
            self._emit_thread.start()
            self._sync_thread = threading.Thread(target=self.sync_driver.loop, args=(self._stop,),
                                                 name="capsheet-sync", daemon=True)
            self._sync_thread.start()
        if self._recover_thread is None and self._driver is None:
            self._recover_thread = threading.Thread(target=self.recovery.loop, args=(self._stop,),
                                                    name="capsheet-recover", daemon=True)
            self._recover_thread.start()
        return n_ok

    def stop(self) -> None:
        """Stop driving SYNC, STOP every chip (broadcast, best effort), emit what is open."""
        with self.sync_driver.step_lock:  # a SYNC step in flight finishes first: its counter is then open
            self.streaming.clear()
        # let the counters in flight complete (up to their deadline) before masking them
        end = self.now() + self.aggregator.deadline_s + 0.02
        while self.feed.n_open and self.now() < end:
            self.idle(0.005)
            self.feed.poll()
        self.commands.broadcast(Stop(0))
        self.feed.flush()

    # -- receive path ------------------------------------------------------------------------
    def _rx_loop(self, bus: int, t: Transport) -> None:
        while not self._stop.is_set():
            if self.receiver.receive(bus, t, 0.05) is None:
                return

    @property
    def stopping(self) -> bool:
        """`close` was called: the receive threads end."""
        return self._stop.is_set()

    def _check_health(self, snap: LatticeSnapshot) -> None:
        """Feed listener: every emitted snapshot, corrected, to `health` (if set)."""
        health = self.health
        if health is not None:
            for ev in health.update(snap.readings, snap.valid, snap.timestamp):
                self.report(ev.kind, ev.detail, link=ev.link)

    # -- bring-up (`host.session.bringup`) -------------------------------------------------------------
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
        return self.bringup.bring_up(discover_timeout_s, discover_rounds, reset=reset, strict=strict,
                                     capacity=capacity, packed=packed)

    def quiesce(self, quiet_s: float = 0.1, max_s: float = 3.0, reset: bool = True) -> int:
        """Bring every chip to a known state whatever a previous session left: broadcast STOP, drain
        the stale input (samples, answers, a previous session's backlog) until nothing but SYNC came for
        ``quiet_s`` (at most ``max_s``), then broadcast RESET (every chip to BOOT; calibration is
        kept, docs/protocol.md §4.14) and forget what the host knew. Returns the frames drained."""
        return self.bringup.quiesce(quiet_s, max_s, reset)

    def discover(self, timeout_s: float = 0.5, rounds: int = 2) -> dict[int, ChipRecord]:
        """Broadcast GET_INFO on every bus and collect ANNOUNCE + INFO for ``timeout_s`` per round."""
        return self.bringup.discover(timeout_s, rounds)

    def check_discovery(self, strict: bool = True) -> None:
        """Mismatches between what the host was told and what answered, before anything streams.

        Always an error: CAN FD frames on a bus opened for classic CAN ("add --fd"). With ``strict``
        also: layout chips that never answered and announcing chips the layout does not name (each
        named by uid and link). Otherwise those are reported (events) and the session goes on."""
        self.bringup.check_discovery(strict)

    def assign(self, layout: Layout | None = None, uids=None) -> dict[int, ChipRecord]:
        """ASSIGN every discovered chip to its link: node id ``link + 1``. Chips the layout does not
        name are reported (``unknown_chip``) and left unassigned; layout chips not found are links
        marked UNASSIGNED."""
        return self.bringup.assign(layout, uids)

    def configure(self, uids=None) -> int:
        """CONFIG every assigned chip (or those of ``uids``): rate, range, filter, heartbeat. Returns
        how many ACKed."""
        return self.bringup.configure(uids)

    def configure_imu(self, uids=None) -> int:
        """CONFIG_IMU every assigned chip (docs §16.2) with `imu_config`; the aggregator converts the
        records at those ranges. Returns how many ACKed (a chip without the sensors NACKs UNSUPPORTED)."""
        return self.bringup.configure_imu(uids)

    def read_calibration(self, uids=None) -> int:
        """CAL_READ the three axes of every assigned chip; chips that do not answer keep nominal
        values (reported). CAL_DATA refers to ±2 g counts; they are scaled to the configured range.
        Returns the number of chips fully calibrated (of ``uids``, if given)."""
        return self.bringup.read_calibration(uids)

    def read_imu_calibration(self, uids=None) -> int:
        """CAL_IMU_READ every element of the gyroscope's (and magnetometer's) calibration of every
        assigned chip whose INFO has GYRO (MAG) (docs/protocol.md §17) into its record's
        ``imu_cal``; the chip applies it itself, so nothing is converted with it. Returns the number
        of chips whose every element answered."""
        return self.bringup.read_imu_calibration(uids)

    def calibration_summary(self) -> dict:
        """Of the assigned chips whose calibration was read, ``{"own": n, "nominal": m}``: those whose
        CAL_DATA differs from the nominal values on some axis, and those reporting the nominal values
        on all three (what a chip with no stored calibration reports, docs/protocol.md §4.7)."""
        return self.bringup.calibration_summary()

    def set_calibration(self, calibration) -> None:
        """Correct every snapshot with ``calibration`` (a `host.analysis.calibration.Calibration`
        of this lattice: ``capsheet calibrate``'s file) from now on, or none (None). It is rebased
        to the calibration the chips report whenever the host reads it (`read_calibration`), so a
        file works whether or not it was written to the chips; applied once, where every consumer
        reads (`feed`). Set it before bring-up so the first snapshot streamed is corrected too."""
        self.bringup.set_calibration(calibration)

    def check_capacity(self, action: str = "refuse", packed: bool = False) -> list[dict]:
        """The load each bus would carry at ``rate_hz`` (docs/protocol.md §10, `protocol.capacity`),
        in SNAPSHOT frames where a gateway node says it packs (or everywhere with ``packed``).

        Over 100 %: `CapacityError` naming the remedy (``action="refuse"``), else a warning; over
        80 %: a warning. A bus whose bit rate is unknown and that has no wire (a memory link, the
        in-process python-can ``virtual`` bus) is not checked; other CAN buses without ``--bitrate``
        are checked at 1 Mbit/s (CAN FD: 1/8 Mbit/s). Returns one dict per bus."""
        return self.bringup.check_capacity(action, packed)

    def check_sync_source(self) -> None:
        """Before START: in drive mode, another SYNC source already on the bus is a conflict —
        ``sync="auto"`` follows it, ``sync="drive"`` raises `SyncConflictError`.

        The host listens for at least `sync_listen_s` after the bus was drained (`quiesce`) before
        it decides: a bring-up is shorter than one period of a slow source (3x3 chips: 20-40 ms),
        so without the wait a gateway's SYNC was caught only once streaming (exit 1, not 2)."""
        self.sync_driver.check_source()

    def recover(self) -> int:
        """Bring the queued chips back into the stream: ASSIGN, CONFIG, CAL_READ, START (only those;
        the others keep streaming). One report per incident. Returns the chips streaming again."""
        return self.recovery.recover()

    @property
    def calibration(self):
        """The host calibration applied now, rebased to the chips' own (what a recording attaches
        for its replay), or None."""
        return self.bringup.calibration

    def chip_calibration(self) -> tuple[np.ndarray, np.ndarray]:
        """The calibration the chips report (CAL_DATA, nominal where they did not answer), in ±2 g
        counts: ``(offset_counts (n_links, 3), sensitivity (n_links, 3))``; links without a chip
        nominal."""
        return self.registry.chip_calibration(self.range_code)

    # -- chips and commands (`host.session.registry`, `host.session.commands`): what tools and the gateway nodes ask
    def assigned_chips(self) -> list[ChipRecord]:
        """The chips assigned to a link."""
        return self.registry.assigned()

    def chips_by_node(self, uids=None) -> dict[tuple[int, int], ChipRecord]:
        """``(bus, node) -> ChipRecord`` of the assigned chips (of ``uids``, if given): the keys a
        `command_round` addresses chips by."""
        return self.registry.by_node(uids)

    def uid_at(self, bus: int, node: int) -> int | None:
        """The uid whose ANNOUNCE last came from ``node`` on transport ``bus`` (None: none heard)."""
        return self.registry.uid_at(bus, node)

    def drop_chip(self, bus: int, node: int, uid: int) -> None:
        """Forget the chip record an ANNOUNCE made of ``uid`` at ``node``: it is a gateway node (its INFO
        says so), which the host does not drive as a chip."""
        self.registry.drop(bus, node, uid)

    def node_ids_in_use(self) -> set[int]:
        """Node ids the chips hold or will be given: assigned chips and every link of the layout."""
        return self.registry.node_ids_in_use()

    def command_round(self, requests: dict, build, match, what: str) -> tuple[dict, list]:
        """One command round, as every bring-up step runs it: send each request, collect the
        answers, resend the unanswered, `retries` times (a tool's own command: ``capsheet calibrate``'s
        CAL_WRITE). ``build(key, attempt) -> [(bus, message), ...]``; ``match(bus, message) -> key``
        answered (by an ACK, NACK or CAL_DATA) or None. Returns ``(answers, unanswered keys)``."""
        return self.commands.round(requests, build, match, what)

    def report(self, kind: str, detail: str, **kw) -> None:
        """Record an incident (`events`, `event_counts`) and log it (``quiet=True``: record only)."""
        self.event_log.report(kind, detail, **kw)

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
        end = None if duration_s is None else self.now() + duration_s
        n, quiet_since = 0, self.now()
        while count is None or n < count:
            for snap in self.feed.drain():
                n += 1
                quiet_since = self.now()
                yield snap
                if count is not None and n >= count:
                    return
            now = self.now()
            if (end is not None and now >= end) or now - quiet_since >= timeout_s:
                return
            self.idle(self.tick_s)

    def summary(self) -> dict:
        """The end-of-run account: completeness, missing links (index and uid), errors by kind,
        reconnects, recoveries, stray frames and resyncs (`host.session.report.run_summary`)."""
        return run_summary(self)

    @property
    def stats(self) -> dict:
        """Everything counted, as plain numbers: per bus, per chip (link), the aggregator's totals
        (`host.session.report.run_stats`)."""
        return run_stats(self)
