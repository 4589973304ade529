"""The aggregator's completion deadline: how long an open counter waits for its missing links.

Sans-I/O and clock-free: `DeadlinePolicy` is told latencies (SYNC -> last frame, in seconds) and
answers with a deadline; `host.snapshots.aggregator.Aggregator` measures them and asks ``deadline_s``.

* **Fixed** (``min_deadline_s`` / ``max_deadline_s`` not both given): the deadline stays
  ``deadline_s``; measurements are ignored.
* **Adaptive deadline** (``min_deadline_s`` and ``max_deadline_s`` given): the deadline follows
  the measured SYNC -> last-frame latency (one measurement per emitted snapshot, and one per
  batch of late frames: how long after its SYNC the latest of them came). Every 32 measurements
  the target is 1.5 x the *maximum* of the last 256 measurements + 2 ms, bounded to
  ``[min_deadline_s, max_deadline_s]``; the deadline rises to a higher target at once and falls
  towards a lower one by at most 5 % per update (the first update replaces the starting value
  outright: that was a guess, not a measurement). A frame that arrives after its counter was
  emitted raises the deadline at once to 1.5 x its latency + 2 ms (bounded), without waiting for
  the next update: counted in ``late_raises`` (and ``changes``). So one slow read keeps
  the deadline up for the 256 measurements it stays in the window, then lets it decay slowly,
  instead of a 95th percentile over 32 that forgot the tail and shrank it until frames were lost.
"""

from __future__ import annotations

from collections import deque

import numpy as np

__all__ = ["DeadlinePolicy", "LATENCY_WINDOW", "UPDATE_EVERY", "SLACK_S", "DECAY"]

LATENCY_WINDOW = 256  #: latencies remembered
UPDATE_EVERY = 32  #: measurements between two updates
SLACK_S = 0.002  #: target = 1.5 x the largest remembered latency + this
DECAY = 0.05  #: at most this fraction lower per update


class DeadlinePolicy:
    """The deadline of an open counter, fixed or adapted to measured latencies (module docstring).

    Parameters
    ----------
    deadline_s : float
        The deadline (the starting value when adaptive: clipped to the bounds).
    min_deadline_s, max_deadline_s : float, optional
        Both given: the deadline adapts within these bounds. Otherwise it stays ``deadline_s``.

    Attributes
    ----------
    deadline_s : float
        The deadline now.
    adaptive : bool
        Whether measurements move it (an owner may switch it off: the deadline then stays).
    changes, late_raises : int
        Times the deadline moved (late raises included); times a late frame raised it at once.
    """

    def __init__(self, deadline_s: float = 0.05, min_deadline_s: float | None = None,
                 max_deadline_s: float | None = None) -> None:
        self.deadline_s = float(deadline_s)
        if not (np.isfinite(self.deadline_s) and self.deadline_s > 0):
            raise ValueError(f"Invalid deadline_s: {deadline_s!r} (need a finite value > 0 s)")
        self.adaptive = min_deadline_s is not None and max_deadline_s is not None
        if self.adaptive:
            if not (0 < min_deadline_s <= max_deadline_s and np.isfinite(max_deadline_s)):
                raise ValueError(f"Invalid deadline bounds: min_deadline_s={min_deadline_s!r}, "
                                 f"max_deadline_s={max_deadline_s!r} (need 0 < min <= max, finite)")
            self.deadline_s = float(np.clip(self.deadline_s, min_deadline_s, max_deadline_s))
        self.min_deadline_s = float(min_deadline_s) if self.adaptive else self.deadline_s
        self.max_deadline_s = float(max_deadline_s) if self.adaptive else self.deadline_s
        self.changes = 0
        self.late_raises = 0
        self._lat: deque[float] = deque(maxlen=LATENCY_WINDOW)  # the last measured latencies (s)
        self._n_measured = 0  # measurements since the last update of the deadline
        self._measured_once = False  # the deadline has been set from measurements at least once

    def target(self, latency_s: float) -> float:
        """The deadline a latency calls for: 1.5 x it + 2 ms, within the bounds."""
        return min(max(1.5 * latency_s + SLACK_S, self.min_deadline_s), self.max_deadline_s)

    def measure(self, latency_s: float, late: bool = False) -> None:
        """One SYNC -> last-frame latency (module docstring). ``late``: it is a frame's whose counter
        was already emitted, so the deadline was too short: raise it now. Ignored when not adaptive."""
        if not self.adaptive:
            return
        self._lat.append(latency_s)
        self._n_measured += 1
        if late:
            new = self.target(latency_s)
            if new > self.deadline_s + 1e-9:
                self.deadline_s = new
                self.changes += 1
                self.late_raises += 1
        if self._n_measured < UPDATE_EVERY:
            return
        self._n_measured = 0
        target = self.target(max(self._lat))
        if self._measured_once and target < self.deadline_s:
            target = max(target, (1.0 - DECAY) * self.deadline_s)
        self._measured_once = True
        if abs(target - self.deadline_s) > 1e-4:
            self.deadline_s = target
            self.changes += 1
