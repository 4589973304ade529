"""When a SYNC reached the chips, from when the virtual sheet read it.

A real chip samples when its SYNC arrives on the wire, about when the host sent it; the host's
timing model (`host.session.syncdriver`: the counter's time is when it was written, plus each record's
``time_us``) rests on that. A virtual sheet behind a pty learns of a SYNC only when its process
reads the pty — on a loaded machine some reads come milliseconds late, a delay no wire adds. Its
chips would sample (and say ``time_us`` against) that late instant, and the host would integrate
the gyroscopes over a time it never had.

`SyncArrival` gives each SYNC the instant the chips take as its arrival, from the device's read
times alone (it cannot see the host's clock): the host sends SYNC on a fixed grid, one per slot,
so a SYNC read later than its slot on that grid (plus ``slack_s``) is taken to have arrived there —
the rest of the wait was the reader's:

    arrival(c) = min(read(c), arrival(a) + (c − a) · period + slack)

with ``a`` the newest SYNC of this run taken as read (its read was on time), and never before
``arrival(c − 1)``. The slack is allowed once, not once a SYNC: chained from the SYNC just before,
a reader that stays behind for a second let the arrivals creep later by the slack every period —
at 100 Hz, 5 % of the time the chips saw, which a gyroscope scale fit took for the gyroscopes'
(`capsheet calibrate` on a loaded machine). ``period`` is measured, not told, from the
reads of the last ``window`` consecutive SYNCs before it (`period_s`: the median spacing, which late reads,
backlogs and skipped slots leave alone while most spacings are one period). A SYNC after a gap
in the counters, and the first ones (8 spacings), arrive when read. The same counter read
again (another gateway of the sheet: the host writes every port at once) arrives when it did the
first time, whatever was read in between, and leaves the model as it was: a device serves each
port's read whole, so after a stall the second gateway reads SYNCs c, c+1, c+2 only once the
first has read them all (the newest `KEPT` counters' arrivals are kept for it). Taken as a new
SYNC, the second gateway's copy of c came two counters back — a gap: its chips sampled at the
late read, the truth of c moved there too, and the measured period was thrown away, so every
SYNC until 8 more spacings were read arrived when read.

What it cannot know: a host that really sent a SYNC late (its thread woke late, or it skipped a
slot) looks the same as a late read; the arrival is then early by the host's delay less ``slack_s``
(at most one period for a skipped slot). The two part after that: a stalled reader reads its
backlog at once and is on time again, a host that skipped a slot keeps sending one period apart on
its new phase — so ``steady`` SYNCs in a row read one period apart but still put before their reads
take the reads again (`rephased`). docs/motion.md ("Time on a pty") measures both delays live.

Sans-I/O: read times are arguments; exact on a simulated clock.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from statistics import median

__all__ = ["SyncArrival", "KEPT"]

#: the newest counters whose arrivals are kept for another gateway's copy of the same SYNC
#: (1.8 s at 145 Hz: far longer than one port is read behind another)
KEPT = 256


class SyncArrival:
    """The arrival instants of SYNCs from their read times (module docstring).

    Parameters
    ----------
    slack_s : float
        How much later than one period after the previous arrival a SYNC may arrive (a host's
        own wake-up jitter) before the rest of its read delay is taken for the reader's.
    window : int
        Spacings of consecutive SYNCs over which the period is measured (at least 2).
    max_gap_s : float
        Reads further apart than this start afresh (a stream stopped and started again).
    steady : int
        After this many SYNCs in a row put before their reads although read one period apart (as
        a host that sent late or skipped a slot, then keeps its grid), the reads are taken again.
    """

    def __init__(self, *, slack_s: float = 0.5e-3, window: int = 64, max_gap_s: float = 0.5,
                 steady: int = 3) -> None:
        if not (slack_s >= 0 and window >= 2 and max_gap_s > 0 and steady >= 1):
            raise ValueError(f"Invalid slack_s={slack_s!r} / window={window!r} / max_gap_s={max_gap_s!r}")
        self.slack_s = float(slack_s)
        self.window = int(window)
        self.max_gap_s = float(max_gap_s)
        self._spacings: deque[float] = deque(maxlen=self.window)  # between reads of consecutive counters
        self._last: tuple[int, float, float] | None = None  # (counter, arrival, read) of the newest SYNC
        self._anchor: tuple[int, float] | None = None  # (counter, arrival) of the newest SYNC taken as read
        self.pulled = 0  #: SYNCs whose arrival was put before their read (a late read)
        self.pulled_s = 0.0  #: the total of those corrections, s
        self.steady = int(steady)
        self._steady = 0  # SYNCs in a row read one period apart yet put before their reads
        self.rephased = 0  #: times the reads were taken again after a host's late SYNC or skipped slot
        self._kept: OrderedDict[int, float] = OrderedDict()  # counter -> arrival, the newest `KEPT`
        self.copies = 0  #: SYNCs read again on another port, given the arrival of their first read

    @property
    def period_s(self) -> float | None:
        """The measured SYNC period: the median of the spacings between the reads of consecutive
        SYNCs, over the last ``window`` of them, those of SYNCs read together (0) left out. Each
        late read stretches one spacing and shortens the next, a backlog read at once gives one
        long spacing, a skipped slot one of two periods: the median keeps the host's period while
        most spacings are untouched. None until there are 8 (or half the window, if smaller)."""
        sp = [x for x in self._spacings if x > 0]
        if len(sp) < min(8, self.window // 2):
            return None
        return median(sp)

    def arrival(self, counter: int, read_s: float) -> float:
        """The instant the chips take SYNC ``counter`` (16 bits), read at ``read_s``, to have arrived."""
        c = int(counter) & 0xFFFF
        kept = self._kept.get(c)
        if kept is not None and read_s - kept <= self.max_gap_s:  # the same SYNC on another port
            self.copies += 1
            return kept if read_s >= kept else read_s
        last = self._last
        a = read_s
        if last is not None and (c - last[0]) & 0xFFFF == 1 and 0 <= read_s - last[2] <= self.max_gap_s:
            p = self.period_s  # of the reads before this one
            if p is not None:
                ac, aa = self._anchor if self._anchor is not None else (last[0], last[1])
                a = min(read_s, aa + ((c - ac) & 0xFFFF) * p + self.slack_s)
                a = max(a, last[1])  # never before the previous one
                # still behind its read while the reads come one period apart: not a stalled reader
                # (it reads a backlog at once, then on time) but a host that sent late or skipped
                # a slot and keeps its new phase; after `steady` such SYNCs, take the reads again
                if a < read_s and abs(read_s - last[2] - p) <= self.slack_s:
                    self._steady += 1
                    if self._steady >= self.steady:
                        a, self._steady = read_s, 0
                        self.rephased += 1
                else:
                    self._steady = 0
            self._spacings.append(read_s - last[2])
        else:
            self._spacings.clear()
        if a < read_s:
            self.pulled += 1
            self.pulled_s += read_s - a
        else:
            self._anchor = (c, a)
        self._last = (c, a, read_s)
        self._kept[c] = a
        self._kept.move_to_end(c)
        if len(self._kept) > KEPT:
            self._kept.popitem(last=False)
        return a
