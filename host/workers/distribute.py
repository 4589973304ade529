"""Estimation spread over processes (docs/distribution.md "Estimate workers").

`capsheet estimate --subscribe` runs `SheetWork` per sheet: it takes the sheet's snapshots as a host
published them (``capsheet/<sheet>/snapshot``, `host.publish.zenoh_pub.decode_snapshot`), in the order they
came, and makes one estimate for each (`host.publish.zenoh_pub.encode_estimate`; a snapshot that cannot be
estimated gets an estimate flagged `host.publish.zenoh_pub.FLAG_NOT_ESTIMATED`, joints NaN, so that every
snapshot has exactly one). What is lost on the way is counted from the SYNC counter in every
header (`Sequence`). This module is sans I/O: payloads in, payloads out, ``now`` given.

Which worker takes which sheet: ``--sheets NAME,...`` names them, or ``--worker I/N`` takes the
sheets whose `shard` is I — CRC-32 of the name modulo N, so N workers started with 0/N .. N-1/N
share every sheet without talking to each other or to a coordinator, each sheet to exactly one.
"""

from __future__ import annotations

import re
import zlib
from collections import deque
from dataclasses import dataclass, field
from fnmatch import fnmatchcase

import numpy as np

__all__ = ["Sequence", "SheetWork", "Selection", "shard", "parse_worker", "parse_sheets", "COUNTER_MODULO",
           "latency_ms"]

#: latencies a sheet keeps for its percentiles: the newest (11.5 minutes at 145 Hz)
LATENCIES_KEPT = 100_000
#: the SYNC counter is 16-bit on the wire (docs/protocol.md): it wraps here
COUNTER_MODULO = 1 << 16
#: a jump of at most this many counters is a gap whatever the time says (`Sequence`)
RESTART_MIN_JUMP = 64
#: a counter more than half the circle ahead of the last one is taken as an old one come late
_HALF = COUNTER_MODULO // 2


def shard(sheet: str, n: int) -> int:
    """The worker index (0 .. n-1) that takes ``sheet`` under ``--worker I/N``: CRC-32 (zlib's,
    IEEE 802.3) of its UTF-8 name modulo ``n``.

    >>> shard("left_arm", 2), shard("right_arm", 2)
    (1, 0)
    """
    return zlib.crc32(sheet.encode()) % n


def parse_worker(text: str) -> tuple[int, int]:
    """``"I/N"`` -> ``(I, N)``, 0 <= I < N <= 1024; ValueError otherwise."""
    i, slash, n = text.partition("/")
    try:
        i_, n_ = int(i), int(n)
    except ValueError:
        i_ = n_ = -1
    if not slash or not (0 <= i_ < n_ <= 1024):
        raise ValueError(f"bad --worker {text!r}: I/N with 0 <= I < N <= 1024 (e.g. 0/2 and 1/2 for two workers)")
    return i_, n_


#: a sheet name, or a pattern of names (``*`` any characters, ``?`` one)
_SHEET_PATTERN = re.compile(r"^[A-Za-z0-9_.\-*?]{1,64}$")


def parse_sheets(text: str) -> list[str]:
    """``"a,b_*"`` -> ``["a", "b_*"]``: each a sheet name (`host.publish.zenoh_pub.SHEET_NAME`) or a pattern
    with ``*`` / ``?``, none twice."""
    names = [s.strip() for s in text.split(",")]
    for s in names:
        if not _SHEET_PATTERN.match(s):
            raise ValueError(f"bad sheet name {s!r} in --sheets {text!r}: 1-64 of A-Z a-z 0-9 _ . - each (or a "
                             f"pattern with * and ?), separated by commas")
    if len(set(names)) != len(names):
        raise ValueError(f"--sheets {text!r} names a sheet twice")
    return names


@dataclass(frozen=True)
class Selection:
    """Which sheets a worker takes: ``names`` (exact: each must exist), ``patterns`` (``*``, ``?``:
    whichever publish; none of either: every sheet), and of those, with ``worker`` ``(I, N)``, the
    ones whose `shard` is I."""

    names: tuple[str, ...] = ()
    patterns: tuple[str, ...] = ()
    worker: tuple[int, int] | None = None

    @classmethod
    def of(cls, sheets: list[str] | None, worker: tuple[int, int] | None) -> "Selection":
        sheets = sheets or []
        return cls(tuple(s for s in sheets if not set(s) & set("*?")),
                   tuple(s for s in sheets if set(s) & set("*?")), worker)

    def in_share(self, sheet: str) -> bool:
        return self.worker is None or shard(sheet, self.worker[1]) == self.worker[0]

    def takes(self, sheet: str) -> bool:
        if not self.in_share(sheet):
            return False
        if not self.names and not self.patterns:
            return True
        return sheet in self.names or any(fnmatchcase(sheet, p) for p in self.patterns)

    @property
    def keys(self) -> list[str]:
        """The key expressions to subscribe to: the named sheets' snapshots, or every sheet's."""
        if self.names and not self.patterns:
            return [f"capsheet/{s}/snapshot" for s in self.names]
        return ["capsheet/*/snapshot"]


