"""The IMU records of 6-axis and 9-axis chips (docs §16): IMU_SAMPLE, its classic-CAN parts IMU_GYRO,
IMU_MAG, IMU_ACCEL, and the packed SNAPSHOT_IMU."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..constants import ADC_MAX, ADC_MIN
from .base import (Direction, IMU_RECORD_SIZE, MAX_SNAPSHOT_SAMPLES, Message, MsgType, PayloadError,
    SAMPLE_WORD_SIZE, SampleFormat, TIME_UNKNOWN, check_int, check_uint, pack_sample_words,
    unpack_sample_words)


# --------------------------------------------------------------------------------------------
# IMU records (docs §16, new in 1.2): 6-axis and 9-axis chips
# --------------------------------------------------------------------------------------------

_I16_MIN, _I16_MAX = -32768, 32767


def _record_dtype(fmt: int) -> np.dtype:
    fields_ = [("word", "u1", (SAMPLE_WORD_SIZE,)), ("time_us", "<i2"), ("gyro", "<i2", (3,))]
    if fmt == SampleFormat.IMU9:
        fields_.append(("mag", "<i2", (3,)))
    dt = np.dtype(fields_)
    assert dt.itemsize == IMU_RECORD_SIZE[SampleFormat(fmt)]
    return dt


def imu_saturated(counts, gyro, mag=None) -> np.ndarray:
    """Per record, whether a count sent is at its rail (docs §16.1's SATURATED): an accelerometer
    count −2048 or +2047, a gyroscope or magnetometer count −32768 or +32767."""
    counts = np.asarray(counts)
    out = np.any((counts == ADC_MIN) | (counts == ADC_MAX), axis=-1)
    for a in (gyro, mag):
        if a is not None:
            a = np.asarray(a)
            out = out | np.any((a == _I16_MIN) | (a == _I16_MAX), axis=-1)
    return out


def pack_imu_records(counts, status, time_us, gyro, mag=None) -> bytes:
    """Pack IMU records (docs §16.1): 13 bytes each (``mag`` None, format 1) or 19 (format 2).

    ``counts`` (n, 3) accelerometer counts −2048..2047, ``status`` (n,) 0..15, ``time_us`` (n,)
    −32768..32767, ``gyro`` and ``mag`` (n, 3) −32768..32767. The status bits are sent as given."""
    counts = np.asarray(counts, dtype=np.int64)
    n = counts.shape[0] if counts.ndim == 2 else -1
    cols = {"time_us": (np.asarray(time_us, dtype=np.int64), (n,)), "gyro": (np.asarray(gyro, dtype=np.int64), (n, 3))}
    if mag is not None:
        cols["mag"] = (np.asarray(mag, dtype=np.int64), (n, 3))
    for name, (a, shape) in cols.items():
        if a.shape != shape:
            raise ValueError(f"Expected `{name}` to have shape {shape}, got {a.shape}.")
        if a.size and (a.min() < _I16_MIN or a.max() > _I16_MAX):
            raise ValueError(f"Invalid {name}: outside {_I16_MIN}..{_I16_MAX}")
    words = pack_sample_words(counts, status)  # checks counts and status
    fmt = SampleFormat.IMU9 if mag is not None else SampleFormat.IMU6
    rec = np.zeros(n, dtype=_record_dtype(fmt))
    rec["word"] = np.frombuffer(words, dtype=np.uint8).reshape(n, SAMPLE_WORD_SIZE)
    for name, (a, _shape) in cols.items():
        rec[name] = a
    return rec.tobytes()


def unpack_imu_records(data, fmt: int):
    """Inverse of `pack_imu_records`: ``(counts int16 (n, 3), status uint8 (n,), time_us int16 (n,),
    gyro int16 (n, 3), mag int16 (n, 3) or None)``."""
    fmt = SampleFormat(fmt)
    if fmt not in IMU_RECORD_SIZE:
        raise ValueError(f"Invalid format: {int(fmt)} (IMU records are format 1 or 2)")
    b = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data.reshape(-1)
    size = IMU_RECORD_SIZE[fmt]
    if b.size % size:
        raise ValueError(f"Format-{int(fmt)} records are a multiple of {size} bytes, got {b.size}")
    rec = np.ascontiguousarray(b).view(_record_dtype(fmt))
    counts, status = unpack_sample_words(np.ascontiguousarray(rec["word"]).reshape(-1))
    mag = rec["mag"].astype(np.int16) if fmt == SampleFormat.IMU9 else None
    return counts, status, rec["time_us"].astype(np.int16), rec["gyro"].astype(np.int16), mag


def unpack_snapshots_imu(snapshots):
    """Unpack many SNAPSHOT_IMU messages at once (one numpy pass instead of `SnapshotImu.arrays` on each):
    the IMU twin of `unpack_snapshots`, the host's fast path for a gateway packing 6/9-axis records.

    Returns ``(counter uint16 (n,), link uint32 (n,), counts int16 (n, 3), status uint8 (n,), time_us
    int16 (n,), gyro int16 (n, 3), mag int16 (n, 3) or None)`` over all their records, in order: exactly
    the concatenation of each message's `arrays` (tests/protocol/test_messages.py). The messages are of one
    format (a gateway packs one, GATEWAY_INFO ``sample_format``); a list that mixes formats 1 and 2 is a
    ValueError (the caller groups by format); no message gives format-1 empties (``mag`` None)."""
    snapshots = snapshots if isinstance(snapshots, list) else list(snapshots)
    if not snapshots:
        return (np.zeros(0, np.uint16), np.zeros(0, np.uint32), np.zeros((0, 3), np.int16), np.zeros(0, np.uint8),
                np.zeros(0, np.int16), np.zeros((0, 3), np.int16), None)
    fmt = snapshots[0].format
    if any(s.format != fmt for s in snapshots):
        raise ValueError(f"SNAPSHOT_IMU of formats {sorted({int(s.format) for s in snapshots})} in one batch "
                         f"(unpack each format apart)")
    size = IMU_RECORD_SIZE[fmt]
    k = len(snapshots)
    sizes = np.fromiter((len(s.records) for s in snapshots), dtype=np.int64, count=k) // size
    counter = np.repeat(np.fromiter((s.counter for s in snapshots), dtype=np.uint16, count=k), sizes)
    firsts = np.fromiter((s.first_link for s in snapshots), dtype=np.int64, count=k)
    offsets = np.arange(sizes.sum()) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    link = (np.repeat(firsts, sizes) + offsets).astype(np.uint32)
    counts, status, time_us, gyro, mag = unpack_imu_records(b"".join(s.records for s in snapshots), fmt)
    return counter, link, counts, status, time_us, gyro, mag


def _check_i16(name: str, value) -> None:
    check_int(name, value, _I16_MIN, _I16_MAX)


@dataclass(frozen=True, slots=True)
class ImuSample(Message):
    """§16.3 IMU_SAMPLE: ``counter`` u16, then one IMU record (§16.1): the accelerometer word (x, y, z
    12-bit counts, 4 status bits), ``time_us`` i16 (µs after the SYNC; `TIME_UNKNOWN` = unknown),
    gyroscope ``gx, gy, gz`` i16, and for format 2 magnetometer ``mx, my, mz`` i16 (None in format 1).
    15 or 21 bytes; on classic CAN it travels as IMU_GYRO (+ IMU_MAG) + IMU_ACCEL (§16.4)."""

    TYPE = MsgType.IMU_SAMPLE
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 2
    counter: int = 0
    x: int = 0
    y: int = 0
    z: int = 0
    status: int = 0
    time_us: int = TIME_UNKNOWN
    gx: int = 0
    gy: int = 0
    gz: int = 0
    mx: int | None = None
    my: int | None = None
    mz: int | None = None

    SIZES: ClassVar[dict] = {2 + 13: SampleFormat.IMU6, 2 + 19: SampleFormat.IMU9}

    def _validate(self) -> None:
        check_uint("counter", self.counter, 16)
        for name in ("x", "y", "z"):
            check_int(name, getattr(self, name), ADC_MIN, ADC_MAX)
        check_uint("status", self.status, 4)
        for name in ("time_us", "gx", "gy", "gz"):
            _check_i16(name, getattr(self, name))
        mags = (self.mx, self.my, self.mz)
        if any(m is not None for m in mags):
            if any(m is None for m in mags):
                raise ValueError(f"Invalid magnetometer: {mags!r} (all three axes or none)")
            for name in ("mx", "my", "mz"):
                _check_i16(name, getattr(self, name))

    @property
    def format(self) -> SampleFormat:
        return SampleFormat.IMU6 if self.mx is None else SampleFormat.IMU9

    @property
    def gyro(self) -> tuple[int, int, int]:
        return (self.gx, self.gy, self.gz)

    @property
    def mag(self) -> tuple[int, int, int] | None:
        return None if self.mx is None else (self.mx, self.my, self.mz)

    def record(self) -> bytes:
        """The IMU record (§16.1), without the counter."""
        mag = None if self.mx is None else [self.mag]
        return pack_imu_records([(self.x, self.y, self.z)], [self.status], [self.time_us], [self.gyro], mag)

    def payload(self) -> bytes:
        return self.counter.to_bytes(2, "little") + self.record()

    @classmethod
    def from_payload(cls, node: int, payload: bytes) -> "ImuSample":
        fmt = cls.SIZES.get(len(payload))
        if fmt is None:
            raise PayloadError("BAD_LENGTH", f"IMU_SAMPLE payload is 15 or 21 bytes, got {len(payload)}")
        counts, status, t, g, m = unpack_imu_records(bytes(payload[2:]), fmt)
        mag = (None, None, None) if m is None else tuple(int(v) for v in m[0])
        return cls(node, payload[0] | (payload[1] << 8), *(int(v) for v in counts[0]), int(status[0]),
                   int(t[0]), *(int(v) for v in g[0]), *mag)


@dataclass(frozen=True, slots=True)
class ImuGyro(Message):
    """§16.4 IMU_GYRO (classic CAN, a record's first frame): ``counter`` u16, ``gx, gy, gz`` i16."""

    TYPE = MsgType.IMU_GYRO
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 2
    _FMT = struct.Struct("<Hhhh")
    counter: int = 0
    gx: int = 0
    gy: int = 0
    gz: int = 0

    def _validate(self) -> None:
        check_uint("counter", self.counter, 16)
        for name in ("gx", "gy", "gz"):
            _check_i16(name, getattr(self, name))


@dataclass(frozen=True, slots=True)
class ImuMag(Message):
    """§16.4 IMU_MAG (classic CAN, format 2's middle frame): ``counter`` u16, ``mx, my, mz`` i16."""

    TYPE = MsgType.IMU_MAG
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 2
    _FMT = struct.Struct("<Hhhh")
    counter: int = 0
    mx: int = 0
    my: int = 0
    mz: int = 0

    def _validate(self) -> None:
        check_uint("counter", self.counter, 16)
        for name in ("mx", "my", "mz"):
            _check_i16(name, getattr(self, name))


@dataclass(frozen=True, slots=True)
class ImuAccel(Message):
    """§16.4 IMU_ACCEL (classic CAN, a record's last frame): ``counter_lo`` u8 (the counter's low
    byte), the accelerometer word (x, y, z, status; §5.2), ``time_us`` i16. 8 bytes."""

    TYPE = MsgType.IMU_ACCEL
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 2
    counter_lo: int = 0
    x: int = 0
    y: int = 0
    z: int = 0
    status: int = 0
    time_us: int = TIME_UNKNOWN

    SIZE: ClassVar[int] = 8

    def _validate(self) -> None:
        check_uint("counter_lo", self.counter_lo, 8)
        for name in ("x", "y", "z"):
            check_int(name, getattr(self, name), ADC_MIN, ADC_MAX)
        check_uint("status", self.status, 4)
        _check_i16("time_us", self.time_us)

    def payload(self) -> bytes:
        return (bytes([self.counter_lo]) + pack_sample_words([(self.x, self.y, self.z)], [self.status])
                + struct.pack("<h", self.time_us))

    @classmethod
    def from_payload(cls, node: int, payload: bytes) -> "ImuAccel":
        if len(payload) != cls.SIZE:
            raise PayloadError("BAD_LENGTH", f"IMU_ACCEL payload is {cls.SIZE} bytes, got {len(payload)}")
        counts, status = unpack_sample_words(bytes(payload[1:6]))
        return cls(node, payload[0], *(int(v) for v in counts[0]), int(status[0]),
                   struct.unpack_from("<h", payload, 6)[0])


def imu_sample_to_can_parts(msg: ImuSample) -> list[Message]:
    """The classic CAN frames of one record (§16.4), in their sending order."""
    parts: list[Message] = [ImuGyro(msg.node, msg.counter, msg.gx, msg.gy, msg.gz)]
    if msg.mx is not None:
        parts.append(ImuMag(msg.node, msg.counter, msg.mx, msg.my, msg.mz))
    parts.append(ImuAccel(msg.node, msg.counter & 0xFF, msg.x, msg.y, msg.z, msg.status, msg.time_us))
    return parts


@dataclass(frozen=True, slots=True, eq=False)
class SnapshotImu(Message):
    """§16.5 SNAPSHOT_IMU (gateway): ``counter`` u16, ``first_link`` u16, ``count`` u8, ``format`` u8
    (1: 13-byte, 2: 19-byte records), then ``count`` IMU records (§16.1) for links
    ``first_link .. first_link + count − 1``. Records are kept packed (``records``); `arrays` unpacks."""

    TYPE = MsgType.SNAPSHOT_IMU
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 2
    counter: int = 0
    first_link: int = 0
    format: int = SampleFormat.IMU6
    records: bytes = b""

    HEADER_SIZE: ClassVar[int] = 6

    def _validate(self) -> None:
        check_uint("counter", self.counter, 16)
        check_uint("first_link", self.first_link, 16)
        if self.format not in IMU_RECORD_SIZE:
            raise ValueError(f"Invalid format: {self.format!r} (1 = 6-axis, 2 = 9-axis records)")
        object.__setattr__(self, "format", SampleFormat(self.format))
        if not isinstance(self.records, (bytes, bytearray, memoryview)):
            raise ValueError(f"Invalid records: {type(self.records).__name__} (need bytes)")
        object.__setattr__(self, "records", bytes(self.records))
        n, rem = divmod(len(self.records), IMU_RECORD_SIZE[self.format])
        if rem:
            raise ValueError(f"Invalid records: length {len(self.records)} is not a multiple of "
                             f"{IMU_RECORD_SIZE[self.format]}")
        if not 1 <= n <= MAX_SNAPSHOT_SAMPLES:
            raise ValueError(f"Invalid count: {n} (need 1..{MAX_SNAPSHOT_SAMPLES})")
        if self.first_link + n > 0x10000:
            raise ValueError(f"Invalid first_link: {self.first_link} + count {n} exceeds 65536")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SnapshotImu):
            return NotImplemented
        return (self.node, self.counter, self.first_link, self.format, self.records) == (
            other.node, other.counter, other.first_link, other.format, other.records)

    def __hash__(self) -> int:
        return hash((self.node, self.counter, self.first_link, self.format, self.records))

    @classmethod
    def from_arrays(cls, node: int, counter: int, first_link: int, counts, status, time_us, gyro,
                    mag=None) -> "SnapshotImu":
        fmt = SampleFormat.IMU6 if mag is None else SampleFormat.IMU9
        return cls(node, counter, first_link, fmt, pack_imu_records(counts, status, time_us, gyro, mag))

    @property
    def count(self) -> int:
        return len(self.records) // IMU_RECORD_SIZE[self.format]

    def arrays(self):
        """``(counts, status, time_us, gyro, mag or None)`` as `unpack_imu_records`."""
        return unpack_imu_records(self.records, self.format)

    def payload(self) -> bytes:
        return struct.pack("<HHBB", self.counter, self.first_link, self.count, self.format) + self.records

    @classmethod
    def from_payload(cls, node: int, payload: bytes) -> "SnapshotImu":
        if len(payload) < cls.HEADER_SIZE:
            raise PayloadError("BAD_LENGTH", f"SNAPSHOT_IMU payload is at least 6 bytes, got {len(payload)}")
        counter, first, count, fmt = struct.unpack_from("<HHBB", payload)
        size = IMU_RECORD_SIZE.get(fmt)
        if size is None:
            raise PayloadError("BAD_FIELD", f"SNAPSHOT_IMU format {fmt} (1 = 6-axis, 2 = 9-axis records)")
        if count == 0 or len(payload) != cls.HEADER_SIZE + size * count:
            raise PayloadError("BAD_LENGTH", f"SNAPSHOT_IMU with format {fmt} and count {count} is "
                                             f"{cls.HEADER_SIZE + size * count} bytes, got {len(payload)}")
        try:
            return cls(node, counter, first, fmt, bytes(payload[cls.HEADER_SIZE:]))
        except ValueError as exc:
            raise PayloadError("BAD_FIELD", str(exc)) from exc


