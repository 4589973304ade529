"""Bounded run statistics for commands that run as long as the user asks (``capsheet demo
--duration``): a run of a day must not keep a float per estimate (145 a second, three series: about
50 MB an hour of Python floats) to print a median at the end (every history has a bound,
what is cut is counted).

`Samples` keeps count, mean, minimum and maximum exactly and a uniform sample of at most `capacity`
values (reservoir sampling, seeded) for the median; `CompletenessWindow` counts a window's complete
snapshots as they are emitted, holding only the newest few thousand counters.
"""

from __future__ import annotations

from collections import deque

import numpy as np


class Samples:
    """A series of floats with a bounded memory.

    ``count``, ``mean``, ``min`` and ``max`` are exact over every value added. The median is exact
    while at most ``capacity`` values were added, then estimated from a uniform random sample of
    ``capacity`` of them (Vitter's algorithm R, seeded: the same values give the same median);
    ``cut`` says how many values are not in the sample. ``recent(n)`` gives the newest ``n`` (at
    most ``recent_capacity``) for a live display.
    """

    def __init__(self, capacity: int = 65536, recent_capacity: int = 256, seed: int = 0) -> None:
        if capacity < 1 or recent_capacity < 1:
            raise ValueError(f"Invalid capacity: {capacity}, {recent_capacity} (need >= 1)")
        self.capacity = int(capacity)
        self._kept = np.empty(self.capacity)
        self._recent: deque[float] = deque(maxlen=int(recent_capacity))
        self._rng = np.random.Generator(np.random.PCG64(seed))
        self.count = 0
        self._sum = 0.0
        self.min = float("inf")
        self.max = float("-inf")

    def add(self, value: float) -> None:
        v = float(value)
        if self.count < self.capacity:
            self._kept[self.count] = v
        else:  # keep it with probability capacity / (count + 1), in place of a uniform choice
            k = int(self._rng.integers(0, self.count + 1))
            if k < self.capacity:
                self._kept[k] = v
        self.count += 1
        self._sum += v
        self.min = min(self.min, v)
        self.max = max(self.max, v)
        self._recent.append(v)

    def __len__(self) -> int:
        return self.count

    def __bool__(self) -> bool:
        return self.count > 0

    @property
    def cut(self) -> int:
        """Values added but not in the sample the median is taken from."""
        return max(0, self.count - self.capacity)

    @property
    def mean(self) -> float | None:
        return self._sum / self.count if self.count else None

    def median(self) -> float | None:
        if not self.count:
            return None
        return float(np.median(self._kept[:min(self.count, self.capacity)]))

    def recent(self, n: int) -> list[float]:
        """The newest ``n`` values (at most ``recent_capacity``), oldest first."""
        return list(self._recent)[-n:] if n > 0 else []

    @property
    def last(self) -> float | None:
        return self._recent[-1] if self._recent else None


class CompletenessWindow:
    """`host.snapshots.snapshot.window_completeness` computed as snapshots are emitted, in bounded memory.

    ``add(counter, complete)`` for every snapshot emitted, in emission order; ``result(end_counter,
    syncs_sent)`` as ``window_completeness(all of them, first_counter, end_counter, syncs_sent)``.
    Counters are unwrapped one snapshot after the other as there; a position older than the newest
    by more than ``keep`` is folded (in batches, when ``2 * keep`` are held) into two counts (it can no longer be emitted again: a snapshot is
    emitted a few deadlines after its SYNC at most, and ``keep`` is many seconds of SYNCs), so the
    memory held is at most ``2 * keep`` positions however long the run.
    """

    def __init__(self, first_counter: int, keep: int = 8192) -> None:
        if keep < 1:
            raise ValueError(f"Invalid keep: {keep} (need >= 1)")
        self.first_counter = first_counter & 0xFFFF
        self.keep = int(keep)
        self._pos = 0
        self._prev = self.first_counter
        self._newest = -1
        self._open: dict[int, bool] = {}  # position -> complete, the newest `keep` positions
        self._folded_snapshots = 0
        self._folded_complete = 0
        #: the counter of the snapshot added last (None before the first)
        self.last_counter: int | None = None

    def add(self, counter: int, complete: bool) -> None:
        c = counter & 0xFFFF
        self.last_counter = c
        self._pos += (((c - self._prev) + 0x8000) & 0xFFFF) - 0x8000
        self._prev = c
        pos = self._pos
        if pos < 0:
            return  # a SYNC sent before the window
        self._open[pos] = self._open.get(pos, False) or bool(complete)
        self._newest = max(self._newest, pos)
        if len(self._open) > 2 * self.keep:  # fold in batches: O(1) per snapshot on average
            oldest = self._newest - self.keep
            for p in [p for p in self._open if p < oldest]:
                self._folded_snapshots += 1
                self._folded_complete += self._open.pop(p)

    def result(self, end_counter: int, syncs_sent: int | None = None) -> dict:
        sent = (end_counter - self.first_counter) & 0xFFFF
        if syncs_sent is not None:
            sent = syncs_sent + ((((sent - syncs_sent) + 0x8000) & 0xFFFF) - 0x8000)
        inside = [ok for p, ok in self._open.items() if p < sent]
        snapshots = self._folded_snapshots + len(inside)
        complete = self._folded_complete + sum(inside)
        return {"syncs_sent": sent, "snapshots": snapshots, "complete": complete,
                "complete_pct": round(100.0 * complete / sent, 2) if sent else 0.0}

    @property
    def held(self) -> int:
        """Positions held individually (at most ``2 * keep`` after any `add`)."""
        return len(self._open)
