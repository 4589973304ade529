"""The estimator on a stream: consecutive snapshots of one sheet at 145 Hz, as the estimator process
sees them live, each warm-started from the last (`ShapeEstimator`, the stateful path the process
runs). Prints JSON.

Streams (64x64 joints by default, L = 1 cm, readings through the virtual chips' 12-bit ADC at
±2 g with `capsheet virtual`'s default noise, 0.02 % g, then back to m/s² as the host hands them
over):

``live``
    `capsheet virtual`'s default sheet: the Gaussian bump, still. Consecutive snapshots differ by
    the noise and the ADC's rounding only.
``moving``
    The bump rising and falling (`virtual_sheet.shapes.GrowScene`, period 4 s), sampled at 145 Hz
    from t = 1 s (the bump half up, rising fastest).
``noisy``
    The moving bump with 1 % g noise per axis (no ADC): a far noisier chip than any real part.

Per stream: milliseconds per snapshot of `ShapeEstimator.update` (the best of ``--repeats``
passes over the same snapshots, each pass from a fresh estimator warmed on the snapshot before
the first; wall time, and process CPU time which a loaded machine inflates less), the chord
steps and factorisations per snapshot, and how far each estimate is from the cold `estimate` of
the same readings (no warm start) and from the minimiser of the same cost (solved to 1e-12 rad),
as the largest joint distance in % of the side, against the solver's stopping rule
(``near_minimiser_bound_pct_side``, the bound the estimator's tests hold every path to); and how
far the cold estimates themselves stopped from that minimiser (a cold solve from the rest layout
can stop further from it than a warm one: on the ``noisy`` stream one cold estimate in twelve
stopped 0.07 % of the side short, where the warm chain's was 0.0001 % from it).
With ``--process`` also the estimator process (`host.workers.estimate_worker.EstimatorProcess`)
fed a stream (``--process-stream``, default ``live``; ``moving`` is the sheet a live host sees
move) as fast as it answers: its own seconds per estimate and snapshots per second.

Load matters on a shared machine: the JSON carries ``os.getloadavg()`` at start and end.

    .venv/bin/python benchmarks/bench_estimator_stream.py                   # 64x64, all streams
    .venv/bin/python benchmarks/bench_estimator_stream.py --process         # and the process
    .venv/bin/python benchmarks/bench_estimator_stream.py --process --process-stream moving
    .venv/bin/python benchmarks/bench_estimator_stream.py --lattice 32 --snapshots 60 --streams live
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

from host.analysis import estimator as E  # noqa: E402
from host.analysis.estimator import ShapeEstimator, estimate  # noqa: E402
from protocol.constants import counts_to_si  # noqa: E402
from virtual_sheet.geometry import ideal_readings  # noqa: E402
from virtual_sheet.sensor import SensorModel, noisy_readings  # noqa: E402
from virtual_sheet.shapes import GrowScene, make_sheet  # noqa: E402

L = 0.01
RATE_HZ = 145.0
#: `capsheet virtual`'s default noise, % of g per axis
LIVE_NOISE_PCT_G = 0.02
STREAMS = ("live", "moving", "noisy")
#: the goal per 64x64 snapshot on a quiet machine, ms
GOAL_MS_64 = 3.0
#: every path stops within this of the minimiser (tests/host/analysis/test_estimate_batch.py)
NEAR_MINIMISER_PCT = 0.03


def rng(seed: int) -> np.random.Generator:
    return np.random.Generator(np.random.MT19937(seed))


def stream(kind: str, n: int, count: int, seed: int) -> list[np.ndarray]:
    """``count + 1`` consecutive snapshots of stream ``kind`` (module docstring), m/s²."""
    g = rng(seed)
    adc = SensorModel(noise_pct_g=LIVE_NOISE_PCT_G)
    if kind == "live":
        r0 = ideal_readings(make_sheet("gaussian", n, n, L))
        return [counts_to_si(adc.sample(r0, g)[0]) for _ in range(count + 1)]
    scene = GrowScene(n, n, L)
    truth = [ideal_readings(scene.joints(1.0 + k / RATE_HZ)) for k in range(count + 1)]
    if kind == "moving":
        return [counts_to_si(adc.sample(r, g)[0]) for r in truth]
    return [noisy_readings(r, 1.0, g) for r in truth]


def timed_chain(snaps, n: int, repeats: int):
    """Best wall and CPU ms per snapshot over ``repeats`` passes of a fresh `ShapeEstimator`
    (warmed on ``snaps[0]``, untimed) over ``snaps[1:]``; and the last pass's estimates."""
    walls, cpus, out = [], [], []
    for _ in range(repeats):
        est = ShapeEstimator(n, n, L)
        est.update(snaps[0])
        got = []
        w0, c0 = time.perf_counter(), time.process_time()
        for r in snaps[1:]:
            got.append(est.update(r))
        walls.append((time.perf_counter() - w0) / (len(snaps) - 1))
        cpus.append((time.process_time() - c0) / (len(snaps) - 1))
        out = got
    return min(walls), float(np.median(walls)), min(cpus), out


