"""6/9-axis chips through the real command line on every transport: a moving
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
#: the streaming runs' length. What they assert is counted over the run's snapshots (more than none,
#: >= 95 % of link samples valid, every valid one with its gyroscope); 1 s was tried: at load 9-10 a
#: burst of udp_multicast records dropped at the start (31 of 103 snapshots) fell below 95 %
RUN_S = "2"
#: what is delivered is under test, not how soon: a modest rate, and a host that waits 2 s for a
#: snapshot's links (its watchdog then waits as long). On a loaded machine the default adaptive
#: deadline (50-250 ms at 100 Hz) cut snapshots, and a 500 ms one with the watchdog's 0.5 s marked a
#: udp_multicast sheet's links missing (15 % valid beside two busy loops and three test workers)
DELIVERY = ("--rate", "50", "--deadline-ms", "2000")


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_host_streams_imu_records_on_every_transport(transport, tmp_path):
    shape, sensors = CASES[transport]
    args = ["host", "{port}", "--lattice", "3x3", "--layout", "{layout}", "--sensors", sensors, *DELIVERY,
            "--duration", RUN_S, "-q", "--json"]
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

    from host.record.recording import read
    from tests.host.test_matrix import PY, ROOT
    mcap = tmp_path / "imu.mcap"
    # `DELIVERY`: at load 6-7 the default deadline left 87.6 % of link samples valid
    args = ["host", "{port}", "--lattice", "3x3", "--layout", "{layout}", "--sensors", "accel+gyro", *DELIVERY,
            "--duration", RUN_S, "-q", "--record", str(mcap)]
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
    # the live host shaped every snapshot with the fused estimator (estimates at its --live-rate); the
    # replay does it again, in order, on the same snapshots: the same shapes (float32 in the file)
    assert r["estimates_compared"] >= 1 and r["estimate_change_pct_side_max"] < 1e-3, r


def _kabsch_error(est: "np.ndarray", truth: "np.ndarray") -> float:
    """Mean joint distance after the least-squares rigid overlay (written here, apart from
    host.analysis.metrics), metres."""
    import numpy as np
    a, b = est.reshape(-1, 3), truth.reshape(-1, 3)
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return float(np.linalg.norm((a - ca) @ R.T + cb - b, axis=1).mean())


def _record(tmp_path, name: str, shape: str, sensors: str, duration: str = "3"):
    """``capsheet host --record`` of a 3x3 sheet on a pty, and the sheet's own truth per counter."""
    mcap, truth = tmp_path / f"{name}.mcap", tmp_path / f"{name}-truth.npz"
    # a 1.2 s deadline (what 100 SYNC/s and the host's 128 open counters hold): a loaded machine's
    # late frames are waited for rather than recorded as missing links
    args = ["host", "{port}", "--lattice", "3x3", "--layout", "{layout}", "--sensors", sensors, "--rate", "100",
            "--deadline-ms", "1200", "--duration", duration, "-q", "--record", str(mcap)]
    job = Job("pty", tmp_path, name, args, ["--shape", shape, "--sensors", sensors, "--noise", "1",
                                             "--truth-out", str(truth)]).finish()
    assert job.rc == 0, job.stderr
    return mcap, truth


@pytest.fixture(scope="module")
def carry6(tmp_path_factory):
    """One recording of a carried-and-turned 6-axis sheet and its truth, made once for the module's
    estimate tests (the shapes and the refusals look at the same kind of recording)."""
    return _record(tmp_path_factory.mktemp("carry6"), "carry6", "carry", "accel+gyro")


def _estimate_here(capsys, mcap, out, *extra) -> tuple[int, str, str]:
    """``capsheet estimate`` through its entry point in this process (its run through a real process
    is `test_estimate_shapes_a_6_axis_recording_with_its_gyroscopes`): (exit status, stdout, stderr)."""
    from host.cli import main
    capsys.readouterr()
    try:
        code = main(["estimate", str(mcap), "--out", str(out), "--json", "-q", *extra])
    except SystemExit as exc:  # argparse's own refusals
        code = exc.code
    got = capsys.readouterr()
    return code, got.out, got.err


