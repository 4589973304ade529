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

import csv
import json
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

from protocol.constants import Range, nominal_sensitivity
from protocol.framing import DecodeError, SampleBatch
from protocol.lattice import Lattice
from protocol.messages import (NODE_MAX_ASSIGNED, Ack, Announce, Assign, CalData, CalRead, ChipState, Config,
                               GetInfo, Info, Message, MsgType, Nack, NackReason, Sample, Snapshot, Start,
                               Status, Stop, Sync)

from .aggregator import Aggregator, LatticeSnapshot
from .transport import Transport, TransportError

__all__ = ["Layout", "ChipRecord", "HostEvent", "Host", "node_for_link"]

log = logging.getLogger("capsheet.host")


def node_for_link(link: int) -> int:
    """Node id the host assigns to the chip on ``link``: ``link + 1``."""
    if not 0 <= link < NODE_MAX_ASSIGNED:
        raise ValueError(f"Invalid link {link}: node ids cover links 0..{NODE_MAX_ASSIGNED - 1}")
    return link + 1


# --------------------------------------------------------------------------------------------
# Layout files
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Layout:
    """Which chip (64-bit uid) sits on which link (lattice address, DESIGN.md link order).

    File formats (chosen by extension; docs/host.md):

    * CSV (``.csv`` or anything else): a header line ``uid,link``, then one chip per line, uid in
      hex (``0x`` optional), link in decimal; ``#`` starts a comment. Example::

          uid,link
          0x0123456789ABCDEF,0
          0x0123456789ABCDF0,1

    * JSON (``.json``), the format `virtual_sheet.sheet.VirtualSheet.write_layout` writes::

          {"format": "capsheet-layout", "version": 1, "rows": 14, "cols": 14,
           "chips": [{"uid": "0x0123456789ABCDEF", "link": 0}, ...]}
    """

    links: dict  # uid -> link
    lattice: str | None = None
    is_auto: bool = False  #: made by `Layout.auto`: positions are arbitrary

    def __post_init__(self) -> None:
        seen: dict[int, int] = {}
        for uid, link in self.links.items():
            if not 0 <= uid < (1 << 64):
                raise ValueError(f"Invalid uid: {uid!r} (need 64 bits)")
            if not isinstance(link, int) or link < 0:
                raise ValueError(f"Invalid link for uid 0x{uid:016X}: {link!r}")
            if link in seen:
                raise ValueError(f"Link {link} is given to two chips: 0x{seen[link]:016X} and 0x{uid:016X}")
            seen[link] = uid

    @classmethod
    def load(cls, path) -> "Layout":
        path = Path(path)
        text = path.read_text()
        if path.suffix.lower() == ".json":
            doc = json.loads(text)
            lattice = f"{doc['rows']}x{doc['cols']}" if "rows" in doc and "cols" in doc else None
            links = {}
            for i, chip in enumerate(doc.get("chips", [])):
                try:
                    uid, link = int(str(chip["uid"]), 16), int(chip["link"])
                except (KeyError, ValueError, TypeError) as exc:
                    raise ValueError(f"{path}: chips[{i}]: expected {{'uid': '0x..', 'link': N}}, got {chip!r}") from exc
                if uid in links:
                    raise ValueError(f"{path}: uid 0x{uid:016X} appears twice")
                links[uid] = link
            return cls(links, lattice)
        links: dict[int, int] = {}
        rows = [ln.split("#", 1)[0].strip() for ln in text.splitlines()]
        for lineno, row in enumerate(csv.reader(r for r in rows), start=1):
            if not row or not "".join(row).strip():
                continue
            if row[0].strip().lower() == "uid":
                continue
            try:
                uid, link = int(row[0].strip(), 16), int(row[1].strip())
            except (ValueError, IndexError) as exc:
                raise ValueError(f"{path}:{lineno}: expected 'uid,link' (hex uid, decimal link), got {row!r}") from exc
            if uid in links:
                raise ValueError(f"{path}:{lineno}: uid 0x{uid:016X} appears twice")
            links[uid] = link
        return cls(links)

    def save(self, path) -> None:
        path = Path(path)
        if path.suffix.lower() == ".json":
            doc: dict = {"format": "capsheet-layout", "version": 1}
            if self.lattice:
                r, c = self.lattice.lower().split("x")
                doc.update(rows=int(r), cols=int(c))
            doc["chips"] = [{"uid": f"0x{u:016X}", "link": k}
                            for u, k in sorted(self.links.items(), key=lambda kv: kv[1])]
            path.write_text(json.dumps(doc, indent=1))
        else:
            lines = ["uid,link"] + [f"0x{u:016X},{k}" for u, k in sorted(self.links.items(), key=lambda kv: kv[1])]
            path.write_text("\n".join(lines) + "\n")

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
    nacks: list = field(default_factory=list)  #: (command name, reason name)


