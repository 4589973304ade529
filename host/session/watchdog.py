"""The watchdog: which links fell silent, never blamed for the host's own lag.

A link is marked silent (SILENT in every snapshot, not waited for) when

* it was missing from ``n`` consecutive snapshots in which most other expected links arrived (its
  neighbours' frames for the same counters came, its did not; the aggregator's ``miss_run``),
  ``n`` = ``watchdog_s`` worth of SYNCs (at least 3); or
* no frame (SAMPLE or STATUS) came from it for ``watchdog_s`` of the host's *stall-free* time
  (`host.session.syncdriver.SyncDriver.service_s`): the whole sheet or bus fell silent while the host
  kept running;

and, either way, its own port was read within the last ``watchdog_s`` (the aggregator's
``input_mark``: how far each bus's input was read, up to the present when its reader found it empty). The host's SYNC thread may run on while one
receive thread does not (a busy machine gives the interpreter to the others): then the frames of
that port's links wait unread, and a whole gateway's links were marked missing for the host's own
lag. Such a port is reported instead (``behind``, and ``caught_up`` once it is read again), an
event per incident.

It speaks again as soon as a frame of it comes. One log line per incident, an event per link.
"""

from __future__ import annotations

import logging

import numpy as np

from host.session.registry import node_for_link
from host.session.report import link_ranges

__all__ = ["Watchdog"]

log = logging.getLogger("capsheet.host")


class Watchdog:
    """Silent links of one `host.session.core.Host` (module docstring).

    Attributes
    ----------
    watchdog_s : float
        A link silent this long is reported and marked missing.
    silent : ndarray of bool, (n_links,)
        The links marked silent now.
    next_check : float
        Host time of the next check (`tick`).
    """

    def __init__(self, host, watchdog_s: float) -> None:
        n = host.lattice.n_links
        self.host = host
        self.watchdog_s = watchdog_s
        self.silent = np.zeros(n, dtype=bool)
        self.next_check = -np.inf
        self._status_seen = np.full(n, -np.inf)  # per link, host time of its last STATUS
        self._seen_real = np.full(n, -np.inf)  # per link, host time of its last frame, as last checked
        self._seen_service = np.zeros(n)  # per link, service time when a frame was last seen
        self._bus_of: np.ndarray | None = None  # per link, the bus its chip speaks on (-1: none known)
        #: the buses reported ``behind`` now (their input not read for ``watchdog_s``)
        self.behind: set[int] = set()

    @property
    def silent_links(self) -> list[int]:
        return np.flatnonzero(self.silent).tolist()

    def status_seen(self, link: int, now: float) -> None:
        """A STATUS from ``link``'s chip at ``now``: it is alive."""
        self._status_seen[link] = now

    def restart(self, now: float, service_s: float) -> None:
        """Streaming (re)starts at ``now``: every link counts as just heard, none silent."""
        self._seen_real[:] = now
        self._seen_service[:] = service_s
        self.silent[:] = False
        self._bus_of = self._buses()

    def _buses(self) -> np.ndarray | None:
        """Per link, the bus its assigned chip speaks on (-1 where none); None when the host has no
        chip registry or its aggregator does not follow each bus's input (``hold_for_input``)."""
        host = self.host
        registry = getattr(host, "registry", None)
        if registry is None or not getattr(host.aggregator, "hold_for_input", False):
            return None
        bus_of = np.full(self.silent.shape[0], -1, dtype=np.int64)
        for rec in registry.assigned():
            if rec.link is not None and 0 <= rec.link < bus_of.shape[0]:
                bus_of[rec.link] = rec.bus
        return bus_of

    def tick(self, now: float, service_s: float) -> None:
        """`check` if it is due (every ``min(50 ms, watchdog_s / 4)``)."""
        if now >= self.next_check:
            self.check(now, service_s)
            self.next_check = now + min(0.05, self.watchdog_s / 4)

    def check(self, now: float, service_s: float) -> None:
        """Mark silent the links whose chip stopped answering, and speaking those that came back
        (module docstring). ``service_s``: the host's stall-free time now."""
        host = self.host
        agg = host.aggregator
        assigned = ~agg.unassigned
        seen = np.maximum(agg.stats.link_last_seen, self._status_seen)
        fresh = seen > self._seen_real
        self._seen_real = np.where(fresh, seen, self._seen_real)
        self._seen_service[fresh] = service_s
        quiet = service_s - self._seen_service
        n_runs = max(3, int(np.ceil(self.watchdog_s * host.rate_hz)))
        silent = assigned & ((agg.miss_run >= n_runs) | (quiet > self.watchdog_s))
        if self._bus_of is not None:  # only where its own port was read past its silence
            bus_of = self._bus_of
            known = bus_of >= 0
            mark = np.where(known, agg.input_mark[np.clip(bus_of, 0, agg.input_mark.shape[0] - 1)], np.inf)
            unread = known & (now - mark > self.watchdog_s)
            self._ports_behind(now, silent & unread & ~self.silent & known, bus_of)
            silent &= ~unread | self.silent  # a link already marked stays so until it speaks
        newly = silent & ~self.silent
        back = self.silent & ~silent
        for link in np.flatnonzero(newly).tolist():
            host.feed.mark_silent(link, True)
            host.report("silent", f"link {link} (node {node_for_link(link)}) silent "
                                  f"({int(agg.miss_run[link])} snapshots without it, "
                                  f"{quiet[link]:.2f} s host time): marked missing",
                        link=link, node=node_for_link(link), quiet=True)
        for link in np.flatnonzero(back).tolist():
            host.feed.mark_silent(link, False)
            host.report("recovered", f"link {link} (node {node_for_link(link)}) speaks again",
                        link=link, node=node_for_link(link), quiet=True)
        if newly.any():  # one log line per incident, not one per link
            log.warning("silent: links %s marked missing (no frame while their neighbours' came, or "
                        "none for %.2f s)", link_ranges(np.flatnonzero(newly)), self.watchdog_s)
        if back.any():
            log.info("links %s speak again", link_ranges(np.flatnonzero(back)))
        self.silent = silent

    def _ports_behind(self, now: float, waiting: np.ndarray, bus_of: np.ndarray) -> None:
        """Report each bus whose input was not read for ``watchdog_s`` while its links would have
        been marked silent (``waiting``), once, and once more when it is read again."""
        host, mark = self.host, self.host.aggregator.input_mark
        lagging = {int(x) for x in bus_of[waiting]}
        for b in sorted(lagging - self.behind):
            links = np.flatnonzero(bus_of == b)
            host.report("behind", f"{host.transports[b].name}: not read for {now - float(mark[b]):.2f} s (the "
                                  f"host's own lag): links {link_ranges(links)} waited for, not marked silent")
        for b in sorted(self.behind - lagging):
            host.report("caught_up", f"{host.transports[b].name}: read again", quiet=True)
        self.behind = lagging
