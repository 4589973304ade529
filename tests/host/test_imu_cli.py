"""6/9-axis chips through the real command line on every transport (issue 29 point 1, 5, 6): a moving
virtual sheet (`--shape wave`/`carry`, `--sensors ...`) behind memory, pty, SLCAN, python-can virtual
and udp_multicast; ``capsheet host --sensors ...`` sends CONFIG_IMU, receives IMU records (serial:
IMU_SAMPLE; classic CAN: IMU_GYRO [+ IMU_MAG] + IMU_ACCEL assembled by the host) and reports them.
Assertions are on what is delivered, never a rate (tests/host/test_matrix.py's harness)."""

from __future__ import annotations

import contextlib
import json

import pytest

from tests.host.test_matrix import TRANSPORTS, Job
from tests.host.udp_lock import udp_multicast_lock

#: transport -> (scene, sensors): both formats, serial and CAN, each transport once
CASES = {"memory": ("wave", "accel+gyro+mag"), "pty": ("carry", "accel+gyro"), "slcan": ("wave", "accel+gyro+mag"),
         "virtual": ("carry", "accel+gyro"), "udp_multicast": ("elbow", "accel+gyro+mag")}
assert set(CASES) == set(TRANSPORTS)


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_host_streams_imu_records_on_every_transport(transport, tmp_path):
    shape, sensors = CASES[transport]
    args = ["host", "{port}", "--lattice", "3x3", "--layout", "{layout}", "--sensors", sensors, "--rate", "100",
            "--duration", "2", "-q", "--json"]
    lock = udp_multicast_lock() if transport == "udp_multicast" else contextlib.nullcontext()
    with lock:
        job = Job(transport, tmp_path, f"imu-{transport}", args,
                  ["--shape", shape, "--sensors", sensors, "--noise", "1"]).finish()
    assert job.rc == 0, job.stderr
    s = job.json()["summary"]
    assert s["sensors"] == sensors
    assert s["snapshots"] > 0 and s["valid_links_pct"] >= 95.0
    # every valid link sample of the run came with its gyroscope (the records were assembled, none lost)
    assert s["imu_links_pct"] == pytest.approx(s["valid_links_pct"], abs=1e-6)
    assert s["errors"] == {}, s["errors"]
    assert "IMU records (gyroscope" in job.stderr
    assert ("magnetometer" in job.stderr) == sensors.endswith("mag")


def test_an_accel_only_sheet_refuses_config_imu_and_the_host_says_so(tmp_path):
    """A v1.1-style accelerometer chip (no GYRO): CONFIG_IMU is NACKed UNSUPPORTED; the host streams
    accelerometer samples and reports no IMU records (the old chips keep working beside the new)."""
    args = ["host", "{port}", "--lattice", "3x3", "--layout", "{layout}", "--sensors", "accel+gyro", "--rate", "100",
            "--duration", "1", "-q", "--json"]
    job = Job("memory", tmp_path, "imu-accel-only", args, ["--shape", "gaussian"]).finish()
    s = job.json()["summary"]
    assert s["valid_links_pct"] >= 95.0 and s["imu_links_pct"] == 0.0


@pytest.mark.parametrize("transport", ["pty", "virtual"])
def test_a_recording_of_a_6_axis_sheet_carries_its_axes_and_replays_identical(transport, tmp_path):
    """``--record`` keeps every snapshot's gyroscope and sample time (serial: IMU_SAMPLE; CAN: the
    classic frames of §16.4), and ``capsheet replay`` rebuilds every one identical from the raw bytes."""
    import subprocess

    import numpy as np

    from host.record import read
    from tests.host.test_matrix import PY, ROOT
    mcap = tmp_path / "imu.mcap"
    args = ["host", "{port}", "--lattice", "3x3", "--layout", "{layout}", "--sensors", "accel+gyro", "--rate", "100",
            "--duration", "2", "-q", "--record", str(mcap)]
    job = Job(transport, tmp_path, f"imu-rec-{transport}", args, ["--shape", "carry", "--sensors", "accel+gyro"]).finish()
    assert job.rc == 0, job.stderr
    rec = read(mcap)
    assert len(rec) >= 10 and rec.gyro is not None and rec.mag is None
    assert rec.gyro.shape == (len(rec), 12, 3) and rec.sample_time_s.shape == (len(rec), 12)
    got = rec.valid & np.isfinite(rec.gyro[..., 0])
    assert got.sum() == rec.valid.sum() > 0  # every valid link sample has its gyroscope
    assert np.nanmax(np.abs(rec.gyro)) > 0.1  # the sheet is carried and turned: rad/s, not counts
    assert np.all(np.abs(rec.sample_time_s[got]) < 0.01)  # within a grid step of the SYNC
    out = subprocess.run([PY, "-m", "host.cli", "replay", str(mcap), "--json", "-q"], cwd=ROOT,
                         capture_output=True, text=True, timeout=240)
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout[out.stdout.index("{"):])
    assert r["snapshots_identical"] == r["snapshots_compared"] == r["recorded_snapshots"] == len(rec), r
