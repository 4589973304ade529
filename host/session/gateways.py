"""Gateway nodes as the host sees them (docs/protocol.md §13): discovered like chips, assigned a
node id, and asked nothing — the host *learns* from them whether a port's samples come packed in
SNAPSHOT frames and whether a gateway is its segment's SYNC source, instead of being told
(``--packed`` stays as an override).

`GatewayNodes` is what `host.session.core.Host` consults: every control frame goes through `observe`
first (a gateway's ANNOUNCE, INFO, GATEWAY_INFO and STATUS are its business, so a gateway never
becomes a chip record); `assign` gives each gateway a node id (from 0x7FFF downwards, skipping the
chips' ids) in one command round; `packing(bus)` and `sync_sources()` answer the bring-up.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field

import numpy as np

from protocol.messages import (LINK_NONE, NODE_MAX_ASSIGNED, Ack, Announce, Assign, Capability, GatewayFlag,
                               GatewayInfo, Info, Message, MsgType, SampleFormat, Snapshot, SnapshotFrames, SnapshotImu,
                               Status)

#: GATEWAY_INFO ``sample_format`` values this host reads: §5.2's words in SNAPSHOT, and the 6/9-axis
#: IMU records in SNAPSHOT_IMU (§16.5, protocol 1.2)
KNOWN_SAMPLE_FORMATS = (SampleFormat.ACCEL_12, SampleFormat.IMU6, SampleFormat.IMU9)

__all__ = ["GatewayRecord", "GatewayNodes"]

log = logging.getLogger("capsheet.host")


@dataclass
class GatewayRecord:
    """What the host knows about one gateway node."""

    uid: int
    node: int  #: the node id it speaks from now (provisional until assigned)
    bus: int
    info: Info | None = None
    runs: dict = field(default_factory=dict)  #: first_link -> GatewayInfo (its last word on that run)
    assigned: bool = False
    last_status: Status | None = None

    @property
    def flags(self) -> GatewayFlag:
        out = GatewayFlag.NONE
        for g in self.runs.values():
            out |= g.flags
        return out

    @property
    def links(self) -> list[range]:
        return [g.links for _, g in sorted(self.runs.items()) if g.link_count]

    @property
    def sync_rate_hz(self) -> int:
        return max((g.sync_rate_hz for g in self.runs.values()), default=0)

    def covers(self, link: int) -> bool:
        return any(link in g.links for g in self.runs.values())

    def first_link(self) -> int | None:
        """The first link of its first non-empty run (None: it announced no links)."""
        runs = self.links
        return runs[0].start if runs else None

    def label(self) -> str:
        return f"gateway 0x{self.uid:016X} (node 0x{self.node:04X})"

    def describe(self) -> str:
        f = self.flags
        what = [n for n, b in (("packs SNAPSHOTs", GatewayFlag.PACKING), ("is its segment's SYNC source",
                                                                          GatewayFlag.SYNC_SOURCE)) if f & b]
        runs = ", ".join(f"{r.start}-{r.stop - 1}" for r in self.links) or "no links announced"
        return (f"gateway 0x{self.uid:016X} (node 0x{self.node:04X}, links {runs}) "
                + (" and ".join(what) if what else "forwards frames"))


class GatewayNodes:
    """The gateways of one `Host` (module docstring). Thread-safe through ``lock`` (the host passes its
    own, so a gateway's INFO and the chip record it replaces change together)."""

    def __init__(self, host, lock: threading.RLock | None = None) -> None:
        self.host = host
        self.lock = lock if lock is not None else threading.RLock()
        self.by_uid: dict[int, GatewayRecord] = {}
        self._node: dict[tuple[int, int], int] = {}  # (bus, node) -> uid, for every id a gateway used
        # (bus, node) -> the uid of the last ANNOUNCE from there, a chip's or a gateway's: the INFO
        # that follows an ANNOUNCE (§4.2) is that uid's, whoever spoke from the node before
        self._announced: dict[tuple[int, int], int] = {}
        #: uids of gateways whose SNAPSHOT words are in a format this host does not know (§4.16)
        self.unreadable: set[int] = set()
        self.unreadable_frames = 0  #: their SNAPSHOT frames dropped, not read

    # ---- receiving
    def observe(self, bus: int, msg: Message) -> bool:
        """Take a control frame if it is a gateway's; True when it was (the host then ignores it)."""
        key = (bus, msg.node)
        if isinstance(msg, Info) and msg.capabilities & Capability.GATEWAY:
            uid = self._announced.get(key) or self.host.uid_at(bus, msg.node) or self._node.get(key)
            if uid is None:
                return True  # an INFO whose ANNOUNCE was lost: the next round tells
            with self.lock:
                self.host.drop_chip(bus, msg.node, uid)  # its ANNOUNCE made it look like a chip until now
                rec = self.by_uid.get(uid)
                if rec is None:
                    rec = self.by_uid[uid] = GatewayRecord(uid, msg.node, bus)
                    log.info("found %s", rec.describe())
                rec.node, rec.bus, rec.info = msg.node, bus, msg
                self._node[key] = uid
            return True
        uid = self._node.get(key)
        if isinstance(msg, Announce):
            self._announced[key] = msg.uid  # at most one per node id (u16) and bus: bounded
            if msg.uid not in self.by_uid:
                return False
            rec = self.by_uid[msg.uid]
            if rec.assigned and msg.node != rec.node and msg.node >= 0x8000:
                rec.assigned = False  # it rebooted (RESET, power loss): assign it again
            rec.node, rec.bus = msg.node, bus
            self._node[key] = msg.uid
            return True
        if uid is None:
            return False
        rec = self.by_uid[uid]
        if isinstance(msg, GatewayInfo):
            if msg.sample_format not in KNOWN_SAMPLE_FORMATS:
                if uid not in self.unreadable:
                    self.unreadable.add(uid)
                    self.host.report("not_a_sheet", f"{rec.describe()} packs sample format {msg.sample_format}, "
                                                     f"which protocol 1.2 does not define: its SNAPSHOTs are not read")
            else:
                self.unreadable.discard(uid)
            rec.runs[msg.first_link] = msg
            return True
        if isinstance(msg, Status):
            rec.last_status = msg
            return True
        return False  # ACK / NACK: the command round's

    def nodes_on(self, bus: int) -> np.ndarray:
        """The node ids of the gateways heard on transport ``bus`` (their frames are `observe`'s)."""
        return np.fromiter((n for b, n in list(self._node) if b == bus), dtype=np.int64)

    def drop_unreadable(self, bus: int, events: list) -> list:
        """``events`` without the SNAPSHOTs of gateways whose sample format is unknown (§4.16: a host
        MUST NOT interpret those words); they are counted in `unreadable_frames`."""
        out = []
        for ev in events:
            if type(ev) is SnapshotFrames:
                keep = np.fromiter((self._node.get((bus, int(n))) not in self.unreadable for n in ev.node),
                                   dtype=bool, count=len(ev))
                if not keep.all():
                    self.unreadable_frames += len(ev) - int(keep.sum())
                    if keep.any():
                        out.append(ev.select(keep))
                    continue
            elif isinstance(ev, (Snapshot, SnapshotImu)) and self._node.get((bus, ev.node)) in self.unreadable:
                self.unreadable_frames += 1
                continue
            out.append(ev)
        return out

    def forget(self) -> None:
        """After a broadcast RESET: every gateway is in BOOT again (they re-announce)."""
        for rec in self.by_uid.values():
            rec.assigned = False

    # ---- what the bring-up learns
    def packing(self, bus: int) -> bool:
        """A gateway on transport ``bus`` says it packs (GATEWAY_INFO flag PACKING)."""
        return any(r.bus == bus and r.flags & GatewayFlag.PACKING for r in self.by_uid.values())

    def sample_format(self, bus: int) -> int:
        """What the packing gateways on transport ``bus`` pack (GATEWAY_INFO ``sample_format``: 0
        words, 1/2 IMU records; the largest if they differ), 0 when none packs."""
        return max((int(g.sample_format) for r in self.by_uid.values() if r.bus == bus and r.flags & GatewayFlag.PACKING
                    for g in r.runs.values() if g.sample_format in KNOWN_SAMPLE_FORMATS), default=0)

    def runs_on(self, bus: int) -> list[range]:
        """The links the gateways on transport ``bus`` announced (GATEWAY_INFO runs), in link order:
        the chips behind them are on these links (§13.2), so auto-assign places them there."""
        return sorted((x for r in self.by_uid.values() if r.bus == bus for x in r.links), key=lambda x: x.start)

    def sync_sources(self) -> list[GatewayRecord]:
        """The gateways that generate their segment's SYNC (GATEWAY_INFO flag SYNC_SOURCE)."""
        return [r for r in self.by_uid.values() if r.flags & GatewayFlag.SYNC_SOURCE]

    def assign(self) -> int:
        """ASSIGN every unassigned gateway a node id (0x7FFF downwards, free of the chips' ids; link
        0xFFFF) in one command round. Returns how many ACKed."""
        host = self.host
        with self.lock:
            todo = sorted(u for u, r in self.by_uid.items() if not r.assigned)
            if not todo:
                return 0
            used = host.node_ids_in_use() | {r.node for r in self.by_uid.values() if r.assigned}
            want, n = {}, NODE_MAX_ASSIGNED
            for uid in todo:
                while n in used:
                    n -= 1
                want[uid] = n
                used.add(n)

        def build(uid, attempt):
            rec = self.by_uid[uid]
            return [(rec.bus, Assign(rec.node, new_node=want[uid], link=LINK_NONE, uid_low=uid & 0xFFFFFFFF))]

        def match(bus, msg):
            if isinstance(msg, Ack) and msg.command == MsgType.ASSIGN:
                for uid, node in want.items():
                    if node == msg.node and self.by_uid[uid].bus == bus:
                        return uid
            return None
        answers, _ = host.command_round({u: None for u in todo}, build, match, "ASSIGN gateways")
        for uid in answers:
            rec = self.by_uid[uid]
            rec.node, rec.assigned = want[uid], True
            self._node[(rec.bus, rec.node)] = uid
        return len(answers)

    def summary(self) -> list[dict]:
        return [{"uid": f"0x{r.uid:016X}", "node": r.node, "bus": self.host.transports[r.bus].name,
                 "assigned": r.assigned, "packing": bool(r.flags & GatewayFlag.PACKING),
                 "sync_source": bool(r.flags & GatewayFlag.SYNC_SOURCE), "sync_rate_hz": r.sync_rate_hz,
                 "links": [[x.start, x.stop - 1] for x in r.links]}
                for r in sorted(self.by_uid.values(), key=lambda r: r.uid)]
