"""The conformance verdicts on a simulated clock against real time: every mutant and healthy variant of
tests/host/conformance/test_mutants.py run both ways, and the failing checks of each compared.

The test suite runs them on the simulated clock (`host.conformance.simulated`); this shows that the
clock changes no verdict: for every Python chip, IMU and gateway mutant, every C firmware mutant and
every healthy variant (its chip run, and its gateway run behind a packing gateway), the set of checks
that FAIL in real time (the device's thread, the port's reader thread, ``--slack-ms`` 40 as the suite
had it; 8 runs at once in threads, as the suite made them) and on the simulated clock (one after
another, the CLI's default slack of 10 ms). A real-time run that failed a timed check (8, 11, 36, 37)
beyond its simulated verdict is made once more alone, as the suite's `_verdict` did, and both are
printed. Prints one JSON object: per run the two failing sets, whether they are equal, and the wall
and CPU of each way; the load average before and after.

    .venv/bin/python benchmarks/bench_conformance_clock.py
    .venv/bin/python benchmarks/bench_conformance_clock.py --only chip:slow_heartbeat,healthy:noise_free
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: the checks that time a node's own timer (a starved thread in a real-time run may fail them)
TIMED = {8, 11, 36, 37}


def _jobs(simulated: bool) -> dict:
    from tests.host.conformance import test_mutants as tm
    jobs = dict(tm._python_mutant_jobs(simulated))
    jobs.update({f"c:{k}": v for k, v in tm._c_mutant_jobs(simulated).items()})
    jobs.update({f"healthy:{k}": v for k, v in tm._healthy_jobs(simulated).items()})
    return jobs


def _failed(out) -> dict:
    """``{part: sorted failing checks}`` of a job's output (a list of results, or a healthy variant's
    ``{"chip": ..., "gateway": ...}``)."""
    parts = out if isinstance(out, dict) else {"run": out}
    return {p: sorted(r.number for r in rs if r.outcome == "FAIL") for p, rs in parts.items()}


def _one(job, k: int) -> dict:
    t0, c0 = time.monotonic(), time.thread_time()
    try:
        failed = _failed(job(k))
    except Exception as exc:  # noqa: BLE001 - reported
        failed = {"error": f"{type(exc).__name__}: {exc}"}
    return {"failed": failed, "wall_s": round(time.monotonic() - t0, 3), "cpu_s": round(time.thread_time() - c0, 3)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", default="", help="comma-separated keys (chip:NAME, imu:NAME, gateway:NAME, c:NAME, "
                                               "healthy:NAME); default every run")
    ap.add_argument("--at-once", type=int, default=8, help="real-time runs at once, in threads (default 8)")
    args = ap.parse_args()
    real, sim = _jobs(False), _jobs(True)
    keys = [k for k in real if not args.only or k in args.only.split(",")]
    load0 = os.getloadavg()

    t0, c0 = time.monotonic(), time.process_time()
    sim_out = {k: _one(sim[k], i) for i, k in enumerate(keys)}
    sim_wall, sim_cpu = time.monotonic() - t0, time.process_time() - c0

    t0, c0 = time.monotonic(), time.process_time()
    with ThreadPoolExecutor(args.at_once) as pool:
        real_out = dict(zip(keys, pool.map(lambda ik: _one(real[ik[1]], ik[0]), enumerate(keys))))
    real_wall, real_cpu = time.monotonic() - t0, time.process_time() - c0

    runs, differ = {}, []
    for i, k in enumerate(keys):
        r, s = real_out[k], sim_out[k]
        row = {"real": r["failed"], "simulated": s["failed"], "real_wall_s": r["wall_s"], "sim_wall_s": s["wall_s"],
               "sim_cpu_s": s["cpu_s"]}
        extra = {p: set(v) - set(s["failed"].get(p, [])) for p, v in r["failed"].items() if p != "error"}
        if r["failed"] != s["failed"] and "error" not in r["failed"] and all(e <= TIMED for e in extra.values()):
            again = _one(real[k], 10_000 + i)  # alone: a starved thread is the load, not the node
            row["real_again"] = again["failed"]
            r = again
        row["same"] = r["failed"] == s["failed"]
        if not row["same"]:
            differ.append(k)
        runs[k] = row
    print(json.dumps({
        "runs": len(keys), "same": len(keys) - len(differ), "differ": differ,
        "real_time": {"wall_s": round(real_wall, 1), "cpu_s": round(real_cpu, 1), "at_once": args.at_once},
        "simulated": {"wall_s": round(sim_wall, 1), "cpu_s": round(sim_cpu, 1)},
        "load_before": [round(x, 2) for x in load0], "load_after": [round(x, 2) for x in os.getloadavg()],
        "per_run": runs}, indent=1))
    return 0 if not differ else 1


if __name__ == "__main__":
    sys.exit(main())
