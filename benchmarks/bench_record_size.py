"""Bytes per hour of a recording: a per-chip sheet's serial input at 145 Hz through the `Recorder`,
the raw channel as it came (``RawSerial``) and as columns (``RawSerialFrames``, host/record/compact.py).

Deterministic and in one process: the virtual sheet's chips (seeded, ``--noise`` % of g per axis)
answer each SYNC through the gateway (`Gateway.pop_wire`), each SYNC's bytes are cut into
``--reads`` reads at seeded random places (reads of a serial port end anywhere, frames straddle
them), and each read goes, as `Recorder.tap` writes it, to ``Recorder.raw`` and through the serial
decoder into the aggregator on a simulated clock, whose snapshots go to ``Recorder.snapshot``; each
SYNC to ``Recorder.sync``. No estimates and no 3D scene (a live session's file adds ~0.05 GB/h of
them: docs/recording.md, "Size"). The file's size over the simulated seconds, times 3600, is the
figure; per channel, each channel's messages compressed alone (zstd 9) give its share. Every
recording is read back and its raw input compared with what was written (``exact``).

    .venv/bin/python benchmarks/bench_record_size.py                      # JSON on stdout
    .venv/bin/python benchmarks/bench_record_size.py --seconds 10 --noise 1
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import numpy as np  # noqa: E402

RATE_HZ = 145.0


def wire(lattice: str, noise: float, n_syncs: int, seed: int, shape: str) -> list[bytes]:
    """Each SYNC's bytes from a commissioned, streaming per-chip sheet (node = link + 1)."""
    from protocol.framing import encode
    from protocol.messages import Sync
    from virtual_sheet.gateway import Gateway
    from virtual_sheet.sheet import VirtualSheet

    sheet = VirtualSheet(shape, lattice, seed=seed, noise=noise)
    gw = Gateway(sheet, packed=False)
    gw.power_on(0.0)
    gw.commission(0.0)
    gw.pop_output(1.0)
    t, out = 0.01, []
    for k in range(n_syncs):
        t += 1 / RATE_HZ
        gw.feed(encode(Sync(counter=k & 0xFFFF)), t)
        gw.poll(t)
        out.append(gw.pop_wire(t)[0])
    return out


def record(path: str, lattice, syncs: list[bytes], reads: int, seed: int, compact: bool) -> list[bytes]:
    """Record the session; returns the reads as written."""
    from host.record.recording import Recorder
    from host.snapshots.aggregator import Aggregator
    from host.snapshots.feed import SnapshotFeed
    from protocol.framing import StreamDecoder

    rng = np.random.Generator(np.random.MT19937(seed))
    clock = {"t": 100.0}
    agg = Aggregator(lattice.n_links, {k + 1: k for k in range(lattice.n_links)}, deadline_s=0.05)
    feed = SnapshotFeed(agg, clock=lambda: clock["t"])
    dec = StreamDecoder(batch_samples=True)
    written = []
    with Recorder(path, lattice, 0.01, session={"rate_hz": RATE_HZ, "mode": "bench"}, compact=compact) as rec:
        feed.add_open_listener(rec.sync)
        feed.add_listener(rec.snapshot)
        for k, data in enumerate(syncs):
            t0 = 100.0 + k / RATE_HZ
            clock["t"] = t0
            feed.open_counter(k & 0xFFFF)
            cuts = np.sort(rng.integers(0, len(data) + 1, reads - 1))
            for j, (a, b) in enumerate(zip(np.r_[0, cuts], np.r_[cuts, len(data)])):
                clock["t"] = t0 + (j + 1) * 0.004 / reads
                chunk = data[a:b]
                if not chunk:
                    continue
                rec.raw(0, "serial", chunk, "bench", t=clock["t"])
                written.append(chunk)
                feed.ingest(dec.feed(chunk), 0)
            feed.poll()
            feed.drain()
    return written


def per_channel(path: str) -> dict[str, int]:
    """Each channel's messages compressed alone with zstd 9, bytes."""
    import zstandard
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    topic, comp = {}, {}
    with open(path, "rb") as f:
        for r in StreamReader(f).records:
            if isinstance(r, Channel):
                topic[r.id] = r.topic
            elif isinstance(r, Message):
                c = comp.setdefault(topic[r.channel_id], [zstandard.ZstdCompressor(level=9).compressobj(), 0])
                c[1] += len(c[0].compress(bytes(r.data)))
    return {t: n + len(c.flush()) for t, (c, n) in sorted(comp.items())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lattice", default="14x14")
    ap.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per recording (default 20)")
    ap.add_argument("--noise", type=float, nargs="+", default=[0.02, 1.0],
                    help="sensor noise, %% of g per axis, one recording pair each (default 0.02 1)")
    ap.add_argument("--reads", type=int, default=3, help="reads per SYNC's bytes (default 3)")
    ap.add_argument("--shape", default="gaussian", help="the virtual sheet's shape (default gaussian, still)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    from protocol.lattice import Lattice
    try:
        lattice = Lattice.parse(args.lattice)
    except ValueError as e:
        ap.error(str(e))
    if not args.seconds > 0:
        ap.error(f"--seconds must be > 0, not {args.seconds}")
    if args.reads < 1:
        ap.error(f"--reads must be >= 1, not {args.reads}")
    if any(not (0 <= n <= 10) for n in args.noise):
        ap.error(f"--noise must be within 0..10 % of g, not {args.noise}")
    from host.record.recording import read

    load0 = os.getloadavg()
    n = int(round(args.seconds * RATE_HZ))
    per_h = 3600.0 / (n / RATE_HZ)
    rows = []
    for noise in args.noise:
        syncs = wire(args.lattice, noise, n, args.seed, args.shape)
        row = {"noise_pct_g": noise, "wire_gb_per_h": round(sum(map(len, syncs)) * per_h / 1e9, 3)}
        for name, compact in (("raw_serial", False), ("raw_serial_frames", True)):
            with tempfile.TemporaryDirectory() as d:
                path = os.path.join(d, "r.mcap")
                a = time.process_time()
                written = record(path, lattice, syncs, args.reads, args.seed, compact)
                cpu = time.process_time() - a
                size = os.path.getsize(path)
                back = [p for _, _, p in read(path).raw[0]]
                row[name] = {"gb_per_h": round(size * per_h / 1e9, 3),
                             "channels_zstd9_alone_gb_per_h": {t: round(b * per_h / 1e9, 3)
                                                               for t, b in per_channel(path).items()},
                             "record_cpu_s_per_s": round(cpu / (n / RATE_HZ), 3),
                             "exact": back == written}
        rows.append(row)
    print(json.dumps({"lattice": args.lattice, "rate_hz": RATE_HZ, "seconds": n / RATE_HZ, "reads_per_sync": args.reads,
                      "shape": args.shape, "rows": rows, "loadavg_before": [round(x, 2) for x in load0],
                      "loadavg": [round(x, 2) for x in os.getloadavg()]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
