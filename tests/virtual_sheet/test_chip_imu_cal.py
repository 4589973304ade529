"""The chips' gyroscope and magnetometer calibration (the Python model and the C firmware alike) (docs §17, v1.3): CAL_IMU_WRITE /
CAL_IMU_READ read back bit for bit, NACK 5 without the sensor, persistence across RESET, and the
correction applied to the counts sent. Simulated clock; expected counts worked out by hand."""

from __future__ import annotations

import math
import struct

import pytest

from protocol.framing import StreamDecoder, encode
from protocol.messages import (Ack, Assign, CalBlock, CalImuData, CalImuRead, CalImuWrite, Capability, ConfigImu,
                               ImuSample, MsgType, Nack, NackReason, Reset, Start, Stop, Sync, provisional_node)

UID = 0x0123456789ABCDEF


def imu(now_s, gyro_range, mag_range):
    return (100, -200, 3000), (8192, -4096, 1), -1500


def accel(now_s):
    return (0, 0, 1024), 0


def chip(cls, sensors="accel+gyro+mag", caps=None):
    kw = {} if caps is None else {"capabilities": caps}
    c = cls(UID, accel, sensors=sensors, imu=imu if sensors != "accel" else None, **kw)
    c.power_on(0.0)
    assert ask(c, Assign(provisional_node(UID, 0), 1, 0, UID & 0xFFFFFFFF)) == [Ack(1, MsgType.ASSIGN, 0)]
    return c


def ask(c, msg, t=0.1):
    return StreamDecoder().feed(b"".join(c.handle(encode(msg), t)))


def f32_bits(v):
    return struct.pack("<f", v)


def test_every_element_reads_back_bit_for_bit_with_its_stored_flag(chip_class):
    c = chip(chip_class)
    values = {}
    for block, size in ((0, 9), (1, 3), (2, 9), (3, 9), (4, 3)):
        for i in range(size):
            v = -0.0 if (block, i) == (2, 4) else (block + 1) * 0.001 * (i - 4) + 1e-7
            values[block, i] = v
            assert ask(c, CalImuWrite(1, block, i, i & 1, 0, v)) == [Ack(1, MsgType.CAL_IMU_WRITE, 0)]
    for (block, i), v in values.items():
        (ans,) = ask(c, CalImuRead(1, block, i))
        assert isinstance(ans, CalImuData) and (ans.block, ans.index, ans.flags) == (block, i, i & 1)
        assert f32_bits(ans.value) == f32_bits(v)  # −0 stays −0


def test_nominal_values_before_any_write(chip_class):
    c = chip(chip_class)
    assert ask(c, CalImuRead(1, CalBlock.GYRO_MATRIX, 4)) == [CalImuData(1, 0, 4, 0, 0, 1.0)]
    assert ask(c, CalImuRead(1, CalBlock.GYRO_MATRIX, 1)) == [CalImuData(1, 0, 1, 0, 0, 0.0)]
    assert ask(c, CalImuRead(1, CalBlock.MAG_HARD_IRON, 2)) == [CalImuData(1, 4, 2, 0, 0, 0.0)]


def test_a_chip_without_the_sensor_answers_nack_5(chip_class):
    a = chip(chip_class, "accel")
    for block in range(5):
        assert ask(a, CalImuRead(1, block, 0)) == [Nack(1, MsgType.CAL_IMU_READ, NackReason.UNSUPPORTED)]
        assert ask(a, CalImuWrite(1, block, 0, 0, 0, 1.0)) == [Nack(1, MsgType.CAL_IMU_WRITE, NackReason.UNSUPPORTED)]
    g = chip(chip_class, "accel+gyro")
    assert ask(g, CalImuRead(1, CalBlock.GYRO_BIAS, 0)) == [CalImuData(1, 1, 0, 0, 0, 0.0)]
    assert ask(g, CalImuRead(1, CalBlock.MAG_MATRIX, 0)) == [Nack(1, MsgType.CAL_IMU_READ, NackReason.UNSUPPORTED)]


