"""docs/protocol.md §17.2: a 6-axis chip of protocol 1.2 does not know CAL_IMU_READ / CAL_IMU_WRITE and
answers them NACK 1 UNKNOWN_COMMAND. The wire carries no minor version, so a host MUST accept that as
"no IMU calibration on the chip": the host library brings such a sheet up over a real pty, reads no IMU
calibration (counted), and streams its gyroscopes all the same."""

from __future__ import annotations

import numpy as np

from host.session.core import Host, Layout
from host.transport.ports import SerialTransport
from protocol.messages import MsgType, Nack, NackReason
from virtual_sheet.chip import ChipModel
from virtual_sheet.devices import PtyDevice
from virtual_sheet.sheet import VirtualSheet


class ChipV12(ChipModel):
    """A 1.2 chip: 0x1A and 0x1B are undefined types to it (NACK 1 when addressed to it, §8.1). Counts them."""

    nacked = 0

    def handle(self, frame, now_s, decoded=None):
        msg = self.decode(frame) if decoded is None else decoded
        t = getattr(msg, "TYPE", None)
        if t in (MsgType.CAL_IMU_READ, MsgType.CAL_IMU_WRITE):
            if msg.node != self.node:
                return []
            ChipV12.nacked += 1
            return [self._out(Nack(self.node, t, NackReason.UNKNOWN_COMMAND))]
        return super().handle(frame, now_s, decoded)


def test_a_host_brings_up_6_axis_chips_of_1_2_that_answer_cal_imu_read_nack_1():
    ChipV12.nacked = 0
    sheet = VirtualSheet("flat", "2x2", seed=3, noise=0.5, sensors="accel+gyro", chip_factory=ChipV12)
    with PtyDevice(sheet) as dev:
        host = Host([SerialTransport(str(dev.path))], "2x2", layout=Layout(dict(sheet.layout)), rate_hz=100,
                    timeout_s=0.2, retries=3)
        host.imu_config = (1, 3, 0, 0)  # 6-axis, ±1000 °/s
        with host:
            summary = host.bring_up(0.3)
            snaps = list(host.snapshots(count=10))
            host.stop()
    n = sheet.n_links
    assert summary["started"] == n and summary["imu_calibrated"] == 0  # none read, none failed the bring-up
    assert ChipV12.nacked >= n  # every chip was asked (its INFO has GYRO) and said NACK 1
    with_gyro = [s for s in snaps if s.gyro is not None and np.isfinite(s.gyro).all()]
    assert len(with_gyro) >= 5  # and its gyroscopes stream as sent
