"""Python face of the C codec (firmware_ref/src/codec.c, payload.c), for tests and tools: message objects of
`protocol.messages` in, wire bytes out, and back — every step done by the C code.

>>> from protocol.messages import Sync
>>> encode_serial(Sync(counter=0x1234)).hex()
'03011001053412b4c800'
"""

from __future__ import annotations

from dataclasses import fields

from protocol.can import CanFrame
from protocol.framing import ErrorReason
from protocol.messages import IMU_RECORD_SIZE, MESSAGE_TYPES, ImuSample, Message, MsgType, Snapshot, SnapshotImu

from ._ffi import ffi, lib

__all__ = ["CodecError", "ERROR_NAMES", "to_c", "from_c", "encode_payload", "decode_payload",
           "encode_serial", "encode_serial_raw", "decode_frame", "decode_stream", "encode_can",
           "decode_can", "crc16", "cobs_encode", "cobs_decode", "provisional_node", "rule_for"]

#: negative return code -> name (capsheet_fw.h)
ERROR_NAMES = {
    -1: "ARGUMENT", -2: "CAPACITY", -3: "BAD_COBS", -4: "SHORT", -5: "BAD_CRC", -6: "OVERSIZE",
    -7: "BAD_VERSION", -8: "UNKNOWN_TYPE", -9: "BAD_LENGTH", -10: "BAD_FIELD", -11: "NEEDS_FD", -12: "HAL",
}


class CodecError(ValueError):
    """A C codec function returned a negative code. ``reason`` is the `ErrorReason` for decode
    errors (else None); ``code`` the C value; ``name`` its name."""

    def __init__(self, code: int, what: str):
        self.code = code
        self.name = ERROR_NAMES.get(code, str(code))
        self.reason = ErrorReason[self.name] if self.name in ErrorReason.__members__ else None
        super().__init__(f"{what}: {self.name} ({code})")


# union member of capsheet_msg_t per type
_MEMBER = {
    MsgType.ANNOUNCE: "announce", MsgType.INFO: "info", MsgType.SAMPLE: "sample", MsgType.STATUS: "status",
    MsgType.ACK: "ack", MsgType.NACK: "nack", MsgType.CAL_DATA: "cal", MsgType.SNAPSHOT: "snapshot",
    MsgType.GATEWAY_INFO: "gateway_info",
    MsgType.SYNC: "sync", MsgType.ASSIGN: "assign", MsgType.CONFIG: "config", MsgType.CAL_WRITE: "cal",
    MsgType.CAL_READ: "cal_read",
    MsgType.IMU_GYRO: "imu_gyro", MsgType.IMU_MAG: "imu_mag", MsgType.IMU_ACCEL: "imu_accel",
    MsgType.CONFIG_IMU: "config_imu",
    MsgType.CAL_IMU_DATA: "cal_imu", MsgType.CAL_IMU_WRITE: "cal_imu", MsgType.CAL_IMU_READ: "cal_imu_read",
}
_IMU_FIELDS = ("counter", "x", "y", "z", "status", "time_us", "gx", "gy", "gz")


def to_c(msg: Message):
    """A `protocol.messages` message as a ``capsheet_msg_t *`` (plus what must outlive it)."""
    m = ffi.new("capsheet_msg_t *")
    m.type = int(msg.TYPE)
    m.node = msg.node
    keep = None
    member = _MEMBER.get(msg.TYPE)
    if isinstance(msg, Snapshot):
        keep = ffi.new("uint8_t[]", msg.words)
        m.u.snapshot.counter = msg.counter
        m.u.snapshot.first_link = msg.first_link
        m.u.snapshot.count = msg.count
        m.u.snapshot.words = keep
    elif isinstance(msg, SnapshotImu):
        keep = ffi.new("uint8_t[]", msg.records)
        s = m.u.snapshot_imu
        s.counter, s.first_link, s.count, s.format, s.records = (msg.counter, msg.first_link, msg.count,
                                                                 int(msg.format), keep)
    elif isinstance(msg, ImuSample):
        s = m.u.imu_sample
        for name in _IMU_FIELDS:
            setattr(s, name, getattr(msg, name))
        s.format = int(msg.format)
        if msg.mx is not None:
            s.mx, s.my, s.mz = msg.mx, msg.my, msg.mz
    elif member is not None:
        dst = getattr(m.u, member)
        for f in fields(msg)[1:]:
            setattr(dst, f.name, getattr(msg, f.name))
    return m, keep


def from_c(m) -> Message:
    """A decoded ``capsheet_msg_t`` as a `protocol.messages` message (validates again in Python)."""
    cls = MESSAGE_TYPES[MsgType(m.type)]
    member = _MEMBER.get(MsgType(m.type))
    if cls is Snapshot:
        s = m.u.snapshot
        return Snapshot(m.node, s.counter, s.first_link, bytes(ffi.buffer(s.words, 5 * s.count)))
    if cls is SnapshotImu:
        s = m.u.snapshot_imu
        return SnapshotImu(m.node, s.counter, s.first_link, s.format,
                           bytes(ffi.buffer(s.records, IMU_RECORD_SIZE[s.format] * s.count)))
    if cls is ImuSample:
        s = m.u.imu_sample
        mag = (s.mx, s.my, s.mz) if s.format == 2 else (None, None, None)
        return ImuSample(m.node, *(getattr(s, name) for name in _IMU_FIELDS), *mag)
    if member is None:
        return cls(m.node)
    src = getattr(m.u, member)
    return cls(m.node, **{f.name: getattr(src, f.name) for f in fields(cls)[1:]})


