"""``capsheet estimate`` (host/cli/estimate.py): joints of every recorded snapshot, to .npz or MCAP,
equal to the estimator's own; their uncertainty when asked; a CAN log replayed first. (Its bad
arguments and a recording cut short: tests/host/cli/test_replay.py, beside replay's.) The fused
method, which runs in the command's own process, starts no worker pool."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from host.record.recording import read
from host.record.replay import Replay


def test_capsheet_estimate_writes_npz_and_mcap_with_the_estimators_joints(pty_recording, tmp_path, capsys):
    from host.analysis.estimator import estimate
    from host.cli import main

    rec = read(pty_recording, raw=False)
    npz = tmp_path / "joints.npz"
    assert main(["estimate", str(pty_recording), "--out", str(npz), "--jobs", "2", "--batch", "16",
                 "--json", "-q"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["snapshots"] == len(rec) and doc["estimated"] == int(rec.valid.any(axis=1).sum())
    z = np.load(npz)
    assert z["joints"].shape == (len(rec), 5, 5, 3)
    assert z["counter"].tolist() == rec.counter.tolist()
    # each --batch of 16 starts cold at its own first snapshot and is solved one at a time (the
    # compiled kernel built) or by estimate_batch (numpy alone), as here
    from host.analysis.estimator import estimate_batch
    from host.cli.estimate import GROUP, batched
    side = 0.01 * 4
    for s0 in range(0, len(rec), 16):
        ks = [k for k in range(s0, min(s0 + 16, len(rec))) if rec.valid[k].any()]
        for k in range(s0, min(s0 + 16, len(rec))):
            if k not in ks:  # nothing to estimate: NaN
                assert np.isnan(z["joints"][k]).all()
        if not ks:
            continue
        ests = estimate_batch(rec.readings[ks].astype(float), 5, 5, 0.01, valid=rec.valid[ks], batch=GROUP,
                              bad_readings="mask")
        prev = None
        for k, e in zip(ks, ests):
            prev = estimate(rec.readings[k].astype(float), 5, 5, 0.01, valid=rec.valid[k], previous=prev,
                            bad_readings="mask")
            exact, other = (e, prev) if batched() else (prev, e)
            np.testing.assert_allclose(z["joints"][k], exact.joints, rtol=0, atol=1e-12)
            # and the other way agrees to the solver's tolerance (0.03 % of side)
            assert np.abs(z["joints"][k] - other.joints).max() / side * 100 <= 0.03
    out = tmp_path / "shapes.mcap"
    assert main(["estimate", str(pty_recording), "--out", str(out), "--png", "-q", "--batch", "16"]) == 0
    again = read(out)
    ok = np.isfinite(z["residual"])
    assert len(again) == len(rec) and len(again.estimates["counter"]) == int(ok.sum())
    np.testing.assert_allclose(again.estimates["joints"], z["joints"][ok].astype(np.float32), atol=1e-6)
    assert Path(out.with_suffix(".png")).stat().st_size > 10_000
    assert "yaw_std" not in z.files and "yaw_std" not in again.estimates  # sampled: only when asked


def test_capsheet_estimate_uncertainty_is_the_estimators_when_asked_for(pty_recording, tmp_path, capsys):
    from host.analysis.estimator import estimate
    from host.cli import main

    rec = read(pty_recording, raw=False)
    npz = tmp_path / "joints.npz"
    assert main(["estimate", str(pty_recording), "--out", str(npz), "--jobs", "1", "--batch", "8",
                 "--uncertainty", "--json", "-q"]) == 0
    assert json.loads(capsys.readouterr().out)["uncertainty"] is True
    z = np.load(npz)
    ks = [k for k in range(8) if rec.valid[k].any()]  # the first batch
    from host.analysis.estimator import estimate_batch
    from host.cli.estimate import GROUP, batched
    last = estimate_batch(rec.readings[ks].astype(float), 5, 5, 0.01, valid=rec.valid[ks], batch=GROUP,
                          bad_readings="mask")[-1]
    prev = None  # one at a time
    for k in ks:
        prev = estimate(rec.readings[k].astype(float), 5, 5, 0.01, valid=rec.valid[k], previous=prev,
                        bad_readings="mask")
    exact, other = (last, prev) if batched() else (prev, last)
    np.testing.assert_allclose(z["yaw_std"][ks[-1]], exact.yaw_std, rtol=1e-9, equal_nan=True)
    np.testing.assert_allclose(z["joint_std"][ks[-1]], exact.joint_std, rtol=1e-9)
    # the other way: the same uncertainty, to the yaws' tolerance
    np.testing.assert_allclose(z["yaw_std"][ks[-1]], other.yaw_std, rtol=0.02, equal_nan=True)
    assert np.all(z["yaw_std"][ks][:, rec.valid[ks[-1]]] > 0)
    out = tmp_path / "shapes.mcap"
    assert main(["estimate", str(pty_recording), "--out", str(out), "-q", "--uncertainty"]) == 0
    again = read(out)
    assert again.estimates["yaw_std"].shape == (len(again.estimates["counter"]), rec.valid.shape[1])


def test_capsheet_estimate_of_a_can_log_replays_it_first(can_recording, tmp_path, capsys):
    from host.cli import main
    npz = tmp_path / "j.npz"
    assert main(["estimate", str(can_recording / "run.log"), "--lattice", "4x4", "--out", str(npz),
                 "--jobs", "1", "-q", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    replayed = list(Replay(can_recording / "run.log", lattice="4x4").snapshots())
    assert doc["snapshots"] == len(replayed) >= 10 and np.load(npz)["joints"].shape[1:] == (4, 4, 3)


@pytest.fixture(scope="module")
def imu6_recording(tmp_path_factory):
    """A real session of a 2x2 sheet of 6-axis chips on a pty, ``capsheet host --record``."""
    from host.cli import main
    from virtual_sheet.devices import PtyDevice
    from virtual_sheet.sheet import VirtualSheet

    d = tmp_path_factory.mktemp("imu6")
    sheet = VirtualSheet("gaussian", "2x2", seed=8, sensors="accel+gyro")
    layout = sheet.write_layout(d / "sheet.csv")
    out = d / "run.mcap"
    with PtyDevice(sheet) as dev:
        assert main(["host", "--port", dev.path, "--lattice", "2x2", "--layout", str(layout), "--rate", "50",
                     "--sensors", "accel+gyro", "--deadline-ms", "300", "--record", str(out), "--duration", "0.5",
                     "-q"]) == 0
    return out


@pytest.fixture
def pools(monkeypatch):
    """Every worker pool `capsheet estimate` starts (the real one, counted)."""
    import concurrent.futures

    started: list = []

    class Counted(concurrent.futures.ProcessPoolExecutor):
        def __init__(self, *a, **kw):
            started.append(kw.get("max_workers"))
            super().__init__(*a, **kw)

    monkeypatch.setattr(concurrent.futures, "ProcessPoolExecutor", Counted)
    return started


def test_the_fused_method_starts_no_worker_pool(imu6_recording, pty_recording, pools, tmp_path, capsys):
    """The fused method runs in this process, in order: with ``--jobs 2`` (and ``auto`` choosing it
    from the gyroscopes, or named) no worker process is started. The accelerometer-only methods
    still get their two workers."""
    from host.cli import main

    for method in ("auto", "fused"):
        assert main(["estimate", str(imu6_recording), "--out", str(tmp_path / f"{method}.npz"), "--jobs", "2",
                     "--method", method, "--json", "-q"]) == 0
        doc = json.loads(capsys.readouterr().out)
        assert doc["method"] == "fused" and doc["estimated"] > 0
    assert pools == []
    for method in ("auto", "global"):  # the counting sees a pool where one is used
        assert main(["estimate", str(pty_recording), "--out", str(tmp_path / f"g-{method}.npz"), "--jobs", "2",
                     "--method", method, "--json", "-q"]) == 0
        assert json.loads(capsys.readouterr().out)["method"] == "global"
    assert pools == [2, 2]