@dataclass
class Sequence:
    """The SYNC counters of one sheet's snapshots as they arrive, modulo `COUNTER_MODULO`, with the
    time each counter opened (``t``: the header's wall time, else its host time).

    `see` classifies each: ``first``; ``next`` (the one after the last); ``gap`` (newer, with
    ``lost`` snapshots between: counted, the snapshot itself is fine); ``duplicate`` (the last one
    again) or ``old`` (behind the last one, and older): both dropped by the caller, counted, since
    estimating them would break the order of the sheet's estimates; ``restart``: the host started
    counting again (a restarted host, a resynchronised sheet) — a counter not ahead of the last but
    newer in time, or more than `RESTART_MIN_JUMP` ahead of it in less than half the SYNC periods
    (`period`, learnt from consecutive counters) it skipped; a new sequence, nothing counted lost.
    A short skip is always a gap: a late SYNC beside an early one must not hide a lost snapshot.
    """

    last: int | None = None
    first: int | None = None
    received: int = 0  #: snapshots seen, whatever their kind
    lost: int = 0  #: counters skipped between snapshots that came
    gaps: int = 0  #: how many times the sequence skipped (each may lose several)
    duplicates: int = 0
    old: int = 0
    restarts: int = 0
    last_t: float | None = None
    period: float | None = None  #: seconds per counter, a running mean over consecutive counters

    def see(self, counter: int, t: float | None = None) -> str:
        c = int(counter) % COUNTER_MODULO
        t = None if t is None or not np.isfinite(t) else float(t)
        self.received += 1
        if self.last is None:
            self.first = self.last = c
            self.last_t = t
            return "first"
        d = (c - self.last) % COUNTER_MODULO
        dt = None if t is None or self.last_t is None else t - self.last_t
        if d == 0 or d >= _HALF:
            if dt is None or dt <= 0:
                if d == 0:
                    self.duplicates += 1
                    return "duplicate"
                self.old += 1
                return "old"
            kind = "restart"  # behind (or equal) in counter, ahead in time
        elif d > RESTART_MIN_JUMP and dt is not None and self.period is not None and dt < 0.5 * d * self.period:
            kind = "restart"  # skipped d counters in far less than d periods
        else:
            kind = "next" if d == 1 else "gap"
        self.last, self.last_t = c, t if t is not None else self.last_t
        if kind == "restart":
            self.restarts += 1
        elif kind == "next":
            if dt is not None and dt > 0:
                self.period = dt if self.period is None else 0.9 * self.period + 0.1 * dt
        else:
            self.lost += d - 1
            self.gaps += 1
        return kind


