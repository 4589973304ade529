"""A packing gateway of 6/9-axis chips (docs/protocol.md §16.5): SNAPSHOT_IMU frames that hold, byte
for byte, the IMU records the same chips send one by one (IMU_SAMPLE) for the same SYNC; the caps
per frame; GATEWAY_INFO ``sample_format``; the gateway configuring its chips itself; a chip not heard
as an INVALID record. Sans-I/O, on a simulated clock."""

from __future__ import annotations

import numpy as np
import pytest

from protocol.can import decode_can, to_can
from protocol.constants import SampleStatus
from protocol.framing import StreamDecoder, encode
from protocol.messages import (TIME_UNKNOWN, ConfigImu, ConfigImuFlag, GatewayFlag, GatewayInfo, ImuSample, SnapshotImu, Start,
                               Sync)
from virtual_sheet.gateway import Gateway
from virtual_sheet.sheet import VirtualSheet

FORMAT = {"accel+gyro": 1, "accel+gyro+mag": 2}


def _decode(gw, can, until):
    frames = gw.pop_output(until)
    if can:
        return [decode_can(f.arbitration_id, f.data, is_fd=f.is_fd) for f in frames], frames
    return StreamDecoder().feed(b"".join(frames)), frames


def _pair(transport, sensors, lattice, faults=""):
    """The same sheet (same seed) twice: per-chip, its chips given CONFIG_IMU as a host would; and
    behind a packing gateway that configures them itself."""
    can = transport == "can"
    out = []
    for packed in (False, True):
        sheet = VirtualSheet("wave", lattice, noise=1.0, seed=4, transport=transport, fd=can, sensors=sensors,
                             faults=faults)
        gw = Gateway(sheet, packed=packed)
        gw.power_on(0.0)
        gw.commission(0.0, start=False)
        if not packed:
            for k in range(sheet.n_links):
                msg = ConfigImu(1 + k, FORMAT[sensors], 3, 0, ConfigImuFlag.FD if can else 0)
                (gw.receive if can else gw.feed)(to_can(msg) if can else encode(msg), 0.0)
        start = Start(0)
        (gw.receive if can else gw.feed)(to_can(start) if can else encode(start), 0.0)
        gw.pop_output(1.0)
        out.append((sheet, gw))
    return out


@pytest.mark.parametrize("transport, sensors, lattice, per_frame", [
    ("serial", "accel+gyro", "8x8", 77), ("serial", "accel+gyro+mag", "8x8", 53),
    ("can", "accel+gyro", "3x4", 4), ("can", "accel+gyro+mag", "3x4", 3)])
