"""Stability of `capsheet conformance`: N consecutive full runs against every healthy variant the suite
must pass (tests/host/conformance/mutants.py ``HEALTHY``: a noise-free chip, a quiet 12-bit chip, a
chip behind a packing gateway, several chips on one port, a chip behind a SYNC-source gateway, gateways
that flush 5 or 10 ms after the SYNC (SYNC source or not), 6- and 9-axis chips behind gateways packing
SNAPSHOT_IMU — and the gateways themselves in the gateway profile), on the Python chip model and on the C firmware
through cffi (each behind a virtual sheet on a real pty), and the firmware booted in QEMU (a fresh
QEMU per run, UART on a TCP chardev). Optionally with one core kept busy by a spinning process.
Prints one JSON object: per target the runs, how many passed, the failed checks, and run times
(min / median / max s), and the load average before and after.

    .venv/bin/python benchmarks/bench_conformance_stability.py --runs 20
    .venv/bin/python benchmarks/bench_conformance_stability.py --runs 20 --busy
    .venv/bin/python benchmarks/bench_conformance_stability.py --runs 2 --targets python:noise_free,qemu

The runs go round-robin over the targets (run 1 of each, then run 2 of each, ...), so with
``--budget-min M`` a run that would start after M minutes is not started and every target has the
same number of runs (or one fewer): the JSON says how many rounds were done of the ones asked for.
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


def _virtual(factory, variant: str, runs: int, profile: str = "chip", first_seed: int = 0) -> list[dict]:
    from host.conformance import Port, run_checks
    from host.transport.ports import SerialTransport
    from tests.host.conformance.mutants import HEALTHY
    from virtual_sheet.devices import PtyDevice
    from virtual_sheet.sheet import VirtualSheet
    sheet_kw, dev_kw = HEALTHY[variant]
    sheet_kw = dict(sheet_kw)
    lattice = sheet_kw.pop("lattice", "2x2")
    out = []
    for i in range(first_seed, first_seed + runs):
        sheet = VirtualSheet("flat", lattice, seed=i, chip_factory=factory, **sheet_kw)
        t0 = time.monotonic()
        with PtyDevice(sheet, **dev_kw) as dev:
            t = SerialTransport(str(dev.path), reconnect=False)
            port = Port(t)
            try:
                res = run_checks(port, allow_broadcast=True, profile=profile)
            finally:
                port.close()
                t.close()
        bad = [f"{r.number} {r.outcome}: {r.detail}" for r in res if r.outcome not in ("PASS", "SKIP")]
        out.append({"ok": not bad, "seconds": time.monotonic() - t0, "bad": bad,
                    "skipped": sorted(r.number for r in res if r.outcome == "SKIP")})
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


def _targets(spec: str) -> list[tuple[str, str, str]]:
    """``python``, ``c`` (every healthy variant), ``python:noise_free``, ``gateway`` (the gateway profile
    on every packing variant) or ``qemu`` -> [(firmware, variant, profile)]."""
    from tests.host.conformance.mutants import HEALTHY
    out = []
    for item in spec.split(","):
        fw, _, variant = item.partition(":")
        if fw == "qemu":
            out.append(("qemu", "", "chip"))
        elif fw == "gateway":
            out += [("python", v, "gateway") for v, (_, d) in HEALTHY.items() if d.get("packed")
                    and (not variant or v == variant)]
        elif fw in ("python", "c"):
            # the virtual gateway packs IMU records from the chip array only, which the C firmware is not:
            # the C firmware behind a SNAPSHOT_IMU gateway is not measured here
            out += [(fw, v, "chip") for v, (s, d) in HEALTHY.items() if (not variant or v == variant)
                    and not (fw == "c" and d.get("packed") and s.get("sensors", "accel") != "accel")]
        else:
            raise SystemExit(f"unknown target {item!r} (python[:variant], c[:variant], gateway[:variant], qemu)")
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=20)
    p.add_argument("--busy", action="store_true", help="keep one core busy (a spinning process) meanwhile")
    p.add_argument("--targets", default="python,c,gateway,qemu")
    p.add_argument("--budget-min", type=float, default=None,
                   help="start no run after this many minutes (the rounds done are reported)")
    args = p.parse_args()
    targets = _targets(args.targets)
    load_before = os.getloadavg()
    spinner = None
    if args.busy:
        spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        per: dict = {}
        t_start = time.monotonic()
        rounds = 0
        for i in range(args.runs):
            for fw, variant, profile in targets:
                if args.budget_min is not None and time.monotonic() - t_start > 60 * args.budget_min:
                    break
                key = fw if fw == "qemu" else f"{fw}:{variant}" + (" (gateway profile)" if profile == "gateway" else "")
                if fw == "qemu":
                    got = _qemu(1)
                else:
                    if fw == "python":
                        from virtual_sheet.chip import ChipModel as factory
                    else:
                        from firmware_ref.chip import CFirmwareChip as factory
                    got = _virtual(factory, variant, 1, profile, first_seed=i)
                per.setdefault(key, []).extend(got)
            else:
                rounds += 1
                continue
            break
        res = {}
        for key, runs in per.items():
            secs = [r["seconds"] for r in runs]
            res[key] = {"runs": len(runs), "passed": sum(r["ok"] is True for r in runs),
                        "seconds_min_median_max": [round(min(secs), 2), round(statistics.median(secs), 2),
                                                   round(max(secs), 2)],
                        "failures": [b for r in runs for b in r["bad"]]}
            if runs and "skipped" in runs[0]:
                res[key]["skipped_checks"] = sorted({n for r in runs for n in r["skipped"]})
            if key == "qemu" and runs and "stack_high_water_bytes" in runs[0]:
                res[key]["stack_high_water_bytes_max"] = max(r["stack_high_water_bytes"] for r in runs)
        wall = time.monotonic() - t_start
    finally:
        if spinner is not None:
            spinner.kill()
            spinner.wait()
    print(json.dumps({"benchmark": "conformance_stability", "busy_core": args.busy,
                      "rounds_asked": args.runs, "rounds_done": rounds, "budget_min": args.budget_min,
                      "wall_min": round(wall / 60, 1),
                      "load_before": [round(x, 2) for x in load_before],
                      "load_after": [round(x, 2) for x in os.getloadavg()],
                      "total_runs": sum(v["runs"] for v in res.values()),
                      "total_passed": sum(v["passed"] for v in res.values()), "targets": res}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
