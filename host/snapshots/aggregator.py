"""The snapshot aggregator: SAMPLE and SNAPSHOT frames grouped by SYNC counter into lattice snapshots.

Every streaming chip answers SYNC ``counter`` with a SAMPLE carrying that counter (docs/protocol.md
§5.1); a gateway may instead send SNAPSHOT frames carrying many links at once. The aggregator keeps
a bounded set of *open* counters, scatters incoming samples into per-counter buffers (numpy,
vectorised: a batch of node ids becomes link indices through one lookup array), and emits a
`LatticeSnapshot` when a counter is complete, or at its deadline with the missing links masked.
The SNAPSHOT frames of one read go in together (`Aggregator.ingest_snapshots`: one numpy pass per
run of frames, exactly what one frame at a time gives).

Sans-I/O (docs/design.md §8): every call that may emit takes ``now`` (host monotonic seconds); the
aggregator reads no clock, holds no lock and starts no thread. Emitted snapshots are handed to
``on_snapshot`` and kept for `Aggregator.drain`. For threads — a receive thread per bus and a SYNC
thread feeding one aggregator, consumers waiting for snapshots — `host.snapshots.feed.SnapshotFeed` wraps it:
the lock, the clock, the queue consumers block on, and the one place snapshots are corrected.

Rules (all counted in `AggregatorStats`, none raises):

* Counters compare in serial arithmetic mod 2^16 (RFC 1982 style): ``a`` is newer than ``b`` if
  ``(a - b) mod 65536`` is in 1..32767, so 0x0000 follows 0xFFFF.
* Snapshots are emitted in counter order. An incomplete counter holds the newer ones back until it
  completes or its deadline passes.
* A frame for a counter not newer than the last emitted one is *late*; one older than ``max_age`` counters behind the
  newest is *late* too; a second frame for the same (counter, link) is a *duplicate* (the first is
  kept); a frame from a node the layout does not know is *unknown* (counted per node, bounded).
* At most ``max_open`` counters are open; opening one more emits the oldest (masked): memory is
  bounded whatever the input.
* The output buffer holds ``queue_size`` snapshots not yet drained; beyond it the oldest are
  dropped (newest wins) and counted in ``dropped`` (so is what `host.snapshots.feed.SnapshotFeed.latest`
  skips for a slow consumer).
* **The deadline** (`host.snapshots.deadline.DeadlinePolicy`): fixed, or, with ``min_deadline_s`` and
  ``max_deadline_s``, adapted to the measured SYNC -> last-frame latency (one measurement per
  emitted snapshot, and one per batch of late frames).
* **Counter trust** (`host.snapshots.counter_trust.CounterTrust`): which counters may open a snapshot — any
  frame's (``trust="frames"``), only the SYNCs the host sent (``"sent"``), or a gateway's sequence,
  followed through a restart (``"follow"``).
* **Input watermark** (``hold_for_input``, the host's): a deadline says how long to wait for
  frames *after they could have been read*, not how long the host's threads happened to sleep. When
  the whole host process is not scheduled for 100 ms (a loaded machine), the frames of the counters
  opened meanwhile wait in the port's buffer; the thread that wakes first must not give those
  counters up before the receive thread has read them. So, per bus, ``input_mark`` is how far the
  input has been read: the SYNC time of the newest counter whose frames were ingested (a serial
  line and a CAN bus deliver in order, so a counter's frames came before later counters'), or the
  clock when the bus was found idle (`input_idle`: its reader found nothing). A counter past its
  deadline is emitted incomplete only once every bus's mark is a deadline past its SYNC, or
  `INPUT_HOLD_S` after its deadline at the latest (a reader that stopped); such waits are
  counted in ``input_holds``. Measured with ``benchmarks/bench_soak.py`` (docs/host.md).
* **Who is missing** (``miss_run``): per link, how many snapshots in a row were emitted without it
  while at least half of the other expected links arrived — the host's watchdog blames a chip
  only on this evidence (its neighbours' frames for the same counters came, its did not).
"""

from __future__ import annotations

from collections import deque
from typing import Callable, Iterable

import numpy as np

from host.snapshots.counter_trust import MAX_AGE, MAX_JUMP, OPEN, RESYNC, CounterTrust, serial_diff
from host.snapshots.deadline import DeadlinePolicy
from host.snapshots.snapshot import AggregatorStats, LatticeSnapshot, LinkFlag
from protocol.constants import G0, SampleStatus, nominal_sensitivity
from protocol.imu_units import gyro_counts_to_si, mag_counts_to_si
from protocol.messages import (
    SAMPLE_WORD_SIZE,
    TIME_UNKNOWN,
    ImuBatch,
    ImuSample,
    Sample,
    SampleBatch,
    Snapshot,
    SnapshotFrames,
    SnapshotImu,
    unpack_sample_words,
    unpack_snapshots,
)

__all__ = ["Aggregator", "serial_diff", "INPUT_HOLD_S"]

_MOD = 1 << 16
#: holding for input (``hold_for_input``), a counter waits at most this long past its deadline
#: (a bus whose reader stopped must not stop the snapshots), seconds
INPUT_HOLD_S = 0.25
_HALF = 1 << 15


