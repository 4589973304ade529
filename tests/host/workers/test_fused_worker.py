"""`host.workers.fused_worker.FusedProcess`: the fused estimator in its own process makes the same
shapes as `fused_update` in the caller's, for every snapshot, in order, with the counts said.

The snapshots are a host's (manual mode, simulated clock) from a 9-axis carried sheet behind two
gateways (`virtual_sheet.devices.MultiMemoryDevice`), some of them with a gateway's links missing
and one with no IMU record at all. No rate or latency is asserted.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from host.analysis.motion import FusedConfig, MotionEstimator
from host.analysis.motion.snapshots import fused_update
from host.session.core import Host, Layout
from host.transport.ports import MemoryTransport
from host.workers.fused_worker import FusedProcess
from protocol.constants import G0
from virtual_sheet.devices import MultiMemoryDevice
from virtual_sheet.sheet import VirtualSheet

L = 0.01
CONFIG = FusedConfig(accel_noise_mps2=0.01 * G0)


class SimClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture(scope="module")
def snapshots():
    clock = SimClock()
    sheet = VirtualSheet("carry", "4x4", link_length=L, noise=1.0, seed=2, scene_rate_hz=10.0,
                         sensors="accel+gyro+mag")
    sheet.precompute()
    dev = MultiMemoryDevice(sheet, n_gateways=2, clock=clock)
    dev.start()

    def driver(dt: float) -> None:
        clock.t += dt
        dev.step()

    host = Host([MemoryTransport(p) for p in dev.ports], sheet.lattice, layout=Layout(dict(sheet.layout)),
                rate_hz=145.0, clock=clock, driver=driver, timeout_s=0.15)
    host.imu_config = (2, 0, 0, 0)
    try:
        host.open()
        assert host.bring_up(0.2)["started"] == sheet.n_links
        snaps = list(host.snapshots(count=120))
        host.stop()
    finally:
        host.close()
        dev.stop()
    # snapshots 40-59: the second gateway's links (12-23) missing, as a late port leaves them
    out = []
    for k, s in enumerate(snaps):
        if 40 <= k < 60:
            valid = s.valid.copy()
            valid[12:] = False
            s = dataclasses.replace(s, valid=valid, complete=False)
        out.append(s)
    out[80] = dataclasses.replace(out[80], gyro=None, mag=None, sample_time_s=None)  # no IMU record
    return out


def test_the_process_makes_the_shapes_fused_update_makes_in_order(snapshots):
    here = MotionEstimator(4, 4, L, config=CONFIG)
    expected = [fused_update(here, s) for s in snapshots]
    proc = FusedProcess(4, 4, L, config=CONFIG, max_in_flight=8)
    got = []
    try:
        for s in snapshots:
            while not proc.free:
                got += proc.results(timeout_s=1.0)
            proc.submit(s)
        got += proc.close(timeout_s=30.0)
    finally:
        proc.close(0.0)
    assert [r.counter for r in got] == [s.counter for s in snapshots]
    assert [r.ok for r in got] == [e is not None for e in expected]
    assert expected[80] is None and not got[80].ok and got[80].error == ""
    for r, e in zip(got, expected):
        if e is not None:
            np.testing.assert_array_equal(r.joints, e.joints)
            np.testing.assert_array_equal(r.valid, e.valid)
    assert proc.submitted == 120 and proc.made == 119 and proc.left_out == 1 and proc.failed == 0
    assert got[-1].snapshots == here.snapshots  # one sequence in the child too: no restart


def test_a_snapshot_of_another_lattice_is_refused_before_it_is_sent():
    proc = FusedProcess(3, 3, L, config=CONFIG)
    try:
        n = 12
        bad = type("Snap", (), {"counter": 0, "timestamp": 0.0, "valid": np.ones(n + 1, bool),
                                "readings": np.zeros((n + 1, 3)), "gyro": None, "mag": None,
                                "sample_time_s": None})()
        with pytest.raises(ValueError, match="13 links|lattice of 12 links"):
            proc.submit(bad)
        assert proc.submitted == 0
    finally:
        proc.close(0.0)


def test_the_process_says_it_is_ready_before_any_snapshot_and_answers_nothing_else_then():
    proc = FusedProcess(3, 3, L, config=CONFIG)
    try:
        assert proc.wait_ready(60.0)
        assert proc.results(timeout_s=0.2) == []  # the warm-up's shape is not an answer
        assert proc.submitted == proc.made == proc.left_out == 0
    finally:
        proc.close(0.0)
