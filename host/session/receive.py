"""Receiving: every event a transport hands the host takes one way through (docs/host.md).

`Receiver.receive` reads one batch from a transport; `Receiver.dispatch` hands each event to the
part that owns it, chosen by the event's type in one table (`Receiver.routes`):

=================================  ==========================================================
samples, records, decode errors    the feed (`host.snapshots.feed.SnapshotFeed.ingest`)
STATUS (one, or a run of them)     the watchdog and the chip registry
ANNOUNCE                           recovery (does the port lead to this sheet?), then the registry
INFO                               the chip registry
SYNC                               the SYNC driver
ACK, NACK, CAL_DATA, CAL_IMU_DATA  the command rounds
=================================  ==========================================================

A gateway node's control frame goes to the gateway nodes first (`GatewayNodes.observe`). The
parts answer with what they decided — the registry says a chip rebooted, recovery says whether a
port is proven — and the receiver acts on it (a report, a chip queued for recovery); no part
calls back into the host from here. A control frame no part owns (CONFIG from another host on the
bus, say) is counted in ``unrouted`` by type, never dropped silently.
"""

from __future__ import annotations

import logging
from collections import Counter

import numpy as np

from protocol.framing import DecodeError
from protocol.messages import (Ack, Announce, CalData, CalImuData, ChipState, ImuBatch, ImuSample, Info, Message, Nack,
                               Sample, SampleBatch, Snapshot, SnapshotFrames, SnapshotImu, Status, StatusBatch, Sync)

from host.transport.ports import Transport, TransportError

__all__ = ["Receiver", "DATA_EVENTS"]

log = logging.getLogger("capsheet.host")

#: what the receive path hands the feed (IMU records of 6/9-axis chips too, docs/protocol.md §16)
DATA_EVENTS = (SampleBatch, Snapshot, SnapshotFrames, Sample, DecodeError, ImuSample, SnapshotImu, ImuBatch)