def test_store_flag_without_cal_storage_and_write_while_streaming_are_refused_and_change_nothing(chip_class):
    c = chip(chip_class, caps=0)
    assert not c.capabilities & Capability.CAL_STORAGE
    assert ask(c, CalImuWrite(1, 1, 0, 1, 0, 0.5)) == [Nack(1, MsgType.CAL_IMU_WRITE, NackReason.UNSUPPORTED)]
    assert ask(c, Start(1)) == [Ack(1, MsgType.START, 0)]
    assert ask(c, CalImuWrite(1, 1, 0, 0, 0, 0.5)) == [Nack(1, MsgType.CAL_IMU_WRITE, NackReason.BAD_STATE)]
    assert ask(c, CalImuRead(1, 1, 0)) == [CalImuData(1, 1, 0, 0, 0, 0.0)]  # read is allowed while streaming


def test_reset_keeps_stored_elements_and_drops_the_others(chip_class):
    c = chip(chip_class)
    assert c.capabilities & Capability.CAL_STORAGE
    ask(c, CalImuWrite(1, 1, 0, 1, 0, 0.25))
    ask(c, CalImuWrite(1, 1, 1, 0, 0, 0.5))
    ask(c, Reset(1))
    ask(c, Assign(provisional_node(UID, 0), 1, 0, UID & 0xFFFFFFFF))
    assert ask(c, CalImuRead(1, 1, 0)) == [CalImuData(1, 1, 0, 1, 0, 0.25)]
    assert ask(c, CalImuRead(1, 1, 1)) == [CalImuData(1, 1, 1, 0, 0, 0.0)]


def _record(c):
    assert ask(c, Start(1)) == [Ack(1, MsgType.START, 0)]
    (rec,) = ask(c, Sync(counter=7), 0.2)
    assert ask(c, Stop(1)) == [Ack(1, MsgType.STOP, 0)]
    assert isinstance(rec, ImuSample)
    return (rec.gx, rec.gy, rec.gz), (rec.mx, rec.my, rec.mz)


def test_the_chip_sends_corrected_counts(chip_class):
    c = chip(chip_class)
    assert ask(c, ConfigImu(1, 2, 3, 0, 0)) == [Ack(1, MsgType.CONFIG_IMU, 0)]  # ±1000 °/s, ±4 gauss
    assert _record(c) == ((100, -200, 3000), (8192, -4096, 1))  # nominal: the counts unchanged
    s = 32.768 * 180 / math.pi  # counts per rad/s at ±1000 °/s
    writes = [(CalBlock.GYRO_BIAS, 2, 3000 / s),  # gz − 3000 counts → 0
              (CalBlock.GYRO_G_SENS, 2, 100 / s),  # Γ_xz · f_z, f = (0, 0, 1) g → gx − 100 → 0
              (CalBlock.GYRO_MATRIX, 4, 2.0),  # A_yy = 2 → gy = −400
              (CalBlock.MAG_HARD_IRON, 0, 1e-4),  # 1 gauss = 8192 counts → mx = 0
              (CalBlock.MAG_MATRIX, 7, 0.5)]  # S_zy = 0.5 → mz = 1 + 0.5·(−4096) = −2047
    for block, i, v in writes:
        assert ask(c, CalImuWrite(1, block, i, 0, 0, v)) == [Ack(1, MsgType.CAL_IMU_WRITE, 0)]
    assert _record(c) == ((0, -400, 0), (0, -4096, -2047))
    for block, i, _ in writes:  # back to nominal: the counts unchanged again
        nominal = 1.0 if block in (0, 3) and i in (0, 4, 8) else 0.0
        ask(c, CalImuWrite(1, block, i, 0, 0, nominal))
    assert _record(c) == ((100, -200, 3000), (8192, -4096, 1))


def test_a_corrected_count_past_the_rail_is_clamped_and_saturated(chip_class):
    c = chip(chip_class, "accel+gyro")
    ask(c, ConfigImu(1, 1, 3, 0, 0))
    ask(c, CalImuWrite(1, CalBlock.GYRO_MATRIX, 8, 0, 0, 20.0))  # 3000 · 20 = 60000 > 32767
    ask(c, Start(1))
    (rec,) = ask(c, Sync(counter=1), 0.2)
    assert (rec.gx, rec.gy, rec.gz) == (100, -200, 32767) and rec.status & 0x1
