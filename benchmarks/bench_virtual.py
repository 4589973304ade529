"""The virtual sheet alone: cost of one SYNC (gateway + every chip, frames encoded for the host),
for 14x14, 32x32 and 64x64 sheets, per-chip SAMPLE frames and packed SNAPSHOTs, the vectorised
chip array against one ChipModel per chip (and the C firmware, per chip, where built), in the
same run. No host, no port: `Gateway.feed` / `poll` / `pop_wire` in one thread (what a serial
device does with each SYNC: the due frames as one write), time simulated.

    .venv/bin/python benchmarks/bench_virtual.py            # JSON on stdout
    .venv/bin/python benchmarks/bench_virtual.py --quick    # fewer SYNCs and rounds

Targets: array >= 10x the per-chip models in every configuration; 32x32 packed
<= 1 ms per SYNC.

Figures are CPU time of this process per SYNC (``time.process_time``), the best of several
rounds; within a round the engines of one configuration run one after the other, so a burst of
load elsewhere on the machine hits both, and the best round of each is its cost with the least
interference. The load average is printed beside the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from protocol.framing import encode  # noqa: E402
from protocol.lattice import Lattice  # noqa: E402
from protocol.messages import Sync  # noqa: E402
from virtual_sheet.gateway import Gateway  # noqa: E402
from virtual_sheet.sheet import VirtualSheet  # noqa: E402

RATE_HZ = 145.0


class Rig:
    """One commissioned, streaming sheet + gateway; `run` times ``n`` more SYNCs."""

    def __init__(self, lattice: str, packed: bool, engine: str, chip_factory=None) -> None:
        sheet = VirtualSheet("grow", lattice, seed=1, noise=1.0, engine=engine, chip_factory=chip_factory,
                             scene_rate_hz=10.0)
        sheet.precompute()
        self.gw = gw = Gateway(sheet, packed=packed)
        gw.power_on(0.0)
        gw.commission(0.0)
        gw.pop_output(1.0)
        self.t = 0.01
        self.counter = 0
        self.run(5)  # warm-up: first SYNCs, tables, caches

    def run(self, n: int) -> float:
        """CPU seconds per SYNC over ``n`` SYNCs (feed, timers, output)."""
        frames = [encode(Sync(counter=(self.counter + i) & 0xFFFF)) for i in range(n)]
        self.counter += n
        gw, t = self.gw, self.t
        t0 = time.process_time()
        for f in frames:
            t += 1 / RATE_HZ
            gw.feed(f, t)
            gw.poll(t)
            gw.pop_wire(t)
        dt = time.process_time() - t0
        self.t = t
        return dt / n


def measure(lattice: str, packed: bool, n_array: int, n_chips: int, rounds: int, c_firmware=None) -> dict:
    rigs = {"array": (Rig(lattice, packed, "array"), n_array), "chips": (Rig(lattice, packed, "chips"), n_chips)}
    if c_firmware is not None:
        rigs["c"] = (Rig(lattice, packed, "chips", c_firmware), n_chips)
    best = {k: float("inf") for k in rigs}
    for _ in range(rounds):
        for k, (rig, n) in rigs.items():
            best[k] = min(best[k], rig.run(n))
    arr, chips = 1e3 * best["array"], 1e3 * best["chips"]
    row = {"lattice": lattice, "mode": "packed" if packed else "per-chip",
           "array_ms_per_sync": round(arr, 4), "chip_models_ms_per_sync": round(chips, 4),
           "speedup": round(chips / arr, 1)}
    if "c" in best:
        row["c_firmware_ms_per_sync"] = round(1e3 * best["c"], 4)
    row["max_sync_hz_one_core"] = round(1e3 / arr)
    row["meets_10x"] = chips / arr >= 10
    if lattice == "32x32" and packed:
        row["meets_1ms"] = arr <= 1.0
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer SYNCs and rounds per case (a fast re-run)")
    ap.add_argument("--rounds", type=int, default=None, help="rounds per case (default 7, --quick 4)")
    ap.add_argument("--lattices", default="14x14,32x32,64x64", help="comma-separated (default: all three)")
    args = ap.parse_args(argv)
    try:
        from firmware_ref.chip import CFirmwareChip
    except ImportError:
        CFirmwareChip = None
    rounds = args.rounds or (4 if args.quick else 7)
    load0 = os.getloadavg()
    rows = []
    for lattice in args.lattices.split(","):
        links = Lattice.parse(lattice).n_links
        n_array = max(10, (40 if args.quick else 100) * 364 // links)  # ~the same CPU time per case
        n_chips = max(3, n_array // 8)
        for packed in (False, True):
            row = measure(lattice, packed, n_array, n_chips, rounds,
                          CFirmwareChip if lattice == "14x14" else None)
            rows.append(row)
            print(json.dumps(row), file=sys.stderr)
    load1 = os.getloadavg()
    print(json.dumps({"benchmark": "bench_virtual", "quick": args.quick, "rounds": rounds,
                      "loadavg_before": [round(x, 2) for x in load0], "loadavg": [round(x, 2) for x in load1],
                      "cpu_count": os.cpu_count(), "results": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
