"""chip -> host messages of the accelerometer protocol (docs §4.1-§4.8, §4.16): ANNOUNCE, INFO, SAMPLE,
STATUS, ACK, NACK, CAL_DATA, SNAPSHOT, GATEWAY_INFO."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..constants import ADC_MAX, ADC_MIN
from .base import (CHIP_STATE_CODES, NACK_REASON_CODES, Capability, ChipState, Direction, GatewayFlag, MAX_SNAPSHOT_SAMPLES, Message, MsgType,
    NackReason, PROTOCOL_VERSION, PayloadError, SAMPLE_WORD_SIZE, SampleFormat, StatusFlag, check_int,
    check_uint, pack_sample_words, unpack_sample_words, unpack_snapshots)
from .imu import ImuSample


# --------------------------------------------------------------------------------------------
# chip -> host
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class Announce(Message):
    """§4.1 ANNOUNCE: ``uid`` u64. Sent at boot, after RESET, and in answer to GET_INFO; an
    unassigned chip sends it from its provisional node id."""

    TYPE = MsgType.ANNOUNCE
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 5
    _FMT = struct.Struct("<Q")
    uid: int = 0

    def _validate(self) -> None:
        check_uint("uid", self.uid, 64)


assert Announce._FMT.size == 8


@dataclass(frozen=True, slots=True)
class Info(Message):
    """§4.2 INFO: firmware version, protocol version, capabilities, ADC bits, state. Follows every
    ANNOUNCE (split from it so both fit one classic CAN frame)."""

    TYPE = MsgType.INFO
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 5
    _FMT = struct.Struct("<BBBBHBB")
    fw_major: int = 0
    fw_minor: int = 0
    fw_patch: int = 0
    protocol_version: int = PROTOCOL_VERSION
    capabilities: int = 0
    adc_bits: int = 12
    state: int = ChipState.BOOT

    def _validate(self) -> None:
        for name in ("fw_major", "fw_minor", "fw_patch", "protocol_version", "adc_bits"):
            check_uint(name, getattr(self, name), 8)
        check_uint("capabilities", self.capabilities, 16)
        if self.state not in CHIP_STATE_CODES:
            raise ValueError(f"Invalid state: {self.state!r}")
        object.__setattr__(self, "state", ChipState(self.state))
        object.__setattr__(self, "capabilities", Capability(self.capabilities))


assert Info._FMT.size == 8


@dataclass(frozen=True, slots=True)
class Sample(Message):
    """§4.3 SAMPLE: ``counter`` u16 of the SYNC it answers, then one 40-bit sample word
    (x, y, z ADC counts, 12-bit signed; 4 status bits). 7 bytes."""

    TYPE = MsgType.SAMPLE
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 2
    counter: int = 0
    x: int = 0
    y: int = 0
    z: int = 0
    status: int = 0

    SIZE: ClassVar[int] = 2 + SAMPLE_WORD_SIZE

    def _validate(self) -> None:
        check_uint("counter", self.counter, 16)
        for name in ("x", "y", "z"):
            check_int(name, getattr(self, name), ADC_MIN, ADC_MAX)
        check_uint("status", self.status, 4)

    def payload(self) -> bytes:
        word = ((self.x & 0xFFF) | ((self.y & 0xFFF) << 12) | ((self.z & 0xFFF) << 24)
                | (self.status << 36))
        return self.counter.to_bytes(2, "little") + word.to_bytes(5, "little")

    @classmethod
    def from_payload(cls, node: int, payload: bytes) -> "Sample":
        if len(payload) != cls.SIZE:
            raise PayloadError("BAD_LENGTH", f"SAMPLE payload is {cls.SIZE} bytes, got {len(payload)}")
        counter = payload[0] | (payload[1] << 8)
        w = int.from_bytes(payload[2:7], "little")
        x, y, z = ((w >> s) & 0xFFF for s in (0, 12, 24))
        return cls(node, counter, x - ((x & 0x800) << 1), y - ((y & 0x800) << 1),
                   z - ((z & 0x800) << 1), (w >> 36) & 0xF)


@dataclass(frozen=True, slots=True, eq=False)
class SampleBatch:
    """Consecutive SAMPLEs, decoded at once: the event of `framing.StreamDecoder` (batch mode) and of
    `can.CanDecoder` alike (re-exported by `protocol.framing`, where it was first).

    Attributes are arrays of equal length n: ``node`` uint16, ``counter`` uint16,
    ``counts`` int16 (n, 3) ADC counts, ``status`` uint8 SampleStatus bits.
    """

    node: np.ndarray
    counter: np.ndarray
    counts: np.ndarray
    status: np.ndarray

    def __len__(self) -> int:
        return int(self.node.shape[0])

    def messages(self) -> list[Sample]:
        """The batch as `Sample` messages (slow; for tests and display)."""
        return [Sample(int(n), int(c), int(x), int(y), int(z), int(s))
                for n, c, (x, y, z), s in zip(self.node, self.counter, self.counts, self.status)]


@dataclass(frozen=True, slots=True, eq=False)
class ImuBatch:
    """Consecutive IMU_SAMPLE frames of one format, decoded at once: the batch event of
    `framing.StreamDecoder` (re-exported there; docs/protocol.md §16.3).

    Arrays of equal length n: ``node`` uint16, ``counter`` uint16, ``counts`` int16 (n, 3)
    accelerometer counts, ``status`` uint8, ``time_us`` int16 (`TIME_UNKNOWN`: unknown), ``gyro``
    int16 (n, 3), ``mag`` int16 (n, 3) or None (format 1).
    """

    node: np.ndarray
    counter: np.ndarray
    counts: np.ndarray
    status: np.ndarray
    time_us: np.ndarray
    gyro: np.ndarray
    mag: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.node.shape[0])

    def messages(self) -> list[ImuSample]:
        """The batch as `ImuSample` messages (slow; for tests and display)."""
        out = []
        for k in range(len(self)):
            m = (None, None, None) if self.mag is None else tuple(int(v) for v in self.mag[k])
            out.append(ImuSample(int(self.node[k]), int(self.counter[k]), *(int(v) for v in self.counts[k]),
                                 int(self.status[k]), int(self.time_us[k]), *(int(v) for v in self.gyro[k]), *m))
        return out


@dataclass(frozen=True, slots=True)
class Status(Message):
    """§4.4 STATUS (heartbeat): state u8, flags u8, rx_errors u8, missed_syncs u8 (both
    saturating at 255), uptime_s u32."""

    TYPE = MsgType.STATUS
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 6
    _FMT = struct.Struct("<BBBBI")
    SIZE: ClassVar[int] = 8  #: payload bytes
    state: int = ChipState.BOOT
    flags: int = 0
    rx_errors: int = 0
    missed_syncs: int = 0
    uptime_s: int = 0

    def _validate(self) -> None:
        if self.state not in CHIP_STATE_CODES:
            raise ValueError(f"Invalid state: {self.state!r}")
        object.__setattr__(self, "state", ChipState(self.state))
        for name in ("flags", "rx_errors", "missed_syncs"):
            check_uint(name, getattr(self, name), 8)
        check_uint("uptime_s", self.uptime_s, 32)
        object.__setattr__(self, "flags", StatusFlag(self.flags))


assert Status._FMT.size == Status.SIZE == 8

#: the STATUS states a chip may report (§4.4), for the decoders' vectorised checks
STATUS_STATES = np.array(sorted(CHIP_STATE_CODES), dtype=np.int64)


@dataclass(frozen=True, slots=True, eq=False)
class StatusBatch:
    """Consecutive STATUS heartbeats decoded at once: the event of `framing.StreamDecoder` with
    ``batch_status`` (a host's serial transports: 8,064 chips beat 8,064 times a second).

    Arrays of equal length n: ``node`` uint16, ``state``, ``flags``, ``rx_errors``,
    ``missed_syncs`` uint8, ``uptime_s`` uint32; every row is a STATUS `Status` would accept.
    """

    node: np.ndarray
    state: np.ndarray
    flags: np.ndarray
    rx_errors: np.ndarray
    missed_syncs: np.ndarray
    uptime_s: np.ndarray

    def __len__(self) -> int:
        return int(self.node.shape[0])

    def message(self, i: int) -> Status:
        """Row ``i`` as a `Status`."""
        return Status(int(self.node[i]), int(self.state[i]), int(self.flags[i]), int(self.rx_errors[i]),
                      int(self.missed_syncs[i]), int(self.uptime_s[i]))

    def messages(self) -> list[Status]:
        """The batch as `Status` messages (slow; for tests and the rare heartbeat that matters)."""
        return [self.message(i) for i in range(len(self))]


def _check_command(value: int) -> None:
    check_uint("command", value, 8)


@dataclass(frozen=True, slots=True)
class Ack(Message):
    """§4.5 ACK: ``command`` u8 (the type acknowledged), ``detail`` u8 (0 unless stated)."""

    TYPE = MsgType.ACK
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 3
    _FMT = struct.Struct("<BB")
    command: int = 0
    detail: int = 0

    def _validate(self) -> None:
        _check_command(self.command)
        check_uint("detail", self.detail, 8)


@dataclass(frozen=True, slots=True)
class Nack(Message):
    """§4.6 NACK: ``command`` u8 (the type refused), ``reason`` u8 (NackReason)."""

    TYPE = MsgType.NACK
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 3
    _FMT = struct.Struct("<BB")
    command: int = 0
    reason: int = NackReason.UNKNOWN_COMMAND

    def _validate(self) -> None:
        _check_command(self.command)
        if self.reason not in NACK_REASON_CODES:
            raise ValueError(f"Invalid reason: {self.reason!r}")
        object.__setattr__(self, "reason", NackReason(self.reason))


CAL_FMT = struct.Struct("<BBhf")
assert CAL_FMT.size == 8


def validate_cal(msg) -> None:
    check_uint("axis", msg.axis, 8)
    if msg.axis > 2:
        raise ValueError(f"Invalid axis: {msg.axis!r} (0 = x, 1 = y, 2 = z)")
    check_uint("flags", msg.flags, 8)
    check_int("offset_q4", msg.offset_q4, -32768, 32767)
    s = float(msg.sensitivity)
    if not (np.isfinite(s) and s > 0):
        raise ValueError(f"Invalid sensitivity: {msg.sensitivity!r} (need a finite value > 0)")
    # Store as the float32 the wire carries, so that decode(encode(m)) == m.
    object.__setattr__(msg, "sensitivity", float(np.float32(s)))


@dataclass(frozen=True, slots=True)
class CalData(Message):
    """§4.7 CAL_DATA: ``axis`` u8, ``flags`` u8 (bit 0: stored in non-volatile memory),
    ``offset_q4`` i16 (zero-g offset in 1/16 count), ``sensitivity`` f32 (counts per g)."""

    TYPE = MsgType.CAL_DATA
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 5
    _FMT = CAL_FMT
    axis: int = 0
    flags: int = 0
    offset_q4: int = 0
    sensitivity: float = 1024.0

    def _validate(self) -> None:
        validate_cal(self)


@dataclass(frozen=True, slots=True, eq=False)
class Snapshot(Message):
    """§4.8 SNAPSHOT (gateway): ``counter`` u16, ``first_link`` u16, ``count`` u8, then ``count``
    40-bit sample words for links ``first_link .. first_link + count - 1``; ``node`` is the packing
    gateway's node id. Count 1..255 here; the transports cap it (serial 202: a longer frame is over
    1024 bytes; CAN FD 11).

    The samples are kept packed (``words``, 5 bytes each); `counts` and `status` unpack them.
    Build from arrays with `Snapshot.from_arrays`.
    """

    TYPE = MsgType.SNAPSHOT
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 2
    counter: int = 0
    first_link: int = 0
    words: bytes = b""

    HEADER_SIZE: ClassVar[int] = 5

    def _validate(self) -> None:
        check_uint("counter", self.counter, 16)
        check_uint("first_link", self.first_link, 16)
        if not isinstance(self.words, (bytes, bytearray, memoryview)):
            raise ValueError(f"Invalid words: {type(self.words).__name__} (need bytes)")
        object.__setattr__(self, "words", bytes(self.words))
        n, rem = divmod(len(self.words), SAMPLE_WORD_SIZE)
        if rem:
            raise ValueError(f"Invalid words: length {len(self.words)} is not a multiple of {SAMPLE_WORD_SIZE}")
        if not 1 <= n <= MAX_SNAPSHOT_SAMPLES:
            raise ValueError(f"Invalid count: {n} (need 1..{MAX_SNAPSHOT_SAMPLES})")
        if self.first_link + n > 0x10000:
            raise ValueError(f"Invalid first_link: {self.first_link} + count {n} exceeds 65536")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Snapshot):
            return NotImplemented
        return (self.node, self.counter, self.first_link, self.words) == (
            other.node, other.counter, other.first_link, other.words)

    def __hash__(self) -> int:
        return hash((self.node, self.counter, self.first_link, self.words))

    @classmethod
    def from_arrays(cls, node: int, counter: int, first_link: int, counts, status) -> "Snapshot":
        return cls(node, counter, first_link, pack_sample_words(counts, status))

    @property
    def count(self) -> int:
        return len(self.words) // SAMPLE_WORD_SIZE

    @property
    def counts(self) -> np.ndarray:
        """ADC counts, int16, shape (count, 3)."""
        return unpack_sample_words(self.words)[0]

    @property
    def status(self) -> np.ndarray:
        """SampleStatus bits, uint8, shape (count,)."""
        return unpack_sample_words(self.words)[1]

    def payload(self) -> bytes:
        return struct.pack("<HHB", self.counter, self.first_link, self.count) + self.words

    @classmethod
    def from_payload(cls, node: int, payload: bytes) -> "Snapshot":
        if len(payload) < cls.HEADER_SIZE + SAMPLE_WORD_SIZE:
            raise PayloadError("BAD_LENGTH", f"SNAPSHOT payload is at least 10 bytes, got {len(payload)}")
        counter, first, count = struct.unpack_from("<HHB", payload)
        if len(payload) != cls.HEADER_SIZE + SAMPLE_WORD_SIZE * count:
            raise PayloadError("BAD_LENGTH", f"SNAPSHOT with count {count} is "
                                             f"{cls.HEADER_SIZE + SAMPLE_WORD_SIZE * count} bytes, got {len(payload)}")
        try:
            return cls(node, counter, first, bytes(payload[5:]))
        except ValueError as exc:
            raise PayloadError("BAD_FIELD", str(exc)) from exc


@dataclass(frozen=True, slots=True, eq=False)
class SnapshotFrames:
    """Consecutive SNAPSHOT frames of one read, decoded at once: the event of
    `framing.StreamDecoder` with ``batch_snapshots`` (a host's serial transports; the packed
    64x64 sheet sends ~35 of them per SYNC), taken by `host.snapshots.aggregator.Aggregator` without a
    `Snapshot` object per frame.

    Per frame (length f): ``node``, ``frame_counter``, ``first_link`` uint16, ``sizes`` int64
    (its sample count). Per sample, over all frames in order (length n = ``sizes.sum()``):
    ``counter`` uint16, ``link`` int64 (``first_link`` + position), ``counts`` int16 (n, 3),
    ``status`` uint8 — what `unpack_snapshots` returns for the same frames.
    """

    node: np.ndarray
    frame_counter: np.ndarray
    first_link: np.ndarray
    sizes: np.ndarray
    counter: np.ndarray
    link: np.ndarray
    counts: np.ndarray
    status: np.ndarray

    def __len__(self) -> int:
        """The number of frames (what a transport counts as frames in)."""
        return int(self.node.shape[0])

    @classmethod
    def from_frames(cls, frames) -> "SnapshotFrames":
        """The batch of `Snapshot` messages ``frames`` (at least one)."""
        frames = list(frames)
        counter, link, counts, status = unpack_snapshots(frames)
        f = len(frames)
        return cls(np.fromiter((s.node for s in frames), dtype=np.uint16, count=f),
                   np.fromiter((s.counter for s in frames), dtype=np.uint16, count=f),
                   np.fromiter((s.first_link for s in frames), dtype=np.uint16, count=f),
                   np.fromiter((s.count for s in frames), dtype=np.int64, count=f),
                   counter, link.astype(np.int64), counts, status)

    def select(self, keep: np.ndarray) -> "SnapshotFrames":
        """The frames where ``keep`` (bool, per frame) is true, in order."""
        per_sample = np.repeat(keep, self.sizes)
        return SnapshotFrames(self.node[keep], self.frame_counter[keep], self.first_link[keep], self.sizes[keep],
                              self.counter[per_sample], self.link[per_sample], self.counts[per_sample],
                              self.status[per_sample])

    def messages(self) -> list[Snapshot]:
        """The batch as `Snapshot` messages (slow; for tests and display)."""
        ends = np.cumsum(self.sizes)
        return [Snapshot.from_arrays(int(self.node[k]), int(self.frame_counter[k]), int(self.first_link[k]),
                                     self.counts[e - n:e], self.status[e - n:e])
                for k, (n, e) in enumerate(zip(self.sizes.tolist(), ends.tolist()))]


@dataclass(frozen=True, slots=True)
class GatewayInfo(Message):
    """§4.16 GATEWAY_INFO (new in 1.1), sent by a gateway after its INFO: ``flags`` u8 (GatewayFlag: what it
    does now), ``sample_format`` u8 (SampleFormat of its SNAPSHOT words), ``first_link`` u16 and
    ``link_count`` u16 (one contiguous run of the links behind it; a gateway with several runs sends
    one GATEWAY_INFO per run), ``sync_rate_hz`` u16 (the rate of the SYNC it generates; 0 when it
    does not)."""

    TYPE = MsgType.GATEWAY_INFO
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 5
    _FMT = struct.Struct("<BBHHH")
    flags: int = 0
    sample_format: int = SampleFormat.ACCEL_12
    first_link: int = 0
    link_count: int = 0
    sync_rate_hz: int = 0

    def _validate(self) -> None:
        check_uint("flags", self.flags, 8)
        check_uint("sample_format", self.sample_format, 8)
        check_uint("first_link", self.first_link, 16)
        check_uint("link_count", self.link_count, 16)
        check_uint("sync_rate_hz", self.sync_rate_hz, 16)
        if self.first_link + self.link_count > 0x10000:
            raise ValueError(f"Invalid link_count: first_link {self.first_link} + {self.link_count} exceeds 65536")
        object.__setattr__(self, "flags", GatewayFlag(self.flags))

    @property
    def links(self) -> range:
        """The links of this run."""
        return range(self.first_link, self.first_link + self.link_count)


assert GatewayInfo._FMT.size == 8


