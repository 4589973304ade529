"""The run report: what the host reports as it runs (`EventLog`: `HostEvent` s, counted by kind,
and receive errors, each bounded for a run of days), and the account of a run (`run_summary`, what
``capsheet host`` prints at the end; `run_stats`, everything counted). Links in a log line are
named as ranges (`link_ranges`).
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["HostEvent", "link_ranges", "EventLog", "run_summary", "run_stats", "EVENTS_KEPT", "RX_ERRORS_KEPT"]

log = logging.getLogger("capsheet.host")

#: bounds of what a host keeps for a run of days; what goes is counted
EVENTS_KEPT = 10_000
RX_ERRORS_KEPT = 64
#: kinds logged as warnings (the others at info)
WARNING_KINDS = frozenset(("silent", "nack", "no_ack", "recovery", "reconnect", "not_a_sheet", "sync", "resync",
                           "mismatch", "stray", "behind", "health_magnitude", "health_bias_shift"))


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


@dataclass(frozen=True, slots=True)
class HostEvent:
    """Something the host reports: ``kind`` in {"silent", "recovered" (a silent link speaks again),
    "nack", "no_ack", "unknown_chip", "missing_chip", "announce" (a chip rebooted), "recovery" (rebooted
    chips streaming again), "reconnect", "not_a_sheet", "sync", "resync", "stray", "behind" (a port the host
    itself has not read for the watchdog's time: its lag, not its chips'), "caught_up" (that port read
    again), and `host.snapshots.health`'s
    "health_magnitude", "health_magnitude_ok", "health_bias_shift"}; ``link``/``node``/``uid`` where known;
    ``detail`` text."""

    t: float
    kind: str
    detail: str
    link: int | None = None
    node: int | None = None
    uid: int | None = None


class EventLog:
    """What the host reports: ``events`` (the newest `EVENTS_KEPT`; the oldest half goes when full,
    counted in ``events_cut``), ``event_counts`` (every event by kind, never capped), and receive
    errors (``rx_errors_total``; the newest `RX_ERRORS_KEPT` in ``rx_errors``). Any thread may report."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self.clock = clock
        self.events: list[HostEvent] = []  #: the newest events (bounded)
        self.events_cut = 0
        self.event_counts: Counter = Counter()  #: HostEvent kind -> count (never capped)
        self.rx_errors_total = 0  #: every receive error (``rx_errors`` keeps the newest)
        self._rx_errors: list[str] = []
        self._lock = threading.Lock()

    @property
    def rx_errors(self) -> list[str]:
        """The newest `RX_ERRORS_KEPT` receive errors, oldest first."""
        return list(self._rx_errors)

    def rx_error(self, text: str) -> None:
        """A receive error: counted, the newest RX_ERRORS_KEPT kept."""
        self.rx_errors_total += 1
        self._rx_errors.append(text)
        if len(self._rx_errors) > RX_ERRORS_KEPT:
            del self._rx_errors[0]

    def report(self, kind: str, detail: str, *, quiet: bool = False, **kw) -> None:
        """Record an event (bounded) and log it, unless ``quiet`` (the caller logs the incident once).
        ``kw``: the `HostEvent`'s ``link``, ``node``, ``uid``."""
        self.event_counts[kind] += 1
        ev = HostEvent(self.clock(), kind, detail, **kw)
        with self._lock:
            self.events.append(ev)
            if len(self.events) > EVENTS_KEPT:
                del self.events[:EVENTS_KEPT // 2]
                self.events_cut += EVENTS_KEPT // 2
        if not quiet:
            (log.warning if kind in WARNING_KINDS else log.info)("%s: %s", kind, detail)


def run_summary(host) -> dict:
    """The end-of-run account (`Host.summary`): completeness, missing links (index and uid), errors
    by kind, reconnects, recoveries, stray frames and resyncs."""
    agg = host.aggregator.stats
    reg, rec, sync, cmd = host.registry, host.recovery, host.sync_driver, host.commands
    n = host.lattice.n_links
    uid_of = {r.link: r.uid for r in reg.chips.values() if r.link is not None}
    if reg.layout is not None:
        uid_of.update({k: u for u, k in reg.layout.links.items()})
    emitted = agg.emitted
    valid = agg.valid_links
    frac = valid / (emitted * n) if emitted else 0.0
    assigned = {r.link for r in reg.assigned()}
    never = sorted(set(range(n)) - assigned)
    missing = np.flatnonzero(agg.link_missing > 0.5 * max(1, emitted)).tolist() if emitted else []
    missing = sorted(set(missing) | set(host.watchdog.silent_links))
    counts = host.event_log.event_counts
    errors: Counter = Counter()
    for t in host.transports:
        errors.update(t.stats.errors)
    for key, c in cmd.nack_counts.items():
        errors[f"NACK {key[0]} {key[1]}"] += c
    for kind in ("no_ack", "not_a_sheet"):
        if counts.get(kind):
            errors[kind] += counts[kind]
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
            "reconnects": sum(t.stats.reconnects for t in host.transports),
            "recoveries": rec.recoveries, "recovered_chips": rec.recovered_chips,
            "stray_frames": agg.stray, "resyncs": agg.resyncs, "late": agg.late,
            "foreign_syncs": sync.foreign_syncs, "sync_mode": sync.sync_mode,
            "sync_conflict": sync.sync_conflict, "not_a_sheet": list(rec.not_a_sheet.values()),
            # ports that came back but never answered as the sheet, and what was not sent there
            "unproven_ports": [host.transports[b].name for b in sorted(rec.unproven)],
            "muted_sends": cmd.muted_sends,
            "mismatch": rec.mismatch, "gateways": host.gateway_nodes.summary(),
            "chips_dropped": reg.chips_dropped, "stale_frames_drained": host.bringup.stale_frames,
            # a following host: sample frames that answered the gateway's SYNC before it streamed
            "frames_before_start": getattr(host, "frames_before_start", 0),
            # control frames no part of this host owns (CONFIG from another host on the bus), by type
            "unrouted": dict(host.receiver.unrouted) if hasattr(host, "receiver") else {},
            "events_cut": host.event_log.events_cut, "rx_errors": host.event_log.rx_errors_total,
            "incidents": [{"t": e.t, "kind": e.kind, "detail": e.detail} for e in list(host.event_log.events)
                          if e.kind in ("recovery", "reconnect", "resync", "not_a_sheet", "sync")][-100:]}


