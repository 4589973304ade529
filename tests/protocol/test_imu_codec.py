"""v1.2 IMU messages (docs §16): round trips on both transports, the classic-CAN assembly of a record
from its frames (§16.4) and every way it can be left incomplete, each reported exactly once."""

from __future__ import annotations

from types import SimpleNamespace as F

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.can import CanDecoder, decode_can, imu_can_frames, to_can
from protocol.framing import DecodeError, ErrorReason, StreamDecoder, encode
from protocol.messages import (TIME_UNKNOWN, ImuAccel, ImuGyro, ImuMag, ImuSample, SnapshotImu, imu_saturated,
                               pack_imu_records, unpack_imu_records)

i16 = st.integers(-32768, 32767)
acc = st.integers(-2048, 2047)


def imu_samples():
    six = st.builds(ImuSample, st.integers(1, 0x7FFF), st.integers(0, 0xFFFF), acc, acc, acc, st.integers(0, 15),
                    i16, i16, i16, i16)
    nine = st.builds(ImuSample, st.integers(1, 0x7FFF), st.integers(0, 0xFFFF), acc, acc, acc, st.integers(0, 15),
                     i16, i16, i16, i16, i16, i16, i16)
    return st.one_of(six, nine)


def frames(cans):
    return [F(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True, is_fd=f.is_fd,
              is_error_frame=False, is_remote_frame=False) for f in cans]


@given(imu_samples())
def test_an_imu_sample_round_trips_on_serial_fd_and_classic_can(msg):
    assert StreamDecoder().feed(encode(msg)) == [msg]
    fd = imu_can_frames(msg, fd=True)
    assert len(fd) == 1 and len(fd[0].data) == (16 if msg.mx is None else 24)
    assert decode_can(fd[0].arbitration_id, fd[0].data, is_fd=True) == msg
    classic = imu_can_frames(msg, fd=False)
    assert [len(f.data) for f in classic] == [8] * (2 if msg.mx is None else 3)
    dec = CanDecoder()
    assert dec.feed(frames(classic)) == [msg]
    assert not dec.stats.errors and dec.close() == []


def test_records_of_many_nodes_interleaved_are_assembled_per_node():
    a = ImuSample(1, 10, 1, 2, 3, 0, 5, 6, 7, 8, 9, 10, 11)
    b = ImuSample(2, 10, -1, -2, -3, 0, -5, -6, -7, -8)
    fa, fb = imu_can_frames(a), imu_can_frames(b)
    mixed = [fa[0], fb[0], fa[1], fb[1], fa[2]]  # b closes before a's last frame
    ev = CanDecoder().feed(frames(mixed))
    assert ev == [b, a]


def _incomplete(ev):
    return [e for e in ev if isinstance(e, DecodeError)]


def test_every_incomplete_record_is_one_counted_event():
    good = ImuSample(1, 0x0102, 0, 0, 1024, 0, -1500, 100, -200, 3000, 8192, -4096, 1)
    g, m, a = imu_can_frames(good)
    dec = CanDecoder()
    ev = dec.feed(frames([a]))  # an IMU_ACCEL with no open record
    ev += dec.feed(frames([m]))  # an IMU_MAG with no open record
    ev += dec.feed(frames([g, g, m, a]))  # a second IMU_GYRO drops the first; the second completes
    other = to_can(ImuAccel(1, 0x03, 0, 0, 1024, 0, 0))  # counter byte 3 does not close counter 0x0102
    ev += dec.feed(frames([g, other]))
    ev += dec.feed(frames([g]))
    ev += dec.close()  # still open at the end
    bad = _incomplete(ev)
    assert [e.reason for e in bad] == [ErrorReason.BAD_FIELD] * 5
    assert all("incomplete IMU record" in e.detail for e in bad)
    assert [e for e in ev if isinstance(e, ImuSample)] == [good]
    assert dec.stats.errors[ErrorReason.BAD_FIELD] == 5
    assert dec.stats.frames == 9  # every decoded frame, the dropped ones too


def test_time_unknown_and_saturation_rule():
    counts = np.array([[0, 0, 1024], [-2048, 0, 0], [0, 0, 0], [0, 0, 0]])
    gyro = np.array([[0, 0, 0], [0, 0, 0], [32767, 0, 0], [0, 0, 0]])
    mag = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, -32768, 0]])
    assert imu_saturated(counts, gyro).tolist() == [False, True, True, False]
    assert imu_saturated(counts, gyro, mag).tolist() == [False, True, True, True]
    data = pack_imu_records(counts, [0, 1, 1, 1], [TIME_UNKNOWN, -1, 0, 32767], gyro, mag)
    assert len(data) == 4 * 19
    c, s, t, g, m = unpack_imu_records(data, 2)
    assert (c == counts).all() and s.tolist() == [0, 1, 1, 1] and t.tolist() == [-32768, -1, 0, 32767]
    assert (g == gyro).all() and (m == mag).all()


@pytest.mark.parametrize("bad", [dict(time_us=[40000]), dict(gyro=[[0, 0, -40000]]), dict(counts=[[0, 0, 2048]])])
def test_packing_refuses_values_out_of_their_field(bad):
    args = dict(counts=[[0, 0, 0]], status=[0], time_us=[0], gyro=[[0, 0, 0]]) | bad
    with pytest.raises(ValueError, match="Invalid"):
        pack_imu_records(**args)


def test_a_snapshot_imu_holds_its_records():
    s = SnapshotImu.from_arrays(9, 3, 100, [[1, 2, 3], [4, 5, 6]], [0, 8], [10, TIME_UNKNOWN], [[7, 8, 9], [0, 0, 0]])
    assert s.count == 2 and s.format == 1
    assert StreamDecoder().feed(encode(s)) == [s]
    f = to_can(s)
    assert f.is_fd and len(f.data) == 32 and decode_can(f.arbitration_id, f.data, is_fd=True) == s
    with pytest.raises(ValueError):
        ImuSample(1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, None, 2)  # a magnetometer is all three axes or none
    assert ImuGyro(1, 0, 1, 2, 3).payload() == bytes([0, 0, 1, 0, 2, 0, 3, 0])
    assert ImuMag(1, 0x0201, -1, 0, 0).payload() == bytes([1, 2, 0xFF, 0xFF, 0, 0, 0, 0])


def test_a_second_imu_mag_is_reported_and_the_first_kept():
    """§16.4 as 1.4 answers it (G02): a second IMU_MAG of the same node and counter while the record is open
    is one incomplete-record event and is dropped; the record keeps the first and the IMU_ACCEL closes it."""
    good = ImuSample(1, 0x0102, 0, 0, 1024, 0, -1500, 100, -200, 3000, 8192, -4096, 1)
    g, m, a = imu_can_frames(good)
    again = to_can(ImuMag(1, 0x0102, 1, 2, 3))
    ev = CanDecoder().feed(frames([g, m, again, a]))
    bad = _incomplete(ev)
    assert len(bad) == 1 and "IMU_MAG" in bad[0].detail and "incomplete IMU record" in bad[0].detail
    assert [e for e in ev if isinstance(e, ImuSample)] == [good]  # mx, my, mz = 8192, -4096, 1: the first
