"""The Python chip model as a 6/9-axis chip (docs §16): CONFIG_IMU's checks and states, and the IMU
records it answers SYNC with on serial, classic CAN (assembled by the host's CanDecoder) and CAN FD.
Simulated clock; expected values written out by hand."""

from __future__ import annotations

from types import SimpleNamespace as F

import pytest

from protocol.can import CanDecoder, CanFrame, to_can
from protocol.framing import StreamDecoder, encode
from protocol.messages import (TIME_UNKNOWN, Ack, Assign, Capability, ConfigImu, ImuSample, Info, MsgType, Nack,
                               NackReason, Sample, Start, Stop, Sync, provisional_node)
from virtual_sheet.chip import ChipModel

UID = 0x0123456789ABCDEF
GYRO = {3: (100, -200, 3000), 4: (50, -100, 1500)}  # the source's counts by gyro range code


def imu(now_s, gyro_range, mag_range):
    return GYRO[gyro_range], (8192 >> mag_range, -4096, 1), -1500


def accel(now_s):
    return (0, 0, 1024), 0


def chip(sensors="accel+gyro+mag", transport="serial", fd=False):
    c = ChipModel(UID, accel, transport=transport, fd=fd, sensors=sensors, imu=imu if sensors != "accel" else None)
    c.power_on(0.0)
    out = c.handle(send(c, Assign(provisional_node(UID, 0), 1, 0, UID & 0xFFFFFFFF)), 0.1)
    assert decode(c, out) == [Ack(1, MsgType.ASSIGN, 0)]
    return c


def send(c, msg):
    return to_can(msg) if c.transport == "can" else encode(msg)


def decode(c, frames):
    if c.transport == "can":
        dec = CanDecoder(fd=True)
        return dec.feed([F(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True, is_fd=f.is_fd,
                           is_error_frame=False, is_remote_frame=False) for f in frames])
    return StreamDecoder().feed(b"".join(frames))


def test_info_reports_the_sensors():
    for sensors, caps in (("accel", 0), ("accel+gyro", Capability.GYRO | Capability.SAMPLE_TIME),
                          ("accel+gyro+mag", Capability.GYRO | Capability.MAG | Capability.SAMPLE_TIME)):
        c = ChipModel(UID, accel, sensors=sensors, imu=imu)
        info = [m for m in decode(c, c.power_on(0.0)) if isinstance(m, Info)][0]
        assert info.capabilities & (Capability.GYRO | Capability.MAG | Capability.SAMPLE_TIME) == caps


@pytest.mark.parametrize("transport, fd, n_frames", [("serial", False, 1), ("can", False, 3), ("can", True, 1)])
def test_a_9_axis_chip_answers_sync_with_one_record_on_every_transport(transport, fd, n_frames):
    c = chip(transport=transport, fd=fd)
    assert decode(c, c.handle(send(c, ConfigImu(1, 2, 4, 1, 1 if fd else 0)), 0.2)) == [Ack(1, MsgType.CONFIG_IMU, 0)]
    decode(c, c.handle(send(c, Start(1)), 0.3))
    out = c.handle(send(c, Sync(counter=0x0102)), 0.4)
    assert len(out) == n_frames
    if transport == "can":
        assert all(isinstance(f, CanFrame) and f.is_fd == fd for f in out)
    # ±2000 °/s (code 4) and ±8 gauss (code 1): the source's counts at those ranges
    assert decode(c, out) == [ImuSample(1, 0x0102, 0, 0, 1024, 0, -1500, 50, -100, 1500, 4096, -4096, 1)]


def test_format_0_is_todays_sample_and_format_1_has_no_magnetometer():
    c = chip()
    decode(c, c.handle(encode(Start(1)), 0.2))
    assert decode(c, c.handle(encode(Sync(counter=1)), 0.3)) == [Sample(1, 1, 0, 0, 1024, 0)]
    decode(c, c.handle(encode(Stop(1)), 0.35))
    assert decode(c, c.handle(encode(ConfigImu(1, 1, 3, 0, 0)), 0.4)) == [Ack(1, MsgType.CONFIG_IMU, 0)]
    decode(c, c.handle(encode(Start(1)), 0.5))
    assert decode(c, c.handle(encode(Sync(counter=2)), 0.6)) == [ImuSample(1, 2, 0, 0, 1024, 0, -1500, 100, -200, 3000)]


@pytest.mark.parametrize("sensors, cfg, reason", [
    ("accel+gyro+mag", ConfigImu(1, 3, 3, 0, 0), NackReason.BAD_VALUE),
    ("accel+gyro+mag", ConfigImu(1, 1, 5, 0, 0), NackReason.BAD_VALUE),
    ("accel+gyro+mag", ConfigImu(1, 1, 3, 4, 0), NackReason.BAD_VALUE),
    ("accel+gyro", ConfigImu(1, 2, 3, 0, 0), NackReason.UNSUPPORTED),
    ("accel", ConfigImu(1, 1, 3, 0, 0), NackReason.UNSUPPORTED),
    ("accel+gyro", ConfigImu(1, 1, 3, 0, 1), NackReason.UNSUPPORTED),  # FD flag on a chip without CAN_FD
])
def test_config_imu_is_checked_in_order_and_a_refusal_changes_nothing(sensors, cfg, reason):
    c = chip(sensors)
    assert decode(c, c.handle(encode(cfg), 0.2)) == [Nack(1, MsgType.CONFIG_IMU, reason)]
    assert c.imu_format == 0 and (c.gyro_range, c.mag_range) == (3, 0)
    assert c.handle(encode(ConfigImu(0, cfg.format, cfg.gyro_range, cfg.mag_range, cfg.flags)), 0.3) == []  # broadcast: silence


def test_config_imu_while_streaming_is_bad_state_and_an_accel_chip_accepts_format_0():
    c = chip("accel")
    assert decode(c, c.handle(encode(ConfigImu(1, 0, 4, 3, 0)), 0.2)) == [Ack(1, MsgType.CONFIG_IMU, 0)]
    decode(c, c.handle(encode(Start(1)), 0.3))
    assert decode(c, c.handle(encode(ConfigImu(1, 0, 3, 0, 0)), 0.4)) == [Nack(1, MsgType.CONFIG_IMU, NackReason.BAD_STATE)]


def test_saturation_covers_the_gyroscope_and_a_fault_sends_an_invalid_record():
    rail = {"v": (32767, 0, 0)}
    c = ChipModel(UID, accel, sensors="accel+gyro", imu=lambda t, g, m: (rail["v"], None, 10))
    c.power_on(0.0)
    c.handle(encode(Assign(provisional_node(UID, 0), 1, 0, UID & 0xFFFFFFFF)), 0.1)
    c.handle(encode(ConfigImu(1, 1, 3, 0, 0)), 0.2)
    c.handle(encode(Start(1)), 0.3)
    assert decode(c, c.handle(encode(Sync(counter=5)), 0.4)) == [ImuSample(1, 5, 0, 0, 1024, 1, 10, 32767, 0, 0)]
    c.fault()
    assert decode(c, c.handle(encode(Sync(counter=6)), 0.5)) == [ImuSample(1, 6, 0, 0, 0, 8, TIME_UNKNOWN, 0, 0, 0)]
