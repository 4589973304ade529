"""Layout learning (`host.analysis.layout.learn_layout`) on shuffled virtual sheets of several sizes:
links right, the largest unit residual of the learned layout (the loop closure it is judged by),
and the time the decision takes (wall and CPU; the poses' readings are made first, not timed).

Readings: each pose of `virtual_sheet.layout_poses.LayoutPoseScene` through the virtual sheet's
sensor model (``--noise`` % g per axis, quantised), ``--draws`` readings averaged per pose (the
pose detector averages ~50 over its 1 s window at 50 Hz). Prints JSON.

    .venv/bin/python benchmarks/bench_layout_learn.py [--lattice 8x8 --lattice 64x64] [--noise 1] [--draws 40] [--chip-errors realistic]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from host.analysis.layout import learn_layout  # noqa: E402
from tests.host.analysis.test_layout_learn import correct, sheet_poses  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lattice", action="append", default=None)
    ap.add_argument("--noise", type=float, default=1.0)
    ap.add_argument("--draws", type=int, default=40)
    ap.add_argument("--chip-errors", choices=("none", "realistic"), default="none",
                    help="realistic: each chip's own bias, scale and misalignment, uncalibrated")
    args = ap.parse_args()
    learn_layout("3x3", sheet_poses("3x3", draws=1)[0])  # imports and first structures, not timed
    out = {}
    for lat in args.lattice or ["8x8", "14x14", "32x32", "64x64"]:
        poses, truth = sheet_poses(lat, noise=args.noise, draws=args.draws, chip_errors=args.chip_errors)
        t0, c0 = time.perf_counter(), time.process_time()
        res = learn_layout(lat, poses)
        out[lat] = {"links": len(truth), "correct": correct(res.layout, truth),
                    "wall_s": round(time.perf_counter() - t0, 2), "cpu_s": round(time.process_time() - c0, 2),
                    "max_unit_residual": float(f"{res.max_residual:.3g}"), "residual_limit": float(f"{res.limit:.3g}"),
                    "units_over_limit": len(res.bad_units)}
    print(json.dumps({"noise_pct_g": args.noise, "draws": args.draws, "chip_errors": args.chip_errors, "sheets": out},
                     indent=1))


if __name__ == "__main__":
    main()