def test_snapshot_imu_holds_the_records_the_chips_send_one_by_one(transport, sensors, lattice, per_frame):
    can = transport == "can"
    (_s1, plain), (sheet, packed) = _pair(transport, sensors, lattice)
    assert packed.stats.imu_configured == sheet.n_links  # every chip took the gateway's CONFIG_IMU
    for counter, t in ((7, 0.25), (8, 0.5)):
        sync = Sync(counter=counter)
        for gw in (plain, packed):
            (gw.receive if can else gw.feed)(to_can(sync) if can else encode(sync), t)
        one, _ = _decode(plain, can, t + 1.0)
        snaps, frames = _decode(packed, can, t + 1.0)
        records = {m.node - 1: m for m in one if isinstance(m, ImuSample)}  # node = 1 + link (commission)
        assert len(records) == sheet.n_links
        got = [m for m in snaps if isinstance(m, SnapshotImu)]
        assert not [m for m in snaps if isinstance(m, ImuSample)]
        n = sheet.n_links
        assert [m.count for m in got] == [per_frame] * (n // per_frame) + ([n % per_frame] if n % per_frame else [])
        assert all(m.counter == counter and m.format == FORMAT[sensors] and m.node == packed.node_id for m in got)
        if can:
            assert all(f.is_fd and len(f.data) <= 64 for f in frames)
        link = 0
        for m in got:
            assert m.first_link == link
            c, st, t_us, g, mag = m.arrays()
            for j in range(m.count):
                r = records[link + j]
                assert (r.x, r.y, r.z) == tuple(c[j]) and r.status == st[j] and r.time_us == t_us[j]
                assert tuple(r.gyro) == tuple(g[j])
                assert (r.mx is None) == (mag is None)
                if mag is not None:
                    assert tuple(r.mag) == tuple(mag[j])
            link += m.count
        assert np.abs(np.concatenate([m.arrays()[3] for m in got])).max() > 0  # the sheet moves


@pytest.mark.parametrize("transport", ["serial", "can"])
def test_a_gateway_packing_imu_records_says_so_and_marks_a_dead_chip_invalid(transport):
    can = transport == "can"
    (_a, _b), (sheet, gw) = _pair(transport, "accel+gyro+mag", "2x3", faults="dead_chip=2")
    assert gw.node is not None and gw.node.flags & GatewayFlag.PACKING
    info = gw.node.announce()
    decoded = [decode_can(f.arbitration_id, f.data, is_fd=f.is_fd) for f in info] if can else \
        StreamDecoder().feed(b"".join(info))
    assert {m.sample_format for m in decoded if isinstance(m, GatewayInfo)} == {2}
    sync = Sync(counter=3)
    (gw.receive if can else gw.feed)(to_can(sync) if can else encode(sync), 0.3)
    got = [m for m in _decode(gw, can, 2.0)[0] if isinstance(m, SnapshotImu)]
    c, st, t_us, g, mag = (np.concatenate(a) for a in zip(*(m.arrays() for m in got)))
    assert st[2] == SampleStatus.INVALID and t_us[2] == TIME_UNKNOWN
    assert c[2].tolist() == g[2].tolist() == mag[2].tolist() == [0, 0, 0]
    others = np.delete(np.arange(sheet.n_links), 2)
    assert not (st[others] & SampleStatus.INVALID).any() and (t_us[others] != TIME_UNKNOWN).all()


def test_packing_imu_records_on_classic_can_is_refused():
    sheet = VirtualSheet("wave", "2x2", transport="can", fd=False, sensors="accel+gyro")
    with pytest.raises(ValueError, match="CAN FD"):
        Gateway(sheet, packed=True)


@pytest.mark.parametrize("transport, sensors", [("serial", "accel+gyro"), ("serial", "accel+gyro+mag"),
                                                ("can", "accel+gyro"), ("can", "accel+gyro+mag")])
def test_a_babbling_chips_record_is_packed_and_only_its_junk_passes_on(transport, sensors):
    """docs §13.1 (a gateway passes its chips' frames unchanged except the samples it packs), §13.2
    (every link exactly once), §16.5: a faulty chip — here one that floods STATUS frames beside its
    answer — still has its record packed, byte for byte what it sends one by one (on classic CAN its
    IMU_GYRO (+ IMU_MAG) + IMU_ACCEL, assembled); its junk, and nothing else, passes on."""
    can = transport == "can"
    faults = "babble_chip=2,babble_mode=flood,babble_rate=3,seed=5"
    (s1, plain), (sheet, packed) = _pair(transport, sensors, "2x3", faults=faults)
    junk = 0
    for counter, t in ((7, 0.25), (8, 0.5), (9, 0.75)):
        sync = Sync(counter=counter)
        before = sheet.fault_stats.babble_frames
        for gw in (plain, packed):
            (gw.receive if can else gw.feed)(to_can(sync) if can else encode(sync), t)
        one, _ = _decode(plain, can, t + 0.1)
        got, _ = _decode(packed, can, t + 0.1)
        records = {m.node - 1: m for m in one if isinstance(m, ImuSample)}
        assert len(records) == sheet.n_links  # the babbler answers, one by one, as the others do
        snaps = [m for m in got if isinstance(m, SnapshotImu)]
        cap = {(False, 1): 77, (False, 2): 53, (True, 1): 4, (True, 2): 3}[can, FORMAT[sensors]]
        assert [(m.first_link, m.counter) for m in snaps] == [(a, counter) for a in range(0, sheet.n_links, cap)]
        c, st, t_us, g, mag = (None if a[0] is None else np.concatenate(a) for a in zip(*(m.arrays() for m in snaps)))
        assert c.shape == (sheet.n_links, 3)
        for k, r in records.items():
            assert ((r.x, r.y, r.z), r.status, r.time_us, r.gyro) == (tuple(c[k]), st[k], t_us[k], tuple(g[k]))
            assert r.mag == (None if mag is None else tuple(mag[k]))
        assert not st[2] & SampleStatus.INVALID
        rest = [m for m in got if not isinstance(m, SnapshotImu)]
        n_junk = sheet.fault_stats.babble_frames - before
        assert len(rest) == n_junk  # nothing but the babble passes on: no IMU_SAMPLE, no IMU_GYRO/ACCEL
        assert all(type(m).__name__ == "Status" and m.node == 3 for m in rest)
        junk += n_junk
    assert junk > 0  # the chip did babble