def _estimate(mcap, out, *extra):
    import subprocess

    from tests.host.test_matrix import PY, ROOT
    return subprocess.run([PY, "-m", "host.cli", "estimate", str(mcap), "--out", str(out), "--json", "-q", *extra],
                          cwd=ROOT, capture_output=True, text=True, timeout=240)


def test_estimate_shapes_a_6_axis_recording_with_its_gyroscopes(carry6, tmp_path, capsys):
    """``capsheet estimate`` of a carried-and-turned 6-axis sheet's recording runs the fused estimator
    (by default: the recording carries gyroscopes), and its shapes are closer to the virtual sheet's
    own truth than the accelerometer-only estimate of the same recording (which takes the sheet's
    own acceleration for gravity: measured 0.6 against 1.9 % of side). The default method runs
    through a real process (the command's run end to end); the global method and the MCAP out
    through the entry point in this process, which prints and writes the same."""
    import numpy as np

    from host.cli.estimate import STALE
    from host.record.recording import read
    mcap, truth_file = carry6
    truth = np.load(truth_file)
    true_joints = dict(zip(truth["counter"].tolist(), truth["joints"]))
    rec_valid = read(mcap).valid
    errors = {}
    for method in ("auto", "global"):
        out = tmp_path / f"{method}.npz"
        if method == "auto":
            p = _estimate(mcap, out, "--method", method)
            code, stdout, stderr = p.returncode, p.stdout, p.stderr
        else:
            code, stdout, stderr = _estimate_here(capsys, mcap, out, "--method", method)
        assert code == 0, stderr
        summary = json.loads(stdout)
        assert summary["method"] == ("fused" if method == "auto" else "global")
        assert summary["sensors"] == "accel+gyro"
        est = np.load(out)
        # every snapshot is estimated or counted with its reason. A loaded machine's recording held
        # snapshots the live host delivered with no valid link (3 of 301 once), as the recording
        # itself says, and ones whose every record repeated the snapshot before's (the sheet read
        # two SYNCs close together: 2 of 299 once), which the fused method does not take twice
        no_link = int((~rec_valid.any(axis=1)).sum())
        ne = summary["not_estimated"]
        assert ne["no_valid_link"] == no_link, summary
        assert set(ne["reasons"]) <= {STALE}, ne
        assert summary["estimated"] == summary["snapshots"] - no_link - ne["refused"] >= 200, summary
        assert summary["snapshots"] == est["joints"].shape[0] == rec_valid.shape[0]
        assert np.isfinite(est["residual"]).sum() == summary["estimated"]
        side = 2 * 0.01
        errors[method] = np.array([100 * _kabsch_error(j, true_joints[int(c)]) / side
                                   for c, j in zip(est["counter"], est["joints"]) if np.isfinite(j).all()])
        assert errors[method].size >= 200, errors[method].size
    assert errors["auto"].mean() < 0.6 * errors["global"].mean(), {m: e.mean() for m, e in errors.items()}
    assert errors["auto"].mean() < 1.5
    # an MCAP out keeps the axes and names the method
    code, stdout, stderr = _estimate_here(capsys, mcap, tmp_path / "shapes.mcap", "--png")
    assert code == 0, stderr
    assert json.loads(stdout)["png"] == str(tmp_path / "shapes.png") and (tmp_path / "shapes.png").stat().st_size
    rec = read(tmp_path / "shapes.mcap")
    assert rec.gyro is not None and np.isfinite(rec.gyro).any() and rec.mag is None
    assert len(rec.estimates["joints"]) > 0


