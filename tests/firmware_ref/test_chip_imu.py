"""The C firmware as a 6/9-axis chip (docs/protocol.md §16) through cffi: INFO's capabilities,
CONFIG_IMU, and the IMU record on serial, classic CAN and CAN FD — the frames compared byte for byte
with the spec's own examples (§16.3, §16.4), time_us clamped and unknown as §16.1 says. Simulated
clock; expected values written out by hand from the spec."""

from __future__ import annotations

import pytest

from protocol.can import CanFrame, to_can
from protocol.framing import StreamDecoder, encode
from protocol.messages import (TIME_UNKNOWN, Ack, Assign, Capability, ConfigImu, ImuSample, Info, MsgType, Nack,
                               NackReason, Sample, Start, Stop, Sync, provisional_node)

pytest.importorskip("firmware_ref._capsheet_fw", reason="C firmware extension not built")
from firmware_ref.chip import CFirmwareChip, FirmwareError  # noqa: E402

UID = 0x0123456789ABCDEF
#: the §16.1 worked example's gyroscope (at ±1000 °/s, code 3) and magnetometer (at ±4 gauss, code 0)
GYRO = {3: (100, -200, 3000), 4: (50, -100, 1500)}


class Imu:
    """The §16.1 example as an IMU source; ``time_us`` settable."""

    def __init__(self, time_us=-1500):
        self.time_us = time_us
        self.calls = []

    def __call__(self, now_s, gyro_range, mag_range):
        self.calls.append((now_s, gyro_range, mag_range))
        return GYRO[gyro_range], (8192 >> mag_range, -4096, 1), self.time_us


def accel(now_s):
    return (0, 0, 1024), 0


def chip(sensors="accel+gyro+mag", transport="serial", fd=False, imu=None, **kw):
    c = CFirmwareChip(UID, accel, transport=transport, fd=fd, sensors=sensors,
                      imu=(imu or Imu()) if sensors != "accel" or "capabilities" in kw else None, **kw)
    c.power_on(0.0)
    out = c.handle(send(c, Assign(provisional_node(UID, 0), 1, 0, UID & 0xFFFFFFFF)), 0.1)
    assert decode(c, out) == [Ack(1, MsgType.ASSIGN, 0)]
    return c


def send(c, msg):
    return to_can(msg) if c.transport == "can" else encode(msg)


def decode(c, frames):
    if c.transport == "can":
        from protocol.can import decode_can
        return [decode_can(f.arbitration_id, f.data, is_fd=f.is_fd) for f in frames]
    return StreamDecoder().feed(b"".join(frames))


def stream(c, *configs, at=0.2):
    for cfg in configs:
        assert decode(c, c.handle(send(c, cfg), at)) == [Ack(1, MsgType.CONFIG_IMU, 0)]
    assert decode(c, c.handle(send(c, Start(1)), at)) == [Ack(1, MsgType.START, 0)]


def test_info_reports_the_sensors():
    for sensors, caps in (("accel", 0), ("accel+gyro", Capability.GYRO | Capability.SAMPLE_TIME),
                          ("accel+gyro+mag", Capability.GYRO | Capability.MAG | Capability.SAMPLE_TIME)):
        c = CFirmwareChip(UID, accel, sensors=sensors, imu=Imu() if sensors != "accel" else None)
        info = [m for m in decode(c, c.power_on(0.0)) if isinstance(m, Info)][0]
        assert info.capabilities & (Capability.GYRO | Capability.MAG | Capability.SAMPLE_TIME) == caps


def test_a_gyroscope_without_an_imu_source_is_refused():
    with pytest.raises(ValueError, match="imu source"):
        CFirmwareChip(UID, accel, sensors="accel+gyro")
    with pytest.raises(FirmwareError, match="capsheet_chip_init"):  # the C init's own check: GYRO needs read_imu
        CFirmwareChip(UID, accel, capabilities=int(Capability.GYRO))


def test_the_spec_examples_byte_for_byte_on_serial_classic_can_and_can_fd():
    # §16.3: IMU_SAMPLE, node 1, counter 0x0102, the §16.1 record (format 1, then format 2), on the wire
    c = chip()
    stream(c, ConfigImu(1, 1, 3, 0, 0))
    assert c.handle(encode(Sync(counter=0x0102)), 0.3) == [bytes.fromhex(
        "04010d01030201010101050424fa640738ffb80b97de00")]
    c.handle(encode(Stop(1)), 0.3)
    stream(c, ConfigImu(1, 2, 3, 0, 0))
    assert c.handle(encode(Sync(counter=0x0102)), 0.4) == [bytes.fromhex(
        "04010d01030201010101050424fa640538ffb80b022003f00103267800")]
    # §16.4: classic CAN, format 2: IMU_GYRO, IMU_MAG, IMU_ACCEL, in that order
    c = chip(transport="can")
    stream(c, ConfigImu(1, 2, 3, 0, 0))
    assert c.handle(to_can(Sync(counter=0x0102)), 0.3) == [
        CanFrame(0x08A10001, bytes.fromhex("0201640038FFB80B"), False),
        CanFrame(0x08B10001, bytes.fromhex("0201002000F00100"), False),
        CanFrame(0x08C10001, bytes.fromhex("02000000000424FA"), False)]
    # §16.3 on CAN FD: id 0x08D10001, 16 data bytes (the 15 of the payload, one 00)
    c = chip(sensors="accel+gyro", transport="can", fd=True)
    stream(c, ConfigImu(1, 1, 3, 0, 1))
    assert c.handle(to_can(Sync(counter=0x0102)), 0.3) == [
        CanFrame(0x08D10001, bytes.fromhex("0201000000000424fa640038ffb80b00"), True)]


