"""Recovery: sessions that survive real life.

* **Chips**: a chip that rebooted (it ANNOUNCEs from a provisional node id) or says it is not
  streaming (STATUS IDLE while started) is queued; a wave of them (gathered for 50 ms) is brought
  back with ASSIGN, CONFIG, CAL_READ and START of those chips only, while the others keep
  streaming. One report per incident.
* **Ports**: a port that went away is reopened only when the same device is back at its path
  (`host.transport.portlock`; another device there is reported and never opened); once back it
  must prove that it leads to this sheet again —
  one of the chips known on it ANNOUNCEs — before anything but GET_INFO is sent there (a stale
  symlink may lead to another device now); a port where nothing sheet-like answers is reported.
* **Stream incidents**: CAN FD on a bus opened for classic CAN, a SYNC counter that restarted
  (resync), stray frames — reported as they happen (stray at 1, 3, 7, 15, ... frames).

The work runs in the recovery thread (`Recovery.loop`), or in `Host.service` in manual mode.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter, deque

from protocol.messages import GetInfo

from host.session.report import link_ranges
from host.transport.ports import Transport, TransportError

__all__ = ["Recovery", "RECOVERIES_KEPT"]

log = logging.getLogger("capsheet.host")

#: incidents whose recovery time is kept (the newest)
RECOVERIES_KEPT = 1_000


class Recovery:
    """Chips and ports brought back into the stream of one `host.session.core.Host` (module docstring).

    Attributes
    ----------
    recoveries, recovered_chips : int
        Incidents recovered (a reboot wave, a reconnect); chips started again.
    recovery_times_s : deque
        Per incident, the newest `RECOVERIES_KEPT`: first report -> chips started again (s).
    unproven : dict
        bus -> the uids it must answer with after a reconnect (empty: any chip). Until one of them
        ANNOUNCEs, nothing but GET_INFO is sent there (`host.session.commands.CommandRounds.send`).
    not_a_sheet : dict
        bus -> why (after a reconnect nothing sheet-like answered).
    mismatch : str or None
        A mismatch found only once streaming (e.g. FD SNAPSHOTs on classic CAN).
    """

    def __init__(self, host) -> None:
        self.host = host
        self.recoveries = 0
        self.recovered_chips = 0
        self.recovery_times_s: deque[float] = deque(maxlen=RECOVERIES_KEPT)
        self.unproven: dict[int, set[int]] = {}
        self.not_a_sheet: dict[int, str] = {}
        self.mismatch: str | None = None
        self.wake = threading.Event()  #: set: the recovery thread looks now, not in up to 0.1 s
        self._queue: dict[int, str] = {}  # uid -> why
        self._since: float | None = None  # when the first chip of the queued wave was reported
        self._in_recovery = False
        self._probes: dict[int, dict] = {}  # bus -> reconnect probe state
        self._reconnects = [0] * len(host.transports)
        self._disconnects = [t.stats.disconnects for t in host.transports]
        self._resyncs_reported = 0
        self._stray_reported = 0

    # -- chips -----------------------------------------------------------------------------
    def queue(self, uid: int, why: str) -> None:
        """Bring chip ``uid`` back into the stream (soon, with the others of its wave)."""
        with self.host.registry.lock:
            if not self._queue:
                self._since = self.host.now()
            self._queue[uid] = why
        self.wake.set()

    def recover(self) -> int:
        """Bring the queued chips back into the stream: ASSIGN, CONFIG, CAL_READ, START (only those;
        the others keep streaming). One report per incident. Returns the chips streaming again."""
        host = self.host
        chips = host.registry.chips
        with host.registry.lock:
            queued, self._queue = self._queue, {}
            since = self._since if self._since is not None else host.now()
            self._since = None
        uids = {u for u in queued if u in chips and chips[u].link is not None}
        if not uids:
            return 0
        self._in_recovery = True
        try:
            links = [chips[u].link for u in uids]
            whys = Counter(queued[u] for u in uids)
            log.warning("recovering %d chip(s) (%s) on links %s", len(uids),
                        ", ".join(f"{k}: {v}" for k, v in whys.items()), link_ranges(links))
            host.assign(uids=uids)
            host.configure(uids)
            host.read_calibration(uids)
            host.start(uids)
        finally:
            self._in_recovery = False
        ok = [u for u in uids if chips[u].started]
        dt = host.now() - since
        self.recoveries += 1
        self.recovered_chips += len(ok)
        self.recovery_times_s.append(dt)
        left = sorted(chips[u].link for u in uids if not chips[u].started)
        host.report("recovery", f"{len(ok)} of {len(uids)} chip(s) streaming again after {dt:.2f} s"
                    + (f"; still out: links {link_ranges(left)}" if left else ""))
        return len(ok)

    # -- ports -----------------------------------------------------------------------------
    def check_port(self, bus: int) -> None:
        """Whether transport ``bus`` went away since last asked (`port_lost` if so)."""
        if self.host.transports[bus].stats.disconnects != self._disconnects[bus]:
            self.port_lost(bus)

    def port_lost(self, bus: int) -> None:
        """A port went away: from now on it must prove it leads to this sheet again (`prove`) before
        anything but GET_INFO is sent there. Marked at the loss, not at the reconnect: the transport
        reopens the path in its receive thread, and a SYNC sent between the reopen and the host
        hearing of it would already reach whatever the path leads to then."""
        reg = self.host.registry
        with reg.lock:
            t = self.host.transports[bus]
            if t.stats.disconnects == self._disconnects[bus]:
                return
            self._disconnects[bus] = t.stats.disconnects
            self.unproven[bus] = {u for u, r in reg.chips.items() if r.bus == bus}

    def check_reconnect(self, bus: int, t: Transport) -> None:
        """After a receive from ``t``: a loss (`port_lost`), a reopen refused because another device
        sits at the port's path now (`host.transport.portlock`: reported once, as ``not_a_sheet``),
        or a reconnect (`reconnected`) since."""
        if t.stats.disconnects != self._disconnects[bus]:
            self.port_lost(bus)
        if t.stats.refused_reopens and bus not in self.not_a_sheet:
            why = getattr(t, "refused", None)
            if why:
                self.not_a_sheet[bus] = why
                self.host.report("not_a_sheet", why)
        if t.stats.reconnects != self._reconnects[bus]:
            self._reconnects[bus] = t.stats.reconnects
            self.host.report("reconnect", f"{t.name} is back (reconnect #{t.stats.reconnects})")
            self.reconnected(bus, t)

    def reconnected(self, bus: int, t: Transport) -> None:
        """The port came back: drive nothing there until it proves to lead to this sheet (`prove`:
        one of the chips known on it ANNOUNCEs); ask every chip who it is (a rebooted chip answers
        from a provisional node id and is recovered) and report a port where none answers."""
        reg, now = self.host.registry, self.host.now
        with reg.lock:
            self.unproven[bus] = {u for u, r in reg.chips.items() if r.bus == bus}
        self._probes[bus] = {"t": now(), "frames": t.stats.frames_in, "bytes": t.stats.bytes_in,
                             "errors": t.stats.error_count, "asks": 0, "next": now()}
        self.wake.set()

    def prove(self, bus: int, uid: int) -> bool:
        """A chip ANNOUNCEd on a port: the port leads to this sheet if it was not lost, or if the chip
        is one of those known on it (any chip when none was known yet). Returns whether it does."""
        expected = self.unproven.get(bus)
        if expected is None:
            return True
        host = self.host
        t = host.transports[bus]
        if expected and uid not in expected:
            if bus not in self.not_a_sheet:
                why = (f"{t.name} came back but chip 0x{uid:016X} answers there, which was never on it "
                       f"(another sheet on this path?): nothing is driven there")
                self.not_a_sheet[bus] = why
                host.report("not_a_sheet", why)
            return False
        self.unproven.pop(bus, None)
        self._probes.pop(bus, None)
        self.not_a_sheet.pop(bus, None)
        host.report("reconnect", f"{t.name} answers as the sheet (chip 0x{uid:016X}): driven again", quiet=True)
        return True

    def _check_probes(self, now: float) -> None:
        host = self.host
        for bus, pr in list(self._probes.items()):
            t = host.transports[bus]
            if bus not in self.unproven:  # proven by an ANNOUNCE (`prove`)
                del self._probes[bus]
                continue
            if now >= pr["next"] and pr["asks"] < 6:
                pr["asks"] += 1
                pr["next"] = now + 0.3
                try:
                    host.commands.send(bus, GetInfo(0))
                except TransportError:
                    pass
            if now - pr["t"] > 2.0 and bus not in self.not_a_sheet:
                why = (f"{t.name} came back but answers nothing like a sheet: {t.stats.bytes_in - pr['bytes']} "
                       f"bytes, {t.stats.error_count - pr['errors']} undecodable, no chip of it announced in "
                       f"{now - pr['t']:.1f} s (a stale symlink to another device?): nothing is driven there")
                self.not_a_sheet[bus] = why
                host.report("not_a_sheet", why)
            if now - pr["t"] > 30.0:
                del self._probes[bus]  # stop asking; the port stays muted until a chip of it announces

    # -- the work and its thread -----------------------------------------------------------
    def loop(self, stop: threading.Event) -> None:
        """The recovery thread: `maybe_recover` when woken, at least every 0.1 s, until ``stop``."""
        while not stop.is_set():
            self.wake.wait(0.1)
            self.wake.clear()
            try:
                self.maybe_recover()
            except Exception:  # noqa: BLE001 - never let recovery die silently
                log.exception("recovery")

    def maybe_recover(self) -> None:
        """Recovery work, if any is due (the recovery thread; `Host.service` in manual mode)."""
        host = self.host
        if self._in_recovery or not host.streaming.is_set():
            return
        now = host.now()
        if self._probes:
            self._check_probes(now)
        self._report_stream_incidents()
        if self._queue and now - (self._since or now) >= 0.05:  # gather a reboot wave
            self.recover()

    def _report_stream_incidents(self) -> None:
        host = self.host
        if self.mismatch is None:
            for t in host.transports:
                n_fd = t.stats.errors.get("FD_ON_CLASSIC", 0)
                if n_fd:
                    self.mismatch = (f"{t.name} carries CAN FD frames ({n_fd} seen) but was opened for classic "
                                     f"CAN: add --fd")
                    host.report("mismatch", self.mismatch)
                    break
        agg = host.aggregator
        st = agg.stats
        if st.resyncs != self._resyncs_reported:
            self._resyncs_reported = st.resyncs
            ev = agg.resync_events[-1] if agg.resync_events else None
            host.report("resync", f"the SYNC counter restarted or jumped ({ev[0]} -> {ev[1]}): resynchronised "
                                  f"(resync #{st.resyncs})" if ev else f"resync #{st.resyncs}")
        if st.stray and st.stray >= 2 * self._stray_reported + 1:  # at 1, 3, 7, 15, ...: log lines grow as log2
            self._stray_reported = st.stray
            host.report("stray", f"{st.stray} frame(s) for counters this host did not expect dropped "
                                 f"(each costs at most its own sample)")
