"""host -> chip commands (docs §4.9-§4.15, §16.2): SYNC, ASSIGN, CONFIG, START, STOP, GET_INFO, RESET,
CAL_WRITE, CAL_READ, CONFIG_IMU."""

from __future__ import annotations

import struct
from dataclasses import dataclass

from .base import (Direction, Message, MsgType, NODE_BROADCAST, NODE_MAX_ASSIGNED, SampleFormat, check_int,
    check_uint)
from .chip_to_host import CAL_FMT, validate_cal


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
        check_uint("counter", self.counter, 16)


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
        check_int("new_node", self.new_node, 1, NODE_MAX_ASSIGNED)
        check_uint("link", self.link, 16)
        check_uint("uid_low", self.uid_low, 32)


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
        check_uint("rate_hz", self.rate_hz, 16)
        check_uint("range", self.range, 8)
        check_uint("filter", self.filter, 8)
        check_uint("heartbeat_ms", self.heartbeat_ms, 16)


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
    _FMT = CAL_FMT
    axis: int = 0
    flags: int = 0
    offset_q4: int = 0
    sensitivity: float = 1024.0

    def _validate(self) -> None:
        if self.node == NODE_BROADCAST:
            raise ValueError("Invalid node: 0 (CAL_WRITE is addressed to one chip)")
        validate_cal(self)


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
        check_uint("axis", self.axis, 8)
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
            check_uint(name, getattr(self, name), 8)


