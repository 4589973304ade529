"""The chip registry: what the host knows of each chip (`ChipRecord`, kept by `ChipRegistry`), which
chip sits on which link (`Layout`), and the node id a link's chip gets (`node_for_link`).

Node ids: the chip on link ``k`` gets node id ``k + 1`` (1..0x7FFF), so node ids are dense, stable
across runs and the aggregator's lookup is a fixed table.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from protocol.constants import nominal_sensitivity
from protocol.lattice import Lattice
from protocol.layout import LayoutDoc, load_layout, save_layout
from protocol.messages import NODE_MAX_ASSIGNED, Info, Status

from host.session.errors import MismatchError

__all__ = ["Layout", "ChipRecord", "ChipRegistry", "node_for_link"]

log = logging.getLogger("capsheet.host")


def node_for_link(link: int) -> int:
    """Node id the host assigns to the chip on ``link``: ``link + 1``."""
    if not 0 <= link < NODE_MAX_ASSIGNED:
        raise ValueError(f"Invalid link {link}: node ids cover links 0..{NODE_MAX_ASSIGNED - 1}")
    return link + 1


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
            rows, cols = self._rows_cols()
        LayoutDoc(dict(self.links), rows, cols)  # validates uids, links, duplicates

    @classmethod
    def load(cls, path) -> "Layout":
        """Read a layout file; raises `protocol.layout.LayoutError` (a ValueError) naming the problem."""
        doc = load_layout(path)
        return cls(dict(doc.links), doc.lattice)

    def save(self, path) -> None:
        rows, cols = self._rows_cols() if self.lattice else (None, None)
        save_layout(path, self.links, rows, cols)

    def _rows_cols(self) -> tuple[int, int]:
        try:
            lat = Lattice.parse(str(self.lattice))
        except ValueError:
            raise ValueError(f"Invalid lattice: {self.lattice!r} (need 'ROWSxCOLS')") from None
        return lat.rows, lat.cols

    @classmethod
    def auto(cls, uids: Sequence[int], lattice: Lattice, runs: dict | None = None) -> "Layout":
        """Auto-assign: chips in ascending uid order take links 0, 1, 2, ... The positions are then
        arbitrary (a shape estimate is meaningless until a real layout is given); a warning says so.

        ``runs``: uid -> the links its gateway announced (GATEWAY_INFO runs, a list of ranges). A
        packing gateway carries exactly its runs in its SNAPSHOTs (docs/protocol.md §13.2), so its
        chips take the free links of those runs first (in uid order); placed elsewhere, their samples
        would come as SAMPLEs while the gateway sends their links INVALID in its SNAPSHOTs and a
        link behind another gateway got two answers per SYNC. The chips left take the lowest free
        links in uid order."""
        uids = sorted(set(int(u) for u in uids))
        n = lattice.n_links
        if len(uids) > n:
            log.warning("auto-assign: %d chips for %d links; the extra chips stay unassigned", len(uids), n)
        links: dict[int, int] = {}
        taken = np.zeros(n, dtype=bool)
        for u in uids:
            for run in (runs or {}).get(u, ()):
                r = range(max(0, run.start), min(n, run.stop))
                free = np.flatnonzero(~taken[r.start:r.stop]) if len(r) else ()
                if len(free):
                    links[u] = r.start + int(free[0])
                    taken[links[u]] = True
                    break
        free = iter(np.flatnonzero(~taken).tolist())
        for u in uids:
            if u not in links:
                k = next(free, None)
                if k is None:
                    break
                links[u] = k
        if links:  # no chip answered: the caller says so in its own words, not "0 chips placed"
            log.warning("auto-assign: %d %s placed on links in uid order%s; positions are arbitrary "
                        "(give a layout file for a meaningful shape)", len(links),
                        "chip" if len(links) == 1 else "chips", " within their gateways' runs" if runs else "")
        return cls(links, f"{lattice.rows}x{lattice.cols}", is_auto=True)

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
    #: v1.3 (§17): (block, index) -> (value, stored flag) the chip answered CAL_IMU_READ with
    imu_cal: dict = field(default_factory=dict)
    #: the last STATUS heard: a `Status`, or ``(StatusBatch, row)`` as the serial decoder gave it
    #: (made a `Status` when read, `last_status`: a 64x64 sheet beats 8,064 times a second)
    heartbeat: object = None
    nacks: list = field(default_factory=list)  #: (command name, reason name), the last `MAX_NACKS` kept
    started_at: float = float("-inf")  #: host time of its START ACK

    MAX_NACKS = 16

    @property
    def last_status(self) -> Status | None:
        """The last STATUS heard from this chip (None: none yet)."""
        hb = self.heartbeat
        if isinstance(hb, tuple):
            hb = self.heartbeat = hb[0].message(hb[1])
        return hb

    @last_status.setter
    def last_status(self, msg: Status | None) -> None:
        self.heartbeat = msg


class ChipRegistry:
    """Every chip the host heard of (``chips``: uid -> `ChipRecord`), where it speaks from (bus,
    node), and the layout that places chips on links.

    Parameters
    ----------
    lattice : Lattice
    layout : Layout or None
        None: made by `Layout.auto` at the first assignment.
    lock : RLock
        Shared with whoever else changes chip records (the host's bring-up, the gateway nodes).

    Attributes
    ----------
    max_chips : int
        At most this many chip records (an ANNOUNCE flood with new uids is counted in
        ``chips_dropped``, not kept).
    unknown_chips : set
        Uids that announced but are not in the layout (reported once each).
    cross_bus_uids : dict
        uid -> the buses it announced on, for uids heard on more than one (the same chips behind
        two ports: one gateway named twice, or two sheets with the same uids); bounded by max_chips.
    """

    def __init__(self, lattice: Lattice, layout: Layout | None, lock: threading.RLock) -> None:
        if layout is not None:
            far = {u: k for u, k in layout.links.items() if k >= lattice.n_links}
            if far:
                u, k = min(far.items(), key=lambda kv: kv[1])
                raise MismatchError(f"the layout puts {len(far)} chip(s) beyond lattice {lattice.rows}x"
                                    f"{lattice.cols} ({lattice.n_links} links), e.g. 0x{u:016X} on link {k}")
        self.lattice = lattice
        self.layout: Layout | None = layout
        self.lock = lock
        self.chips: dict[int, ChipRecord] = {}  # uid -> record
        self.max_chips = max(4 * lattice.n_links, 64)
        self.chips_dropped = 0
        self.unknown_chips: set[int] = set()
        self.cross_bus_uids: dict[int, set[int]] = {}
        self._node_uid: dict[tuple[int, int], int] = {}  # (bus, node) -> uid

    def announced(self, bus: int, uid: int, node: int) -> tuple[ChipRecord | None, bool, bool]:
        """An ANNOUNCE of ``uid`` from ``node`` on ``bus``. Returns ``(record, rebooted, was_started)``:
        the record (None: not kept, a flood); ``rebooted`` when an assigned chip announces from a
        provisional node id (a RESET, a power loss): it is then unassigned, unconfigured and not
        started, and must be assigned again; ``was_started``: it was started before."""
        with self.lock:
            rec = self.chips.get(uid)
            rebooted = was_started = False
            if rec is None:
                if len(self.chips) >= self.max_chips:  # an ANNOUNCE flood: bounded, counted
                    self.chips_dropped += 1
                    if self.chips_dropped == 1:
                        log.warning("more than %d chips announce: further uids are counted, not kept "
                                    "(a babbling bus or a foreign device?)", self.max_chips)
                    return None, False, False
                rec = self.chips[uid] = ChipRecord(uid, node, bus)
            else:
                if rec.assigned and node != rec.node and node >= 0x8000:
                    rebooted, was_started = True, rec.started
                    rec.assigned = rec.configured = rec.started = False
                if rec.bus != bus and len(self.cross_bus_uids) < self.max_chips:
                    self.cross_bus_uids.setdefault(uid, {rec.bus}).add(bus)
                rec.node, rec.bus = node, bus
            self._node_uid[(bus, node)] = uid
            return rec, rebooted, was_started

    def assigned_to(self, rec: ChipRecord, node: int) -> None:
        """``rec``'s chip ACKed its ASSIGN: it speaks from ``node`` now."""
        with self.lock:
            rec.node = node
            rec.assigned = True
            self._node_uid[(rec.bus, node)] = rec.uid

    def info(self, bus: int, msg: Info) -> None:
        """An INFO: kept in the record of the chip that speaks from its node."""
        with self.lock:
            rec = self.chips.get(self._node_uid.get((bus, msg.node)))
            if rec is not None:
                rec.info = msg

    def heartbeats(self, bus: int, batch) -> None:
        """A `StatusBatch` from transport ``bus``: each row kept as its chip's last STATUS."""
        with self.lock:
            get, chips = self._node_uid.get, self.chips
            for i, node in enumerate(batch.node.tolist()):
                uid = get((bus, node))
                if uid is not None:
                    chips[uid].heartbeat = (batch, i)

    def uid_at(self, bus: int, node: int) -> int | None:
        """The uid whose ANNOUNCE last came from ``node`` on transport ``bus`` (None: none heard)."""
        with self.lock:
            return self._node_uid.get((bus, node))

    def drop(self, bus: int, node: int, uid: int) -> None:
        """Forget the chip record an ANNOUNCE made of ``uid`` at ``node`` (a gateway node)."""
        with self.lock:
            self.chips.pop(uid, None)
            self._node_uid.pop((bus, node), None)
            # every node the record spoke from (a chip that announced again from another node keeps
            # its old one mapped too): none may lead to a record that is gone (a receive thread's
            # KeyError, seen at 64x64 under load). Rare (gateway nodes only): a scan is fine
            for key in [k for k, u in self._node_uid.items() if u == uid]:
                del self._node_uid[key]

    def forget(self) -> None:
        """Forget every chip (the chips were RESET: they announce again)."""
        with self.lock:
            self.chips.clear()
            self._node_uid.clear()
            self.unknown_chips.clear()

    def node_ids_in_use(self) -> set[int]:
        """Node ids the chips hold or will be given: assigned chips and every link of the layout."""
        with self.lock:
            used = {rec.node for rec in self.chips.values() if rec.assigned}
            if self.layout is not None:
                used |= {k + 1 for k in self.layout.links.values()}
            return used

    def assigned(self) -> list[ChipRecord]:
        """The chips assigned to a link (a list taken under the lock: a receive thread adds records)."""
        with self.lock:
            return [r for r in self.chips.values() if r.assigned and r.link is not None]

    def by_node(self, uids=None) -> dict[tuple[int, int], ChipRecord]:
        """``(bus, node) -> ChipRecord`` of the assigned chips (of ``uids``, if given)."""
        return {(r.bus, r.node): r for r in self.assigned() if uids is None or r.uid in uids}

    def key_name(self, key) -> str:
        """A command round's key (a uid, or (bus, node)) as 'link L (uid 0x..)' where known."""
        rec = self.chips.get(key) if isinstance(key, int) else None
        if rec is None and isinstance(key, tuple):
            uid = self._node_uid.get(key)
            rec = self.chips.get(uid) if uid is not None else None
        if rec is None:
            return repr(key)
        return f"link {rec.link} (uid 0x{rec.uid:016X})" if rec.link is not None else f"uid 0x{rec.uid:016X}"

    def node_map(self) -> tuple[np.ndarray, np.ndarray]:
        """``(node -> link lookup of 65536, -1 = none; links without an assigned chip)``: the
        aggregator's map of the assigned chips."""
        lut = np.full(1 << 16, -1, dtype=np.int64)
        unassigned = np.ones(self.lattice.n_links, dtype=bool)
        with self.lock:  # one consistent map (the caller hands it to the feed after releasing it)
            for rec in self.assigned():
                lut[rec.node] = rec.link
                unassigned[rec.link] = False
        return lut, unassigned

    def chip_calibration(self, range_code: int) -> tuple[np.ndarray, np.ndarray]:
        """The calibration the chips report (CAL_DATA, nominal where they did not answer), in ±2 g
        counts: ``(offset_counts (n_links, 3), sensitivity (n_links, 3))``; links without a chip
        nominal. ``range_code``: the range the records' values are in."""
        n = self.lattice.n_links
        scale = float(1 << int(range_code))
        off, sens = np.zeros((n, 3)), np.full((n, 3), nominal_sensitivity())
        for rec in self.assigned():
            off[rec.link] = np.asarray(rec.offset) * scale
            sens[rec.link] = np.asarray(rec.sensitivity) * scale
        return off, sens
