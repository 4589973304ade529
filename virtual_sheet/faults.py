"""Fault injection for the virtual sheet: each fault on demand, with a rate and a seed.

Every injected fault is counted on the sending side in `FaultStats`, so a test can compare it with
what the receiver counted (`protocol.framing.StreamDecoder.stats`, `decode_can`, the host's
statistics). Randomness is seeded only: ``np.random.Generator(np.random.MT19937(seed))``.

A fault spec is a comma-separated ``key=value`` list (the CLI's ``--faults``), e.g.
``bitflip=1e-4,drop_frame=0.01,dead_chip=5,seed=3``. Keys:

=============== ===================================================================================
bitflip         probability per bit of flipping it (sheet -> host). Serial: the frame is damaged
                in place. CAN: the controllers see a CRC error, signal an error frame and the
                sender retransmits: the host receives an error frame, then the frame intact.
drop_byte       probability per byte of losing it (serial; on CAN treated like ``bitflip``).
drop_frame      probability per frame of losing it whole.
dup_frame       probability per frame of sending it twice.
reorder         probability per frame of holding it back and sending it after the next one.
delay_ms        fixed extra latency of every frame, ms.
jitter_ms       extra latency uniform in [0, jitter_ms] per frame (frames stay in order, as on a
                FIFO wire or bus).
dead_chip       link(s) whose chip is dead, ``:``-separated, e.g. ``dead_chip=5:9``.
dead_after_s    the dead chips work until this time (default 0: dead from power-on).
babble_chip     link(s) whose chip babbles.
babble_rate     babble frames per SYNC the chip hears, and per poll (default 1).
babble_mode     ``garbage`` (undecodable bytes / undefined CAN type codes) or ``flood`` (valid
                STATUS frames from the chip's node).
drift_chip      link(s) whose chip's clock runs slow.
drift           fraction by which its clock is slow (default 0.05): that fraction of its samples
                repeat the previous value flagged STALE.
drift_late_ms   how late its replies leave (default 5 ms, beyond the 2 ms reply deadline).
outage_at_s     the bus goes away at this time (s after start) ...
outage_s        ... for this long (default 1 s) ...
outage_every_s  ... and again every this many seconds (default: once).
seed            seed of every random choice (default 0).
=============== ===================================================================================

A frame made undeliverable by byte damage is counted once in ``frames_corrupted``; when the
damage hits the 0x00 delimiter (flipped or dropped) the next frame is merged with it and counted
as corrupted too — so on the receiver, good frames = frames sent - ``frames_corrupted`` exactly.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from protocol.can import CanFrame, make_id
from protocol.constants import SampleStatus
from protocol.framing import encode
from protocol.messages import ChipState, MsgType, Status, Sync

__all__ = ["FaultSpec", "FaultStats", "FrameFaults", "ERROR_FRAME", "DeadChip", "BabblingChip",
           "DriftingSensor", "wrap_chip", "parse_faults", "UNDEFINED_TYPES"]

#: Marker in a CAN output stream: the bus signalled an error frame here.
ERROR_FRAME = "error-frame"
#: Type codes protocol v1 does not define (what a garbage-babbling CAN chip sends).
UNDEFINED_TYPES = tuple(t for t in range(64) if t not in set(int(m) for m in MsgType))


def _links(value: str) -> tuple[int, ...]:
    return tuple(int(v) for v in str(value).replace("+", ":").split(":") if v != "")


@dataclass(frozen=True)
class FaultSpec:
    """Which faults to inject, and how often (module docstring). All off by default."""

    bitflip: float = 0.0
    drop_byte: float = 0.0
    drop_frame: float = 0.0
    dup_frame: float = 0.0
    reorder: float = 0.0
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    dead_chip: tuple[int, ...] = ()
    dead_after_s: float = 0.0
    babble_chip: tuple[int, ...] = ()
    babble_rate: float = 1.0
    babble_mode: str = "garbage"
    drift_chip: tuple[int, ...] = ()
    drift: float = 0.05
    drift_late_ms: float = 5.0
    outage_at_s: float | None = None
    outage_s: float = 1.0
    outage_every_s: float | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("bitflip", "drop_byte", "drop_frame", "dup_frame", "reorder", "drift"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"Invalid fault {name}: {v!r} (need a probability in 0..1)")
        for name in ("delay_ms", "jitter_ms", "dead_after_s", "babble_rate", "drift_late_ms", "outage_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"Invalid fault {name}: {v!r} (need a finite value >= 0)")
        if self.babble_mode not in ("garbage", "flood"):
            raise ValueError(f"Invalid fault babble_mode: {self.babble_mode!r} (expected garbage or flood)")
        if self.outage_every_s is not None and self.outage_every_s <= self.outage_s:
            raise ValueError(f"Invalid fault outage_every_s: {self.outage_every_s!r} (need > outage_s)")

    @classmethod
    def parse(cls, text: str | None) -> "FaultSpec":
        """Parse ``"bitflip=1e-4,drop_frame=0.01,dead_chip=5,seed=3"`` (empty: no faults)."""
        if not text:
            return cls()
        known = {f.name: f for f in fields(cls)}
        kw: dict[str, Any] = {}
        for item in text.split(","):
            item = item.strip()
            if not item:
                continue
            key, sep, value = item.partition("=")
            key = key.strip()
            if not sep or key not in known:
                raise ValueError(f"Invalid fault {item!r}; known faults: {', '.join(known)} "
                                 "(format key=value,key=value)")
            try:
                if key in ("dead_chip", "babble_chip", "drift_chip"):
                    kw[key] = _links(value)
                elif key == "babble_mode":
                    kw[key] = value.strip()
                elif key == "seed":
                    kw[key] = int(value)
                else:
                    kw[key] = float(value)
            except ValueError as exc:
                raise ValueError(f"Invalid fault value {item!r}: {exc}") from exc
        return cls(**kw)

    @property
    def any_stream(self) -> bool:
        """True if any frame-stream fault is on (what `FrameFaults` does)."""
        return any((self.bitflip, self.drop_byte, self.drop_frame, self.dup_frame, self.reorder,
                    self.delay_ms, self.jitter_ms))

    def outage_windows(self):
        """``(start_s, end_s)`` of every outage, in order (a generator; endless if periodic)."""
        if self.outage_at_s is None:
            return
        t = self.outage_at_s
        while True:
            yield t, t + self.outage_s
            if self.outage_every_s is None:
                return
            t += self.outage_every_s


def parse_faults(text: str | None) -> FaultSpec:
    return FaultSpec.parse(text)


@dataclass
class FaultStats:
    """What was injected, counted where it was injected (thread-safe enough: one writer each)."""

    frames_in: int = 0  #: frames offered to the stream faults
    frames_out: int = 0  #: frames (copies) put on the wire
    bits_flipped: int = 0
    bytes_dropped: int = 0
    frames_corrupted: int = 0  #: frames made undecodable (incl. ones merged by delimiter damage)
    frames_dropped: int = 0
    frames_duplicated: int = 0
    frames_reordered: int = 0  #: frames sent after their successor
    frames_delayed: int = 0
    error_frames: int = 0  #: CAN: error frames signalled (then the frame retransmitted)
    dead_frames_suppressed: int = 0  #: frames a dead chip did not answer (heard while dead)
    dead_syncs_ignored: int = 0  #: SYNCs a dead chip did not answer
    babble_frames: int = 0
    stale_samples: int = 0
    late_replies: int = 0
    outages: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "lock"}

    def nonzero(self) -> dict[str, int]:
        return {k: v for k, v in self.as_dict().items() if v}


class FrameFaults:
    """Stream faults on the frames a gateway sends, sans-I/O.

    `process` takes frames in send order and returns ``(due_s, frame)`` pairs in wire order;
    ``frame`` is serial bytes, a `CanFrame`, or `ERROR_FRAME` on CAN.
    """

    def __init__(self, spec: FaultSpec, stats: FaultStats | None = None, *, can: bool = False,
                 stream: int = 0) -> None:
        self.spec = spec
        self.stats = stats if stats is not None else FaultStats()
        self.can = can
        self.rng = np.random.Generator(np.random.MT19937([spec.seed, 0xFA17, stream]))
        self._held: tuple[float, Any] | None = None
        self._merge_next = False
        self._last_due = 0.0

    def _damage(self, frame: bytes) -> tuple[bytes, bool, bool]:
        """Byte damage of one serial frame: ``(bytes, damaged, delimiter_hit)``."""
        s, rng = self.spec, self.rng
        buf = bytearray(frame)
        damaged = delim = False
        if s.bitflip:
            k = int(rng.binomial(8 * len(buf), s.bitflip))
            if k:
                for pos in rng.choice(8 * len(buf), size=k, replace=False).tolist():
                    buf[pos >> 3] ^= 1 << (pos & 7)
                self.stats.bits_flipped += k
                damaged = True
                delim = buf[-1] != 0
        if s.drop_byte:
            keep = rng.random(len(buf)) >= s.drop_byte
            n = int((~keep).sum())
            if n:
                if not keep[-1]:
                    delim = True
                buf = bytearray(np.frombuffer(bytes(buf), np.uint8)[keep].tobytes())
                self.stats.bytes_dropped += n
                damaged = True
        return bytes(buf), damaged, delim

    def process(self, frames: list, now_s: float) -> list[tuple[float, Any]]:
        s, rng, st = self.spec, self.rng, self.stats
        out: list[tuple[float, Any]] = []
        for frame in frames:
            st.frames_in += 1
            if s.drop_frame and rng.random() < s.drop_frame:
                st.frames_dropped += 1
                continue
            copies = 2 if (s.dup_frame and rng.random() < s.dup_frame) else 1
            if copies == 2:
                st.frames_duplicated += 1
            for _ in range(copies):
                pieces: list = []
                if self.can:
                    if (s.bitflip or s.drop_byte) and rng.random() < 1.0 - (1.0 - max(s.bitflip, s.drop_byte)) ** (
                            8 * (len(frame.data) + 8)):
                        st.error_frames += 1
                        pieces.append(ERROR_FRAME)
                    pieces.append(frame)
                else:
                    f = frame
                    if s.bitflip or s.drop_byte:
                        f, damaged, delim = self._damage(frame)
                        if damaged or self._merge_next:
                            st.frames_corrupted += 1
                        self._merge_next = delim
                    elif self._merge_next:
                        st.frames_corrupted += 1
                        self._merge_next = False
                    pieces.append(f)
                due = now_s
                if s.delay_ms or s.jitter_ms:
                    due += s.delay_ms / 1e3 + (rng.random() * s.jitter_ms / 1e3 if s.jitter_ms else 0.0)
                    st.frames_delayed += 1
                due = max(due, self._last_due)  # a FIFO: no overtaking
                self._last_due = due
                for p in pieces:
                    if s.reorder and self._held is None and p is not ERROR_FRAME and rng.random() < s.reorder:
                        self._held = (due, p)
                        st.frames_reordered += 1
                        continue
                    out.append((due, p))
                    st.frames_out += p is not ERROR_FRAME
                    if self._held is not None and p is not ERROR_FRAME:
                        out.append((due, self._held[1]))
                        st.frames_out += 1
                        self._held = None
        return out

    def flush(self, now_s: float, max_hold_s: float = 0.05) -> list[tuple[float, Any]]:
        """Release a held (reordered) frame that no successor came to overtake in time."""
        if self._held is not None and now_s - self._held[0] >= max_hold_s:
            due, p = self._held
            self._held = None
            self.stats.frames_out += 1
            return [(max(now_s, due), p)]
        return []


# ---------------------------------------------------------------------------------------------
# Chip faults: wrappers around any chip class (ChipModel or CFirmwareChip)
# ---------------------------------------------------------------------------------------------

class _ChipWrapper:
    def __init__(self, inner, stats: FaultStats) -> None:
        self.inner = inner
        self.stats = stats

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def power_on(self, now_s):
        return self.inner.power_on(now_s)

    def handle(self, frame, now_s, decoded=None):
        return self.inner.handle(frame, now_s, decoded)

    def poll(self, now_s):
        return self.inner.poll(now_s)


class DeadChip(_ChipWrapper):
    """A chip that stops (or never starts) answering: from ``dead_after_s`` on it hears nothing
    and sends nothing. Counts the SYNCs and frames it ignored while dead."""

    def __init__(self, inner, stats: FaultStats, dead_after_s: float = 0.0) -> None:
        super().__init__(inner, stats)
        self.dead_after_s = dead_after_s

    def power_on(self, now_s):
        return self.inner.power_on(now_s) if now_s < self.dead_after_s else []

    def handle(self, frame, now_s, decoded=None):
        if now_s < self.dead_after_s:
            return self.inner.handle(frame, now_s, decoded)
        with self.stats.lock:
            self.stats.dead_frames_suppressed += 1
            if type(decoded) is Sync:
                self.stats.dead_syncs_ignored += 1
        return []

    def poll(self, now_s):
        return self.inner.poll(now_s) if now_s < self.dead_after_s else []


class BabblingChip(_ChipWrapper):
    """A chip that adds junk to what it sends: ``rate`` frames (Poisson mean) after every SYNC it
    hears and every poll. ``garbage``: undecodable frames (serial: random non-zero bytes then the
    delimiter, which the receiver must report as BAD_COBS / SHORT / BAD_CRC; CAN: undefined type
    codes, UNKNOWN_TYPE). ``flood``: valid STATUS frames from its node."""

    def __init__(self, inner, stats: FaultStats, rate: float, mode: str, seed: int, can: bool) -> None:
        super().__init__(inner, stats)
        self.rate, self.mode, self.can = rate, mode, can
        self.rng = np.random.Generator(np.random.MT19937([seed, 0xBAB1E, inner.uid & 0xFFFFFFFF]))

    def _junk(self) -> list:
        n = int(self.rng.poisson(self.rate))
        out = []
        for _ in range(n):
            if self.mode == "flood":
                node = self.inner.node
                msg = Status(node, ChipState.IDLE, 0, 0, 0, 0)
                if self.can:
                    from protocol.can import to_can
                    out.append(to_can(msg))
                else:
                    out.append(encode(msg))
            elif self.can:
                t = int(self.rng.choice(UNDEFINED_TYPES))
                data = self.rng.integers(0, 256, int(self.rng.integers(0, 9)), dtype=np.uint8).tobytes()
                out.append(CanFrame(make_id(t, int(self.rng.integers(1, 0xFFFF)), priority=7), data, False))
            else:
                body = self.rng.integers(1, 256, int(self.rng.integers(1, 40)), dtype=np.uint8).tobytes()
                # a 1-byte body is SHORT, longer ones fail COBS or CRC (CRC passes with p ~ 2**-16;
                # force a bad CRC by construction: the decoder would need a valid COBS + CRC)
                out.append(body + b"\x00")
        with self.stats.lock:
            self.stats.babble_frames += len(out)
        return out

    def handle(self, frame, now_s, decoded=None):
        out = self.inner.handle(frame, now_s, decoded)
        if type(decoded) is Sync:
            out = out + self._junk()
        return out

    def poll(self, now_s):
        return self.inner.poll(now_s) + self._junk()


class DriftingSensor:
    """A sensor source whose chip's clock runs slow by ``drift``: that fraction of SYNCs find no
    fresh conversion, and the previous sample is repeated flagged STALE (counted)."""

    def __init__(self, source, drift: float, stats: FaultStats) -> None:
        self.source, self.drift, self.stats = source, drift, stats
        self._credit = 1.0
        self._last = None

    def __call__(self, now_s: float):
        self._credit += 1.0 - self.drift
        if self._credit < 1.0 and self._last is not None:
            with self.stats.lock:
                self.stats.stale_samples += 1
            counts, st = self._last
            return counts, int(st) | SampleStatus.STALE
        self._credit = min(self._credit, 2.0) - 1.0
        self._last = self.source(now_s)
        return self._last


def wrap_chip(chip, link: int, spec: FaultSpec, stats: FaultStats, *, can: bool):
    """Apply the chip faults of ``spec`` that name ``link`` (dead, babbling)."""
    if link in spec.babble_chip:
        chip = BabblingChip(chip, stats, spec.babble_rate, spec.babble_mode, spec.seed, can)
    if link in spec.dead_chip:
        chip = DeadChip(chip, stats, spec.dead_after_s)
    return chip
