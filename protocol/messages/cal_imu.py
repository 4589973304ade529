"""The gyroscope's and magnetometer's calibration on the chip (docs §17): CAL_IMU_DATA, CAL_IMU_WRITE,
CAL_IMU_READ."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from .base import Direction, Message, MsgType, NODE_BROADCAST, check_uint


# --------------------------------------------------------------------------------------------
# new in 1.3: the gyroscope's and magnetometer's calibration on the chip (docs §17)
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
    check_uint("block", msg.block, 8)
    if msg.block not in CAL_BLOCK_SIZE:
        raise ValueError(f"Invalid block: {msg.block!r} (0..4)")
    check_uint("index", msg.index, 8)
    size = CAL_BLOCK_SIZE[CalBlock(msg.block)]
    if msg.index >= size:
        raise ValueError(f"Invalid index: {msg.index!r} (block {msg.block} has {size} elements)")


_CAL_IMU_FMT = struct.Struct("<BBBBf")


def _validate_cal_imu(msg) -> None:
    _check_cal_element(msg)
    check_uint("flags", msg.flags, 8)
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
