"""Message set of the capsheet wire protocol v1.2 (docs/protocol.md §4, §16).

Every message is a frozen, slotted dataclass that validates itself when built. The *payload* layout
of a message is the same on every transport; serial wraps it in a header + CRC + COBS
(`protocol.framing`), CAN carries it as the frame data with type and node in the identifier
(`protocol.can`). All multi-byte fields are little-endian.

``node`` is the chip a frame comes from (chip -> host) or is addressed to (host -> chip);
``node == 0`` from the host means every chip (broadcast). See docs/protocol.md §3.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, fields
from enum import IntEnum, IntFlag
from typing import ClassVar

import numpy as np

from .constants import ADC_MAX, ADC_MIN

__all__ = [
    "PROTOCOL_VERSION", "SPEC_VERSION", "MsgType", "Direction", "ChipState", "Capability", "StatusFlag",
    "NackReason", "GatewayFlag", "SampleFormat", "RESERVED_CAPABILITIES", "NODE_TO_HOST_TYPES", "HOST_TO_NODE_TYPES",
    "LINK_NONE", "is_node_to_host_type",
    "NODE_BROADCAST", "NODE_MAX_ASSIGNED", "NODE_PROVISIONAL_MIN", "NODE_PROVISIONAL_MAX",
    "SAMPLE_WORD_SIZE", "MAX_SNAPSHOT_SAMPLES",
    "Message", "Announce", "Info", "Sample", "SampleBatch", "ImuBatch", "Status", "StatusBatch", "STATUS_STATES", "Ack", "Nack", "CalData", "Snapshot", "SnapshotFrames",
    "GatewayInfo", "Sync", "Assign", "Config", "Start", "Stop", "GetInfo", "Reset", "CalWrite", "CalRead",
    "MESSAGE_TYPES", "message_to_fields", "message_from_fields", "pack_sample_words", "unpack_sample_words", "unpack_snapshots", "PayloadError", "decode_payload",
    "provisional_node",
    "ImuGyro", "ImuMag", "ImuAccel", "ImuSample", "SnapshotImu", "ConfigImu", "TIME_UNKNOWN", "IMU_RECORD_SIZE",
    "MAX_SERIAL_IMU_RECORDS", "ConfigImuFlag", "IMU_TYPES", "imu_sample_to_can_parts", "pack_imu_records", "unpack_imu_records", "unpack_snapshots_imu", "imu_saturated",
    "CalBlock", "CAL_BLOCK_SIZE", "CalImuData", "CalImuWrite", "CalImuRead", "cal_block_nominal",
]

#: Protocol version carried in every serial frame (byte 0) and every CAN identifier (bits 19..16):
#: the major version. Minor revisions of the document (1.1) add types and capability bits only and
#: keep it (docs §12).
PROTOCOL_VERSION = 1
#: The revision of docs/protocol.md this code implements (major, minor).
SPEC_VERSION = (1, 3)

#: Type codes a node sends to the host (docs §4): 0x01..0x0F, defined or not. A chip ignores every
#: frame with such a type, whatever its node (another node's frame, perhaps of a later revision).
NODE_TO_HOST_TYPES = range(0x01, 0x10)
#: Type codes the host sends to nodes: 0x10..0x2F. 0x00 and 0x30..0x3F are reserved.
HOST_TO_NODE_TYPES = range(0x10, 0x30)
#: ASSIGN ``link`` for a node that sits on no link (a gateway, docs §13).
LINK_NONE = 0xFFFF


def is_node_to_host_type(type_code: int) -> bool:
    """Whether ``type_code`` is in the node -> host range 0x01..0x0F (docs §4), defined or not."""
    return 0x01 <= type_code <= 0x0F

NODE_BROADCAST = 0x0000  #: host -> every chip
NODE_MAX_ASSIGNED = 0x7FFF  #: assigned node ids are 1..0x7FFF
NODE_PROVISIONAL_MIN = 0x8000  #: an unassigned chip speaks from 0x8000..0xFFFE (docs §3.2)
NODE_PROVISIONAL_MAX = 0xFFFE  #: 0xFFFF is reserved and never valid

SAMPLE_WORD_SIZE = 5  #: one packed sample: 3 x 12-bit axes + 4 status bits = 40 bits
MAX_SNAPSHOT_SAMPLES = 255  #: SNAPSHOT's count field is u8; transports cap it lower (§6, §7)


class MsgType(IntEnum):
    """Message type codes (docs/protocol.md §4). 6 bits: the CAN identifier has room for 0..63."""

    # chip -> host
    ANNOUNCE = 0x01  #: §4.1 a chip is here: its 64-bit unique id
    INFO = 0x02  #: §4.2 firmware version, protocol version, capabilities, state
    SAMPLE = 0x03  #: §4.3 one sample for one SYNC counter
    STATUS = 0x04  #: §4.4 heartbeat: state, error counters, uptime
    ACK = 0x05  #: §4.5 a command was carried out
    NACK = 0x06  #: §4.6 a command was refused, with a reason
    CAL_DATA = 0x07  #: §4.7 one axis of stored calibration
    SNAPSHOT = 0x08  #: §4.8 a gateway's packed samples of many links for one counter
    GATEWAY_INFO = 0x09  #: §4.16 a gateway's packing, SYNC source and links (v1.1)
    IMU_GYRO = 0x0A  #: §16.4 classic CAN, first frame of an IMU record: counter + gyroscope (v1.2)
    IMU_MAG = 0x0B  #: §16.4 classic CAN, format 2's middle frame: counter + magnetometer (v1.2)
    IMU_ACCEL = 0x0C  #: §16.4 classic CAN, last frame: counter low byte + accel word + time_us (v1.2)
    IMU_SAMPLE = 0x0D  #: §16.3 one IMU record for one SYNC counter, serial and CAN FD (v1.2)
    SNAPSHOT_IMU = 0x0E  #: §16.5 a gateway's packed IMU records of many links for one counter (v1.2)
    CAL_IMU_DATA = 0x0F  #: §17.1 one element of a gyroscope or magnetometer calibration (v1.3)
    # host -> chip
    SYNC = 0x10  #: §4.9 sample now; broadcast, carries the counter
    ASSIGN = 0x11  #: §4.10 give a chip its node id and lattice address
    CONFIG = 0x12  #: §4.11 rate, range, filter, heartbeat period
    START = 0x13  #: §4.12 start answering SYNC
    STOP = 0x14  #: §4.12 stop answering SYNC
    GET_INFO = 0x15  #: §4.13 ask for ANNOUNCE + INFO
    RESET = 0x16  #: §4.14 forget the assignment, reboot, announce again
    CAL_WRITE = 0x17  #: §4.15 write one axis of calibration
    CAL_READ = 0x18  #: §4.15 read one axis of calibration (answered by CAL_DATA)
    CONFIG_IMU = 0x19  #: §16.2 sample format, gyroscope and magnetometer ranges (v1.2)
    CAL_IMU_WRITE = 0x1A  #: §17.2 write one element of a gyroscope or magnetometer calibration (v1.3)
    CAL_IMU_READ = 0x1B  #: §17.2 read one element (answered by CAL_IMU_DATA) (v1.3)


class Direction(IntEnum):
    CHIP_TO_HOST = 0
    HOST_TO_CHIP = 1


class ChipState(IntEnum):
    """Chip states (docs/protocol.md §8; the tables are protocol/state.py)."""

    BOOT = 0  #: unassigned: speaks from a provisional node id, announces
    IDLE = 1  #: assigned, configured, not streaming
    STREAMING = 2  #: answers every SYNC with a SAMPLE
    FAULT = 3  #: sensor fault: answers SYNC with INVALID samples, reports in STATUS


class Capability(IntFlag):
    """INFO capability bits (docs/protocol.md §4.2)."""

    NONE = 0
    CAN_FD = 0x0001  #: can send and receive CAN FD frames
    SNAPSHOT = 0x0002  #: a gateway that can pack samples into SNAPSHOT frames (§13.2)
    SELF_TEST = 0x0004  #: has a self-test started by means outside the protocol (no v1.1 command)
    CAL_STORAGE = 0x0008  #: keeps calibration in non-volatile memory
    MULTI_RANGE = 0x0010  #: supports range codes other than ±2 g
    FILTER = 0x0020  #: supports CONFIG filter codes other than 0
    GATEWAY = 0x0040  #: the node is a gateway, not a chip: it sits on no link (v1.1, §13)
    SYNC_SOURCE = 0x0080  #: a gateway that can generate its segment's SYNC (v1.1, §13.3)
    GYRO = 0x0100  #: a triaxial gyroscope: CONFIG_IMU formats 1 and 2 (v1.2, §16)
    MAG = 0x0200  #: a triaxial magnetometer: CONFIG_IMU format 2 (v1.2, §16)
    SAMPLE_TIME = 0x0400  #: IMU records carry a true time_us (without it: TIME_UNKNOWN) (v1.2, §16.1)


#: INFO capability bits reserved in v1.2 (bits 11..15): sent as 0, ignored on receipt.
RESERVED_CAPABILITIES = 0xF800


class GatewayFlag(IntFlag):
    """GATEWAY_INFO flags (docs/protocol.md §4.16): what the gateway does now."""

    NONE = 0
    PACKING = 0x01  #: answers SYNC with SNAPSHOT frames of its links (not the chips' SAMPLEs)
    SYNC_SOURCE = 0x02  #: generates its segment's SYNC; passes no SYNC from the host to the segment


class SampleFormat(IntEnum):
    """What a chip answers SYNC with (CONFIG_IMU ``format``, docs §16.2) and what a gateway packs
    (GATEWAY_INFO ``sample_format``, §4.16): the same codes."""

    ACCEL_12 = 0  #: §5.2: three 12-bit accelerometer axes + 4 status bits, 5 bytes (SAMPLE, SNAPSHOT)
    IMU6 = 1  #: §16.1: accel word, time_us, gyroscope: 13-byte records (IMU_SAMPLE, SNAPSHOT_IMU)
    IMU9 = 2  #: §16.1: accel word, time_us, gyroscope, magnetometer: 19-byte records


class ConfigImuFlag(IntFlag):
    """CONFIG_IMU ``flags`` (docs §16.2)."""

    NONE = 0
    FD = 0x01  #: on CAN, one IMU_SAMPLE per record in a CAN FD frame (else the classic frames of §16.4)


#: ``time_us`` of an IMU record whose time is not known (a chip without SAMPLE_TIME, an INVALID record).
TIME_UNKNOWN = -32768
#: bytes of one IMU record by format (docs §16.1)
IMU_RECORD_SIZE = {SampleFormat.IMU6: 13, SampleFormat.IMU9: 19}
#: SNAPSHOT_IMU records in one serial frame (payload <= 1018 bytes, docs §16.5)
MAX_SERIAL_IMU_RECORDS = {f: (1018 - 6) // size for f, size in IMU_RECORD_SIZE.items()}
assert MAX_SERIAL_IMU_RECORDS == {SampleFormat.IMU6: 77, SampleFormat.IMU9: 53}


class StatusFlag(IntFlag):
    """STATUS flag bits (docs/protocol.md §4.4)."""

    NONE = 0
    CAL_VALID = 0x01  #: calibration was loaded from storage (else nominal values)
    SELF_TEST_ON = 0x02  #: self-test excitation is on
    ADC_FAULT = 0x04  #: the sensor did not answer
    CONFIGURED = 0x08  #: a CONFIG was accepted since the last reset


class NackReason(IntEnum):
    """NACK reason codes (docs/protocol.md §4.6)."""

    UNKNOWN_COMMAND = 1  #: an undefined type outside 0x01..0x0F, addressed to the node
    BAD_LENGTH = 2  #: the payload length does not match the type
    BAD_VALUE = 3  #: a field is out of range (e.g. range code 7)
    BAD_STATE = 4  #: not allowed in the current state (e.g. START before ASSIGN)
    UNSUPPORTED = 5  #: valid but this chip lacks the capability
    BAD_VERSION = 6  #: the frame's protocol version is not this chip's
    STORAGE_FAILED = 7  #: calibration could not be written


class PayloadError(ValueError):
    """A payload that does not decode: ``reason`` is an ErrorReason name (see protocol.framing)."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


