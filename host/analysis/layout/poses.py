"""Telling held poses apart from the readings alone: changed, then settled.

Sans-I/O: `PoseDetector` is fed ``(uid, reading, now)`` (one chip's reading, m/s², sensor frame,
and the time it was taken, seconds on any clock) and asked `poll(now)`; it never reads a clock.

How it decides (docs/host.md, "Learning the layout"):

* Readings are averaged per chip over **chunks** of ``chunk_s`` (0.1 s): a chunk's mean has the
  sensor noise of one sample over the square root of the samples in it.
* The sheet is **settled** when, over the last ``settle_s`` of chunks, at least
  ``settle_fraction`` of the chips heard in that window kept every chunk's mean within
  ``settle_deg`` of their window mean (the angle between the two directions), each chip heard in
  at least half of the window's chunks.
* A settled window is a **new pose** when it differs from the pose taken before: at least
  ``change_fraction`` of its chips lie more than ``change_deg`` from where that pose had them.
  The first settled window is the first pose.
* Between poses the sheet must have **moved**: after a pose is taken the detector holds it until a
  chunk has ``change_fraction`` of the chips more than ``change_deg`` away; only then does the next
  settled window count. A sheet put back where it was settles as the same pose and is not taken
  twice.

A pose is reported once, as soon as its window has settled (`Pose`: the mean reading of every
chip over that window), so a prompt for the next step can follow at once.

>>> det = PoseDetector(chunk_s=0.1, settle_s=0.5)
>>> flat = (0.0, 0.0, 9.80665)
>>> poses = []
>>> for k in range(100):  # 2 s flat at 50 Hz, two chips
...     t = k / 50
...     det.add(0xA, flat, t); det.add(0xB, flat, t)
...     p = det.poll(t)
...     if p is not None:
...         poses.append((p.index, round(p.end_s, 2), p.uids.tolist()))
>>> poses
[(0, 0.5, [10, 11])]
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

__all__ = ["Pose", "PoseDetector"]


@dataclass(frozen=True, slots=True)
class Pose:
    """One held pose of the sheet.

    Attributes
    ----------
    index : int
        0, 1, 2 ... in the order the poses were held.
    start_s, end_s : float
        The settled window the pose was taken over (the detector's clock, seconds).
    uids : ndarray, shape (n,), uint64
        The chips heard in that window, in the order they were first heard.
    mean : ndarray, shape (n, 3)
        Each chip's mean reading over the window, m/s², sensor frame.
    samples : ndarray, shape (n,), int
        How many readings each mean is of.
    """

    index: int
    start_s: float
    end_s: float
    uids: np.ndarray
    mean: np.ndarray
    samples: np.ndarray

    def readings(self) -> dict:
        """``{uid: mean reading (3,)}``."""
        return {int(u): self.mean[k] for k, u in enumerate(self.uids.tolist())}


def _positive(name: str, v) -> float:
    v = float(v)
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"Invalid {name}: {v!r} (need > 0)")
    return v


def _fraction(name: str, v) -> float:
    v = float(v)
    if not (np.isfinite(v) and 0 < v <= 1):
        raise ValueError(f"Invalid {name}: {v!r} (need 0 < {name} <= 1)")
    return v


class PoseDetector:
    """Held poses from a stream of ``(uid, reading, now)`` (module docstring).

    Parameters
    ----------
    chunk_s : float
        Seconds of readings averaged into one chunk per chip.
    settle_s : float
        How long the readings must stay still for a pose, seconds (a whole number of chunks, at
        least two).
    settle_deg : float
        How far a chunk's mean may lie from the window's mean for a chip that is still, degrees.
    change_deg : float
        How far a chip must move for the sheet to have changed pose, degrees.
    change_fraction : float
        The share of chips that must move that far.
    settle_fraction : float
        The share of chips that must be still for the sheet to be settled (a chip that babbles or
        is knocked does not hold the procedure up).

    Counters: ``samples`` (readings taken), ``bad_samples`` (readings not finite or of zero
    length: counted and left out), ``chunks`` (chunks closed).
    """

    def __init__(self, *, chunk_s: float = 0.1, settle_s: float = 1.0, settle_deg: float = 2.0,
                 change_deg: float = 10.0, change_fraction: float = 0.1, settle_fraction: float = 0.98) -> None:
        self.chunk_s = _positive("chunk_s", chunk_s)
        settle_s = _positive("settle_s", settle_s)
        self.window = int(round(settle_s / self.chunk_s))
        if self.window < 2:
            raise ValueError(f"Invalid settle_s: {settle_s!r} (need at least two chunks of {self.chunk_s:g} s)")
        self.settle_s = self.window * self.chunk_s
        self.cos_settle = float(np.cos(np.radians(_positive("settle_deg", settle_deg))))
        self.change_deg = _positive("change_deg", change_deg)
        if not self.change_deg < 180:
            raise ValueError(f"Invalid change_deg: {change_deg!r} (need < 180)")
        self.cos_change = float(np.cos(np.radians(self.change_deg)))
        self.change_fraction = _fraction("change_fraction", change_fraction)
        self.settle_fraction = _fraction("settle_fraction", settle_fraction)
        self._slot: dict[int, int] = {}
        self._uids: list[int] = []
        self._sorted: tuple[np.ndarray, np.ndarray] | None = None  # (uids ascending, their slots)
        self._sum = np.zeros((16, 3))
        self._cnt = np.zeros(16, dtype=np.int64)
        self._chunk_start: float | None = None
        self._chunks: deque = deque(maxlen=self.window)  # (start, sums (m, 3), counts (m,))
        self._last: tuple[np.ndarray, np.ndarray] | None = None  # (slots, unit directions) of the last pose
        self.state = "waiting"  #: "waiting" (no pose yet), "holding" a pose, "moving" since
        self.poses_taken = 0
        self.samples = 0
        self.bad_samples = 0
        self.chunks = 0
        self._pending: Pose | None = None

    # ------------------------------------------------------------------ input
    def _slot_of(self, uid: int) -> int:
        k = self._slot.get(uid)
        if k is None:
            k = self._slot[uid] = len(self._uids)
            self._uids.append(uid)
            self._sorted = None
            if k >= len(self._cnt):
                self._sum = np.concatenate([self._sum, np.zeros_like(self._sum)])
                self._cnt = np.concatenate([self._cnt, np.zeros_like(self._cnt)])
        return k

    def add(self, uid: int, reading, now: float) -> None:
        """One chip's reading (3,), m/s², taken at ``now``."""
        self._advance(now)
        r = np.asarray(reading, dtype=float).reshape(3)
        if not np.all(np.isfinite(r)) or not np.any(r):
            self.bad_samples += 1
            return
        k = self._slot_of(int(uid))
        self._sum[k] += r
        self._cnt[k] += 1
        self.samples += 1

    def add_many(self, uids, readings, now: float) -> None:
        """Several chips' readings taken at ``now``: ``uids`` (n,), ``readings`` (n, 3) — the same as
        `add` for each, in one step."""
        self._advance(now)
        r = np.asarray(readings, dtype=float)
        u = np.asarray(uids, dtype=np.uint64).reshape(-1)
        if r.shape != (len(u), 3):
            raise ValueError(f"Expected `readings` to have shape ({len(u)}, 3), got {r.shape}.")
        good = np.all(np.isfinite(r), axis=1) & np.any(r != 0, axis=1)
        self.bad_samples += int((~good).sum())
        if not good.any():
            return
        slots = self._slots_of(u[good])
        np.add.at(self._sum, slots, r[good])
        np.add.at(self._cnt, slots, 1)
        self.samples += int(good.sum())

    def _slots_of(self, u: np.ndarray) -> np.ndarray:
        """Slots of the uids ``u`` (uint64), new ones given slots in the order first seen (a whole
        sheet's snapshot looked up at once: 8,064 chips at 50 Hz)."""
        for _ in range(2):
            if self._sorted is None:
                keys = np.array(self._uids, dtype=np.uint64)
                order = np.argsort(keys, kind="stable")
                self._sorted = (keys[order], order.astype(np.int64))
            keys, slots = self._sorted
            idx = np.minimum(np.searchsorted(keys, u), max(len(keys) - 1, 0))
            found = (keys[idx] == u) if len(keys) else np.zeros(len(u), dtype=bool)
            if found.all():
                return slots[idx]
            for x in u[~found].tolist():
                self._slot_of(int(x))
        raise AssertionError("unreachable: every uid has a slot after the second pass")

    # ------------------------------------------------------------------ time
    def _advance(self, now: float) -> None:
        now = float(now)
        if self._chunk_start is None:
            self._chunk_start = now
            return
        while now >= self._chunk_start + self.chunk_s:
            self._close_chunk()

    def _close_chunk(self) -> None:
        m = len(self._uids)
        self._chunks.append((self._chunk_start, self._sum[:m].copy(), self._cnt[:m].copy()))
        self._sum[:] = 0
        self._cnt[:] = 0
        self._chunk_start += self.chunk_s
        self.chunks += 1
        if self._pending is None:
            self._pending = self._judge()

    def poll(self, now: float) -> Pose | None:
        """The pose taken since the last call, if one settled by ``now``; else None."""
        self._advance(now)
        p, self._pending = self._pending, None
        return p

    # ------------------------------------------------------------------ decisions
    def _judge(self) -> Pose | None:
        m = len(self._uids)
        if m == 0:
            return None
        last_start, last_sum, last_cnt = self._chunks[-1]
        if self.state == "holding":
            slots, ldir = self._last
            heard = last_cnt[slots] > 0
            d = last_sum[slots][heard] / last_cnt[slots][heard, None]
            moved = self._moved(d, ldir[heard])
            if heard.any() and moved >= self.change_fraction * heard.sum():
                self.state = "moving"
            return None
        if len(self._chunks) < self.window:
            return None
        sums = np.zeros((self.window, m, 3))
        cnts = np.zeros((self.window, m), dtype=np.int64)
        for w, (_t, s, c) in enumerate(self._chunks):
            sums[w, :len(c)] = s
            cnts[w, :len(c)] = c
        present = (cnts > 0).sum(axis=0) * 2 >= self.window
        if not present.any():
            return None
        total = cnts.sum(axis=0)
        mean = sums.sum(axis=0)[present] / total[present, None]
        unit = mean / np.linalg.norm(mean, axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            chunk_means = sums[:, present] / cnts[:, present, None]
            cos = np.einsum("wnk,nk->wn", chunk_means, unit) / np.linalg.norm(chunk_means, axis=2)
        still = np.all(np.where(cnts[:, present] > 0, cos >= self.cos_settle, True), axis=0)
        if still.sum() < self.settle_fraction * present.sum():
            return None
        slots = np.flatnonzero(present)
        if self._last is not None:  # the same pose again (put back where it was): hold it, take nothing
            common, ia, ib = np.intersect1d(slots, self._last[0], assume_unique=True, return_indices=True)
            if len(common) and self._moved(unit[ia], self._last[1][ib]) < self.change_fraction * len(common):
                self.state = "holding"
                return None
        self.state = "holding"
        self._last = (slots, unit)
        uids = np.array(self._uids, dtype=np.uint64)[present]
        start = self._chunks[0][0]
        pose = Pose(self.poses_taken, start, start + self.window * self.chunk_s, uids, mean, total[present])
        self.poses_taken += 1
        return pose

    def _moved(self, d: np.ndarray, ref_unit: np.ndarray) -> int:
        """How many of the directions ``d`` (n, 3) lie more than ``change_deg`` from ``ref_unit``."""
        if len(d) == 0:
            return 0
        cos = np.einsum("nk,nk->n", d, ref_unit) / np.linalg.norm(d, axis=1)
        return int((cos < self.cos_change).sum())