def run_stats(host) -> dict:
    """Everything counted, as plain numbers (`Host.stats`): per bus, per chip (link), the
    aggregator's totals."""
    agg = host.aggregator.stats
    sync, silent = host.sync_driver, host.watchdog.silent
    buses = []
    for i, t in enumerate(host.transports):
        d = {"name": t.name, "kind": t.capabilities.kind, **t.stats.as_dict(),
             "samples": int(agg.bus_frames[i]), "late": int(agg.bus_late[i]),
             "duplicates": int(agg.bus_duplicates[i]), "unknown": int(agg.bus_unknown[i])}
        buses.append(d)
    chips = {}
    for rec in host.registry.assigned():
        k = rec.link
        chips[k] = {"uid": f"0x{rec.uid:016X}", "node": rec.node, "bus": rec.bus,
                    "frames": int(agg.link_frames[k]), "late": int(agg.link_late[k]),
                    "duplicates": int(agg.link_duplicates[k]), "missing": int(agg.link_missing[k]),
                    "latency_s": float(agg.link_latency_s[k]), "silent": bool(silent[k]),
                    "calibrated": rec.calibrated,
                    "missed_syncs": rec.last_status.missed_syncs if rec.last_status else None,
                    "rx_errors": rec.last_status.rx_errors if rec.last_status else None}
    sched = sync.sync_schedule
    live = {"loop_lag_s": round(sync.loop_lag_s, 6), "max_loop_lag_s": round(sync.max_loop_lag_s, 6),
            "syncs_missed": sync.syncs_missed,
            "sync_late_s": round(sched.max_late_s, 6) if sched else 0.0,
            "deadline_s": round(host.aggregator.deadline_s, 6), **host.aggregator.completeness()}
    return {"aggregator": agg.summary(), "live": live, "buses": buses, "chips": chips,
            "syncs_sent": sync.syncs_sent,
            "syncs_seen": sync.syncs_seen, "sync_copies": sync.copies.copies, "silent_links": host.watchdog.silent_links,
            "unknown_nodes": dict(agg.unknown_nodes),
            "unknown_chips": [f"0x{u:016X}" for u in host.registry.unknown_chips]}
