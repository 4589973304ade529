"""Estimator throughput: snapshots/s on one core, warm start from the previous snapshot, 1 % g noise.

Truth: the virtual sheet's Gaussian (exact Chebyshev net) on 14x14, 32x32 and 64x64 joints,
L = 1 cm. Every snapshot has fresh noise (seeded MT19937); ``method="global"`` warm-starts from the
previous estimate. The paper's method (no warm start in the paper) runs on the same snapshots,
fewer of them on big lattices. The machine may be shared: each rate is the best of ``--repeats``
timed passes (and the median is reported too). Prints JSON. Targets (issue 5), global:
14x14 >= 1000/s, 32x32 >= 200/s, 64x64 >= 50/s.

    .venv/bin/python benchmarks/bench_estimator.py [--quick]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
             "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"  # one core, before numpy is imported

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from host.estimator import error_percent_of_side, estimate  # noqa: E402
from virtual_sheet.geometry import ideal_readings  # noqa: E402
from virtual_sheet.sensor import noisy_readings  # noqa: E402
from virtual_sheet.shapes import make_sheet  # noqa: E402

TARGETS = {14: 1000.0, 32: 200.0, 64: 50.0}
L = 0.01
NOISE_PCT_G = 1.0


def _pass(snaps, n, method, warm):
    prev = None
    if warm:  # the snapshot before the first: not timed
        prev = estimate(snaps[-1], n, n, L, method=method)
    t0 = time.perf_counter()
    for r in snaps:
        prev = estimate(r, n, n, L, previous=prev if warm else None, method=method)
    return (time.perf_counter() - t0) / len(snaps), prev


def run(n: int, n_global: int, n_paper: int, repeats: int, seed: int) -> dict:
    P = make_sheet("gaussian", n, n, L)
    r0 = ideal_readings(P)
    rng = np.random.Generator(np.random.MT19937(seed))
    snaps = [noisy_readings(r0, NOISE_PCT_G, rng) for _ in range(n_global)]
    estimate(snaps[0], n, n, L)  # build the per-lattice structure once (cached, not timed)
    out = {"lattice": f"{n}x{n}", "links": 2 * n * (n - 1)}
    for method, count, warm in (("global", n_global, True), ("paper", n_paper, False)):
        times = []
        for _ in range(repeats if method == "global" else 1):
            dt, last = _pass(snaps[:count], n, method, warm)
            times.append(dt)
        out[method] = {
            "snapshots_per_s_best": round(1.0 / min(times), 1),
            "snapshots_per_s_median": round(1.0 / float(np.median(times)), 1),
            "snapshots_timed": count * len(times),
            "last_error_pct_side": round(float(error_percent_of_side(last.joints, P, L).mean()), 4),
            "iterations_last": last.iterations,
        }
    out["global"]["target_per_s"] = TARGETS.get(n)
    out["global"]["meets_target"] = out["global"]["snapshots_per_s_best"] >= TARGETS.get(n, 0)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer snapshots")
    ap.add_argument("--repeats", type=int, default=5, help="timed passes of global per size")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    plan = {14: (400, 10), 32: (100, 3), 64: (30, 1)}
    if args.quick:
        plan = {14: (50, 2), 32: (20, 1), 64: (5, 1)}
    results = [run(n, g, p, 2 if args.quick else args.repeats, args.seed)
               for n, (g, p) in plan.items()]
    print(json.dumps({"benchmark": "estimator", "noise_pct_g": NOISE_PCT_G, "threads": 1,
                      "warm_start": "global: previous snapshot; paper: none (as published)",
                      "results": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