def _check_uint(name: str, value: int, bits: int) -> None:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or not 0 <= value < (1 << bits):
        raise ValueError(f"Invalid {name}: {value!r} (need an integer in 0..{(1 << bits) - 1})")


def _check_int(name: str, value: int, lo: int, hi: int) -> None:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or not lo <= value <= hi:
        raise ValueError(f"Invalid {name}: {value!r} (need an integer in {lo}..{hi})")


def provisional_node(uid: int, salt: int = 0) -> int:
    """The recommended provisional node id of an unassigned chip (docs §3.2), in 32-bit
    arithmetic a small MCU does cheaply::

        h  = (uint32)(uid ^ (uid >> 32)) ^ (uint32)(salt * 0x9E3779B9)
        h ^= h >> 16
        node = 0x8000 | (h % 0x7FFF)

    A chip takes a new ``salt`` (e.g. the number of unanswered ANNOUNCEs) when its ANNOUNCE goes
    unanswered, so two chips that collided once do not collide again.

    >>> hex(provisional_node(0x0123456789ABCDEF))
    '0x9112'
    """
    _check_uint("uid", uid, 64)
    h = ((uid ^ (uid >> 32)) & 0xFFFFFFFF) ^ ((salt * 0x9E3779B9) & 0xFFFFFFFF)
    h ^= h >> 16
    return NODE_PROVISIONAL_MIN | (h % 0x7FFF)