@dataclass(frozen=True, slots=True)
class HostEvent:
    """Something the host reports: ``kind`` in {"silent", "recovered", "nack", "no_ack", "unknown_chip",
    "announce", "reconnect", and `host.health`'s "health_magnitude", "health_magnitude_ok",
    "health_bias_shift"}; ``link``/``node``/``uid`` where known; ``detail`` text."""

    t: float
    kind: str
    detail: str
    link: int | None = None
    node: int | None = None
    uid: int | None = None


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
        Called (in a receive or SYNC thread) with every emitted `LatticeSnapshot`.
    queue_size : int
        Snapshots kept for `snapshots` / `get`; older ones are dropped when the consumer is slow.
    """

    def __init__(self, transports: Transport | Sequence[Transport], lattice: Lattice | str, *,
                 layout: Layout | str | Path | None = None, rate_hz: float = 100.0, sync: str = "drive",
                 deadline_s: float | None = None, watchdog_s: float | None = None, range_code: int = Range.G2,
                 filter_code: int = 0, heartbeat_ms: int = 1000, timeout_s: float = 0.25, retries: int = 4,
                 on_snapshot: Callable[[LatticeSnapshot], None] | None = None, queue_size: int = 64,
                 start_counter: int = 0) -> None:
        self.transports: list[Transport] = [transports] if isinstance(transports, Transport) else list(transports)
        if not self.transports:
            raise ValueError("Host needs at least one transport")
        self.lattice = Lattice.parse(lattice) if isinstance(lattice, str) else lattice
        if isinstance(layout, (str, Path)):
            layout = Layout.load(layout)
        self.layout: Layout | None = layout
        if sync not in ("drive", "follow"):
            raise ValueError(f"Invalid sync: {sync!r} (need 'drive' or 'follow')")
        if not 0 < rate_hz <= 4000:
            raise ValueError(f"Invalid rate_hz: {rate_hz!r} (need 0 < rate <= 4000)")
        self.rate_hz = float(rate_hz)
        self.sync_mode = sync
        self.range_code = Range(range_code)
        self.filter_code = filter_code
        self.heartbeat_ms = heartbeat_ms
        self.timeout_s = timeout_s
        self.retries = retries
        self.watchdog_s = watchdog_s if watchdog_s is not None else max(0.5, 20.0 / self.rate_hz)
        n = self.lattice.n_links
        self.aggregator = Aggregator(n, node_to_link=None, n_buses=len(self.transports),
                                     deadline_s=deadline_s if deadline_s is not None else max(2.0 / self.rate_hz, 0.05),
                                     queue_size=queue_size, on_snapshot=on_snapshot)
        self.chips: dict[int, ChipRecord] = {}  # uid -> record
        self._node_uid: dict[tuple[int, int], int] = {}  # (bus, node) -> uid
        self.events: list[HostEvent] = []
        self._events_lock = threading.Lock()
        self._inbox: queue.Queue = queue.Queue(maxsize=100_000)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._rx_threads: list[threading.Thread] = []
        self._sync_thread: threading.Thread | None = None
        self._streaming = threading.Event()
        self.counter = start_counter & 0xFFFF
        self.syncs_sent = 0
        self.syncs_seen = 0
        self._status_seen = np.full(n, -np.inf)
        self._silent_reported = np.zeros(n, dtype=bool)
        self._rx_errors: list[str] = []
        self.unknown_chips: set[int] = set()
        self._send_failing: set[int] = set()
        #: callable ``snapshot -> snapshot`` that `get` applies first (``capsheet host --calibration``)
        self.snapshot_filter: Callable[[LatticeSnapshot], LatticeSnapshot] | None = None
        #: a `host.health.HealthChecker` fed every snapshot `get` returns; its findings are host events
        self.health = None

    # -- lifetime ----------------------------------------------------------------------------
    def open(self) -> "Host":
        """Start the receive threads (one per transport). Idempotent; done by every other step."""
        if self._rx_threads:
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
        for th in self._rx_threads + ([self._sync_thread] if self._sync_thread else []):
            th.join(timeout=2.0)
        self._rx_threads = []
        self._sync_thread = None
        for t in self.transports:
            t.close()

    def __enter__(self) -> "Host":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def _report(self, kind: str, detail: str, **kw) -> None:
        ev = HostEvent(time.monotonic(), kind, detail, **kw)
        with self._events_lock:
            self.events.append(ev)
            if len(self.events) > 10_000:
                del self.events[:5_000]
        (log.warning if kind in ("silent", "nack", "no_ack", "health_magnitude", "health_bias_shift")
         else log.info)("%s: %s", kind, detail)

    # -- receive path ------------------------------------------------------------------------
    def _rx_loop(self, bus: int, t: Transport) -> None:
        agg = self.aggregator
        reconnects = 0
        while not self._stop.is_set():
            try:
                events = t.recv(0.05)
            except TransportError as exc:
                if self._stop.is_set() or t.closed:
                    return
                self._rx_errors.append(str(exc))
                time.sleep(0.05)
                continue
            except Exception as exc:  # noqa: BLE001 - never let the receive thread die silently
                log.exception("receive thread %d", bus)
                self._rx_errors.append(repr(exc))
                time.sleep(0.05)
                continue
            if t.stats.reconnects != reconnects:
                reconnects = t.stats.reconnects
                self._report("reconnect", f"{t.name} is back (reconnect #{reconnects})")
            if not events:
                agg.poll()
                continue
            control = False
            for ev in events:
                if not isinstance(ev, (SampleBatch, Snapshot, Sample, DecodeError)):
                    control = True
                    break
            agg.ingest(events, bus)
            if control:
                for ev in events:
                    if not isinstance(ev, (SampleBatch, Snapshot, Sample, DecodeError)):
                        self._on_control(bus, ev)

    def _on_control(self, bus: int, msg: Message) -> None:
        if isinstance(msg, Announce):
            with self._lock:
                rec = self.chips.get(msg.uid)
                if rec is None:
                    rec = self.chips[msg.uid] = ChipRecord(msg.uid, msg.node, bus)
                else:
                    if rec.assigned and msg.node != rec.node and msg.node >= 0x8000:
                        # the chip rebooted (RESET, power loss): it must be assigned again
                        rec.assigned = rec.configured = rec.started = False
                        self._report("announce", f"chip 0x{msg.uid:016X} rebooted (link {rec.link})",
                                     link=rec.link, node=msg.node, uid=msg.uid)
                    rec.node, rec.bus = msg.node, bus
                self._node_uid[(bus, msg.node)] = msg.uid
        elif isinstance(msg, Info):
            with self._lock:
                uid = self._node_uid.get((bus, msg.node))
                if uid is not None:
                    self.chips[uid].info = msg
        elif isinstance(msg, Status):
            link = self.aggregator._lut[msg.node]
            if link >= 0:
                self._status_seen[link] = time.monotonic()
            uid = self._node_uid.get((bus, msg.node))
            if uid is not None:
                self.chips[uid].last_status = msg
        elif isinstance(msg, Sync):
            self.syncs_seen += 1
            if self.sync_mode == "follow" and self._streaming.is_set():
                self.aggregator.open_counter(msg.counter)
        elif isinstance(msg, (Ack, Nack, CalData)):
            if isinstance(msg, Nack):
                uid = self._node_uid.get((bus, msg.node))
                name = MsgType(msg.command).name if msg.command in MsgType._value2member_map_ else str(msg.command)
                if uid is not None:
                    self.chips[uid].nacks.append((name, msg.reason.name))
                self._report("nack", f"node {msg.node} refused {name}: {msg.reason.name}", node=msg.node, uid=uid)
            try:
                self._inbox.put_nowait((bus, msg))
            except queue.Full:
                pass

    # -- command rounds ------------------------------------------------------------------------
    def _send(self, bus: int, msg: Message) -> None:
        self.transports[bus].send(msg)

    def _broadcast(self, msg: Message) -> None:
        for bus in range(len(self.transports)):
            try:
                self._send(bus, msg)
                self._send_failing.discard(bus)
            except TransportError as exc:
                if bus not in self._send_failing:  # once per failure spell, not once per SYNC
                    self._send_failing.add(bus)
                    log.warning("%s", exc)

    def _round(self, requests: dict, build: Callable[[object, int], list[tuple[int, Message]]],
               match: Callable[[int, Message], object | None], what: str) -> tuple[dict, list]:
        """Send every request, collect answers, resend the unanswered; ``retries`` times.

        ``requests``: key -> anything; ``build(key, attempt)`` -> [(bus, message), ...];
        ``match(bus, msg)`` -> key answered (by an ACK, NACK or CAL_DATA) or None.
        Returns ``(answers: key -> message, unanswered keys)``.
        """
        self.open()
        answers: dict = {}
        pending = set(requests)
        while True:  # drop stale answers
            try:
                self._inbox.get_nowait()
            except queue.Empty:
                break
        for attempt in range(self.retries + 1):
            if not pending:
                break
            for key in list(pending):
                for bus, msg in build(key, attempt):
                    try:
                        self._send(bus, msg)
                    except TransportError as exc:
                        log.warning("%s", exc)
            deadline = time.monotonic() + self.timeout_s * (1 + 0.5 * attempt)
            while pending:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                try:
                    bus, msg = self._inbox.get(timeout=remaining)
                except queue.Empty:
                    break
                key = match(bus, msg)
                if key is not None and key in pending:
                    answers[key] = msg
                    pending.discard(key)
        for key in pending:
            self._report("no_ack", f"{what}: no answer from {key!r} after {self.retries + 1} attempts")
        return answers, sorted(pending, key=repr)

    # -- steps ---------------------------------------------------------------------------------
    def discover(self, timeout_s: float = 0.5, rounds: int = 2) -> dict[int, ChipRecord]:
        """Broadcast GET_INFO on every bus and collect ANNOUNCE + INFO for ``timeout_s`` per round."""
        self.open()
        for _ in range(rounds):
            self._broadcast(GetInfo(0))
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                time.sleep(0.01)
                with self._lock:
                    expect = len(self.layout.links) if self.layout is not None else None
                    if expect is not None and all(u in self.chips and self.chips[u].info is not None
                                                  for u in self.layout.links):
                        return dict(self.chips)
        with self._lock:
            return dict(self.chips)

    def assign(self, layout: Layout | None = None) -> dict[int, ChipRecord]:
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
                link = links.get(uid)
                if link is None:
                    if uid not in self.unknown_chips:
                        self.unknown_chips.add(uid)
                        self._report("unknown_chip", f"chip 0x{uid:016X} is not in the layout", uid=uid)
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
        self.aggregator.set_node_map(lut)
        self.aggregator.set_unassigned(unassigned)
        self._apply_calibration()

    def _apply_calibration(self) -> None:
        n = self.lattice.n_links
        off = np.zeros((n, 3))
        sens = np.full((n, 3), nominal_sensitivity(self.range_code))
        for rec in self._assigned():
            off[rec.link] = rec.offset
            sens[rec.link] = rec.sensitivity
        self.aggregator.set_calibration(off, sens)

    def _by_node(self) -> dict[tuple[int, int], ChipRecord]:
        return {(r.bus, r.node): r for r in self._assigned()}

    def _simple_round(self, make: Callable[[ChipRecord], Message], command: MsgType, what: str) -> list[ChipRecord]:
        chips = self._by_node()

        def match(bus, msg):
            return (bus, msg.node) if isinstance(msg, (Ack, Nack)) and msg.command == command else None

        answers, _ = self._round(chips, lambda key, _a: [(key[0], make(chips[key]))], match, what)
        return [chips[k] for k, m in answers.items() if isinstance(m, Ack)]

    def configure(self) -> int:
        """CONFIG every assigned chip (rate, range, filter, heartbeat). Returns how many ACKed."""
        ok = self._simple_round(lambda r: Config(r.node, rate_hz=max(1, min(4000, round(self.rate_hz))),
                                                 range=self.range_code, filter=self.filter_code,
                                                 heartbeat_ms=self.heartbeat_ms), MsgType.CONFIG, "CONFIG")
        for rec in ok:
            rec.configured = True
        return len(ok)

    def read_calibration(self) -> int:
        """CAL_READ the three axes of every assigned chip; chips that do not answer keep nominal
        values (reported). CAL_DATA refers to ±2 g counts; they are scaled to the configured range.
        Returns the number of chips fully calibrated."""
        chips = self._by_node()
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
        return n_ok

    def start(self) -> int:
        """START every assigned chip, then drive SYNC (or follow the gateway's). Returns ACK count."""
        ok = self._simple_round(lambda r: Start(r.node), MsgType.START, "START")
        for rec in ok:
            rec.started = True
        now = time.monotonic()
        self.aggregator.stats.link_last_seen[:] = now
        self._silent_reported[:] = False
        self._streaming.set()
        if self.sync_mode == "follow":
            self.aggregator.restart()
        if self._sync_thread is None:
            self._sync_thread = threading.Thread(target=self._sync_loop, name="capsheet-sync", daemon=True)
            self._sync_thread.start()
        return len(ok)

    def stop(self) -> None:
        """Stop driving SYNC, STOP every chip (broadcast, best effort), emit what is open."""
        self._streaming.clear()
        # let the counters in flight complete (up to their deadline) before masking them
        end = time.monotonic() + self.aggregator.deadline_s + 0.02
        while self.aggregator.n_open and time.monotonic() < end:
            time.sleep(0.005)
            self.aggregator.poll()
        self._broadcast(Stop(0))
        self.aggregator.flush()

    def bring_up(self, discover_timeout_s: float = 0.5, discover_rounds: int = 3) -> dict:
        """discover + assign + configure + read_calibration + start; returns a summary dict."""
        found = self.discover(discover_timeout_s, discover_rounds)
        self.assign()
        n_cfg = self.configure()
        n_cal = self.read_calibration()
        n_start = self.start()
        return {"discovered": len(found), "assigned": len(self._assigned()), "configured": n_cfg,
                "calibrated": n_cal, "started": n_start}

    # -- SYNC and watchdog --------------------------------------------------------------------
    def _sync_loop(self) -> None:
        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        next_wd = next_t
        first = True
        while not self._stop.is_set():
            now = time.monotonic()
            if not self._streaming.is_set():
                time.sleep(0.01)
                next_t = time.monotonic()
                first = True
                continue
            if self.sync_mode == "drive" and now >= next_t:
                c = self.counter
                self.aggregator.open_counter(c, now, restart=first)
                first = False
                self._broadcast(Sync(counter=c))
                self.syncs_sent += 1
                self.counter = (c + 1) & 0xFFFF
                next_t += period
                if now - next_t > 10 * period:  # fell far behind (suspended): do not burst
                    next_t = now + period
            self.aggregator.poll()
            if now >= next_wd:
                self._watchdog(now)
                next_wd = now + min(0.05, self.watchdog_s / 4)
            wait = min(next_t if self.sync_mode == "drive" else now + 0.01, next_wd) - time.monotonic()
            if wait > 0:
                self._stop.wait(min(wait, 0.01))

    def _watchdog(self, now: float) -> None:
        agg = self.aggregator
        assigned = ~agg.unassigned
        seen = np.maximum(agg.stats.link_last_seen, self._status_seen)
        silent = assigned & (now - seen > self.watchdog_s)
        newly = silent & ~self._silent_reported
        back = self._silent_reported & ~silent
        for link in np.flatnonzero(newly).tolist():
            agg.mark_silent(link, True)
            self._report("silent", f"link {link} (node {node_for_link(link)}) silent for "
                                   f"{now - seen[link]:.2f} s: marked missing", link=link, node=node_for_link(link))
        for link in np.flatnonzero(back).tolist():
            agg.mark_silent(link, False)
            self._report("recovered", f"link {link} (node {node_for_link(link)}) speaks again",
                         link=link, node=node_for_link(link))
        self._silent_reported = silent

    # -- output -------------------------------------------------------------------------------
    def get(self, timeout_s: float | None = None) -> LatticeSnapshot | None:
        """The next snapshot (oldest queued), or None after ``timeout_s``."""
        snap = self.aggregator.get(timeout_s)
        if snap is not None and self.snapshot_filter is not None:
            snap = self.snapshot_filter(snap)
        if snap is not None and self.health is not None:
            for ev in self.health.update(snap.readings, snap.valid, snap.timestamp):
                self._report(ev.kind, ev.detail, link=ev.link)
        return snap

    def snapshots(self, duration_s: float | None = None, count: int | None = None,
                  timeout_s: float = 1.0) -> Iterator[LatticeSnapshot]:
        """Iterate over snapshots until ``duration_s`` passed, ``count`` were given, or none came
        for ``timeout_s``."""
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
        return {"aggregator": agg.summary(), "buses": buses, "chips": chips, "syncs_sent": self.syncs_sent,
                "syncs_seen": self.syncs_seen, "silent_links": self.silent_links,
                "unknown_nodes": dict(agg.unknown_nodes), "unknown_chips": [f"0x{u:016X}" for u in self.unknown_chips]}
