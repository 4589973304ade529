"""What parts of a live host cost in memory and in stalls over a long run. Prints JSON.

* ``masked_structures``: a live host estimates the newest snapshot; on a loaded machine some are
  incomplete, each missing another link. ``--masks`` estimates of a 14x14 sheet, each with one
  different link missing (seeded), after one with all links: how many structures the estimator
  keeps (`host.analysis.estimator.structure.cached_structure`), glibc's heap in use plus mmapped
  blocks (`host.memory.mallinfo2`) and the resident anonymous memory, grown since the first.
* ``recorder_lock``: does the MCAP writer (foxglove-sdk, zstd level 9) hold the interpreter lock
  while it compresses a chunk? ``--seconds`` s of 5 KB messages at 145 Hz (725 KB/s, a chunk closed
  every ~1.4 s) while a thread sleeps 1 ms in a loop: the longest ``log`` call, and the sleeper's
  gaps over 5 ms with and without the writer (a gap as long as a compression would be the lock).

    python benchmarks/bench_host_memory.py [--masks 40] [--seconds 15]
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from host.memory import fix_mmap_threshold, mallinfo2  # noqa: E402


def _rss_anon_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("RssAnon")) / 1024.0


def masked_structures(n_masks: int) -> dict:
    from host.analysis.estimator import estimate
    from host.analysis.estimator.structure import cached_structure
    rng = np.random.default_rng(1)
    r = np.tile([0.0, 0.0, 9.81], (364, 1)) + rng.normal(0, 0.1, (364, 3))
    prev = estimate(r, 14, 14, 0.01, bad_readings="mask")

    def used():
        gc.collect()
        m = mallinfo2() or {"uordblks": 0, "hblkhd": 0}
        return (m["uordblks"] + m["hblkhd"]) / 1e6
    u0, r0 = used(), _rss_anon_mb()
    rows = []
    for k in range(1, n_masks + 1):
        valid = np.ones(364, bool)
        valid[(k * 37) % 364] = False  # another link each time
        prev = estimate(r, 14, 14, 0.01, valid=valid, previous=prev, bad_readings="mask")
        if k in (1, 4, 8, 16, 24, n_masks):
            rows.append({"masks": k, "masked_structures_kept": cached_structure.cache_info().currsize,
                         "heap_and_mmapped_growth_mb": round(used() - u0, 2),
                         "rss_anon_growth_mb": round(_rss_anon_mb() - r0, 2)})
    return {"lattice": "14x14", "rows": rows}


def recorder_lock(seconds: float) -> dict:
    import foxglove
    from foxglove.mcap import MCAPWriteOptions

    from host.record.recording import COMPRESSION_LEVEL
    out = {}
    for writer in (False, True):
        ctx = foxglove.Context()
        w = foxglove.open_mcap(os.path.join(tempfile.mkdtemp(), "x.mcap"), allow_overwrite=True, context=ctx,
                               writer_options=MCAPWriteOptions(chunk_size=1 << 20, compression_threads=0, profile="",
                                                               compression_level=COMPRESSION_LEVEL))
        ch = foxglove.Channel("/t", message_encoding="protobuf",
                              schema=foxglove.Schema(name="x", encoding="protobuf", data=b""), context=ctx)
        rng = np.random.default_rng(1)
        msgs = [rng.integers(0, 64, 5000, dtype=np.uint8).tobytes() for _ in range(64)]
        gaps: list[float] = []
        stop = threading.Event()

        def sleeper():
            t = time.perf_counter()
            while not stop.is_set():
                time.sleep(0.001)
                n = time.perf_counter()
                gaps.append(n - t)
                t = n
        th = threading.Thread(target=sleeper)
        th.start()
        calls = []
        for i in range(int(145 * seconds)):
            if writer:
                a = time.perf_counter()
                ch.log(msgs[i % 64])
                calls.append(time.perf_counter() - a)
            time.sleep(1 / 145)
        stop.set()
        th.join()
        w.close()
        g = np.array(gaps) * 1e3
        out["with_writer" if writer else "without_writer"] = {
            "sleeper_gaps_over_5ms": int((g > 5).sum()), "sleeper_gap_max_ms": round(float(g.max()), 2),
            **({"log_call_max_ms": round(1e3 * max(calls), 2), "log_calls_over_2ms": int(sum(c > 0.002 for c in calls))}
               if calls else {})}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--masks", type=int, default=40)
    ap.add_argument("--seconds", type=float, default=15.0)
    args = ap.parse_args()
    fix_mmap_threshold()
    sys.setswitchinterval(0.0005)  # as capsheet host
    with open("/proc/loadavg") as f:
        load0 = [float(v) for v in f.read().split()[:3]]
    doc = {"masked_structures": masked_structures(args.masks), "recorder_lock": recorder_lock(args.seconds),
           "load_average_start": load0}
    print(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