# --------------------------------------------------------------------------------------------
# Base class
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class Message:
    """Base of every message. Subclasses set TYPE, DIRECTION, PRIORITY and their payload codec."""

    TYPE: ClassVar[MsgType]
    DIRECTION: ClassVar[Direction]
    PRIORITY: ClassVar[int]  #: CAN identifier bits 28..26 (0 = most urgent), docs §7.1
    _FMT: ClassVar[struct.Struct | None] = None  #: fixed payload layout, if any

    node: int

    def __post_init__(self) -> None:
        _check_uint("node", self.node, 16)
        if self.node == 0xFFFF:
            raise ValueError("Invalid node: 65535 (0xFFFF is reserved)")
        self._validate()

    def _validate(self) -> None:  # pragma: no cover - overridden where there are fields
        pass

    @classmethod
    def payload_struct(cls) -> struct.Struct | None:
        """The fixed payload layout (docs §4) of this type, or None where the payload is not one
        fixed struct (SAMPLE, SNAPSHOT). The DBC is generated from it (`protocol.dbc`)."""
        return cls._FMT

    # Fixed-layout messages: the payload is the struct of the fields after `node`, in order.
    def payload(self) -> bytes:
        """The payload bytes (docs §4), without header, CRC or CAN identifier."""
        fmt = self._FMT
        assert fmt is not None, type(self).__name__
        return fmt.pack(*(getattr(self, f.name) for f in fields(self)[1:]))

    @classmethod
    def from_payload(cls, node: int, payload: bytes) -> "Message":
        """Build from payload bytes; raises `PayloadError` (BAD_LENGTH or BAD_FIELD)."""
        fmt = cls._FMT
        assert fmt is not None, cls.__name__
        if len(payload) != fmt.size:
            raise PayloadError("BAD_LENGTH", f"{cls.TYPE.name} payload is {fmt.size} bytes, got {len(payload)}")
        try:
            return cls(node, *fmt.unpack(payload))
        except ValueError as exc:
            raise PayloadError("BAD_FIELD", str(exc)) from exc


