"""The protocol's constants, enumerations and the `Message` base class (docs §3, §4, §5.2).

The packed 40-bit sample word (§5.2) lives here too: every family of messages uses it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, fields
from enum import IntEnum, IntFlag
from typing import ClassVar

import numpy as np

from ..constants import ADC_MAX, ADC_MIN


PROTOCOL_VERSION = 1
#: The revision of docs/protocol.md this code implements (major, minor).
SPEC_VERSION = (1, 4)

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
    GATEWAY_INFO = 0x09  #: §4.16 a gateway's packing, SYNC source and links (new in 1.1)
    IMU_GYRO = 0x0A  #: §16.4 classic CAN, first frame of an IMU record: counter + gyroscope (new in 1.2)
    IMU_MAG = 0x0B  #: §16.4 classic CAN, format 2's middle frame: counter + magnetometer (new in 1.2)
    IMU_ACCEL = 0x0C  #: §16.4 classic CAN, last frame: counter low byte + accel word + time_us (new in 1.2)
    IMU_SAMPLE = 0x0D  #: §16.3 one IMU record for one SYNC counter, serial and CAN FD (new in 1.2)
    SNAPSHOT_IMU = 0x0E  #: §16.5 a gateway's packed IMU records of many links for one counter (new in 1.2)
    CAL_IMU_DATA = 0x0F  #: §17.1 one element of a gyroscope or magnetometer calibration (new in 1.3)
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
    CONFIG_IMU = 0x19  #: §16.2 sample format, gyroscope and magnetometer ranges (new in 1.2)
    CAL_IMU_WRITE = 0x1A  #: §17.2 write one element of a gyroscope or magnetometer calibration (new in 1.3)
    CAL_IMU_READ = 0x1B  #: §17.2 read one element (answered by CAL_IMU_DATA) (new in 1.3)


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
    SELF_TEST = 0x0004  #: has a self-test started by means outside the protocol (there is no command for it)
    CAL_STORAGE = 0x0008  #: keeps calibration in non-volatile memory
    MULTI_RANGE = 0x0010  #: supports range codes other than ±2 g
    FILTER = 0x0020  #: supports CONFIG filter codes other than 0
    GATEWAY = 0x0040  #: the node is a gateway, not a chip: it sits on no link (new in 1.1, §13)
    SYNC_SOURCE = 0x0080  #: a gateway that can generate its segment's SYNC (new in 1.1, §13.3)
    GYRO = 0x0100  #: a triaxial gyroscope: CONFIG_IMU formats 1 and 2 (new in 1.2, §16)
    MAG = 0x0200  #: a triaxial magnetometer: CONFIG_IMU format 2 (new in 1.2, §16)
    SAMPLE_TIME = 0x0400  #: IMU records carry a true time_us (without it: TIME_UNKNOWN) (new in 1.2, §16.1)


#: INFO capability bits reserved (bits 11..15): sent as 0, ignored on receipt.
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


def codes_of(enum: type[IntEnum]) -> frozenset[int]:
    """The values an enumeration defines, as plain ints: what a decoder checks a wire field
    against before it builds the member (``ChipState(v)`` raises on anything else).

    >>> sorted(codes_of(ChipState))
    [0, 1, 2, 3]
    """
    return frozenset(int(m) for m in enum)


#: the codes of `MsgType`, `ChipState`, `SampleFormat`, `NackReason` (`codes_of`)
MSG_TYPE_CODES = codes_of(MsgType)
CHIP_STATE_CODES = codes_of(ChipState)
SAMPLE_FORMAT_CODES = codes_of(SampleFormat)
NACK_REASON_CODES = codes_of(NackReason)


class PayloadError(ValueError):
    """A payload that does not decode: ``reason`` is an ErrorReason name (see protocol.framing)."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


def check_uint(name: str, value: int, bits: int) -> None:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or not 0 <= value < (1 << bits):
        raise ValueError(f"Invalid {name}: {value!r} (need an integer in 0..{(1 << bits) - 1})")


def check_int(name: str, value: int, lo: int, hi: int) -> None:
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
    check_uint("uid", uid, 64)
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
        check_uint("node", self.node, 16)
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


