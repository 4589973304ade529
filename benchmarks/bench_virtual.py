"""The virtual sheet alone: cost of one SYNC (gateway + every chip, frames encoded for the host),
for 14x14, 32x32 and 64x64 sheets, per-chip SAMPLE frames and packed SNAPSHOTs, the vectorised
chip array against one ChipModel per chip (and the C firmware, per chip, where built), in the
same run. No host, no port: `Gateway.feed` / `pop_output` in one thread, time simulated.

    .venv/bin/python benchmarks/bench_virtual.py            # JSON on stdout
    .venv/bin/python benchmarks/bench_virtual.py --quick    # fewer SYNCs, no 64x64 per-chip models

Targets (issue 11): array >= 10x the per-chip models; 32x32 packed <= 1 ms per SYNC.
Figures are CPU time of this process per SYNC (``time.process_time``), best of 3 runs.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from protocol.framing import encode  # noqa: E402
from protocol.messages import Sync  # noqa: E402
from virtual_sheet.gateway import Gateway  # noqa: E402
from virtual_sheet.sheet import VirtualSheet  # noqa: E402


def ms_per_sync(lattice: str, packed: bool, engine: str, n_sync: int, chip_factory=None) -> float:
    """CPU milliseconds of this process per SYNC (best of 3; CPU time, so other processes on a
    busy machine inflate it far less than wall time)."""
    sheet = VirtualSheet("grow", lattice, seed=1, noise=1.0, engine=engine, chip_factory=chip_factory,
                         scene_rate_hz=10.0)
    sheet.precompute()
    gw = Gateway(sheet, packed=packed)
    gw.power_on(0.0)
    gw.commission(0.0)
    gw.pop_output(1.0)
    frames = [encode(Sync(counter=c & 0xFFFF)) for c in range(n_sync + 5)]
    t = 0.01
    for f in frames[:5]:  # warm-up
        t += 1 / 145
        gw.feed(f, t)
        gw.pop_wire(t)
    best = float("inf")
    for rep in range(3):
        t0 = time.process_time()
        for f in frames[5:]:
            t += 1 / 145
            gw.feed(f, t)
            gw.poll(t)
            gw.pop_wire(t)
        best = min(best, (time.process_time() - t0) / n_sync)
    return 1e3 * best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer SYNCs per case (a fast re-run)")
    args = ap.parse_args(argv)
    try:
        from firmware_ref.chip import CFirmwareChip
    except ImportError:
        CFirmwareChip = None
    rows = []
    for lattice in ("14x14", "32x32", "64x64"):
        for packed in (False, True):
            n = 20 if args.quick else 100
            arr = ms_per_sync(lattice, packed, "array", n)
            row = {"lattice": lattice, "mode": "packed" if packed else "per-chip", "array_ms_per_sync": round(arr, 4)}
            if not (args.quick and lattice == "64x64"):
                chips = ms_per_sync(lattice, packed, "chips", max(5, n // 5))
                row["chip_models_ms_per_sync"] = round(chips, 4)
                row["speedup"] = round(chips / arr, 1)
            if CFirmwareChip is not None and lattice == "14x14":
                row["c_firmware_ms_per_sync"] = round(ms_per_sync(lattice, packed, "chips", max(5, n // 5),
                                                                  CFirmwareChip), 4)
            row["max_sync_hz_one_core"] = round(1e3 / arr)
            rows.append(row)
            print(json.dumps(row), file=sys.stderr)
    load = os.getloadavg()
    print(json.dumps({"benchmark": "bench_virtual", "quick": args.quick, "loadavg": [round(x, 2) for x in load],
                      "results": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