class Aggregator:
    """Group samples by SYNC counter into `LatticeSnapshot` s.

    Parameters
    ----------
    n_links : int
        Links in the lattice (`protocol.lattice.Lattice.n_links`).
    node_to_link : mapping or ndarray, optional
        Node id -> link index for per-chip SAMPLE frames (a dict, or an int array of 65536 with -1
        for unknown). Default: node ``k`` is link ``k - 1`` (the host's assignment rule).
    offset : ndarray, shape (n_links, 3), optional
        Zero-g offset in ADC counts per link and axis (CAL_DATA ``offset_q4 / 16``). Default 0.
    sensitivity : ndarray, shape (n_links, 3), optional
        Counts per g per link and axis. Default: nominal for ±2 g (1024).
    deadline_s : float
        An incomplete counter is emitted (masked) this long after it opened (the starting value
        when adaptive).
    min_deadline_s, max_deadline_s : float, optional
        Both given: the deadline adapts to the measured latency within these bounds
        (`host.snapshots.deadline.DeadlinePolicy`). Otherwise it stays ``deadline_s``.
    max_open : int
        At most this many counters are open at once.
    max_age : int
        Frames more than this many counters behind the newest open one are late.
    queue_size : int
        Snapshots kept for `drain` (newest wins; the dropped ones counted in ``stats.dropped``).
    n_buses : int
        Number of buses feeding this aggregator (for per-bus statistics).
    on_snapshot : callable, optional
        Called with each emitted snapshot, during the call that emitted it, in addition to the
        buffer `drain` empties.
    trust, max_jump, resync_after
        Which counters may open a snapshot (`host.snapshots.counter_trust.CounterTrust`).
    hold_for_input : bool
        A counter past its deadline is emitted only once the input is known to have been read past
        it (`input_idle`, module docstring "Input watermark"); at most `INPUT_HOLD_S` longer. Off:
        the deadline alone decides (a replay, which re-decides at recorded times, leaves it off).
    emit_at_deadline : bool
        False: a counter is emitted only when it completes, by `emit_through` or `flush` — never by
        its deadline (a replay that follows the host's recorded emissions: the host's deadline
        adapted and held for input as it ran; this one would emit a counter in the middle of a
        read the host had taken in whole).

    Attributes
    ----------
    wall_offset : float
        Unix seconds minus monotonic seconds: a snapshot's ``wall_time`` is its ``timestamp`` plus
        this, as set when its counter opened (the owner keeps it current; 0 by default).
    """

    #: the shortcuts for the common cases (`_scatter`: one counter's fresh samples; `_emit`: every
    #: link there); False: the general path alone, what the tests hold the shortcuts to
    _FAST = True

    def __init__(self, n_links: int, node_to_link=None, *, offset=None, sensitivity=None,
                 deadline_s: float = 0.05, max_open: int = 32, max_age: int = MAX_AGE, queue_size: int = 64,
                 n_buses: int = 1, on_snapshot: Callable[[LatticeSnapshot], None] | None = None,
                 min_deadline_s: float | None = None,
                 max_deadline_s: float | None = None, trust: str = "frames", max_jump: int = MAX_JUMP,
                 resync_after: int = 3, hold_for_input: bool = False, emit_at_deadline: bool = True) -> None:
        if not isinstance(n_links, (int, np.integer)) or n_links < 1:
            raise ValueError(f"Invalid n_links: {n_links!r} (need an integer >= 1)")
        if max_open < 1:
            raise ValueError(f"Invalid max_open: {max_open!r} (need >= 1)")
        self.n_links = int(n_links)
        #: how long an open counter waits for its missing links (`host.snapshots.deadline.DeadlinePolicy`)
        self.deadline = DeadlinePolicy(deadline_s, min_deadline_s, max_deadline_s)
        self.max_open = int(max_open)
        self.emit_at_deadline = bool(emit_at_deadline)
        self.max_age = int(max_age)
        self.on_snapshot = on_snapshot
        self.wall_offset = 0.0
        self.stats = AggregatorStats(self.n_links, n_buses)
        self._out: deque[LatticeSnapshot] = deque()
        self.queue_size = int(queue_size)
        self._lut = self._node_lut(node_to_link)  # node id -> link, -1 = unknown
        self._offset, self._sens = self._checked_calibration(offset, sensitivity)  # per link and axis
        #: links expected in every snapshot (a snapshot is complete when all of these arrived)
        self.expected = np.ones(self.n_links, dtype=bool)
        #: links with no chip assigned (flagged UNASSIGNED, never expected)
        self.unassigned = np.zeros(self.n_links, dtype=bool)
        self.silent = np.zeros(self.n_links, dtype=bool)
        # per-slot buffers
        S, L = self.max_open, self.n_links
        self._counts = np.zeros((S, L, 3), dtype=np.int16)
        self._status = np.zeros((S, L), dtype=np.uint8)
        self._got = np.zeros((S, L), dtype=bool)
        self._n_got = np.zeros(S, dtype=np.int64)
        self._slot_counter = np.full(S, -1, dtype=np.int64)
        self._slot_t0 = np.zeros(S)
        self._slot_wall = np.zeros(S)
        self._slot_first = np.full(S, np.nan)
        self._slot_last = np.full(S, np.nan)
        self._free = list(range(S - 1, -1, -1))
        self._open: list[int] = []  # slots, in counter order (oldest first)
        self._slot_of = np.full(_MOD, -1, dtype=np.int64)  # counter -> slot
        self._newest: int | None = None  # newest counter opened
        self._last_emitted: int | None = None
        self._stamp = np.zeros(S * L, dtype=np.int64)  # scratch for in-batch duplicates
        self._t0_of = np.full(_MOD, np.nan)  # counter -> when it opened (latency of late frames)
        #: per link: snapshots in a row emitted without it while most expected links arrived
        self.miss_run = np.zeros(L, dtype=np.int64)
        #: which counters may open a snapshot (`host.snapshots.counter_trust.CounterTrust`)
        self.counter_trust = CounterTrust(trust, max_jump, resync_after, self.max_age)
        #: CONFIG_IMU ranges the chips were given (docs §16.2): how IMU counts convert (the owner sets them)
        self.gyro_range, self.mag_range = 3, 0
        #: CONFIG_IMU format the chips were given (SampleFormat: 0 accelerometer only, 1 + gyroscope,
        #: 2 + magnetometer; the owner sets it): with 1 or 2 every snapshot carries the IMU arrays, NaN
        #: where no record came, so a snapshot none of whose records arrived (a SYNC the chips' frames
        #: missed, the run's last counter) is still a 6/9-axis snapshot to its readers
        self.imu_format = 0
        self._imu: dict[int, list] = {}  # open counter -> [gyro (L, 3), mag (L, 3) or None, time (L,)], SI
        self.hold_for_input = bool(hold_for_input)
        self._held = -1  # the slot last held for input (counted once in stats.input_holds)
        #: per bus: input read up to here (the newest SYNC time of a counter whose frames were
        #: ingested, or when the bus was last found idle); -inf: nothing yet (module docstring)
        self.input_mark = np.full(max(1, int(n_buses)), -np.inf)

    # -- configuration ---------------------------------------------------------------------
    def set_node_map(self, node_to_link=None) -> None:
        """Node id -> link index (dict or array of 65536, -1 = unknown). None: node k -> link k-1."""
        self._lut = self._node_lut(node_to_link)

    def _node_lut(self, node_to_link) -> np.ndarray:
        lut = np.full(_MOD, -1, dtype=np.int64)
        if node_to_link is None:
            n = min(self.n_links, _MOD - 1)
            lut[1:n + 1] = np.arange(n)
        elif isinstance(node_to_link, dict):
            for node, link in node_to_link.items():
                if not 0 <= link < self.n_links:
                    raise ValueError(f"Invalid link {link} for node {node} ({self.n_links} links)")
                lut[int(node)] = int(link)
        else:
            arr = np.asarray(node_to_link, dtype=np.int64)
            if arr.shape != (_MOD,):
                raise ValueError(f"Expected `node_to_link` to have shape (65536,), got {arr.shape}.")
            lut[:] = arr
        return lut

    def link_of(self, node):
        """Link of node id ``node`` (an int or an array of them), -1 where the map has none."""
        return self._lut[node]

    def set_calibration(self, offset=None, sensitivity=None) -> None:
        """Per-link calibration: ``offset`` counts and ``sensitivity`` counts/g, each (n_links, 3)."""
        self._offset, self._sens = self._checked_calibration(offset, sensitivity)

    def _checked_calibration(self, offset, sensitivity) -> tuple[np.ndarray, np.ndarray]:
        L = self.n_links
        off = np.zeros((L, 3)) if offset is None else np.asarray(offset, dtype=float)
        sens = np.full((L, 3), nominal_sensitivity()) if sensitivity is None else np.asarray(sensitivity, dtype=float)
        for name, a in (("offset", off), ("sensitivity", sens)):
            if a.shape != (L, 3):
                raise ValueError(f"Expected `{name}` to have shape ({L}, 3), got {a.shape}.")
        if not np.all(np.isfinite(sens) & (sens > 0)):
            raise ValueError("Invalid sensitivity: every value must be finite and > 0")
        return off, sens

    def mark_silent(self, link: int, silent: bool, now: float) -> None:
        """Watchdog: a silent link is not waited for (and flagged SILENT) until it speaks again."""
        self.silent[link] = silent
        self.expected[link] = not silent and not self.unassigned[link]
        self._pump(now)

    def set_unassigned(self, unassigned: np.ndarray, now: float) -> None:
        """Links with no chip assigned: flagged UNASSIGNED, never expected."""
        self.unassigned = np.asarray(unassigned, dtype=bool).copy()
        self.expected = ~self.unassigned & ~self.silent
        self._pump(now)

    # -- counters --------------------------------------------------------------------------
    def open_counter(self, counter: int, now: float, *, restart: bool = False) -> bool:
        """The host sent (or saw) SYNC ``counter`` at ``now``: open it so its timestamp and
        deadline start at the SYNC. Returns False if it is late (not newer than the last emitted
        counter). ``restart=True`` starts a new counter sequence: every open counter is emitted and
        the ordering history is forgotten (the host does this when it (re)starts streaming)."""
        if restart:
            self.restart(now)
        slot = self._slot_for(int(counter) & 0xFFFF, now)
        self._pump(now)
        return slot >= 0

    @property
    def newest(self) -> int | None:
        """The newest counter opened (None: none since the sequence began)."""
        return self._newest

    def restart(self, now: float) -> None:
        """A new counter sequence begins (the host (re)starts streaming): emit what is open and
        forget the ordering history, so the new counters are not taken for late ones."""
        while self._open:
            self._emit(self._open[0], now)
        self._last_emitted = None
        self._newest = None

    def _slot_for(self, c: int, now: float, from_frame: bool = False) -> int:
        """Slot of counter ``c``, opening it if allowed; -1 if late, -2 if stray (counter trust)."""
        s = int(self._slot_of[c])
        if s >= 0:
            return s
        verdict = self._trust_verdict(c, now, from_frame)
        if verdict < 0:
            return verdict
        # snapshots leave in counter order, so anything not newer than the last emitted is late
        if self._last_emitted is not None and serial_diff(c, self._last_emitted) <= 0:
            return -1
        if self._newest is not None and serial_diff(c, self._newest) < -self.max_age:
            return -1
        if not self._free:
            self._emit(self._open[0], now, evicted=True)
            if self._last_emitted is not None and serial_diff(c, self._last_emitted) <= 0:
                return -1
        s = self._free.pop()
        self._slot_of[c] = s
        self._slot_counter[s] = c
        self._slot_t0[s] = now
        self._t0_of[c] = now
        self._slot_wall[s] = now + self.wall_offset
        self._slot_first[s] = np.nan
        self._slot_last[s] = np.nan
        self._got[s] = False
        self._n_got[s] = 0
        # insert in counter order
        if self._newest is None or serial_diff(c, self._newest) > 0:
            self._newest = c
            self._open.append(s)
        else:
            k = len(self._open)
            while k > 0 and serial_diff(int(self._slot_counter[self._open[k - 1]]), c) > 0:
                k -= 1
            self._open.insert(k, s)
        return s

    # -- counter trust (`host.snapshots.counter_trust`; only `_slot_for` asks it) --------------------------
    def set_trust(self, trust: str) -> None:
        """Switch the rule (the host does when it changes between driving and following SYNC)."""
        ct = self.counter_trust
        self.counter_trust = CounterTrust(trust, ct.max_jump, ct.resync_after, self.max_age)

    @property
    def trust(self) -> str:
        """The counter-trust rule: "frames", "sent" or "follow"."""
        return self.counter_trust.trust

    @property
    def resync_events(self):
        """``(previous newest, counter followed)`` of the newest resyncs (`CounterTrust.resync_events`)."""
        return self.counter_trust.resync_events

    def _trust_verdict(self, c: int, now: float, from_frame: bool) -> int:
        """0: ``c`` may be opened; -1: late; -2: stray. On a resync (follow) what is open is emitted
        and the ordering history forgotten first."""
        v = self.counter_trust.verdict(c, self._newest, self._last_emitted, from_frame)
        if v != RESYNC:
            return v
        while self._open:
            self._emit(self._open[0], now)
        self._last_emitted = None
        self._newest = None
        self.stats.resyncs += 1
        return OPEN

    # -- the deadline (`host.snapshots.deadline`) --------------------------------------------------------
    @property
    def deadline_s(self) -> float:
        """The deadline now (`DeadlinePolicy.deadline_s`)."""
        return self.deadline.deadline_s

    @property
    def adaptive(self) -> bool:
        """Whether the deadline adapts to measured latency (settable: False keeps it where it is)."""
        return self.deadline.adaptive

    @adaptive.setter
    def adaptive(self, on: bool) -> None:
        self.deadline.adaptive = bool(on)

    @property
    def min_deadline_s(self) -> float:
        return self.deadline.min_deadline_s

    @property
    def max_deadline_s(self) -> float:
        return self.deadline.max_deadline_s

    def _measure(self, latency_s: float, late: bool = False) -> None:
        """One latency to the deadline policy; its counts to ``stats``."""
        dl = self.deadline
        dl.measure(latency_s, late)
        self.stats.deadline_changes = dl.changes
        self.stats.late_raises = dl.late_raises

    # -- ingest ----------------------------------------------------------------------------
    def ingest(self, events: Iterable, bus: int = 0, *, now: float) -> None:
        """Feed decoder/transport events that arrived at ``now``; anything but samples (SAMPLE,
        SampleBatch, SNAPSHOT, SnapshotFrames, IMU records) is ignored (a replay at a recorded
        ``now`` decides alike)."""
        snaps: list[Snapshot] = []  # a run of SNAPSHOT frames: ingested together, in one pass
        for ev in events:
            if isinstance(ev, Snapshot):
                snaps.append(ev)
                continue
            if type(ev) is SnapshotFrames:  # a run the decoder unpacked already
                if snaps:
                    self.ingest_snapshots(snaps, bus, now=now)
                    snaps = []
                self.ingest_snapshot_frames(ev, bus, now=now)
                continue
            if isinstance(ev, (ImuSample, SnapshotImu, ImuBatch)):
                if snaps:
                    self.ingest_snapshots(snaps, bus, now=now)
                    snaps = []
                self.ingest_imu(ev, bus, now=now)
                continue
            if not isinstance(ev, (SampleBatch, Sample)):
                continue  # ignored: does not end a run
            if snaps:
                self.ingest_snapshots(snaps, bus, now=now)
                snaps = []
            if isinstance(ev, SampleBatch):
                self.ingest_batch(ev.node, ev.counter, ev.counts, ev.status, bus, now=now)
            else:
                self.ingest_batch(np.array([ev.node], dtype=np.uint16), np.array([ev.counter], dtype=np.uint16),
                                  np.array([[ev.x, ev.y, ev.z]], dtype=np.int16),
                                  np.array([ev.status], dtype=np.uint8), bus, now=now)
        if snaps:
            self.ingest_snapshots(snaps, bus, now=now)

    def ingest_batch(self, node: np.ndarray, counter: np.ndarray, counts: np.ndarray, status: np.ndarray,
                     bus: int = 0, *, now: float) -> None:
        """Per-chip samples: arrays of equal length n (node u16, counter u16, counts (n, 3), status)."""
        links = self._lut[node]
        known = links >= 0
        if not known.all():
            self._count_unknown(node[~known], bus)
            links, counter, counts, status = links[known], counter[known], counts[known], status[known]
        self._scatter(links, counter, counts, status, bus, now)

    def ingest_imu(self, ev, bus: int = 0, *, now: float) -> None:
        """An IMU_SAMPLE or a SNAPSHOT_IMU (docs §16): the accelerometer part as any sample, the
        gyroscope, magnetometer and sample time kept beside it for the counter's snapshot (the first
        record of a link and counter wins, as for the accelerometer)."""
        if isinstance(ev, ImuSample):
            node = np.array([ev.node], dtype=np.uint16)
            counter = np.array([ev.counter], dtype=np.uint16)
            counts = np.array([[ev.x, ev.y, ev.z]], dtype=np.int16)
            status = np.array([ev.status], dtype=np.uint8)
            t_us, gyro = np.array([ev.time_us]), np.array([ev.gyro])
            mag = None if ev.mx is None else np.array([ev.mag])
        elif isinstance(ev, ImuBatch):
            node, counter, counts, status, t_us, gyro, mag = (ev.node, ev.counter, ev.counts, ev.status, ev.time_us,
                                                              ev.gyro, ev.mag)
        else:
            counts, status, t_us, gyro, mag = ev.arrays()
            link = ev.first_link + np.arange(counts.shape[0], dtype=np.int64)
            counter = np.full(link.shape[0], ev.counter, dtype=np.uint16)
            self._imu_extras(link, counter, t_us, gyro, mag)
            self._scatter_inside(link, counter, counts, status, bus, now)
            self._imu_prune(counter)
            return
        self._imu_extras(self._lut[node], counter, t_us, gyro, mag)
        self.ingest_batch(node, counter, counts, status, bus, now=now)
        self._imu_prune(counter)

    def _imu_extras(self, link, counter, t_us, gyro, mag) -> None:
        """Keep the records' gyroscope, magnetometer and time beside their counters (first per link wins)."""
        ok = (link >= 0) & (link < self.n_links)
        for c in np.unique(counter[ok]).tolist():
            sel = ok & (counter == c)
            e = self._imu.get(c)
            if e is None:
                L = self.n_links
                e = self._imu[c] = [np.full((L, 3), np.nan), None, np.full(L, np.nan)]
            lk = link[sel]
            new = np.isnan(e[0][lk, 0])
            lk = lk[new]
            e[0][lk] = gyro_counts_to_si(gyro[sel][new].astype(np.float64), self.gyro_range)
            t = t_us[sel][new].astype(np.float64)
            e[2][lk] = np.where(t == TIME_UNKNOWN, np.nan, t * 1e-6)
            if mag is not None:
                if e[1] is None:
                    e[1] = np.full((self.n_links, 3), np.nan)
                e[1][lk] = mag_counts_to_si(mag[sel][new].astype(np.float64), self.mag_range)

    def _imu_prune(self, counter) -> None:
        for c in np.unique(counter).tolist():
            if c in self._imu and self._slot_of[c] < 0:
                del self._imu[c]  # late or stray: its accelerometer part was not taken either

    def ingest_snapshot(self, snap: Snapshot, bus: int = 0, *, now: float) -> None:
        """A gateway's SNAPSHOT: links ``first_link ..`` of one counter."""
        counts, status = unpack_sample_words(snap.words)
        links = snap.first_link + np.arange(counts.shape[0], dtype=np.int64)
        counter = np.full(links.shape[0], snap.counter, dtype=np.uint16)
        self._scatter_inside(links, counter, counts, status, bus, now)

    def ingest_snapshots(self, frames: Iterable[Snapshot], bus: int = 0, *, now: float) -> None:
        """Many SNAPSHOT frames (what one read delivered), unpacked and scattered in one numpy pass:
        exactly what `ingest_snapshot` on each in turn, at the same ``now``, gives — the same
        snapshots, the same counts of late, duplicate, stray and out-of-range samples.

        One pass needs that nothing is emitted between two of the frames, so the frames are cut
        into runs: a run ends at the frame that completes the oldest open counter (one by one, it
        would be emitted there and later frames for it would be late); a frame whose counter is
        not open (it opens one, or is late or stray), and a frame while the oldest counter is past
        its deadline, go alone, as one by one. Live, a read of a
        packed gateway holds the frames of one or two counters: one or two passes.
        """
        frames = frames if isinstance(frames, list) else list(frames)
        if len(frames) <= 1:
            for f in frames:
                self.ingest_snapshot(f, bus, now=now)
            return
        counter, links, counts, status = unpack_snapshots(frames)
        sizes = np.fromiter((len(f.words) for f in frames), dtype=np.int64, count=len(frames)) // SAMPLE_WORD_SIZE
        self._ingest_runs(counter, links.astype(np.int64), counts, status, sizes, bus, now)

    def ingest_snapshot_frames(self, batch: SnapshotFrames, bus: int = 0, *, now: float) -> None:
        """`ingest_snapshots` of a `protocol.messages.SnapshotFrames` (the frames of one read that
        the stream decoder unpacked already): the same snapshots and counts."""
        if len(batch) == 1:
            self._scatter_inside(batch.link, batch.counter, batch.counts, batch.status, bus, now)
            return
        self._ingest_runs(batch.counter, batch.link, batch.counts, batch.status, batch.sizes, bus, now)

    def _ingest_runs(self, counter, links, counts, status, sizes, bus: int, now: float) -> None:
        """`ingest_snapshots` on unpacked frames: per sample ``counter``, ``links`` (int64),
        ``counts``, ``status``; per frame its sample count ``sizes``."""
        nf = sizes.shape[0]
        ends = np.cumsum(sizes)  # frame k: samples ends[k] - sizes[k] .. ends[k] - 1
        starts = ends - sizes
        fcounter = counter[starts]
        i = 0
        while i < nf:
            j = self._run_end(i, nf, fcounter, links, counter, starts, ends, now)
            a, b = int(starts[i]), int(ends[j - 1])
            self._scatter_inside(links[a:b], counter[a:b], counts[a:b], status[a:b], bus, now)
            i = j

    def _run_end(self, i: int, nf: int, fcounter, links, counter, starts, ends, now: float) -> int:
        """`ingest_snapshots`: frames ``i .. j-1`` may be scattered in one pass; returns ``j``."""
        if self._slot_of[int(fcounter[i])] < 0 or not self._open:
            return i + 1  # opens a counter, or late / stray: alone
        head = self._open[0]
        if self.emit_at_deadline and now - self._slot_t0[head] >= self.deadline_s:
            return i + 1  # the pump after this frame emits the head
        # frames of open counters, up to the first frame of a counter not open
        is_open = self._slot_of[fcounter[i:]] >= 0
        m = i + (int(np.argmin(is_open)) if not is_open.all() else nf - i)
        L = self.n_links
        # the frame that completes the head (the one-by-one pump would emit it right after). A
        # silent link's frame makes it expected again, which only delays completion — unless
        # nothing was expected: then it may complete the head at once, so go one at a time
        n_exp = int(np.count_nonzero(self.expected))
        if n_exp == 0:
            return i + 1 if self.silent.any() else m  # else the head waits for its deadline
        need = self.expected & ~self._got[head]
        n_need = int(np.count_nonzero(need))
        a, b = int(starts[i]), int(ends[m - 1])
        lk = links[a:b]
        pos = np.flatnonzero((counter[a:b] == self._slot_counter[head]) & (lk < L))
        if pos.size:
            pos = pos[need[lk[pos]]]
        if n_need == 0 or pos.size < n_need:
            return m if n_need else i + 1
        u, first = np.unique(lk[pos], return_index=True)
        if u.size < n_need:
            return m
        done_at = a + int(np.sort(pos[first])[n_need - 1])  # the sample that completes it
        return int(np.searchsorted(ends, done_at, side="right")) + 1

    def _scatter_inside(self, links, counter, counts, status, bus: int, now: float) -> None:
        """SNAPSHOT samples: those beyond the lattice are counted (``out_of_range``), the rest scattered."""
        inside = links < self.n_links
        if not inside.all():
            self.stats.out_of_range += int(np.count_nonzero(~inside))
            links, counter, counts, status = links[inside], counter[inside], counts[inside], status[inside]
        self._scatter(links, counter, counts, status, bus, now)

    def _count_unknown(self, nodes: np.ndarray, bus: int) -> None:
        st = self.stats
        st.unknown += int(nodes.shape[0])
        st.bus_unknown[bus] += int(nodes.shape[0])
        u, c = np.unique(nodes, return_counts=True)
        for n, k in zip(u.tolist(), c.tolist()):
            if n in st.unknown_nodes or len(st.unknown_nodes) < 256:
                st.unknown_nodes[n] = st.unknown_nodes.get(n, 0) + k

    def _scatter(self, links: np.ndarray, counter: np.ndarray, counts: np.ndarray, status: np.ndarray,
                 bus: int, now: float) -> None:
        n = links.shape[0]
        if n == 0:
            return
        st = self.stats
        st.bus_frames[bus] += n
        st.link_last_seen[links] = now  # the chip is alive, even if its frame turns out late
        if self.hold_for_input and 0 <= bus < self.input_mark.shape[0]:
            # the bus was read up to frames answering this SYNC (a serial line, a CAN bus: in order)
            t0 = self._t0_of[counter]
            top = t0.max()
            if top != top:  # a counter never opened (NaN): the newest of those that were
                top = np.nanmax(t0) if np.isfinite(t0).any() else None
            if top is not None:
                self.input_mark[bus] = max(self.input_mark[bus], float(top))
        if self.silent.any():  # links that were silent and speak again are waited for again
            back = self.silent[links]
            if back.any():
                for link in np.unique(links[back]).tolist():
                    self.silent[link] = False
                    self.expected[link] = not self.unassigned[link]
                    self.miss_run[link] = 0
        slots = self._slot_of[counter]
        if (slots < 0).any():
            missing = np.unique(counter[slots < 0])
            # open in counter order relative to the newest, oldest first
            if missing.shape[0] > 1 and self._newest is not None:
                missing = missing[np.argsort(serial_diff(missing.astype(np.int64), self._newest), kind="stable")]
            elif missing.shape[0] > 1:
                missing = missing[np.argsort(serial_diff(missing.astype(np.int64), int(missing[-1])), kind="stable")]
            stray_c = [c for c in missing.tolist() if self._slot_for(c, now, from_frame=True) == -2]
            slots = self._slot_of[counter]
            late = slots < 0
            if stray_c:  # counter trust: dropped, counted apart from late frames
                stray = late & np.isin(counter, np.asarray(stray_c, dtype=counter.dtype))
                st.stray += int(np.count_nonzero(stray))
                late &= ~stray
                ok = slots >= 0
                links, counter, counts, status, slots = links[ok], counter[ok], counts[ok], status[ok], slots[ok]
                late = late[ok]
                n = links.shape[0]
                if n == 0:
                    return
            if late.any():
                nl = int(np.count_nonzero(late))
                if self.adaptive:  # how late they were: a deadline too short grows at once
                    t0 = self._t0_of[counter[late].astype(np.int64)]
                    t0 = t0[np.isfinite(t0) & (now - t0 < 4 * self.max_deadline_s)]
                    if t0.size:
                        self._measure(float(now - t0.min()), late=True)
                st.late += nl
                st.bus_late[bus] += nl
                st.link_late += np.bincount(links[late], minlength=self.n_links)
                ok = ~late
                links, counter, counts, status, slots = links[ok], counter[ok], counts[ok], status[ok], slots[ok]
                n = links.shape[0]
                if n == 0:
                    return
        L = self.n_links
        if self._FAST and slots[0] == slots[-1]:
            s0, a, b = int(slots[0]), int(links[0]), int(links[-1]) + 1
            if (b - a == n and (slots == s0).all() and (n == 1 or (np.diff(links) == 1).all())
                    and not self._got[s0, a:b].any()):
                # a packing gateway's read: one counter, a run of consecutive links none of which
                # came before; slices instead of gathers and scatters (the general path's result)
                block = slice(a, b)
                self._counts[s0, block] = counts
                self._status[s0, block] = status
                self._got[s0, block] = True
                st.samples += n
                self._one_slot(s0, block, n, now)
                return
        flat = slots * L + links
        got_flat = self._got.reshape(-1)
        fresh = ~got_flat[flat]
        # first occurrence within the batch wins
        idx = np.arange(n)
        stamp = self._stamp
        stamp[flat[::-1]] = idx[::-1]
        fresh &= stamp[flat] == idx
        n_fresh = int(np.count_nonzero(fresh))
        if n_fresh != n:
            dup = ~fresh
            nd = n - n_fresh
            st.duplicates += nd
            st.bus_duplicates[bus] += nd
            st.link_duplicates += np.bincount(links[dup], minlength=L)
            flat, links, counts, status, slots = flat[fresh], links[fresh], counts[fresh], status[fresh], slots[fresh]
        self._counts.reshape(-1, 3)[flat] = counts
        self._status.reshape(-1)[flat] = status
        got_flat[flat] = True
        st.samples += n_fresh
        if n_fresh and self._FAST and slots[0] == slots[-1] and (slots == slots[0]).all():
            # every fresh sample for one counter (a packing gateway's read): each link once, so
            # the per-link counts and latencies take the links directly, without an array per
            # link of the lattice
            self._one_slot(int(slots[0]), links, n_fresh, now)
            return
        per_link = np.bincount(links, minlength=L)
        st.link_frames += per_link
        lat = now - self._slot_t0[slots]
        if n_fresh and per_link.max() > 1:
            # a link in several counters' frames: its EWMA steps once per frame, in order, as
            # one frame at a time would (one step per occurrence rank, the links unique in each)
            order = np.argsort(links, kind="stable")
            sl = links[order]
            k = np.arange(n_fresh)
            run0 = np.maximum.accumulate(np.where(np.r_[True, sl[1:] != sl[:-1]], k, 0))
            rank = np.empty(n_fresh, dtype=np.int64)
            rank[order] = k - run0
            for r in range(int(rank.max()) + 1):
                sel = rank == r
                self._ewma_latency(links[sel], lat[sel])
        else:
            self._ewma_latency(links, lat)
        touched = np.bincount(slots, minlength=self.max_open)
        self._n_got += touched
        for s in np.flatnonzero(touched).tolist():
            t_rel = now - self._slot_t0[s]
            if np.isnan(self._slot_first[s]):
                self._slot_first[s] = t_rel
            self._slot_last[s] = t_rel
        self._pump(now)

    def _one_slot(self, s: int, links, n_fresh: int, now: float) -> None:
        """`_scatter`'s bookkeeping after ``n_fresh`` fresh samples of slot ``s`` alone, each link
        once (``links``: an index array or a slice of the links)."""
        self.stats.link_frames[links] += 1
        t_rel = now - self._slot_t0[s]
        self._ewma_latency(links, t_rel)
        self._n_got[s] += n_fresh
        if np.isnan(self._slot_first[s]):
            self._slot_first[s] = t_rel
        self._slot_last[s] = t_rel
        self._pump(now)

    def _ewma_latency(self, links: np.ndarray, lat: np.ndarray) -> None:
        """One EWMA step of ``link_latency_s`` for each of ``links`` (unique)."""
        ll = self.stats.link_latency_s
        prev = ll[links]
        ll[links] = np.where(np.isnan(prev), lat, prev + 0.1 * (lat - prev))

    # -- emission --------------------------------------------------------------------------
    def _is_complete(self, s: int) -> bool:
        n_exp = int(np.count_nonzero(self.expected))
        if n_exp == 0 or self._n_got[s] < n_exp:  # nothing expected: wait for the deadline
            return False
        return bool(np.all(self._got[s] | ~self.expected))

    def poll(self, now: float) -> None:
        """Emit counters whose deadline has passed at ``now``. Call periodically (the host's threads do)."""
        self._pump(now)

    def input_idle(self, bus: int, now: float) -> None:
        """Bus ``bus`` had nothing more to read at ``now`` (its reader found it empty): the input
        watermark of an idle bus is the clock. Then emit what is due."""
        if 0 <= bus < self.input_mark.shape[0]:
            self.input_mark[bus] = max(self.input_mark[bus], now)
        self._pump(now)

    def _due(self, s: int, now: float) -> bool:
        """Whether open slot ``s`` is past its deadline and, holding for input, the input was read
        past that deadline (or `INPUT_HOLD_S` more passed)."""
        waited = now - self._slot_t0[s]
        if waited < self.deadline_s or not self.emit_at_deadline:
            return False
        if not self.hold_for_input or waited >= self.deadline_s + INPUT_HOLD_S:
            return True
        if float(self.input_mark.min()) - self._slot_t0[s] >= self.deadline_s:
            return True
        self.stats.input_holds += self._held != s
        self._held = s
        return False

    def _pump(self, now: float) -> None:
        while self._open:
            s = self._open[0]
            if self._is_complete(s) or self._due(s, now):
                self._emit(s, now)
            else:
                break

    def emit_through(self, counter: int, now: float) -> None:
        """Emit, at ``now``, open counters oldest first up to and including ``counter`` (if it is
        open), and the complete ones it held back: what a replay does where the recording says the host emitted ``counter`` at its
        deadline, whatever deadline this aggregator would have chosen."""
        if self._slot_of[int(counter) & 0xFFFF] < 0:
            return
        while self._open:
            s = self._open[0]
            c = int(self._slot_counter[s])
            self._emit(s, now)
            if c == int(counter) & 0xFFFF:
                break
        while self._open and self._is_complete(self._open[0]):  # held back behind it, as `poll`
            self._emit(self._open[0], now)

    def flush(self, now: float) -> None:
        """Emit every open counter at ``now`` (masked where incomplete), oldest first."""
        while self._open:
            self._emit(self._open[0], now)

    def _emit(self, s: int, now: float, evicted: bool = False) -> None:
        st = self.stats
        c = int(self._slot_counter[s])
        self._open.remove(s)
        got = self._got[s].copy()
        status = self._status[s].copy()
        every = self._FAST and bool(got.all())  # every link there (a complete 64x64 snapshot)
        if not every:
            status[~got] = 0
        valid = got & ((status & SampleStatus.INVALID) == 0)
        all_valid = every and bool(valid.all())
        complete = bool(self.expected.any() and np.all(got | ~self.expected))
        # counts_to_si's arithmetic, in place: (counts - offset) / sensitivity * G0
        readings = self._counts[s].astype(np.float64)
        readings -= self._offset
        readings /= self._sens
        readings *= G0
        counts = self._counts[s].copy()
        if not all_valid:
            readings[~valid] = np.nan
            counts[~valid] = 0
        counts.setflags(write=False)
        if not every:
            status |= np.where(got, 0, LinkFlag.MISSING).astype(np.uint8)
        if not self._FAST or self.silent.any():
            status |= np.where(self.silent, LinkFlag.SILENT, 0).astype(np.uint8)
        if not self._FAST or self.unassigned.any():
            status |= np.where(self.unassigned, LinkFlag.UNASSIGNED, 0).astype(np.uint8)
        readings.setflags(write=False)
        valid.setflags(write=False)
        status.setflags(write=False)
        imu = self._imu.pop(c, None)
        if imu is None and self.imu_format:
            L = self.n_links
            imu = [np.full((L, 3), np.nan), np.full((L, 3), np.nan) if self.imu_format >= 2 else None,
                   np.full(L, np.nan)]
        gyro = mag = t_s = None
        if imu is not None:
            gyro, mag, t_s = imu
            gyro[~valid] = np.nan
            t_s[~valid] = np.nan
            st.imu_links += int(np.count_nonzero(np.isfinite(gyro[:, 0])))
            if mag is not None:
                mag[~valid] = np.nan
                st.mag_links += int(np.count_nonzero(np.isfinite(mag[:, 0])))
        snap = LatticeSnapshot(c, float(self._slot_t0[s]), float(self._slot_wall[s]), readings, valid, status,
                               complete, float(now - self._slot_t0[s]), float(self._slot_first[s]),
                               float(self._slot_last[s]), counts, gyro, mag, t_s)
        st.emitted += 1
        assigned = ~self.unassigned
        st.assigned_links += int(np.count_nonzero(assigned))
        st.valid_links += int(np.count_nonzero(valid & assigned))
        exp = self.expected
        n_exp = int(np.count_nonzero(exp))
        if every:
            self.miss_run.fill(0)
        else:
            if n_exp and 2 * int(np.count_nonzero(got & exp)) >= n_exp:
                self.miss_run[exp & ~got] += 1  # its neighbours came for this counter, it did not
            self.miss_run[got] = 0
        if self.adaptive and not np.isnan(self._slot_last[s]) and (complete or got.any()):
            self._measure(float(self._slot_last[s]))
        if complete:
            st.complete += 1
        else:
            st.incomplete += 1
            st.link_missing += (~got & self.expected)
        if evicted:
            st.evicted += 1
        self._slot_of[c] = -1
        self._slot_counter[s] = -1
        self._last_emitted = c
        self._free.append(s)
        if len(self._out) >= self.queue_size:
            self._out.popleft()
            st.dropped += 1
        self._out.append(snap)
        if self.on_snapshot is not None:
            self.on_snapshot(snap)

    def reset_miss_runs(self) -> None:
        """Forget who was missing (the host (re)starts streaming)."""
        self.miss_run[:] = 0

    def completeness(self) -> dict:
        """Completeness so far: by snapshot (complete / emitted) and by valid link (valid samples of
        assigned links / assigned links, over every emitted snapshot), in %; None before any."""
        st = self.stats
        return {"complete_snapshots_pct": round(100.0 * st.complete / st.emitted, 3) if st.emitted else None,
                "valid_links_pct": round(100.0 * st.valid_links / st.assigned_links, 3) if st.assigned_links else None}

    # -- output ----------------------------------------------------------------------------
    def drain(self) -> list[LatticeSnapshot]:
        """Every snapshot emitted since the last call, oldest first."""
        out = list(self._out)
        self._out.clear()
        return out

    @property
    def n_open(self) -> int:
        return len(self._open)

    @property
    def pending(self) -> int:
        return len(self._out)