def exact(r, n: int, previous):
    """The minimiser of the same cost: the warm solve continued to 1e-12 rad."""
    old = E.solver.YAW_TOL_RAD, E.solver.YAW_TOL_NOISE
    E.solver.YAW_TOL_RAD, E.solver.YAW_TOL_NOISE = 1e-12, 0.0
    try:
        return estimate(r, n, n, L, previous=previous)
    finally:
        E.solver.YAW_TOL_RAD, E.solver.YAW_TOL_NOISE = old


def run_stream(kind: str, n: int, count: int, repeats: int, seed: int, check_every: int) -> dict:
    snaps = stream(kind, n, count, seed)
    estimate(snaps[0], n, n, L)  # the lattice's structure, built once (cached, not timed)
    best, median, cpu, got = timed_chain(snaps, n, repeats)
    side = L * (n - 1)
    far_cold, far_min, cold_min = [], [], []
    for k in range(0, len(got), check_every):
        r = snaps[k + 1]
        cold = estimate(r, n, n, L)
        ref = exact(r, n, got[k - 1] if k else None)
        far_cold.append(float(np.max(np.linalg.norm(got[k].joints - cold.joints, axis=-1))))
        far_min.append(float(np.max(np.linalg.norm(got[k].joints - ref.joints, axis=-1))))
        cold_min.append(float(np.max(np.linalg.norm(cold.joints - ref.joints, axis=-1))))
    its = np.array([e.iterations for e in got])
    return {
        "stream": kind, "lattice": f"{n}x{n}", "links": 2 * n * (n - 1), "snapshots_timed": len(got),
        "ms_per_snapshot_best": round(1e3 * best, 3),
        "ms_per_snapshot_median_pass": round(1e3 * median, 3),
        "cpu_ms_per_snapshot_best": round(1e3 * cpu, 3),
        "snapshots_per_s_best": round(1.0 / best, 1),
        "mean_chord_steps": round(float(its.mean()), 3),
        "chord_steps_histogram": np.bincount(its).tolist(),
        "factorisations": int(sum(e.factorisations for e in got)),
        "stage_ms_mean": {k_: round(1e3 * float(np.mean([e.timings[k_] for e in got])), 3)
                          for k_ in ("angles", "yaw", "joints", "total")},
        "checked_snapshots": len(far_cold),
        "max_from_cold_estimate_pct_side": float("%.3g" % (100.0 / side * max(far_cold))),
        "max_from_minimiser_pct_side": float("%.3g" % (100.0 / side * max(far_min))),
        "cold_estimate_max_from_minimiser_pct_side": float("%.3g" % (100.0 / side * max(cold_min))),
        "near_minimiser_bound_pct_side": NEAR_MINIMISER_PCT,
    }


