"""Counter trust: which SYNC counters may open a snapshot in the aggregator.

Sans-I/O and clock-free: `CounterTrust.verdict` is told a counter not open yet, the newest counter
opened and the last one emitted, and answers OPEN, LATE, STRAY or RESYNC;
`host.snapshots.aggregator.Aggregator` acts on the answer (opens the counter, counts the frame, or on RESYNC
emits what is open and forgets its ordering history).

* ``"frames"`` (default, standalone use): any frame opens its counter (the old rule).
* ``"sent"`` (a host driving SYNC): only SYNCs (`Aggregator.open_counter`) open counters; a frame for
  a counter not open and newer than the newest sent is *stray* (dropped, counted), so a stray or
  foreign frame never moves the sequence and costs at most its own sample.
* ``"follow"`` (a gateway drives SYNC): SYNCs and frames open counters within
  ``-max_age .. +max_jump`` of the newest (a SYNC only when newer: a SYNC source never goes
  back; a SYNC up to ``max_jump`` behind is another port's copy of one already heard: late); one
  outside is stray, unless ``resync_after`` consecutive counters (each 1..2 after the
  previous) continue it: then the sequence has restarted or jumped (a gateway reset) and is
  followed — RESYNC, and ``resync_events`` records ``(old newest, new counter)``.

Counters compare in serial arithmetic mod 2^16 (`serial_diff`).
"""

from __future__ import annotations

from collections import deque

import numpy as np

__all__ = ["CounterTrust", "SyncCopies", "serial_diff", "OPEN", "LATE", "STRAY", "RESYNC", "TRUST_RULES", "MAX_JUMP", "MAX_AGE"]

_MOD = 1 << 16
_HALF = 1 << 15

OPEN = 0  #: the counter may be opened
LATE = -1  #: a frame for a counter already gone (or too old): late
STRAY = -2  #: a counter nobody sent (drive) or out of the sequence (follow): dropped
RESYNC = 1  #: follow: the sequence restarted or jumped; emit what is open, forget, then open it

TRUST_RULES = ("frames", "sent", "follow")
MAX_JUMP = 64  #: follow: how far ahead of the newest a counter may open (default)
MAX_AGE = 256  #: counters further behind the newest are late (default; the aggregator's too)


def serial_diff(a, b):
    """``a - b`` in serial arithmetic mod 2^16, in -32768..32767 (works on arrays).

    >>> serial_diff(0, 0xFFFF), serial_diff(0xFFFF, 0), serial_diff(5, 3)
    (1, -1, 2)
    """
    return ((np.asarray(a, dtype=np.int64) - b + _HALF) % _MOD) - _HALF if isinstance(a, np.ndarray) \
        else ((int(a) - int(b) + _HALF) % _MOD) - _HALF


class CounterTrust:
    """Which counters may open a snapshot (module docstring).

    Parameters
    ----------
    trust : {"frames", "sent", "follow"}
        The rule.
    max_jump : int
        Follow: how far ahead of the newest a counter may open.
    resync_after : int
        Follow: consecutive counters of a new sequence before it is followed.
    max_age : int
        Counters more than this behind the newest are late (the aggregator's ``max_age``).

    Attributes
    ----------
    resync_events : deque
        ``(previous newest, counter followed)`` of the newest 64 resyncs.
    """

    def __init__(self, trust: str = "frames", max_jump: int = MAX_JUMP, resync_after: int = 3,
                 max_age: int = MAX_AGE) -> None:
        if trust not in TRUST_RULES:
            raise ValueError(f"Invalid trust: {trust!r} (need 'frames', 'sent' or 'follow')")
        if not (isinstance(max_jump, int) and 1 <= max_jump < _HALF):
            raise ValueError(f"Invalid max_jump: {max_jump!r} (need 1..32767)")
        if not (isinstance(resync_after, int) and resync_after >= 1):
            raise ValueError(f"Invalid resync_after: {resync_after!r} (need >= 1)")
        self.trust = trust
        self.max_jump = max_jump
        self.resync_after = resync_after
        self.max_age = int(max_age)
        self.resync_events: deque = deque(maxlen=64)  #: (previous newest, counter followed)
        self._cand: int | None = None  # follow: newest counter of a candidate new sequence
        self._cand_run = 0

    def verdict(self, c: int, newest: int | None, last_emitted: int | None, from_frame: bool) -> int:
        """OPEN, LATE, STRAY or RESYNC for counter ``c`` (not open) heard in a frame (``from_frame``)
        or a SYNC, given the newest counter opened and the last emitted (None: none since the
        sequence began)."""
        if self.trust == "frames" or newest is None:
            if self.trust == "sent" and from_frame:
                return STRAY if last_emitted is None or serial_diff(c, last_emitted) > 0 else LATE
            return OPEN
        d = serial_diff(c, newest)
        if self.trust == "sent":
            if not from_frame:
                return OPEN
            return LATE if -self.max_age <= d <= 0 else STRAY  # sent recently and gone: late; else never sent
        # follow. A SYNC (not a frame) for a counter not newer than the newest is out of sequence
        # too: a SYNC source never goes back, unless it restarted (frames may just be late) —
        # except a SYNC up to max_jump behind: several gateways on one SYNC line (or one gateway
        # heard on several ports) bring every SYNC once per port, and a port read later than the
        # others brings its copy after the counter was emitted. That copy is late, and no start
        # of a new sequence: taken for one, a port lagging three SYNCs resynced the sheet again
        # and again (64x64 on five gateways: 561 resyncs, 1.3 % complete).
        if (-self.max_age <= d <= self.max_jump) and (from_frame or d > 0):
            if d > 0:
                self._cand, self._cand_run = None, 0
            return OPEN
        if not from_frame and -self.max_jump <= d <= 0:
            return LATE
        if self._cand is not None and 1 <= serial_diff(c, self._cand) <= 2:
            self._cand, self._cand_run = c, self._cand_run + 1
        elif self._cand is None or c != self._cand:
            self._cand, self._cand_run = c, 1
        if self._cand_run < self.resync_after:
            return STRAY
        self._cand, self._cand_run = None, 0
        self.resync_events.append((newest, c))
        return RESYNC