def test_format_0_is_todays_sample_and_the_ranges_reach_the_source():
    imu = Imu()
    c = chip(imu=imu)
    stream(c)
    assert decode(c, c.handle(encode(Sync(counter=1)), 0.3)) == [Sample(1, 1, 0, 0, 1024, 0)]
    assert imu.calls == []  # format 0 never reads the gyroscope
    c.handle(encode(Stop(1)), 0.35)
    stream(c, ConfigImu(1, 2, 4, 1, 0), at=0.4)
    assert decode(c, c.handle(encode(Sync(counter=2)), 0.5)) == [
        ImuSample(1, 2, 0, 0, 1024, 0, -1500, 50, -100, 1500, 4096, -4096, 1)]
    assert imu.calls == [(0.5, 4, 1)]
    assert c.imu_config == (2, 4, 1, 0)


@pytest.mark.parametrize("sensors, cfg, reason", [
    ("accel+gyro+mag", (3, 3, 0, 0), NackReason.BAD_VALUE),       # format 3
    ("accel+gyro+mag", (1, 5, 0, 0), NackReason.BAD_VALUE),       # gyro range 5
    ("accel", (0, 3, 4, 0), NackReason.BAD_VALUE),                # mag range 4, even at format 0
    ("accel+gyro", (2, 3, 0, 0), NackReason.UNSUPPORTED),         # format 2 without MAG
    ("accel", (1, 3, 0, 0), NackReason.UNSUPPORTED),              # format 1 without GYRO
    ("accel+gyro", (1, 3, 0, 1), NackReason.UNSUPPORTED),         # flag FD on a serial chip (no CAN_FD)
    ("accel+gyro", (9, 9, 9, 1), NackReason.BAD_VALUE),           # BAD_VALUE before UNSUPPORTED
])
def test_config_imu_is_checked_in_order_and_a_refusal_changes_nothing(sensors, cfg, reason):
    c = chip(sensors=sensors)
    assert decode(c, c.handle(encode(ConfigImu(1, *cfg)), 0.2)) == [Nack(1, MsgType.CONFIG_IMU, reason)]
    assert c.imu_config == (0, 3, 0, 0)  # §16.2's defaults, untouched
    assert c.handle(encode(ConfigImu(0, *cfg)), 0.2) == []  # broadcast: never a NACK


def test_config_imu_is_refused_while_streaming_and_in_boot():
    c = chip()
    stream(c)
    assert decode(c, c.handle(encode(ConfigImu(1, 1, 3, 0, 0)), 0.3)) == [
        Nack(1, MsgType.CONFIG_IMU, NackReason.BAD_STATE)]
    b = CFirmwareChip(UID, accel, sensors="accel+gyro", imu=Imu())
    b.power_on(0.0)
    node = provisional_node(UID, 0)
    assert decode(b, b.handle(encode(ConfigImu(node, 1, 3, 0, 0)), 0.1)) == [
        Nack(node, MsgType.CONFIG_IMU, NackReason.BAD_STATE)]


@pytest.mark.parametrize("t_us, sent", [(-1500, -1500), (0, 0), (32767, 32767), (40000, 32767), (-32767, -32767),
                                        (-40000, -32767)])
def test_time_us_is_the_latch_minus_the_sync_clamped(t_us, sent):
    c = chip(sensors="accel+gyro", imu=Imu(t_us))
    stream(c, ConfigImu(1, 1, 3, 0, 0))
    (m,) = decode(c, c.handle(encode(Sync(counter=7)), 1.0))
    assert (m.counter, m.time_us) == (7, sent)


def test_a_chip_without_sample_time_sends_unknown():
    c = chip(sensors="accel", capabilities=int(Capability.GYRO))
    stream(c, ConfigImu(1, 1, 3, 0, 0))
    (m,) = decode(c, c.handle(encode(Sync(counter=7)), 1.0))
    assert m == ImuSample(1, 7, 0, 0, 1024, 0, TIME_UNKNOWN, 100, -200, 3000)


def test_rails_of_the_gyroscope_and_magnetometer_set_saturated_and_a_fault_sends_an_invalid_record():
    readings = iter([((32767, 0, 0), (0, 0, 0)), ((0, 0, 0), (0, -32768, 0)), ((0, 0, 0), (0, 0, 0))])

    def imu(now_s, g, m):
        gy, mg = next(readings)
        return gy, mg, 10

    c = chip(imu=imu)
    stream(c, ConfigImu(1, 2, 3, 0, 0))
    got = [decode(c, c.handle(encode(Sync(counter=k)), 0.3 + k / 100))[0] for k in range(3)]
    assert [m.status for m in got] == [1, 1, 0]
    c.fault()  # the sensor stopped answering: FAULT, INVALID records (counts 0, time unknown)
    assert decode(c, c.handle(encode(Sync(counter=9)), 0.5)) == [
        ImuSample(1, 9, 0, 0, 0, 8, TIME_UNKNOWN, 0, 0, 0, 0, 0, 0)]
