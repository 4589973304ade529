"""`capsheet demo` with 9-axis chips on moving scenes, run as a user runs it, quiet and beside busy
cores: does the live path pass on a loaded 2-core machine as the accelerometer
demo does?

    .venv/bin/python benchmarks/bench_demo_imu.py                     # grow, carry, wave; quiet and 2 busy; 3 runs
    .venv/bin/python benchmarks/bench_demo_imu.py --busy 2 --runs 1 --scenes wave
    .venv/bin/python benchmarks/bench_demo_imu.py --sensors accel --scenes grow   # the accelerometer demo
    .venv/bin/python benchmarks/bench_demo_imu.py --baseline 49754a2 --busy 2     # the code before the live fused path

Each run is ``python -m host.cli demo --sensors S --shape SCENE --json`` (6 s of streaming, the demo's pass
rule: mean joint error <= 1 % of side and >= 99 % of the SYNCs sent complete) in a subprocess. With
``--busy N`` (default: 0 then 2) N ``python3 -c 'while True: pass'`` loops run beside it, started
before and killed (by their pids) after each group of runs. Rows: the demo's verdict, error,
completeness, SYNCs sent per second, how long after the host sent each compared SYNC the chips
took it to arrive (``sync_sample_lag_ms``), and the load average at the end of the run. JSON on
stdout.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")


def run_demo(scene: str, sensors: str, duration: float, out_dir: str, tag: str, root: str = ROOT) -> dict:
    cmd = [sys.executable, "-m", "host.cli", "demo", "--shape", scene, "--json", "--duration", str(duration),
           "--out", os.path.join(out_dir, f"{tag}.png")]
    if sensors != "accel":
        cmd += ["--sensors", sensors]
    t0 = time.monotonic()
    env = dict(os.environ, PYTHONPATH=os.path.abspath(root))
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=root, timeout=600, env=env)
    row = {"scene": scene, "sensors": sensors, "exit": p.returncode, "wall_s": round(time.monotonic() - t0, 1),
           "loadavg": [round(x, 2) for x in os.getloadavg()]}
    try:
        d = json.loads(p.stdout)
    except json.JSONDecodeError:
        row["error"] = (p.stderr.strip().splitlines() or ["no output"])[-1]
        return row
    for k in ("pass", "mean_error_pct_side", "complete_pct_of_syncs", "syncs_sent", "syncs_per_s",
              "estimates_per_s", "median_latency_ms", "median_estimate_ms", "sync_sample_lag_ms", "syncs_missed"):
        row[k] = d.get(k)
    return row


def _head() -> str:
    rev = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", ROOT, "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return rev.stdout.strip() + ("+dirty" if dirty else "")


def _archive(rev: str, into: str) -> str:
    """``git archive rev`` under ``into``, with this tree's built kernels (not tracked) copied in."""
    import shutil
    dst = os.path.join(into, f"code-{rev}")
    os.makedirs(dst)
    arch = subprocess.run(["git", "-C", ROOT, "archive", "--format=tar", rev], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", dst], input=arch, check=True)
    for d, _dirs, files in os.walk(os.path.join(ROOT, "host")):
        for f in files:
            if f.endswith(".so"):
                rel = os.path.relpath(os.path.join(d, f), ROOT)
                if os.path.isdir(os.path.dirname(os.path.join(dst, rel))):
                    shutil.copy2(os.path.join(ROOT, rel), os.path.join(dst, rel))
    return dst


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="grow,carry,wave", help="comma-separated (default grow,carry,wave)")
    ap.add_argument("--sensors", default="accel+gyro+mag", help="accel, accel+gyro or accel+gyro+mag (default 9-axis)")
    ap.add_argument("--busy", default="0,2", help="comma-separated busy-loop counts, a group each (default 0,2)")
    ap.add_argument("--runs", type=int, default=3, help="runs per scene and group (default 3)")
    ap.add_argument("--duration", type=float, default=6.0, help="seconds of streaming per run (the demo's default 6)")
    ap.add_argument("--baseline", metavar="REV", default=None,
                    help="run the demo of this git revision instead (git archive, the built kernels copied)")
    args = ap.parse_args(argv)
    rows = []
    out_dir = tempfile.mkdtemp(prefix="capsheet-bench-demo-")
    root = ROOT if args.baseline is None else _archive(args.baseline, out_dir)
    for busy in [int(b) for b in args.busy.split(",")]:
        loops = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)]
        pids = [p.pid for p in loops]
        try:
            time.sleep(2.0 if busy else 0.0)  # the loops at full speed before the first run
            for run in range(args.runs):
                for scene in args.scenes.split(","):
                    row = run_demo(scene, args.sensors, args.duration, out_dir, f"{scene}-{busy}-{run}", root)
                    row.update(busy_loops=busy, run=run)
                    rows.append(row)
                    print(json.dumps(row), file=sys.stderr)
        finally:
            for p in loops:  # ours, by pid
                p.kill()
                p.wait()
        rows_b = [r for r in rows if r["busy_loops"] == busy]
        print(json.dumps({"busy_loops": busy, "killed": pids, "passed": sum(bool(r.get("pass")) for r in rows_b),
                          "of": len(rows_b)}), file=sys.stderr)
    summary = {}
    for r in rows:
        key = f"{r['scene']} busy={r['busy_loops']}"
        s = summary.setdefault(key, {"passed": 0, "runs": 0, "mean_error_pct_side": [], "complete_pct": [],
                                     "syncs_per_s": [], "sample_lag_median_ms": []})
        s["runs"] += 1
        s["passed"] += bool(r.get("pass"))
        s["mean_error_pct_side"].append(r.get("mean_error_pct_side"))
        s["complete_pct"].append(r.get("complete_pct_of_syncs"))
        s["syncs_per_s"].append(r.get("syncs_per_s"))
        s["sample_lag_median_ms"].append((r.get("sync_sample_lag_ms") or {}).get("median"))
    print(json.dumps({"benchmark": "bench_demo_imu", "code": args.baseline or _head(), "sensors": args.sensors,
                      "duration_s": args.duration,
                      "cpu_count": os.cpu_count(), "summary": summary, "results": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
