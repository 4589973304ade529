"""Stability of `capsheet conformance`: N consecutive full runs against the Python chip model and the
C firmware through cffi (each behind a virtual sheet on a real pty), and the firmware booted in QEMU
(a fresh QEMU per run, UART on a TCP chardev). Optionally with one core kept busy by a spinning
process. Prints one JSON object: per target the runs, how many passed, the failed checks, and run
times (min / median / max s).

    .venv/bin/python benchmarks/bench_conformance_stability.py --runs 20
    .venv/bin/python benchmarks/bench_conformance_stability.py --runs 20 --busy
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _virtual(factory, runs: int) -> list[dict]:
    from host.conformance import Port, run_checks
    from host.transport import SerialTransport
    from virtual_sheet.devices import PtyDevice
    from virtual_sheet.sheet import VirtualSheet
    out = []
    for i in range(runs):
        sheet = VirtualSheet("flat", "2x2", noise=0.5, seed=i, chip_factory=factory)
        t0 = time.monotonic()
        with PtyDevice(sheet) as dev:
            t = SerialTransport(str(dev.path), reconnect=False)
            port = Port(t)
            try:
                res = run_checks(port)
            finally:
                port.close()
                t.close()
        bad = [f"{r.number} {r.outcome}: {r.detail}" for r in res if r.outcome not in ("PASS", "SKIP")]
        out.append({"ok": not bad, "seconds": time.monotonic() - t0, "bad": bad})
    return out


def _qemu(runs: int) -> list[dict]:
    from firmware_ref.qemu import missing_tools
    why = missing_tools()
    if why:
        return [{"ok": None, "seconds": 0.0, "bad": [f"SKIPPED: {why}"]}]
    r = subprocess.run([sys.executable, "-m", "firmware_ref.qemu", "conformance", "--json", "--runs", str(runs)],
                       capture_output=True, text=True, cwd=str(ROOT))
    rep = json.loads(r.stdout)
    return [{"ok": x["exit"] == 0, "seconds": x["seconds"], "bad": x["failed"],
             "stack_high_water_bytes": x["stack_high_water_bytes"]} for x in rep["per_run"]]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=20)
    p.add_argument("--busy", action="store_true", help="keep one core busy (a spinning process) meanwhile")
    p.add_argument("--targets", default="python,c,qemu")
    args = p.parse_args()
    spinner = None
    if args.busy:
        spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        res = {}
        for target in args.targets.split(","):
            if target == "python":
                from virtual_sheet.chip import ChipModel
                runs = _virtual(ChipModel, args.runs)
            elif target == "c":
                from firmware_ref.chip import CFirmwareChip
                runs = _virtual(CFirmwareChip, args.runs)
            elif target == "qemu":
                runs = _qemu(args.runs)
            else:
                raise SystemExit(f"unknown target {target!r}")
            secs = [r["seconds"] for r in runs]
            res[target] = {"runs": len(runs), "passed": sum(r["ok"] is True for r in runs),
                           "seconds_min_median_max": [round(min(secs), 2), round(statistics.median(secs), 2),
                                                      round(max(secs), 2)],
                           "failures": [b for r in runs for b in r["bad"]]}
            if target == "qemu" and runs and "stack_high_water_bytes" in runs[0]:
                res[target]["stack_high_water_bytes_max"] = max(r["stack_high_water_bytes"] for r in runs)
    finally:
        if spinner is not None:
            spinner.kill()
            spinner.wait()
    print(json.dumps({"benchmark": "conformance_stability", "busy_core": args.busy, "load": os.getloadavg(),
                      "targets": res}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