def run_process(n: int, count: int, seed: int, kind: str = "live") -> dict:
    """The estimator process fed stream ``kind`` as fast as it answers (at most its
    ``max_in_flight`` outstanding)."""
    from types import SimpleNamespace

    from host.workers.estimate_worker import EstimatorProcess

    snaps = stream(kind, n, count + 5, seed)
    valid = np.ones(snaps[0].shape[0], bool)
    proc = EstimatorProcess(n, n, L)
    try:
        t_end = time.monotonic() + 120.0
        while not proc.warm and time.monotonic() < t_end:
            proc.results(0.1)
        for k in range(5):  # the chain's first few (its first factorisation), untimed
            proc.submit(SimpleNamespace(readings=snaps[k], valid=valid, counter=k))
            while proc.results(1.0) == [] and time.monotonic() < t_end:
                pass
        got, k = [], 0
        t0 = time.perf_counter()
        while len(got) < count and time.monotonic() < t_end:
            while proc.free and k < count:
                proc.submit(SimpleNamespace(readings=snaps[5 + k], valid=valid, counter=k))
                k += 1
            got += proc.results(1.0)
        wall = time.perf_counter() - t0
    finally:
        proc.close()
    secs = np.array([e.seconds for e in got])
    return {"lattice": f"{n}x{n}", "stream": kind, "estimates": len(got),
            "failed": sum(bool(e.error) for e in got),
            "child_ms_per_estimate_median": round(1e3 * float(np.median(secs)), 3),
            "child_ms_per_estimate_mean": round(1e3 * float(np.mean(secs)), 3),
            "child_ms_per_estimate_p90": round(1e3 * float(np.percentile(secs, 90)), 3),
            "snapshots_per_s": round(len(got) / wall, 1),
            "mean_iterations": round(float(np.mean([e.iterations for e in got])), 3)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lattice", type=int, default=64, help="joints per side (default 64)")
    ap.add_argument("--snapshots", type=int, default=145, help="timed snapshots per stream (default 145: 1 s)")
    ap.add_argument("--repeats", type=int, default=3, help="timed passes per stream (default 3)")
    ap.add_argument("--streams", default=",".join(STREAMS),
                    help=f"comma-separated, among {', '.join(STREAMS)} (default all)")
    ap.add_argument("--check-every", type=int, default=12,
                    help="compare every Nth estimate with a cold one and the minimiser (default 12)")
    ap.add_argument("--process", action="store_true", help="also time the estimator process on a stream")
    ap.add_argument("--process-stream", default="live", choices=STREAMS,
                    help="the stream the estimator process is fed (default live)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    if args.lattice < 2:
        ap.error(f"--lattice: need >= 2 joints per side (got {args.lattice})")
    for name in ("snapshots", "repeats", "check_every"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')}: need >= 1 (got {getattr(args, name)})")
    kinds = [s for s in args.streams.split(",") if s]
    bad = [s for s in kinds if s not in STREAMS]
    if bad or not kinds:
        ap.error(f"--streams: choose among {', '.join(STREAMS)} (got {args.streams!r})")
    load0 = os.getloadavg()
    results = [run_stream(k, args.lattice, args.snapshots, args.repeats, args.seed, args.check_every)
               for k in kinds]
    out = {"benchmark": "estimator_stream", "rate_hz": RATE_HZ, "threads": 1,
           "kernel": bool(E.USE_KERNEL), "loadavg_start": [round(v, 2) for v in load0],
           "results": results}
    if args.lattice == 64:
        out["goal_ms_per_snapshot_quiet"] = GOAL_MS_64
    if args.process:
        out["process"] = run_process(args.lattice, max(args.snapshots, 100), args.seed,
                                     args.process_stream)
    out["loadavg_end"] = [round(v, 2) for v in os.getloadavg()]
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
