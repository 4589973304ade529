"""CPU per SYNC of the live path by sensor set: the virtual sheet, the host and
the shape estimate apart, for accelerometer, 6-axis and 9-axis chips.

    .venv/bin/python benchmarks/bench_imu_path.py                     # JSON on stdout
    .venv/bin/python benchmarks/bench_imu_path.py --baseline 49754a2  # and the same at that commit

What `capsheet demo` runs, in one thread on a simulated clock (`Host(driver=...)`,
`MemoryDevice(clock=...)`, the back-to-back rig of tests/host/test_back2back.py): a 14x14 sheet
(1 % g noise, seed 1) brought up by the host (CONFIG_IMU for 6/9-axis chips), SYNC at 145 Hz for
``--seconds`` simulated seconds, every snapshot shaped — the fused estimator in order
for 6/9-axis chips, `host.estimator.estimate` on every snapshot for accelerometer chips (the demo
takes the newest one: at most every one). CPU seconds (``time.process_time``) split into

* ``sheet_ms_per_sync``: the device's steps (gateway, chips, scene, IMU models, frames encoded);
* ``host_ms_per_sync``: the rest of the host (decoding, aggregation, SYNC, snapshots);
* ``estimate_ms_per_sync``: the shape estimate of each snapshot;

per SYNC sent, the best of ``--rounds`` runs. No pty, no second process: what each side costs,
not how the machine schedules it (`capsheet demo` measures that). ``--baseline REV`` runs the same
cases on ``git archive REV`` in a subprocess, in the same run, rows marked ``"code": REV``.
The load average is printed beside the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

ROOT = os.environ.get("CAPSHEET_BENCH_ROOT") or os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)

CASES = [("grow", "accel"), ("grow", "accel+gyro"), ("grow", "accel+gyro+mag"),
         ("carry", "accel+gyro+mag"), ("wave", "accel+gyro+mag")]
RATE_HZ = 145.0


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def run_case(shape: str, sensors: str, seconds: float, lattice: str = "14x14", seed: int = 1,
             profiler=None) -> dict:
    """One run: CPU seconds of sheet, host and estimate over ``seconds`` of simulated streaming
    (``profiler``: a `cProfile.Profile` enabled over the streaming alone)."""
    import numpy as np

    from host.analysis.motion.snapshots import fused_update
    from host.estimator import estimate
    from host.session.core import Host, Layout
    from host.transport.ports import MemoryTransport
    from virtual_sheet.devices import MemoryDevice
    from virtual_sheet.sheet import VirtualSheet

    clock = _Clock()
    sheet = VirtualSheet(shape, lattice, seed=seed, noise=1.0, scene_rate_hz=10.0, sensors=sensors)
    sheet.precompute()
    # streaming starts past a scene's fade-in (wave: 1 s), as in `capsheet demo`, whose bring-up
    # takes longer: a periodic scene is then looked up, not solved (its period solved above)
    clock.t = float(getattr(sheet.scene, "periodic_from_s", None) or 0.0)
    dev = MemoryDevice(sheet, clock=clock)
    cpu = {"sheet": 0.0}

    def driver(dt: float) -> None:
        clock.t += dt
        t0 = time.process_time()
        dev.step()
        cpu["sheet"] += time.process_time() - t0

    dev.start()
    fmt = {"accel": 0, "accel+gyro": 1, "accel+gyro+mag": 2}[sensors]
    rows, cols = sheet.lattice.rows, sheet.lattice.cols
    host = Host([MemoryTransport(dev.port)], lattice, layout=Layout(dict(sheet.layout)), rate_hz=RATE_HZ,
                clock=clock, driver=driver, deadline_s=0.02)
    host.imu_config = (fmt, 3, 0, 0) if fmt else None
    fused = None
    if fmt:
        from host.analysis.motion import MotionEstimator
        fused = MotionEstimator(rows, cols, 0.01)
    try:
        host.open()
        host.bring_up()
        sent0 = host.syncs_sent
        cpu["sheet"] = 0.0
        est_cpu, n_snap, n_complete, prev = 0.0, 0, 0, None
        if profiler is not None:
            profiler.enable()
        t_all = time.process_time()
        for snap in host.snapshots(duration_s=seconds):
            n_snap += 1
            n_complete += bool(snap.complete)
            t0 = time.process_time()
            if fused is not None:
                fused_update(fused, snap)
            elif snap.valid.any():
                prev = estimate(snap.readings, rows, cols, 0.01, valid=snap.valid, previous=prev)
            est_cpu += time.process_time() - t0
        total = time.process_time() - t_all
        if profiler is not None:
            profiler.disable()
        sent = host.syncs_sent - sent0
    finally:
        host.close()
        dev.stop()
    host_cpu = total - cpu["sheet"] - est_cpu
    per = 1e3 / max(sent, 1)
    return {"shape": shape, "sensors": sensors, "lattice": lattice, "syncs": sent, "snapshots": n_snap,
            "complete": n_complete, "sheet_ms_per_sync": round(cpu["sheet"] * per, 3),
            "host_ms_per_sync": round(host_cpu * per, 3), "estimate_ms_per_sync": round(est_cpu * per, 3),
            "total_ms_per_sync": round(total * per, 3),
            "cpu_s_per_s": {"sheet": round(cpu["sheet"] / seconds, 3), "host": round((host_cpu + est_cpu) / seconds, 3)},
            "loadavg": [round(x, 2) for x in os.getloadavg()], "_np": np.__version__}


def measure(cases, seconds: float, rounds: int) -> list[dict]:
    """The best round of each case (least interference from the rest of the machine)."""
    best: dict = {}
    for _ in range(rounds):
        for shape, sensors in cases:
            r = run_case(shape, sensors, seconds)
            r.pop("_np")
            key = (shape, sensors)
            if key not in best or r["total_ms_per_sync"] < best[key]["total_ms_per_sync"]:
                best[key] = r
            print(json.dumps(r), file=sys.stderr)
    return [best[k] for k in cases if k in best]


def baseline_rows(rev: str, argv: list[str]) -> list[dict]:
    """The same cases on ``git archive rev`` (this script run there by a subprocess)."""
    with tempfile.TemporaryDirectory(prefix="capsheet-bench-") as tmp:
        arch = subprocess.run(["git", "-C", ROOT, "archive", "--format=tar", rev], check=True,
                              capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=arch, check=True)
        import shutil
        for d, _dirs, files in os.walk(os.path.join(ROOT, "host")):  # the compiled kernels (built, not tracked)
            for f in files:
                if f.endswith(".so"):
                    rel = os.path.relpath(os.path.join(d, f), ROOT)
                    if os.path.isdir(os.path.dirname(os.path.join(tmp, rel))):
                        shutil.copy2(os.path.join(ROOT, rel), os.path.join(tmp, rel))
        env = dict(os.environ, CAPSHEET_BENCH_ROOT=tmp)
        out = subprocess.run([sys.executable, os.path.abspath(__file__), *argv], env=env, check=True,
                             capture_output=True, text=True, cwd=tmp)
        sys.stderr.write(out.stderr)
        rows = json.loads(out.stdout)["results"]
    for r in rows:
        r["code"] = rev
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=4.0, help="simulated seconds streamed per run (default 4)")
    ap.add_argument("--rounds", type=int, default=3, help="runs per case, the best kept (default 3)")
    ap.add_argument("--cases", default=None,
                    help="comma-separated SHAPE:SENSORS (default: grow at each sensor set, carry and wave 9-axis)")
    ap.add_argument("--baseline", metavar="REV", default=None, help="also run the cases at this git revision")
    args = ap.parse_args(argv)
    cases = CASES if args.cases is None else [tuple(c.split(":", 1)) for c in args.cases.split(",")]
    from host.cli import one_blas_thread
    one_blas_thread()
    load0 = os.getloadavg()
    rows = []
    if args.baseline:
        sub = ["--seconds", str(args.seconds), "--rounds", str(args.rounds)]
        if args.cases:
            sub += ["--cases", args.cases]
        rows += baseline_rows(args.baseline, sub)
    here = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip() or "?"
    dirty = bool(subprocess.run(["git", "-C", ROOT, "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True).stdout.strip())
    for r in measure(cases, args.seconds, args.rounds):
        r["code"] = here + ("+dirty" if dirty else "") if "CAPSHEET_BENCH_ROOT" not in os.environ else "baseline"
        rows.append(r)
    print(json.dumps({"benchmark": "bench_imu_path", "rate_hz": RATE_HZ, "seconds": args.seconds,
                      "rounds": args.rounds, "cpu_count": os.cpu_count(),
                      "loadavg_before": [round(x, 2) for x in load0],
                      "loadavg": [round(x, 2) for x in os.getloadavg()], "results": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
