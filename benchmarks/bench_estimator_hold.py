"""The estimator process on a 64x64 stream where one snapshot in ten misses a few links: what a
snapshot costs with the missing links held (estimated from their last readings, the default,
`host.workers.estimate_worker.HOLD_SNAPSHOTS`) against without (``hold_snapshots=0``: each new mask
its own structure and factorisation), in the same run. Prints JSON: wall ms per snapshot through
the process (submit to answer, the requests in flight as the host keeps them), the child's busy
seconds, the links held.

    .venv/bin/python benchmarks/bench_estimator_hold.py [--snapshots 150] [--every 10] [--missing 3]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from host.snapshots.snapshot import LatticeSnapshot  # noqa: E402
from host.workers.estimate_worker import HOLD_SNAPSHOTS, EstimatorProcess  # noqa: E402
from virtual_sheet.geometry import chebyshev_net, ideal_readings  # noqa: E402
from protocol.constants import G0  # noqa: E402
from virtual_sheet.shapes import height_field  # noqa: E402


def run(hold: int, n_snap: int, every: int, missing: int, seed: int = 1) -> dict:
    rows = cols = 64
    L = 0.01
    ideal = ideal_readings(chebyshev_net(height_field("gaussian", rows, cols, L), rows, cols, L))
    n = ideal.shape[0]
    rng = np.random.Generator(np.random.MT19937(seed))
    w = EstimatorProcess(rows, cols, L, hold_snapshots=hold)
    end = time.monotonic() + 120.0
    while not w.warm:  # the child's warm-up answer (a child that died never sends it)
        w.results(1.0)
        if time.monotonic() > end or not w.alive:
            raise SystemExit("the estimator process did not warm up")
    got = []
    t0 = time.perf_counter()
    for k in range(n_snap):
        v = np.ones(n, bool)
        if k % every == every // 2:
            v[rng.choice(n, missing, replace=False)] = False
        r = ideal + rng.normal(0, 0.01 * G0, ideal.shape)
        r[~v] = np.nan
        while not w.free:
            got += w.results(5.0)
        w.submit(LatticeSnapshot(k, float(k), 0.0, r, v, np.zeros(n, np.uint8), bool(v.all()), 0.0))
    got += w.close(120.0)
    dt = time.perf_counter() - t0
    return {"hold_snapshots": hold, "estimates": len(got), "wall_ms_per_snapshot": round(1e3 * dt / n_snap, 2),
            "child_busy_s": round(w.busy_s, 3), "held_links": w.held_links, "held_estimates": w.held_estimates}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--snapshots", type=int, default=150)
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--missing", type=int, default=3)
    args = ap.parse_args(argv)
    out = {"lattice": "64x64", "snapshots": args.snapshots, "incomplete_every": args.every,
           "missing_links": args.missing, "loadavg": os.getloadavg()[0],
           "held": run(HOLD_SNAPSHOTS, args.snapshots, args.every, args.missing),
           "not_held": run(0, args.snapshots, args.every, args.missing)}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
