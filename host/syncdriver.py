"""The SYNC driver: when the host sends SYNC (`SyncSchedule`, sans-I/O)."""

from __future__ import annotations

import numpy as np

__all__ = ["SyncSchedule"]


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
