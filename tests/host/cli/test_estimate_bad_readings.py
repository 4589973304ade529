"""`capsheet estimate` on a recording with snapshots the estimator refuses (every valid link's
reading implausible: a dead or saturated sheet for one SYNC): those snapshots are counted and named,
the rest estimated, no traceback — on both estimation paths (one at a time with the compiled kernel,
numpy batches without it) and with worker processes."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from host.snapshots.snapshot import LatticeSnapshot
from host.record.recording import Recorder
from protocol.lattice import Lattice

G = 9.80665
BAD = {10: 0.0, 20: 5 * G}  # snapshot -> every link's reading set to (0, 0, value)


def _recording(path, n_snaps: int = 40):
    lat = Lattice(3, 3)
    n = lat.n_links
    rec = Recorder(path, lat, 0.01, session={"mode": "test"})
    try:
        for k in range(n_snaps):
            r = np.tile([0.0, 0.0, G], (n, 1))
            if k in BAD:
                r[:, 2] = BAD[k]
            rec.snapshot(LatticeSnapshot(k, 0.01 * k, 1e9 + 0.01 * k, r, np.ones(n, bool),
                                         np.zeros(n, np.uint8), True, 0.0))
    finally:
        rec.close()


@pytest.mark.parametrize("jobs", [1, 2])
def test_refused_snapshots_are_counted_and_the_rest_estimated(tmp_path, jobs):
    src, out = tmp_path / "bad.mcap", tmp_path / "joints.npz"
    _recording(src)
    r = subprocess.run([sys.executable, "-m", "host.cli", "estimate", str(src), "--out", str(out),
                        "--jobs", str(jobs), "--json", "-q"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    assert "2 snapshot(s) not estimated: No valid link left" in r.stderr
    summary = json.loads(r.stdout)
    assert summary["snapshots"] == 40 and summary["estimated"] == 38
    assert summary["not_estimated"]["refused"] == 2 and summary["not_estimated"]["no_valid_link"] == 0
    d = np.load(out)
    assert np.flatnonzero(~np.isfinite(d["residual"])).tolist() == sorted(BAD)
    assert np.isnan(d["joints"][sorted(BAD)]).all()
    assert np.isfinite(d["joints"][[0, 9, 11, 19, 21, 39]]).all()


@pytest.mark.parametrize("use_kernel", [False, True])
def test_both_estimation_paths_skip_only_the_refused_snapshots(monkeypatch, use_kernel):
    from host.analysis.estimator import kernel
    from host.cli.estimate import estimate_batch
    if use_kernel and not kernel.USE_KERNEL:
        pytest.skip("the estimator's kernel is not built")
    monkeypatch.setattr(kernel, "USE_KERNEL", use_kernel)
    n = Lattice(3, 3).n_links
    readings = np.tile([0.0, 0.0, G], (30, n, 1))
    readings[[3, 17]] = 0.0
    joints, residual, extra = estimate_batch(readings, np.ones((30, n), bool), 3, 3, 0.01)
    assert np.flatnonzero(~np.isfinite(residual)).tolist() == [3, 17]
    assert sum(extra["skipped"].values()) == 2
    assert np.isfinite(joints[[0, 2, 4, 16, 18, 29]]).all()