# --------------------------------------------------------------------------------------------
# Packed samples: the 40-bit sample word (docs §5.2)
# --------------------------------------------------------------------------------------------

def pack_sample_words(counts: np.ndarray, status: np.ndarray) -> bytes:
    """Pack samples into 5-byte little-endian words.

    Parameters
    ----------
    counts : ndarray, shape (n, 3), int
        ADC counts, each in -2048..2047 (12-bit two's complement on the wire).
    status : ndarray, shape (n,), int
        SampleStatus bits, each in 0..15.

    Returns
    -------
    bytes, length 5 * n. Word bits: x 0..11, y 12..23, z 24..35, status 36..39.
    """
    counts = np.asarray(counts, dtype=np.int64)
    status = np.asarray(status, dtype=np.int64)
    if counts.ndim != 2 or counts.shape[1] != 3:
        raise ValueError(f"Expected `counts` to have shape (n, 3), got {counts.shape}.")
    if status.shape != (counts.shape[0],):
        raise ValueError(f"Expected `status` to have shape ({counts.shape[0]},), got {status.shape}.")
    if counts.size and (counts.min() < ADC_MIN or counts.max() > ADC_MAX):
        raise ValueError(f"Invalid counts: outside {ADC_MIN}..{ADC_MAX}")
    if status.size and (status.min() < 0 or status.max() > 15):
        raise ValueError("Invalid status: outside 0..15")
    u = counts & 0xFFF
    word = u[:, 0] | (u[:, 1] << 12) | (u[:, 2] << 24) | (status << 36)
    return word.astype("<u8").view(np.uint8).reshape(-1, 8)[:, :SAMPLE_WORD_SIZE].tobytes()


