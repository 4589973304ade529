"""Hypothesis strategies for protocol messages, shared by the protocol and firmware tests."""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st

from protocol.constants import ADC_MAX, ADC_MIN
from protocol.messages import (Ack, Announce, Assign, CalData, CalImuData, CalImuRead, CalImuWrite, CalRead, CalWrite, ChipState, Config, GetInfo,
                               Info, MAX_SNAPSHOT_SAMPLES, Nack, NackReason, Reset, Sample, Snapshot, Start,
                               Status, Stop, Sync, MsgType)

u8 = st.integers(0, 0xFF)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)
node = st.integers(0, 0xFFFE)
unicast = st.integers(1, 0xFFFE)
axis_count = st.integers(ADC_MIN, ADC_MAX)
sens = st.floats(1e-3, 1e6, allow_nan=False, allow_infinity=False)


@st.composite
def snapshots(draw, max_count: int = MAX_SNAPSHOT_SAMPLES):
    n = draw(st.integers(1, max_count))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.Generator(np.random.MT19937(seed))
    counts = rng.integers(ADC_MIN, ADC_MAX + 1, size=(n, 3))
    status = rng.integers(0, 16, size=n)
    first = draw(st.integers(0, 0x10000 - n))
    return Snapshot.from_arrays(draw(node), draw(u16), first, counts, status)


def messages(max_snapshot: int = 202):
    """Any valid message of any type (snapshots capped at what one serial frame carries)."""
    return st.one_of(
        st.builds(Announce, node, st.integers(0, 2**64 - 1)),
        st.builds(Info, node, u8, u8, u8, u8, u16, u8, st.sampled_from(list(ChipState))),
        st.builds(Sample, node, u16, axis_count, axis_count, axis_count, st.integers(0, 15)),
        st.builds(Status, node, st.sampled_from(list(ChipState)), u8, u8, u8, u32),
        st.builds(Ack, node, u8, u8),
        st.builds(Nack, node, u8, st.sampled_from(list(NackReason))),
        st.builds(CalData, node, st.integers(0, 2), u8, st.integers(-32768, 32767), sens),
        snapshots(max_snapshot),
        st.builds(Sync, st.just(0), u16),
        st.builds(Assign, unicast, st.integers(1, 0x7FFF), u16, u32),
        st.builds(Config, node, u16, u8, u8, u16),
        st.builds(Start, node), st.builds(Stop, node), st.builds(GetInfo, node), st.builds(Reset, node),
        st.builds(CalWrite, unicast, st.integers(0, 2), u8, st.integers(-32768, 32767), sens),
        st.builds(CalRead, unicast, st.integers(0, 2)),
        # v1.3 (§17)
        st.builds(CalImuData, node, *_cal_imu_element(), u8, st.just(0), _f32),
        st.builds(CalImuWrite, unicast, *_cal_imu_element(), u8, st.just(0), _f32),
        st.builds(CalImuRead, unicast, *_cal_imu_element()),
    )


_f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)


def _cal_imu_element():
    """(block, index) strategies over the 3 x 3 blocks (GYRO_MATRIX, GYRO_G_SENS, MAG_MATRIX), every index."""
    return st.sampled_from([0, 2, 3]), st.integers(0, 8)


ALL_TYPES = list(MsgType)
