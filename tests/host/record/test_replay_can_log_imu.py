"""A CAN log of 6-axis chips replays at the gyroscope range the host configured:
the log holds the host's CONFIG_IMU, and the replay converts the records with its range, not
CONFIG_IMU's power-on default. The log is written with python-can's own Logger; expected rates
worked out by hand from §16.1's sensitivities."""

from __future__ import annotations

import math

import can
import pytest

from host.record.replay import Replay
from protocol.can import to_can
from protocol.messages import ConfigImu, ImuAccel, ImuGyro, Sync


def _log(path, config: bool, n_links: int = 4) -> None:
    t = 1000.0
    with can.Logger(str(path)) as log:
        def put(msg):
            nonlocal t
            f = to_can(msg)
            log(can.Message(timestamp=t, arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True,
                            channel="can0"))
            t += 0.0005
        if config:
            put(ConfigImu(0, 1, 0, 0, 0))  # format 1, ±125 °/s (262.144 counts per °/s)
        for c in range(5, 9):
            put(Sync(counter=c))
            for k in range(n_links):
                put(ImuGyro(k + 1, c, 262, -524, 0))
                put(ImuAccel(k + 1, c & 0xFF, 0, 0, 1024, 0, 100))
            t += 0.01


@pytest.mark.parametrize("suffix", [".log", ".asc"])
def test_a_can_log_replays_at_the_range_its_config_imu_set(tmp_path, suffix):
    path = tmp_path / f"run{suffix}"
    _log(path, config=True)
    rp = Replay(path, lattice="2x2")
    assert rp.imu_ranges_from == "CONFIG_IMU in the log"
    snaps = [s for s in rp.snapshots() if s.gyro is not None]
    assert len(snaps) >= 3
    for s in snaps:
        assert s.gyro[:, 0] == pytest.approx(math.radians(262 / 262.144))  # ≈ 1 °/s, not 8 °/s at ±1000
        assert s.gyro[:, 1] == pytest.approx(math.radians(-524 / 262.144))


def test_without_config_imu_the_default_range_or_the_given_one(tmp_path):
    path = tmp_path / "run.log"
    _log(path, config=False)
    rp = Replay(path, lattice="2x2")
    assert rp.imu_ranges_from == "default"
    s = next(s for s in rp.snapshots() if s.gyro is not None)
    assert s.gyro[0, 0] == pytest.approx(math.radians(262 / 32.768))  # CONFIG_IMU's power-on ±1000 °/s
    rp = Replay(path, lattice="2x2", imu_ranges=(0, 0))
    assert rp.imu_ranges_from == "given"
    s = next(s for s in rp.snapshots() if s.gyro is not None)
    assert s.gyro[0, 0] == pytest.approx(math.radians(262 / 262.144))


def test_capsheet_replay_takes_the_range_of_a_can_log(tmp_path):
    """Through the CLI: --gyro-range is taken for a CAN log and the replay runs (the conversion itself is
    checked through `Replay` above)."""
    import json
    import subprocess
    import sys

    path = tmp_path / "run.log"
    _log(path, config=False)
    out = subprocess.run([sys.executable, "-m", "host.cli", "replay", str(path), "--lattice", "2x2", "--no-estimate",
                          "--gyro-range", "125", "--json", "-q"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout)
    assert r["snapshots"] >= 3 and r["imu_ranges_from"] == "given"  # the JSON says which ranges converted it