def unpack_sample_words(data: bytes | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of `pack_sample_words`: ``(counts int16 (n, 3), status uint8 (n,))``."""
    b = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data
    if b.size % SAMPLE_WORD_SIZE:
        raise ValueError(f"Packed samples are a multiple of {SAMPLE_WORD_SIZE} bytes, got {b.size}")
    n = b.size // SAMPLE_WORD_SIZE
    w = np.zeros((n, 8), dtype=np.uint8)
    w[:, :SAMPLE_WORD_SIZE] = b.reshape(n, SAMPLE_WORD_SIZE)
    word = w.view("<u8")  # (n, 1)
    axes = ((word >> _AXIS_SHIFTS) & np.uint64(0xFFF)).astype(np.int16)
    counts = (axes << 4) >> 4  # sign-extend 12 -> 16 bits (arithmetic shift)
    status = (word[:, 0] >> np.uint64(36)).astype(np.uint8)
    return counts, status


_AXIS_SHIFTS = np.array([0, 12, 24], dtype=np.uint64)


def unpack_snapshots(snapshots) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Unpack many SNAPSHOT messages at once (one numpy pass instead of one per frame).

    Returns ``(counter uint16 (n,), link uint32 (n,), counts int16 (n, 3), status uint8 (n,))``
    over all their samples, in order: the host's fast path for packed gateways.
    """
    snapshots = list(snapshots)
    if not snapshots:
        return (np.zeros(0, np.uint16), np.zeros(0, np.uint32), np.zeros((0, 3), np.int16), np.zeros(0, np.uint8))
    sizes = np.fromiter((len(s.words) // SAMPLE_WORD_SIZE for s in snapshots), dtype=np.int64, count=len(snapshots))
    counter = np.repeat(np.fromiter((s.counter for s in snapshots), dtype=np.uint16, count=len(snapshots)), sizes)
    firsts = np.fromiter((s.first_link for s in snapshots), dtype=np.int64, count=len(snapshots))
    offsets = np.arange(sizes.sum()) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    link = (np.repeat(firsts, sizes) + offsets).astype(np.uint32)
    counts, status = unpack_sample_words(b"".join(s.words for s in snapshots))
    return counter, link, counts, status


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
        _check_uint("uid", self.uid, 64)


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
            _check_uint(name, getattr(self, name), 8)
        _check_uint("capabilities", self.capabilities, 16)
        if self.state not in ChipState._value2member_map_:
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
        _check_uint("counter", self.counter, 16)
        for name in ("x", "y", "z"):
            _check_int(name, getattr(self, name), ADC_MIN, ADC_MAX)
        _check_uint("status", self.status, 4)

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
        if self.state not in ChipState._value2member_map_:
            raise ValueError(f"Invalid state: {self.state!r}")
        object.__setattr__(self, "state", ChipState(self.state))
        for name in ("flags", "rx_errors", "missed_syncs"):
            _check_uint(name, getattr(self, name), 8)
        _check_uint("uptime_s", self.uptime_s, 32)
        object.__setattr__(self, "flags", StatusFlag(self.flags))


assert Status._FMT.size == Status.SIZE == 8

#: the STATUS states a chip may report (§4.4), for the decoders' vectorised checks
STATUS_STATES = np.array(sorted(int(v) for v in ChipState._value2member_map_), dtype=np.int64)


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
    _check_uint("command", value, 8)


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
        _check_uint("detail", self.detail, 8)


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
        if self.reason not in NackReason._value2member_map_:
            raise ValueError(f"Invalid reason: {self.reason!r}")
        object.__setattr__(self, "reason", NackReason(self.reason))


_CAL_FMT = struct.Struct("<BBhf")
assert _CAL_FMT.size == 8


def _validate_cal(msg) -> None:
    _check_uint("axis", msg.axis, 8)
    if msg.axis > 2:
        raise ValueError(f"Invalid axis: {msg.axis!r} (0 = x, 1 = y, 2 = z)")
    _check_uint("flags", msg.flags, 8)
    _check_int("offset_q4", msg.offset_q4, -32768, 32767)
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
    _FMT = _CAL_FMT
    axis: int = 0
    flags: int = 0
    offset_q4: int = 0
    sensitivity: float = 1024.0

    def _validate(self) -> None:
        _validate_cal(self)


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
        _check_uint("counter", self.counter, 16)
        _check_uint("first_link", self.first_link, 16)
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
    """§4.16 GATEWAY_INFO (v1.1), sent by a gateway after its INFO: ``flags`` u8 (GatewayFlag: what it
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
        _check_uint("flags", self.flags, 8)
        _check_uint("sample_format", self.sample_format, 8)
        _check_uint("first_link", self.first_link, 16)
        _check_uint("link_count", self.link_count, 16)
        _check_uint("sync_rate_hz", self.sync_rate_hz, 16)
        if self.first_link + self.link_count > 0x10000:
            raise ValueError(f"Invalid link_count: first_link {self.first_link} + {self.link_count} exceeds 65536")
        object.__setattr__(self, "flags", GatewayFlag(self.flags))

    @property
    def links(self) -> range:
        """The links of this run."""
        return range(self.first_link, self.first_link + self.link_count)


assert GatewayInfo._FMT.size == 8


# --------------------------------------------------------------------------------------------
# IMU records (docs §16, v1.2): 6-axis and 9-axis chips
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
    _check_int(name, value, _I16_MIN, _I16_MAX)


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
        _check_uint("counter", self.counter, 16)
        for name in ("x", "y", "z"):
            _check_int(name, getattr(self, name), ADC_MIN, ADC_MAX)
        _check_uint("status", self.status, 4)
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
        _check_uint("counter", self.counter, 16)
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
        _check_uint("counter", self.counter, 16)
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
        _check_uint("counter_lo", self.counter_lo, 8)
        for name in ("x", "y", "z"):
            _check_int(name, getattr(self, name), ADC_MIN, ADC_MAX)
        _check_uint("status", self.status, 4)
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
        _check_uint("counter", self.counter, 16)
        _check_uint("first_link", self.first_link, 16)
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


# --------------------------------------------------------------------------------------------
# host -> chip
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class Sync(Message):
    """§4.9 SYNC: ``counter`` u16. Always broadcast (node 0). Every streaming chip samples and
    answers with a SAMPLE carrying this counter."""

    TYPE = MsgType.SYNC
    DIRECTION = Direction.HOST_TO_CHIP
    PRIORITY = 0
    _FMT = struct.Struct("<H")
    node: int = NODE_BROADCAST
    counter: int = 0

    def _validate(self) -> None:
        if self.node != NODE_BROADCAST:
            raise ValueError(f"Invalid node: {self.node} (SYNC is always broadcast, node 0)")
        _check_uint("counter", self.counter, 16)


@dataclass(frozen=True, slots=True)
class Assign(Message):
    """§4.10 ASSIGN, sent to the chip's current (provisional or assigned) node id: ``new_node``
    u16 (1..0x7FFF), ``link`` u16 (lattice address), ``uid_low`` u32 (low 32 bits of the chip's
    uid: a chip whose uid does not match ignores the frame)."""

    TYPE = MsgType.ASSIGN
    DIRECTION = Direction.HOST_TO_CHIP
    PRIORITY = 4
    _FMT = struct.Struct("<HHI")
    new_node: int = 1
    link: int = 0
    uid_low: int = 0

    def _validate(self) -> None:
        if self.node == NODE_BROADCAST:
            raise ValueError("Invalid node: 0 (ASSIGN is addressed to one chip)")
        _check_int("new_node", self.new_node, 1, NODE_MAX_ASSIGNED)
        _check_uint("link", self.link, 16)
        _check_uint("uid_low", self.uid_low, 32)


@dataclass(frozen=True, slots=True)
class Config(Message):
    """§4.11 CONFIG: ``rate_hz`` u16 (expected SYNC rate, sizes the chip's filter; 1..4000),
    ``range`` u8 (Range code), ``filter`` u8 (0 = chip default, 1 = 50 Hz, 2 = 100 Hz,
    3 = 200 Hz low-pass), ``heartbeat_ms`` u16 (STATUS period; 0 = off)."""

    TYPE = MsgType.CONFIG
    DIRECTION = Direction.HOST_TO_CHIP
    PRIORITY = 4
    _FMT = struct.Struct("<HBBH")
    rate_hz: int = 145
    range: int = 0
    filter: int = 0
    heartbeat_ms: int = 1000

    def _validate(self) -> None:
        _check_uint("rate_hz", self.rate_hz, 16)
        _check_uint("range", self.range, 8)
        _check_uint("filter", self.filter, 8)
        _check_uint("heartbeat_ms", self.heartbeat_ms, 16)


assert Config._FMT.size == 6


@dataclass(frozen=True, slots=True)
class _Empty(Message):
    _FMT = struct.Struct("")

    def payload(self) -> bytes:
        return b""


@dataclass(frozen=True, slots=True)
class Start(_Empty):
    """§4.12 START: empty. Begin answering SYNC. Node 0 starts every assigned chip."""

    TYPE = MsgType.START
    DIRECTION = Direction.HOST_TO_CHIP
    PRIORITY = 4


@dataclass(frozen=True, slots=True)
class Stop(_Empty):
    """§4.12 STOP: empty. Stop answering SYNC."""

    TYPE = MsgType.STOP
    DIRECTION = Direction.HOST_TO_CHIP
    PRIORITY = 1


@dataclass(frozen=True, slots=True)
class GetInfo(_Empty):
    """§4.13 GET_INFO: empty. The chip answers ANNOUNCE then INFO. Node 0: every chip (discovery)."""

    TYPE = MsgType.GET_INFO
    DIRECTION = Direction.HOST_TO_CHIP
    PRIORITY = 4


@dataclass(frozen=True, slots=True)
class Reset(_Empty):
    """§4.14 RESET: empty. The chip answers ACK, forgets its assignment and boots (ANNOUNCE, INFO)."""

    TYPE = MsgType.RESET
    DIRECTION = Direction.HOST_TO_CHIP
    PRIORITY = 1


@dataclass(frozen=True, slots=True)
class CalWrite(Message):
    """§4.15 CAL_WRITE: same layout as CAL_DATA; ``flags`` bit 0 asks the chip to store it in
    non-volatile memory (NACK UNSUPPORTED without CAL_STORAGE)."""

    TYPE = MsgType.CAL_WRITE
    DIRECTION = Direction.HOST_TO_CHIP
    PRIORITY = 4
    _FMT = _CAL_FMT
    axis: int = 0
    flags: int = 0
    offset_q4: int = 0
    sensitivity: float = 1024.0

    def _validate(self) -> None:
        if self.node == NODE_BROADCAST:
            raise ValueError("Invalid node: 0 (CAL_WRITE is addressed to one chip)")
        _validate_cal(self)


@dataclass(frozen=True, slots=True)
class CalRead(Message):
    """§4.15 CAL_READ: ``axis`` u8. Answered by CAL_DATA."""

    TYPE = MsgType.CAL_READ
    DIRECTION = Direction.HOST_TO_CHIP
    PRIORITY = 4
    _FMT = struct.Struct("<B")
    axis: int = 0

    def _validate(self) -> None:
        if self.node == NODE_BROADCAST:
            raise ValueError("Invalid node: 0 (CAL_READ is addressed to one chip)")
        _check_uint("axis", self.axis, 8)
        if self.axis > 2:
            raise ValueError(f"Invalid axis: {self.axis!r} (0 = x, 1 = y, 2 = z)")


@dataclass(frozen=True, slots=True)
class ConfigImu(Message):
    """§16.2 CONFIG_IMU: ``format`` u8 (SampleFormat: 0 SAMPLE, 1 accel + gyro, 2 accel + gyro + mag),
    ``gyro_range`` u8 (GyroRange 0..4), ``mag_range`` u8 (MagRange 0..3), ``flags`` u8 (ConfigImuFlag).
    The decoder takes every value; the chip checks them (BAD_VALUE, UNSUPPORTED)."""

    TYPE = MsgType.CONFIG_IMU
    DIRECTION = Direction.HOST_TO_CHIP
    PRIORITY = 4
    _FMT = struct.Struct("<BBBB")
    format: int = SampleFormat.ACCEL_12
    gyro_range: int = 3
    mag_range: int = 0
    flags: int = 0

    def _validate(self) -> None:
        for name in ("format", "gyro_range", "mag_range", "flags"):
            _check_uint(name, getattr(self, name), 8)


# --------------------------------------------------------------------------------------------
# v1.3: the gyroscope's and magnetometer's calibration on the chip (docs §17)
# --------------------------------------------------------------------------------------------

class CalBlock(IntEnum):
    """§17.1 the blocks of CAL_IMU_WRITE / CAL_IMU_READ / CAL_IMU_DATA; matrices row-major."""

    GYRO_MATRIX = 0  #: ``A``, 3 x 3, dimensionless (scale, cross-axis, mounting); nominal identity
    GYRO_BIAS = 1  #: ``b``, 3, rad/s; nominal 0
    GYRO_G_SENS = 2  #: ``Γ``, 3 x 3, rad/s per g; nominal 0
    MAG_MATRIX = 3  #: ``S``, 3 x 3, dimensionless (soft iron, mounting); nominal identity
    MAG_HARD_IRON = 4  #: ``h``, 3, tesla; nominal 0


#: elements per block (index 0..size-1)
CAL_BLOCK_SIZE = {CalBlock.GYRO_MATRIX: 9, CalBlock.GYRO_BIAS: 3, CalBlock.GYRO_G_SENS: 9,
                  CalBlock.MAG_MATRIX: 9, CalBlock.MAG_HARD_IRON: 3}


def cal_block_nominal(block: int, index: int) -> float:
    """The value a chip with no calibration reports (§17.1): the matrices' identity, else 0."""
    if block in (CalBlock.GYRO_MATRIX, CalBlock.MAG_MATRIX):
        return 1.0 if index in (0, 4, 8) else 0.0
    return 0.0


def _check_cal_element(msg) -> None:
    if msg.node == NODE_BROADCAST and msg.TYPE != MsgType.CAL_IMU_DATA:
        raise ValueError(f"Invalid node: 0 ({msg.TYPE.name} is addressed to one chip)")
    _check_uint("block", msg.block, 8)
    if msg.block not in CAL_BLOCK_SIZE:
        raise ValueError(f"Invalid block: {msg.block!r} (0..4)")
    _check_uint("index", msg.index, 8)
    size = CAL_BLOCK_SIZE[CalBlock(msg.block)]
    if msg.index >= size:
        raise ValueError(f"Invalid index: {msg.index!r} (block {msg.block} has {size} elements)")


_CAL_IMU_FMT = struct.Struct("<BBBBf")


def _validate_cal_imu(msg) -> None:
    _check_cal_element(msg)
    _check_uint("flags", msg.flags, 8)
    if msg.reserved != 0:
        raise ValueError(f"Invalid reserved: {msg.reserved!r} (must be 0)")
    v = float(msg.value)
    if not np.isfinite(v) or not np.isfinite(np.float32(v)):
        raise ValueError(f"Invalid value: {msg.value!r} (need a finite float32)")
    # Store as the float32 the wire carries, so that decode(encode(m)) == m.
    object.__setattr__(msg, "value", float(np.float32(v)))


@dataclass(frozen=True, slots=True)
class CalImuData(Message):
    """§17.1 CAL_IMU_DATA: ``block`` u8 (CalBlock), ``index`` u8, ``flags`` u8 (bit 0: stored in
    non-volatile memory), ``reserved`` u8 (0), ``value`` f32 (units per block: CalBlock)."""

    TYPE = MsgType.CAL_IMU_DATA
    DIRECTION = Direction.CHIP_TO_HOST
    PRIORITY = 5
    _FMT = _CAL_IMU_FMT
    block: int = 0
    index: int = 0
    flags: int = 0
    reserved: int = 0
    value: float = 1.0

    def _validate(self) -> None:
        _validate_cal_imu(self)


@dataclass(frozen=True, slots=True)
class CalImuWrite(Message):
    """§17.2 CAL_IMU_WRITE: the CAL_IMU_DATA layout; ``flags`` bit 0 asks the chip to store the
    element in non-volatile memory (NACK UNSUPPORTED without CAL_STORAGE)."""

    TYPE = MsgType.CAL_IMU_WRITE
    DIRECTION = Direction.HOST_TO_CHIP
    PRIORITY = 4
    _FMT = _CAL_IMU_FMT
    block: int = 0
    index: int = 0
    flags: int = 0
    reserved: int = 0
    value: float = 1.0

    def _validate(self) -> None:
        _validate_cal_imu(self)


@dataclass(frozen=True, slots=True)
class CalImuRead(Message):
    """§17.2 CAL_IMU_READ: ``block`` u8, ``index`` u8. Answered by CAL_IMU_DATA."""

    TYPE = MsgType.CAL_IMU_READ
    DIRECTION = Direction.HOST_TO_CHIP
    PRIORITY = 4
    _FMT = struct.Struct("<BB")
    block: int = 0
    index: int = 0

    def _validate(self) -> None:
        _check_cal_element(self)


#: type code -> message class
MESSAGE_TYPES: dict[int, type[Message]] = {
    cls.TYPE: cls for cls in (Announce, Info, Sample, Status, Ack, Nack, CalData, Snapshot, GatewayInfo,
                              ImuGyro, ImuMag, ImuAccel, ImuSample, SnapshotImu,
                              Sync, Assign, Config, Start, Stop, GetInfo, Reset, CalWrite, CalRead, ConfigImu,
                              CalImuData, CalImuWrite, CalImuRead)
}
assert set(MESSAGE_TYPES) == set(MsgType)
#: the types v1.2 added (docs §16): 6/9-axis chips
IMU_TYPES = frozenset({MsgType.IMU_GYRO, MsgType.IMU_MAG, MsgType.IMU_ACCEL, MsgType.IMU_SAMPLE,
                       MsgType.SNAPSHOT_IMU, MsgType.CONFIG_IMU})


def decode_payload(type_code: int, node: int, payload: bytes) -> Message:
    """Payload -> message. Raises `PayloadError` with reason UNKNOWN_TYPE, BAD_LENGTH or BAD_FIELD."""
    cls = MESSAGE_TYPES.get(type_code)
    if cls is None:
        raise PayloadError("UNKNOWN_TYPE", f"type 0x{type_code:02X} is not defined in protocol "
                                           f"v{SPEC_VERSION[0]}.{SPEC_VERSION[1]}")
    if node == 0xFFFF:
        raise PayloadError("BAD_FIELD", "node 0xFFFF is reserved")
    return cls.from_payload(node, payload)


def message_to_fields(msg: Message) -> dict:
    """A message's fields as the vector files write them (JSON numbers; a SNAPSHOT's arrays as lists)."""
    if isinstance(msg, Snapshot):
        return {"counter": msg.counter, "first_link": msg.first_link,
                "counts": msg.counts.tolist(), "status": msg.status.tolist()}
    if isinstance(msg, SnapshotImu):
        counts, status, time_us, gyro, mag = msg.arrays()
        out = {"counter": msg.counter, "first_link": msg.first_link, "counts": counts.tolist(),
               "status": status.tolist(), "time_us": time_us.tolist(), "gyro": gyro.tolist()}
        if mag is not None:
            out["mag"] = mag.tolist()
        return out
    return {f.name: (None if v is None else float(v) if isinstance(v, float) else int(v))
            for f in fields(msg)[1:] for v in [getattr(msg, f.name)]
            if not (v is None and isinstance(msg, ImuSample))}


def message_from_fields(type_name: str, node: int, values: dict) -> Message:
    """The message `message_to_fields` wrote (type by name, node, fields)."""
    cls = MESSAGE_TYPES[MsgType[type_name]]
    if cls is Snapshot:
        return Snapshot.from_arrays(node, values["counter"], values["first_link"],
                                    np.array(values["counts"]), np.array(values["status"]))
    if cls is SnapshotImu:
        mag = values.get("mag")
        return SnapshotImu.from_arrays(node, values["counter"], values["first_link"], np.array(values["counts"]),
                                       np.array(values["status"]), np.array(values["time_us"]),
                                       np.array(values["gyro"]), None if mag is None else np.array(mag))
    return cls(node, **values)