class SyncCopies:
    """A following host's SYNCs per port: which are copies of a SYNC already heard on another port.

    Gateways on one SYNC line (or one gateway heard on several ports) bring every SYNC once per
    port. `CounterTrust` takes a copy up to ``max_jump`` behind the newest for late; a port read
    further behind (a 64x64 sheet's five ports, one of them 0.5 s behind: 75 SYNCs) brought runs of
    copies that looked like a restarted source, and the host resynced back and forth between the
    ports (93 resyncs in 16 s, 2-4 % complete). What tells the two apart is the port's own
    sequence: a lagging port's SYNCs go *forward* from its previous one, a restarted source's go
    *back* (or jump) on every port.

    * A SYNC not newer than the newest counter opened that continues its port's own sequence
      (1..``max_jump`` after that port's previous), or is the port's first (up to ``max_age``
      behind), is a copy: `fresh` says False and the host does not hand it on, however far behind.
    * A SYNC that breaks its port's sequence is handed on, and so is the rest of that port's new run
      until one of its SYNCs is no longer behind the newest: `CounterTrust` counts them and follows
      the new sequence after ``resync_after`` (or finds them late, when other ports got there first).

    Sans-I/O: told the port, the counter and the newest counter opened.

    >>> s = SyncCopies(max_jump=64)
    >>> s.fresh(0, 100, None), s.fresh(0, 101, 100), s.fresh(1, 20, 101)   # port 1 first, 81 behind
    (True, True, False)
    >>> s.fresh(1, 21, 101), s.copies                                       # its own next: a copy
    (False, 2)
    >>> s.fresh(0, 0, 101), s.fresh(0, 1, 101), s.fresh(0, 2, 101)         # port 0 went back
    (True, True, True)
    """

    __slots__ = ("max_jump", "max_age", "copies", "_last", "_new_run")

    def __init__(self, max_jump: int = MAX_JUMP, max_age: int = MAX_AGE) -> None:
        self.max_jump = int(max_jump)
        self.max_age = int(max_age)
        self.copies = 0  #: SYNCs taken for another port's copy (not handed on)
        self._last: dict = {}
        self._new_run: set = set()  # ports whose own sequence broke, until they reach the newest

    def fresh(self, port, counter: int, newest: int | None) -> bool:
        """Whether SYNC ``counter`` heard on ``port`` goes on to the aggregator."""
        prev = self._last.get(port)
        self._last[port] = counter
        if newest is None:
            return True
        d = serial_diff(counter, newest)
        if d > 0:
            self._new_run.discard(port)
            return True
        continues = prev is None or 1 <= serial_diff(counter, prev) <= self.max_jump
        if d >= -self.max_jump:  # within CounterTrust's window: in step again
            self._new_run.discard(port)
            copy = continues
        elif prev is None:
            copy = d >= -self.max_age
        elif continues:
            copy = port not in self._new_run
        else:  # this port's own sequence went back or jumped: perhaps a restarted source
            self._new_run.add(port)
            copy = False
        if copy:
            self.copies += 1
        return not copy