def _check(rc: int, what: str) -> int:
    if rc < 0:
        raise CodecError(rc, what)
    return rc


def encode_payload(msg: Message) -> bytes:
    m, _keep = to_c(msg)
    buf = ffi.new("uint8_t[]", 1100)
    n = _check(lib.capsheet_payload_encode(m, buf, 1100), "payload_encode")
    return bytes(ffi.buffer(buf, n))


def decode_payload(type_code: int, node: int, payload: bytes) -> Message:
    m = ffi.new("capsheet_msg_t *")
    p = ffi.new("uint8_t[]", bytes(payload) or b"\x00")
    _check(lib.capsheet_payload_decode(type_code, node, p, len(payload), m), "payload_decode")
    return from_c(m)


def encode_serial(msg: Message) -> bytes:
    """One serial frame (COBS + 0x00) from the C encoder."""
    m, _keep = to_c(msg)
    cap = lib.CAPSHEET_MAX_WIRE_SIZE
    buf = ffi.new("uint8_t[]", cap)
    n = _check(lib.capsheet_serial_encode(m, buf, cap), "serial_encode")
    return bytes(ffi.buffer(buf, n))


def encode_serial_raw(version: int, type_code: int, node: int, payload: bytes) -> bytes:
    cap = lib.CAPSHEET_MAX_WIRE_SIZE + 64
    buf = ffi.new("uint8_t[]", cap)
    n = _check(lib.capsheet_serial_encode_raw(version, type_code, node, payload, len(payload), buf, cap),
               "serial_encode_raw")
    return bytes(ffi.buffer(buf, n))


def decode_frame(encoded: bytes) -> Message:
    """Decode the bytes between two delimiters with the C decoder; raises `CodecError`."""
    buf = ffi.new("uint8_t[]", bytes(encoded) or b"\x00")
    m = ffi.new("capsheet_msg_t *")
    _check(lib.capsheet_serial_decode_frame(buf, len(encoded), m, ffi.NULL), "serial_decode_frame")
    return from_c(m)


def decode_stream(data: bytes, cap: int | None = None) -> list:
    """Feed bytes one at a time to the C stream decoder: a list of messages and `ErrorReason`s."""
    cap = cap or lib.CAPSHEET_MAX_ENCODED_SIZE
    buf = ffi.new("uint8_t[]", cap)
    s = ffi.new("capsheet_stream_t *")
    _check(lib.capsheet_stream_init(s, buf, cap), "stream_init")
    m = ffi.new("capsheet_msg_t *")
    out: list = []
    for b in bytes(data):
        rc = lib.capsheet_stream_feed(s, b, m)
        if rc == 1:
            out.append(from_c(m))
        elif rc < 0:
            out.append(CodecError(rc, "stream").reason)
    return out


def encode_can(msg: Message, *, fd: bool | None = None) -> CanFrame:
    """A message as one CAN frame, by the C encoder (``fd`` as `protocol.can.to_can`)."""
    m, _keep = to_c(msg)
    mode = lib.CAPSHEET_CAN_AUTO if fd is None else (lib.CAPSHEET_CAN_FD if fd else lib.CAPSHEET_CAN_CLASSIC)
    data = ffi.new("uint8_t[]", 64)
    cid = ffi.new("uint32_t *")
    is_fd = ffi.new("bool *")
    n = _check(lib.capsheet_can_encode(m, mode, cid, data, 64, is_fd), "can_encode")
    return CanFrame(cid[0], bytes(ffi.buffer(data, n)), bool(is_fd[0]))


def decode_can(arbitration_id: int, data: bytes, *, is_extended_id: bool = True, is_fd: bool = False) -> Message:
    m = ffi.new("capsheet_msg_t *")
    p = ffi.new("uint8_t[]", bytes(data) or b"\x00")
    _check(lib.capsheet_can_decode(arbitration_id & 0xFFFFFFFF, is_extended_id, is_fd, p, len(data), m, ffi.NULL),
           "can_decode")
    return from_c(m)


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    return lib.capsheet_crc16(data, len(data), crc)


def cobs_encode(data: bytes) -> bytes:
    cap = len(data) + 1 + len(data) // 254
    buf = ffi.new("uint8_t[]", cap)
    n = _check(lib.capsheet_cobs_encode(data, len(data), buf, cap), "cobs_encode")
    return bytes(ffi.buffer(buf, n))


def cobs_decode(data: bytes) -> bytes:
    buf = ffi.new("uint8_t[]", max(1, len(data)))
    n = _check(lib.capsheet_cobs_decode(data, len(data), buf, len(data)), "cobs_decode")
    return bytes(ffi.buffer(buf, n))


def provisional_node(uid: int, salt: int = 0) -> int:
    return lib.capsheet_provisional_node(uid, salt & 0xFFFFFFFF)


def rule_for(state: int, type_code: int):
    """``(reply, next_state or None, validate)`` of the C table, or None if the pair is absent."""
    r = ffi.new("capsheet_rule_t *")
    rc = _check(lib.capsheet_rule_for(state, type_code, r), "rule_for")
    if rc == 0:
        return None
    return r.reply, (None if r.next_state == lib.CAPSHEET_STAY else r.next_state), bool(r.validate)
