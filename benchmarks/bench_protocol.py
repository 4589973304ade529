"""Serial decode throughput, one core: capsheet per-chip SAMPLE frames and packed SNAPSHOT frames
against pymavlink parsing RAW_IMU messages that carry the same samples, measured in the same run.

Prints JSON. Targets: per-chip frames >= 10x pymavlink's samples/s; SNAPSHOT >= 100x.
Usage: python benchmarks/bench_protocol.py [--samples N] [--repeat R]

6-axis chips (docs/protocol.md §16): the same for IMU records (accelerometer, gyroscope,
sample time; RAW_IMU carries as much), per chip (IMU_SAMPLE) and packed (SNAPSHOT_IMU, 77 records a
frame); each row with what a 14x14 sheet (364 chips) at 145 Hz needs — the records per second, how
many times over the decoder keeps up, and the buses `capsheet protocol capacity` says it takes
(`protocol.capacity.buses_needed`, the command's own function).
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
from protocol.messages import (MAX_SERIAL_IMU_RECORDS, ImuBatch, ImuSample, SampleFormat, SnapshotImu,  # noqa: E402
                               unpack_snapshots, unpack_snapshots_imu)
from protocol.capacity import MAX_SERIAL_SNAPSHOT_SAMPLES, bus_load, buses_needed  # noqa: E402

#: the sheet and rate the IMU rows are sized for (14x14 at the paper's 145 Hz)
IMU_LINKS, IMU_RATE_HZ = 364, 145.0


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


def make_imu(n: int, seed: int = 2):
    """6-axis records: gyroscope counts and chip times beside `make_samples`' accelerometer."""
    rng = np.random.Generator(np.random.MT19937(seed))
    return rng.integers(-32768, 32768, size=(n, 3)), rng.integers(-2000, 2000, size=n)


def bench_imu_per_chip(counts, status, nodes, counters, gyro, t_us, repeat):
    """IMU_SAMPLE frames (6-axis, §16.3) through the host's decoder: records/s (ImuBatch path)."""
    wire = b"".join(encode(ImuSample(int(nd), int(c) & 0xFFFF, int(x), int(y), int(z), int(s), int(t),
                                     int(gx), int(gy), int(gz)))
                    for nd, c, (x, y, z), s, t, (gx, gy, gz)
                    in zip(nodes, counters, counts.tolist(), status, t_us.tolist(), gyro.tolist()))

    def run():
        dec = StreamDecoder(batch_samples=True)
        n = 0
        for i in range(0, len(wire), 65536):
            for ev in dec.feed(wire[i:i + 65536]):
                if isinstance(ev, ImuBatch):
                    n += len(ev)
        return n

    return best_rate(run, len(counts), repeat), len(wire)


def bench_imu_snapshot(counts, status, counters, gyro, t_us, repeat):
    """SNAPSHOT_IMU frames (6-axis, §16.5) decoded and unpacked to arrays: every frame of a read at once
    (`unpack_snapshots_imu`, the batch path), and frame by frame (`SnapshotImu.arrays`, for comparison)."""
    n_links, k = IMU_LINKS, MAX_SERIAL_IMU_RECORDS[SampleFormat.IMU6]
    frames = []
    for start in range(0, len(counts), n_links):
        for first in range(0, n_links, k):
            m = min(k, n_links - first)
            a = start + first
            frames.append(encode(SnapshotImu.from_arrays(0, int(counters[a]) & 0xFFFF, first, counts[a:a + m],
                                                         status[a:a + m], t_us[a:a + m], gyro[a:a + m])))
    wire = b"".join(frames)

    def run():
        dec = StreamDecoder(batch_samples=True)
        n = 0
        for i in range(0, len(wire), 65536):
            # every SNAPSHOT_IMU of this read to arrays at once, as `capsheet_snapshot` does SNAPSHOT
            out = unpack_snapshots_imu([ev for ev in dec.feed(wire[i:i + 65536]) if isinstance(ev, SnapshotImu)])
            n += out[2].shape[0]
        return n

    def run_each():
        dec = StreamDecoder(batch_samples=True)
        n = 0
        for i in range(0, len(wire), 65536):
            for ev in dec.feed(wire[i:i + 65536]):
                if isinstance(ev, SnapshotImu):
                    n += ev.arrays()[0].shape[0]
        return n

    return best_rate(run, len(counts), repeat), best_rate(run_each, len(counts), repeat), len(wire)


def imu_needs(rate: float, packed: bool) -> dict:
    """What a 14x14 6-axis sheet at 145 Hz needs of the links that carry this framing, from the
    capacity table (`buses_needed`), and the load of one 12 Mbaud UART (`bus_load`)."""
    want = "SNAPSHOT_IMU" if packed else "IMU_SAMPLE"
    buses = {f"{c.link}: {c.carries}": k for c, k in buses_needed(IMU_LINKS, IMU_RATE_HZ)
             if c.carries.startswith("6-axis") and want in c.carries}
    need = IMU_LINKS * IMU_RATE_HZ
    return {"records_per_s_needed": need, "x_needed": round(rate / need, 1), "buses_needed": buses,
            "load_pct_of_one_12Mbaud_uart": round(100 * bus_load(IMU_LINKS, IMU_RATE_HZ, kind="serial",
                                                                    bitrate=12e6, packed=packed, fmt=1), 1)}


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
    gyro, t_us = make_imu(args.samples)
    imu_pc, imu_pc_bytes = bench_imu_per_chip(counts, status, nodes, counters, gyro, t_us, args.repeat)
    imu_snap, imu_snap_each, imu_snap_bytes = bench_imu_snapshot(counts, status, counters, gyro, t_us, args.repeat)
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
        "imu6_14x14_145hz": {
            "per_chip_imu_sample": {"records_per_s": round(imu_pc), "bytes_per_record": round(imu_pc_bytes / args.samples, 3),
                                    "x_pymavlink": round(imu_pc / mav_rate, 1), **imu_needs(imu_pc, packed=False)},
            "packed_snapshot_imu": {"records_per_s": round(imu_snap),
                                    "bytes_per_record": round(imu_snap_bytes / args.samples, 3),
                                    "x_pymavlink": round(imu_snap / mav_rate, 1), **imu_needs(imu_snap, packed=True),
                                    # the peer: capsheet_snapshot above, same run, same samples, same batch path
                                    "x_of_snapshot_samples_per_s": round(imu_snap / snap, 2),
                                    "x_of_snapshot_bytes_per_s": round((imu_snap * imu_snap_bytes) / (snap * snap_bytes), 2),
                                    "frame_by_frame_records_per_s": round(imu_snap_each),
                                    "batch_x_frame_by_frame": round(imu_snap / imu_snap_each, 2)}},
    }, indent=1))


if __name__ == "__main__":
    main()