def latency_ms(values) -> dict:
    """``{"n", "p50", "p99", "max"}`` of latencies in seconds, as milliseconds (None when empty)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"n": 0, "p50": None, "p99": None, "max": None}
    return {"n": int(v.size), "p50": round(float(np.percentile(v, 50)) * 1e3, 3),
            "p99": round(float(np.percentile(v, 99)) * 1e3, 3), "max": round(float(v.max()) * 1e3, 3)}


@dataclass
class SheetWork:
    """One sheet's estimation in a worker: its facts from ``capsheet/<sheet>/info`` (`set_info`),
    its sequence, its estimator state (the previous estimate warm-starts the next, as the live host
    does) and its counts.

    ``uncertainty_period_s``: an estimate carries ``joint_std`` at most this often (None: never).
    ``method``: ``auto`` (the fused estimator for snapshots that carry gyroscopes, 6/9-axis chips,
    every one in order as ``capsheet estimate --method auto`` does a recording; the global method
    otherwise), ``global`` (the accelerometers alone, whatever the chips) or ``fused`` (a snapshot
    without gyroscopes is then not estimated, counted).
    """

    name: str
    uncertainty_period_s: float | None = None
    method: str = "auto"
    info: dict | None = None
    seq: Sequence = field(default_factory=Sequence)
    estimated: int = 0  #: published with joints
    not_estimated: dict = field(default_factory=dict)  #: reason -> snapshots published flagged, joints NaN
    bad_payloads: int = 0
    last_bad: str = ""
    #: publish wall time - the snapshot's SYNC wall time, s: the newest `LATENCIES_KEPT` (a worker runs for days)
    latencies: deque = field(default_factory=lambda: deque(maxlen=LATENCIES_KEPT))
    methods: dict = field(default_factory=dict)  #: method -> estimates made with it
    _previous: object = None
    _fused: object = None
    _last_unc: float = -np.inf

    @property
    def ready(self) -> bool:
        return self.info is not None

    def set_info(self, doc: dict) -> None:
        """The sheet's ``info`` answer (JSON decoded); ValueError when it lacks the lattice or link length."""
        from host.cli.argtypes import MAX_LINK_M, MIN_LINK_M
        from host.publish.zenoh_pub import check_lattice
        try:
            rows, cols, L = int(doc["rows"]), int(doc["cols"]), float(doc["link_length_m"])
        except (KeyError, TypeError, ValueError, OverflowError):
            raise ValueError(f"capsheet/{self.name}/info lacks rows, cols or link_length_m") from None
        try:
            check_lattice(rows, cols)
        except ValueError as exc:
            raise ValueError(f"capsheet/{self.name}/info: {exc}") from None
        if not MIN_LINK_M <= L <= MAX_LINK_M:  # NaN fails too
            raise ValueError(f"capsheet/{self.name}/info: link_length_m {L} is not in [{MIN_LINK_M}, {MAX_LINK_M}] m")
        self.info = doc

    @property
    def link_length(self) -> float:
        return float(self.info["link_length_m"])

    def work(self, payload: bytes, now: float) -> bytes | None:
        """One snapshot payload -> the estimate payload to publish, or None (a bad payload, a
        duplicate or an old snapshot: counted). Needs `set_info` first. ``now``: monotonic seconds.
        Any bytes are taken: sizes, lattice and counts are checked before anything is allocated
        (`host.publish.zenoh_pub.decode_snapshot`), and a payload that fails is counted, never raised."""
        from host.publish.zenoh_pub import decode_snapshot, encode_estimate, encode_no_estimate
        try:
            s = decode_snapshot(payload)
            if (s["rows"], s["cols"]) != (int(self.info["rows"]), int(self.info["cols"])):
                raise ValueError(f"a {s['rows']}x{s['cols']} snapshot for a {self.info['rows']}x{self.info['cols']} sheet")
        except ValueError as exc:
            self.bad_payloads += 1
            self.last_bad = str(exc)
            return None
        wall = s["wall_time"]
        kind = self.seq.see(s["counter"], wall if np.isfinite(wall) else s["timestamp"])
        if kind in ("duplicate", "old"):
            return None
        if kind == "restart":  # the sheet's host started again: nothing to warm-start from
            self._previous = self._fused = None
        rows, cols = s["rows"], s["cols"]
        fused = self.method == "fused" or (self.method == "auto" and s["gyro"] is not None)
        est, why = None, None
        if not s["valid"].any():
            why = "no valid link"
        elif fused:
            try:
                est, why = self._fused_estimate(s)
            except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
                why = str(exc)
        else:
            from host.analysis.estimator import estimate
            try:
                est = estimate(s["readings"].astype(float), rows, cols, self.link_length, valid=s["valid"],
                               previous=self._previous, bad_readings="mask")
            except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:  # e.g. every valid link's
                why = str(exc)  # reading implausible: this snapshot only
        if why is not None:
            self.not_estimated[why] = self.not_estimated.get(why, 0) + 1
            return encode_no_estimate(rows, cols, s["counter"], s["timestamp"], s["wall_time"])
        unc = False
        if not fused:
            self._previous = est
            unc = self.uncertainty_period_s is not None and now - self._last_unc >= self.uncertainty_period_s
            if unc:
                self._last_unc = now
        m = "fused" if fused else "global"
        self.methods[m] = self.methods.get(m, 0) + 1
        self.estimated += 1
        return encode_estimate(est, s["counter"], s["timestamp"], s["wall_time"], uncertainty=unc)

    def _fused_estimate(self, s: dict):
        """``(estimate, None)`` or ``(None, why)``: the snapshot into the sheet's fused estimator
        (`host.analysis.motion.snapshots.fused_update`), which carries its state to the next."""
        from types import SimpleNamespace

        from host.analysis.motion.snapshots import fused_update
        if s["gyro"] is None:
            return None, "no gyroscopes (--method fused)"
        if self._fused is None:
            from host.analysis.motion import MotionEstimator
            self._fused = MotionEstimator(int(self.info["rows"]), int(self.info["cols"]), self.link_length)
        n = s["n"]
        f64 = (lambda v: None if v is None else v.astype(float))
        snap = SimpleNamespace(timestamp=s["timestamp"], valid=s["valid"], readings=s["readings"].astype(float),
                               gyro=f64(s["gyro"]), mag=f64(s["mag"]),
                               sample_time_s=np.full(n, np.nan) if s["sample_time_s"] is None
                               else s["sample_time_s"].astype(float))
        out = fused_update(self._fused, snap)
        if out is None:
            return None, "no IMU record, or the fused estimator restarted"
        return out, None

    def summary(self) -> dict:
        q = self.seq
        return {"sheet": self.name, "info": self.ready, "received": q.received, "first_counter": q.first,
                "last_counter": q.last, "estimated": self.estimated,
                "not_estimated": sum(self.not_estimated.values()), "not_estimated_reasons": dict(self.not_estimated),
                "methods": dict(self.methods), "lost": q.lost, "gaps": q.gaps, "duplicates": q.duplicates, "old": q.old,
                "restarts": q.restarts,
                "bad_payloads": self.bad_payloads, "latency_ms": latency_ms(self.latencies)}