def test_estimate_refuses_a_method_the_recording_cannot_take(pty_recording, carry6, tmp_path, capsys):
    """``--method fused`` on an accelerometer recording (tests/host/conftest.py's real pty session),
    ``--uncertainty`` with the fused method, an unknown method: one line each, exit 2, nothing
    written; ``auto`` on it is the global method."""
    mcap = pty_recording
    cases = {("--method", "fused"): "--method fused needs gyroscopes",
             ("--method", "kalman"): "invalid choice: 'kalman'"}
    for extra, needle in cases.items():
        out = tmp_path / "x.npz"
        code, _out, err = _estimate_here(capsys, mcap, out, *extra)
        assert code == 2 and needle in err, (extra, err)
        assert "Traceback" not in err and not out.exists()
    code, out, err = _estimate_here(capsys, mcap, tmp_path / "auto.npz")
    assert code == 0, err
    assert json.loads(out)["method"] == "global"
    six, _ = carry6
    code, _out, err = _estimate_here(capsys, six, tmp_path / "u.npz", "--uncertainty")
    assert code == 2 and "--uncertainty is for the accelerometer-only methods" in err, err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "u.npz").exists()


#: transport -> (sensors, host asks with --sensors): packed IMU records on every transport that packs
#: (serial; CAN FD): the 9-axis ones once without --sensors (the gateway configures its chips itself)
PACKED = {"memory": ("accel+gyro+mag", True), "pty": ("accel+gyro", True), "slcan": ("accel+gyro+mag", False),
          "virtual": ("accel+gyro", True), "udp_multicast": ("accel+gyro+mag", True)}


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_a_packing_gateway_carries_imu_records_in_snapshot_imu_on_every_transport(transport, tmp_path):
    """``capsheet virtual --packed --sensors ...`` (CAN: ``--fd``) then ``capsheet host``: the host learns
    the packing gateway, every link sample comes with its gyroscope (and magnetometer) from
    SNAPSHOT_IMU frames, and the recording of the pty run holds SNAPSHOT_IMU and no per-chip record."""
    import numpy as np

    from host.record.recording import read
    from protocol.framing import StreamDecoder
    from protocol.messages import ImuSample, SnapshotImu
    sensors, ask = PACKED[transport]
    can = transport in ("slcan", "virtual", "udp_multicast")
    mcap = tmp_path / "packed.mcap"
    args = ["host", "{port}", "--lattice", "3x3", "--layout", "{layout}", *DELIVERY,
            "--duration", RUN_S, "-q", "--json", *(["--sensors", sensors] if ask else []), *(["--fd"] if can else []),
            *(["--record", str(mcap)] if transport == "pty" else [])]
    lock = udp_multicast_lock() if transport == "udp_multicast" else contextlib.nullcontext()
    with lock:
        job = Job(transport, tmp_path, f"packed-{transport}", args,
                  ["--shape", "wave", "--sensors", sensors, "--noise", "1", "--packed", *(["--fd"] if can else [])]
                  ).finish()
    assert job.rc == 0, job.stderr
    s = job.json()["summary"]
    assert [g["packing"] for g in s["gateways"]] == [True]
    assert s["snapshots"] > 0 and s["valid_links_pct"] >= 95.0 and s["errors"] == {}, s
    assert s["sensors"] == sensors
    assert s["imu_links_pct"] == pytest.approx(s["valid_links_pct"], abs=1e-6)
    if sensors.endswith("mag"):
        assert s["mag_links_pct"] == pytest.approx(s["valid_links_pct"], abs=1e-6)
    if transport == "pty":
        rec = read(mcap)
        assert rec.gyro is not None and np.nanmax(np.abs(rec.gyro)) > 0.01
        ev = StreamDecoder().feed(b"".join(p for _t, _k, p in rec.raw[0]))
        assert any(isinstance(e, SnapshotImu) for e in ev) and not any(isinstance(e, ImuSample) for e in ev)


def test_packing_imu_records_on_classic_can_is_one_line_and_exit_2(capsys):
    """SNAPSHOT_IMU needs CAN FD (§16.5: classic CAN cannot carry it). Through the entry point in
    this process: ``capsheet virtual`` refuses before it makes a sheet or a device (its runs through
    a real process are tests/host/cli/test_virtual.py's)."""
    from host.cli import main
    capsys.readouterr()
    code = main(["virtual", "--transport", "slcan", "--packed", "--sensors", "accel+gyro", "--lattice", "3x3",
                 "--duration", "1"])
    err = capsys.readouterr().err
    assert code == 2 and "SNAPSHOT_IMU needs CAN FD" in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
