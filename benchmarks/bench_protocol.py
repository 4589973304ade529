"""Serial decode throughput, one core: capsheet per-chip SAMPLE frames and packed SNAPSHOT frames
against pymavlink parsing RAW_IMU messages that carry the same samples, measured in the same run.

Prints JSON. Targets (issue 2): per-chip frames >= 10x pymavlink's samples/s; SNAPSHOT >= 100x.
Usage: python benchmarks/bench_protocol.py [--samples N] [--repeat R]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from protocol import Sample, SampleBatch, Snapshot, StreamDecoder, encode  # noqa: E402
from protocol.messages import unpack_snapshots  # noqa: E402
from protocol.capacity import MAX_SERIAL_SNAPSHOT_SAMPLES  # noqa: E402


def make_samples(n: int, seed: int = 1):
    rng = np.random.Generator(np.random.MT19937(seed))
    counts = rng.integers(-2048, 2048, size=(n, 3))
    status = rng.integers(0, 2, size=n)
    nodes = (np.arange(n) % 364) + 1
    counters = np.arange(n) // 364
    return counts, status, nodes, counters


def best_rate(fn, n_samples: int, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        got = fn()
        dt = time.perf_counter() - t0
        assert got == n_samples, (got, n_samples)
        best = min(best, dt)
    return n_samples / best


def bench_capsheet_per_chip(counts, status, nodes, counters, repeat):
    wire = b"".join(encode(Sample(int(nd), int(c) & 0xFFFF, int(x), int(y), int(z), int(s)))
                    for nd, c, (x, y, z), s in zip(nodes, counters, counts.tolist(), status))

    def run():
        dec = StreamDecoder(batch_samples=True)
        n = 0
        for i in range(0, len(wire), 65536):  # as a serial port delivers it: 64 KiB reads
            for ev in dec.feed(wire[i:i + 65536]):
                if isinstance(ev, SampleBatch):
                    n += len(ev)
        return n

    def run_messages():
        dec = StreamDecoder()
        n = 0
        for i in range(0, len(wire), 65536):
            n += sum(isinstance(ev, Sample) for ev in dec.feed(wire[i:i + 65536]))
        return n

    return best_rate(run, len(counts), repeat), best_rate(run_messages, len(counts), repeat), len(wire)


def bench_capsheet_snapshot(counts, status, counters, repeat):
    n_links = 364
    frames = []
    for start in range(0, len(counts), n_links):
        for first in range(0, n_links, MAX_SERIAL_SNAPSHOT_SAMPLES):
            k = min(MAX_SERIAL_SNAPSHOT_SAMPLES, n_links - first)
            a = start + first
            frames.append(encode(Snapshot.from_arrays(0, int(counters[a]) & 0xFFFF, first,
                                                      counts[a:a + k], status[a:a + k])))
    wire = b"".join(frames)

    def run():
        dec = StreamDecoder(batch_samples=True)
        n = 0
        for i in range(0, len(wire), 65536):
            # unpack every snapshot of this read to arrays at once, as the host does
            counter, link, counts_, status_ = unpack_snapshots(dec.feed(wire[i:i + 65536]))
            n += counts_.shape[0]
        return n

    return best_rate(run, len(counts), repeat), len(wire)


def bench_pymavlink(counts, repeat):
    from pymavlink.dialects.v20 import common as mavlink2
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    wire = b"".join(mav.raw_imu_encode(i, int(x), int(y), int(z), 0, 0, 0, 0, 0, 0).pack(mav)
                    for i, (x, y, z) in enumerate(counts.tolist()))

    def run():
        parser = mavlink2.MAVLink(None)
        parser.robust_parsing = True
        n = 0
        for i in range(0, len(wire), 65536):
            msgs = parser.parse_buffer(wire[i:i + 65536])
            if msgs:
                n += len(msgs)
        return n

    native = getattr(mavlink2, "mavnative", None) is not None
    return best_rate(run, len(counts), repeat), len(wire), native


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=364 * 300)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    counts, status, nodes, counters = make_samples(args.samples)
    mav_rate, mav_bytes, mav_native = bench_pymavlink(counts[: args.samples // 4], args.repeat)
    per_chip, per_chip_msgs, pc_bytes = bench_capsheet_per_chip(counts, status, nodes, counters, args.repeat)
    snap, snap_bytes = bench_capsheet_snapshot(counts, status, counters, args.repeat)
    print(json.dumps({
        "benchmark": "serial decode throughput, one core",
        "python": platform.python_version(),
        "samples": args.samples,
        "pymavlink_raw_imu": {"samples_per_s": round(mav_rate), "bytes_per_sample": mav_bytes / (args.samples // 4),
                              "mavnative": mav_native},
        "capsheet_sample_batch": {"samples_per_s": round(per_chip), "bytes_per_sample": pc_bytes / args.samples,
                                  "x_pymavlink": round(per_chip / mav_rate, 1), "target_x": 10,
                                  "pass": per_chip >= 10 * mav_rate},
        "capsheet_sample_messages": {"samples_per_s": round(per_chip_msgs),
                                     "x_pymavlink": round(per_chip_msgs / mav_rate, 1)},
        "capsheet_snapshot": {"samples_per_s": round(snap), "bytes_per_sample": round(snap_bytes / args.samples, 3),
                              "x_pymavlink": round(snap / mav_rate, 1), "target_x": 100,
                              "pass": snap >= 100 * mav_rate},
    }, indent=1))


if __name__ == "__main__":
    main()
