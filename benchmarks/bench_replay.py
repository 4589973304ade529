"""Offline speed: ``capsheet estimate`` and ``capsheet replay --speed max`` on a 14x14 recording at
145 Hz, against real time. Target: estimate >= 10x faster than real time.

The recording is made here, as the host would have written it: the virtual sheet's Gaussian
(14x14 joints, L = 1 cm) with fresh 1 % g noise per snapshot (seeded MT19937), quantised to ADC
counts, one serial chunk of 364 SAMPLE frames per SYNC at 145 Hz on a simulated clock, the SYNCs,
and the snapshots those frames make (readings = the quantised counts). Then both commands run on
it through `host.cli.main` in this process (``--jobs`` as given, default 2). The machine may be
shared: each figure is the best of ``--repeats``; ``snapshots_per_cpu_s`` (the estimator's process
CPU time) and ``x_real_time_if_jobs_had_their_cores`` say what an idle machine would do. Prints JSON.

    .venv/bin/python benchmarks/bench_replay.py [--seconds 10] [--jobs 2] [--quick]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import sys
import tempfile
import time
from pathlib import Path

# No BLAS thread variables here: the commands run as a user runs them (capsheet limits BLAS to one
# thread itself, host.cli.one_blas_thread; a benchmark that set them hid a 2.6x loss).

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

RATE_HZ = 145.0
TARGET_X = 10.0


def synthetic_recording(path: Path, n: int = 14, seconds: float = 10.0, rate_hz: float = RATE_HZ,
                        noise_pct_g: float = 1.0, seed: int = 16) -> int:
    """Write a capsheet MCAP of ``seconds`` at ``rate_hz``; returns the number of snapshots."""
    from host.snapshots.snapshot import LatticeSnapshot
    from host.record.recording import Recorder
    from protocol.constants import ADC_MAX, ADC_MIN, counts_to_si, nominal_sensitivity, si_to_counts
    from protocol.framing import encode
    from protocol.lattice import Lattice
    from protocol.messages import Sample
    from virtual_sheet.geometry import ideal_readings
    from virtual_sheet.sensor import noisy_readings
    from virtual_sheet.shapes import make_sheet

    L = 0.01
    lat = Lattice(n, n)
    r0 = ideal_readings(make_sheet("gaussian", n, n, L))
    rng = np.random.Generator(np.random.MT19937(seed))
    sens = nominal_sensitivity()
    count = int(round(seconds * rate_hz))
    cal = {"range_code": 0, "links": [{"link": k, "uid": f"0x{k + 1:016X}", "node": k + 1, "bus": 0,
                                       "offset": [0.0] * 3, "sensitivity": [sens] * 3, "calibrated": True}
                                      for k in range(lat.n_links)]}
    rec = Recorder(path, lat, L, session={"mode": "benchmark", "rate_hz": rate_hz, "sync": "drive",
                                          "deadline_s": max(2 / rate_hz, 0.05),
                                          "transports": [{"name": "synthetic", "kind": "serial"}]},
                   calibration=cal)
    t0, wall0 = 1000.0, 1.7e9
    for c in range(count):
        t = t0 + c / rate_hz
        counts = np.clip(np.rint(si_to_counts(noisy_readings(r0, noise_pct_g, rng))), ADC_MIN, ADC_MAX).astype(int)
        rec.sync(c & 0xFFFF, t)
        wire = b"".join(encode(Sample(k + 1, c & 0xFFFF, *counts[k].tolist(), 0)) for k in range(lat.n_links))
        rec.raw(0, "serial", wire, "synthetic", t=t + 0.002, log_time_ns=int((wall0 + c / rate_hz + 0.002) * 1e9))
        readings = counts_to_si(counts.astype(float))
        valid = np.ones(lat.n_links, dtype=bool)
        rec.snapshot(LatticeSnapshot(c & 0xFFFF, t, wall0 + c / rate_hz, readings, valid,
                                     np.zeros(lat.n_links, np.uint8), True, 0.002))
    rec.close()
    return count


def _timed(argv: list[str]) -> tuple[float, dict]:
    from host.cli import main
    buf = io.StringIO()
    t = time.perf_counter()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
        rc = main(argv)
    dt = time.perf_counter() - t
    if rc != 0:
        raise SystemExit(f"{argv} exited {rc}")
    return dt, json.loads(buf.getvalue())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="recorded seconds (default 10)")
    ap.add_argument("--jobs", type=int, default=2, help="capsheet estimate --jobs (default 2)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="2 s, one repeat")
    args = ap.parse_args()
    seconds, repeats = (2.0, 1) if args.quick else (args.seconds, args.repeats)
    with tempfile.TemporaryDirectory(prefix="capsheet-bench-") as d:
        path = Path(d) / "run.mcap"
        t = time.perf_counter()
        n = synthetic_recording(path, seconds=seconds)
        t_write = time.perf_counter() - t
        size = path.stat().st_size
        recorded_s = (n - 1) / RATE_HZ
        est_best, rep_best = np.inf, np.inf
        est_json = rep_json = None
        for _ in range(repeats):
            dt, est_json = _timed(["estimate", str(path), "--out", str(Path(d) / "joints.npz"), "--overwrite", "--jobs",
                                   str(args.jobs), "--json", "-q"])
            est_best = min(est_best, dt)
            dt, rep_json = _timed(["replay", str(path), "--speed", "max", "--json", "-q"])
            rep_best = min(rep_best, dt)
    out = {"benchmark": "replay/estimate offline", "lattice": "14x14", "links": 364, "rate_hz": RATE_HZ,
           "snapshots": n, "recorded_s": round(recorded_s, 3), "mcap_bytes_per_recorded_s": round(size / recorded_s),
           "write_recording_s": round(t_write, 3),
           "estimate": {"jobs": args.jobs, "wall_s_best": round(est_best, 3),
                        "x_real_time": round(recorded_s / est_best, 2),
                        "snapshots_per_s": round(n / est_best, 1), "estimated": est_json["estimated"],
                        "snapshots_per_cpu_s": est_json["snapshots_per_cpu_s"],
                        "x_real_time_if_jobs_had_their_cores": round(
                            recorded_s * est_json["snapshots_per_cpu_s"] * args.jobs / n, 2),
                        "target_x_real_time": TARGET_X, "meets_target": bool(recorded_s / est_best >= TARGET_X)},
           "replay_max": {"wall_s_best": round(rep_best, 3), "x_real_time": round(recorded_s / rep_best, 2),
                          "snapshots": rep_json["snapshots"], "identical_to_recorded": rep_json["snapshots_identical"],
                          "note": "decode + aggregate + estimate every snapshot, one process"},
           "load_average": os.getloadavg()}
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
