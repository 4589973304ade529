"""When a SYNC reached the chips, from when the virtual sheet read it (issue 30 point 4).

A real chip samples when its SYNC arrives on the wire, about when the host sent it; the host's
timing model (`host.syncdriver`: the counter's time is when it was written, plus each record's
``time_us``) rests on that. A virtual sheet behind a pty learns of a SYNC only when its process
reads the pty — on a loaded machine some reads come milliseconds late, a delay no wire adds. Its
chips would sample (and say ``time_us`` against) that late instant, and the host would integrate
the gyroscopes over a time it never had.

`SyncArrival` gives each SYNC the instant the chips take as its arrival, from the device's read
times alone (it cannot see the host's clock): the host sends SYNC on a fixed grid, one per slot,
so a SYNC read more than one period (plus ``slack_s``) after the previous one's arrival is taken to
have arrived one period (plus ``slack_s``) after it — the rest of the wait was the reader's:

    arrival(c) = min(read(c), arrival(c − 1) + period + slack)       (c − 1 the SYNC just before)

and never before ``arrival(c − 1)``. ``period`` is measured, not told, from the reads of the
last ``window`` consecutive SYNCs before it (`period_s`: a median, which late reads leave alone
while fewer than half the spacings it takes have one). A SYNC after a gap in the counters, the first ones, or one
read before the window is full arrive when read. The same counter read again (another gateway of
the sheet: the host writes every port at once) arrives when it did the first time.

What it cannot know: a host that really sent a SYNC late (its thread woke late, or it skipped a
slot) looks the same as a late read; the arrival is then early by the host's delay less ``slack_s``
(at most one period for a skipped slot), and the following SYNCs close that gap by ``slack_s``
each. docs/motion.md ("Time on a pty") measures both delays live.

Sans-I/O: read times are arguments; exact on a simulated clock.
"""

from __future__ import annotations

from collections import deque
from statistics import median

__all__ = ["SyncArrival"]


class SyncArrival:
    """The arrival instants of SYNCs from their read times (module docstring).

    Parameters
    ----------
    slack_s : float
        How much later than one period after the previous arrival a SYNC may arrive (a host's
        own wake-up jitter) before the rest of its read delay is taken for the reader's.
    window : int
        Consecutive SYNCs over which the period is measured (at least 2).
    max_gap_s : float
        Reads further apart than this start afresh (a stream stopped and started again).
    """

    def __init__(self, *, slack_s: float = 0.5e-3, window: int = 64, max_gap_s: float = 0.5) -> None:
        if not (slack_s >= 0 and window >= 2 and max_gap_s > 0):
            raise ValueError(f"Invalid slack_s={slack_s!r} / window={window!r} / max_gap_s={max_gap_s!r}")
        self.slack_s = float(slack_s)
        self.window = int(window)
        self.max_gap_s = float(max_gap_s)
        self._reads: deque[float] = deque(maxlen=self.window)  # read times of consecutive counters
        self._last: tuple[int, float, float] | None = None  # (counter, arrival, read) of the newest SYNC
        self.pulled = 0  #: SYNCs whose arrival was put before their read (a late read)
        self.pulled_s = 0.0  #: the total of those corrections, s

    @property
    def period_s(self) -> float | None:
        """The measured SYNC period: over the last ``window`` reads of consecutive SYNCs, the median
        of the spacings across half the window, each divided by the SYNCs it spans (a late read
        stretches the spacings it ends and shortens those it starts: the median keeps the others);
        None until there are that many."""
        r = self._reads
        if len(r) < self.window:
            return None
        h = self.window // 2
        return median([(r[j + h] - r[j]) / h for j in range(len(r) - h)])

    def arrival(self, counter: int, read_s: float) -> float:
        """The instant the chips take SYNC ``counter`` (16 bits), read at ``read_s``, to have arrived."""
        c = int(counter) & 0xFFFF
        last = self._last
        if last is not None and c == last[0]:
            return last[1] if read_s >= last[1] else read_s  # the same SYNC on another port
        a = read_s
        if last is not None and (c - last[0]) & 0xFFFF == 1 and 0 <= read_s - last[2] <= self.max_gap_s:
            p = self.period_s  # of the reads before this one
            if p is not None:
                a = min(read_s, last[1] + p + self.slack_s)  # >= the previous: read_s >= its read
            self._reads.append(read_s)
        else:
            self._reads.clear()
            self._reads.append(read_s)
        if a < read_s:
            self.pulled += 1
            self.pulled_s += read_s - a
        self._last = (c, a, read_s)
        return a