class Receiver:
    """The receive path of one `host.session.core.Host`: what arrives on each transport, to the
    part that owns it (module docstring).

    Attributes
    ----------
    routes : dict
        Control event type -> the method that hands it to its part.
    frames_before_start : int
        A following host's sample frames before it streamed, dropped (`before_start`).
    unrouted : collections.Counter
        Control frames no part owns, by type name.
    """

    def __init__(self, host) -> None:
        self.host = host  # its flags (streaming, awaiting_stream), clock, and the parts below
        self.feed = host.feed
        self.aggregator = host.aggregator
        self.registry = host.registry
        self.recovery = host.recovery
        self.gateways = host.gateway_nodes
        self.watchdog = host.watchdog
        self.sync_driver = host.sync_driver
        self.commands = host.commands
        self.bringup = host.bringup
        self.event_log = host.event_log
        self.frames_before_start = 0
        self.unrouted: Counter[str] = Counter()
        self.routes = {Announce: self.on_announce, Info: self.on_info, Status: self.on_status,
                       StatusBatch: self.on_heartbeats, Sync: self.on_sync, Ack: self.on_answer,
                       Nack: self.on_answer, CalData: self.on_answer, CalImuData: self.on_answer}

    # -- reading -------------------------------------------------------------------------------
    def receive(self, bus: int, t: Transport, timeout_s: float) -> bool | None:
        """One receive from transport ``bus``, dispatched. Returns whether anything arrived, None
        when the transport is closed for good."""
        host = self.host
        try:
            events = t.recv(timeout_s)
        except TransportError as exc:
            if host.stopping or t.closed:
                return None
            self.event_log.rx_error(str(exc))
            host.idle(0.05)
            return False
        except Exception as exc:  # noqa: BLE001 - never let the receive thread die silently
            log.exception("receive thread %d", bus)
            self.event_log.rx_error(repr(exc))
            host.idle(0.05)
            return False
        self.recovery.check_reconnect(bus, t)
        if events and self.bringup.discarding:
            self.bringup.count_stale(events)
            return True
        if not events:
            self.feed.input_idle(bus)  # read up to now: its counters may be given up at their deadline
            return False
        self.dispatch(bus, events)
        return True

    def dispatch(self, bus: int, events: list) -> None:
        """Every event of one read from transport ``bus``, each to its part, in wire order."""
        host = self.host
        if host.awaiting_stream and self.sync_driver.sync_mode == "follow":
            events = self.before_start(events)
        if self.gateways.unreadable:  # a gateway packs words this host cannot read (§4.16)
            events = self.gateways.drop_unreadable(bus, events)
        feed = self.feed
        control = False
        statuses = None
        for ev in events:
            if not isinstance(ev, DATA_EVENTS):
                if type(ev) is not Status and type(ev) is not StatusBatch:
                    control = True
                    break
                if statuses is None:
                    statuses = []
                statuses.append(ev)
        if not control:
            # samples and STATUS only: STATUS (every chip's heartbeat, 8,064 a second from a 64x64
            # sheet: in nearly every read) changes nothing the feed holds, so the read is ingested in
            # one call, as a replay does, without holding the feed across it (under `one_read` the
            # SYNC thread would wait behind the whole read)
            feed.ingest(events, bus)
            if statuses:
                for ev in statuses:
                    self.on_event(bus, ev)
            return
        # in wire order: a SYNC opens its counter before the samples that answer it are ingested;
        # the whole read at once (`SnapshotFeed.one_read`: recorded as one chunk, replayed whole)
        data: list = []
        with feed.one_read():
            for ev in events:
                if isinstance(ev, DATA_EVENTS):
                    data.append(ev)
                    continue
                if data:
                    feed.ingest(data, bus)
                    data = []
                self.on_event(bus, ev)
            if data:
                feed.ingest(data, bus)

    def before_start(self, events: list) -> list:
        """A following host's sample frames before it streams: counted (`frames_before_start`) and
        dropped. The gateway's SYNC runs through the bring-up, so the chips started first answer it
        while the others are still being started: a 64x64 sheet's ~100 snapshots of 48-4,838 of
        its 8,064 links before its bring-up ended. A driving host's first SYNC comes after it; a
        following host's snapshots now begin at the same point, with the first SYNC it hears
        streaming (`SyncDriver.heard`)."""
        keep = []
        for ev in events:
            if isinstance(ev, DATA_EVENTS) and type(ev) is not DecodeError:
                self.frames_before_start += len(ev) if isinstance(ev, (SampleBatch, ImuBatch, SnapshotFrames)) else 1
            else:
                keep.append(ev)
        return keep

    # -- control events, each to its part ------------------------------------------------------
    def on_event(self, bus: int, msg: Message) -> None:
        """One control event from transport ``bus``, to the part that owns it (`routes`)."""
        if type(msg) is not StatusBatch and self.gateways.observe(bus, msg):  # a gateway node's (§13)
            return
        route = self.routes.get(type(msg))
        if route is None:
            self.unrouted[type(msg).__name__] += 1
            return
        route(bus, msg)

    def on_heartbeats(self, bus: int, batch: StatusBatch) -> None:
        """A run of STATUS heartbeats (`StatusBatch`): what `on_status` does with each `Status`,
        at once for the chips that stream, one at a time for the few that need more (a gateway
        node's, a chip that says it is IDLE)."""
        nodes = batch.node
        one_by_one = batch.state == ChipState.IDLE
        gw = self.gateways
        if gw.by_uid:
            one_by_one |= np.isin(nodes, gw.nodes_on(bus))
        if one_by_one.any():
            for i in np.flatnonzero(one_by_one).tolist():
                self.on_event(bus, batch.message(i))
            keep = ~one_by_one
            batch = StatusBatch(*(getattr(batch, f)[keep] for f in
                                  ("node", "state", "flags", "rx_errors", "missed_syncs", "uptime_s")))
            nodes = batch.node
        links = self.aggregator.link_of(nodes)
        self.watchdog.status_seen(links[links >= 0], self.host.now())
        self.registry.heartbeats(bus, batch)

    def on_announce(self, bus: int, msg: Announce) -> None:
        """A chip says who it is: recovery decides whether the port leads to this sheet (a chip
        never on it is reported there, not driven); the registry whether the chip rebooted."""
        host = self.host
        if not self.recovery.prove(bus, msg.uid):
            return
        rec, rebooted, was_started = self.registry.announced(bus, msg.uid, msg.node)
        if rebooted:  # the chip rebooted (RESET, power loss): it must be assigned again
            host.report("announce", f"chip 0x{msg.uid:016X} rebooted (link {rec.link})",
                        quiet=True, link=rec.link, node=msg.node, uid=msg.uid)
            if was_started and host.streaming.is_set():
                self.recovery.queue(msg.uid, "rebooted")

    def on_info(self, bus: int, msg: Info) -> None:
        self.registry.info(bus, msg)

    def on_status(self, bus: int, msg: Status) -> None:
        """One heartbeat: the link is alive; a started chip that says it is IDLE (it lost its
        START: a brown-out, a STOP from elsewhere) is queued to be brought back."""
        host = self.host
        link = self.aggregator.link_of(msg.node)
        if link >= 0:
            self.watchdog.status_seen(link, host.now())
        uid = self.registry.uid_at(bus, msg.node)
        if uid is None:
            return
        rec = self.registry.chips[uid]
        rec.last_status = msg
        if (rec.started and rec.assigned and host.streaming.is_set() and msg.state == ChipState.IDLE
                and host.now() - rec.started_at > max(2 * host.timeout_s, 0.2)):
            rec.started = False
            self.recovery.queue(uid, "not streaming")

    def on_sync(self, bus: int, msg: Sync) -> None:
        self.sync_driver.heard(bus, msg)

    def on_answer(self, bus: int, msg: Message) -> None:
        self.commands.answer(bus, msg)
