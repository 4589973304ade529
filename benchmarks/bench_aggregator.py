"""Aggregator ingest rate on one core, printed as JSON.

For a 14x14 and a 32x32 sheet, a stream of N counters is built in memory two ways:

* ``per_chip``: one SAMPLE frame per link and counter (what a serial gateway relaying chips, or a
  CAN bus, carries), in wire bytes;
* ``snapshot``: SNAPSHOT frames of up to 202 links per frame (a packing gateway).

Each case reports
* ``end_to_end``: wire bytes -> `StreamDecoder(batch_samples=True)` -> `Aggregator` -> snapshots;
* ``aggregator_only`` (per_chip): pre-decoded `SampleBatch` es -> `Aggregator` -> snapshots
  (the host's own cost, without the protocol decoder);
* ``decoder_only`` (per_chip): wire bytes -> `StreamDecoder` (the protocol's cost).

Run: ``.venv/bin/python benchmarks/bench_aggregator.py [--counters N] [--chunk BYTES]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from host.snapshots.aggregator import Aggregator  # noqa: E402
from protocol.framing import MAX_PAYLOAD_SIZE, StreamDecoder, encode_frame  # noqa: E402
from protocol.messages import SampleBatch  # noqa: E402
from protocol.lattice import Lattice  # noqa: E402
from protocol.messages import MsgType, Snapshot, pack_sample_words  # noqa: E402

SNAP_MAX = (MAX_PAYLOAD_SIZE - Snapshot.HEADER_SIZE) // 5


def per_chip_stream(n_links: int, n_counters: int, rng: np.random.Generator) -> bytes:
    """Wire bytes of SAMPLE frames: node k+1 -> link k, every link for every counter (vectorised)."""
    from protocol.framing import HEADER
    from protocol.crc import crc16_ccitt_false
    from cobs import cobs
    frames = []
    counts = rng.integers(-300, 300, size=(n_counters * n_links, 3))
    counts[:, 2] += 1024
    words = np.frombuffer(pack_sample_words(counts, np.zeros(len(counts), dtype=np.int64)), np.uint8).reshape(-1, 5)
    i = 0
    for c in range(n_counters):
        ctr = (c & 0xFFFF).to_bytes(2, "little")
        for link in range(n_links):
            body = HEADER.pack(1, MsgType.SAMPLE, link + 1) + ctr + words[i].tobytes()
            body += crc16_ccitt_false(body).to_bytes(2, "big")
            frames.append(cobs.encode(body) + b"\x00")
            i += 1
    return b"".join(frames)


def snapshot_stream(n_links: int, n_counters: int, rng: np.random.Generator) -> bytes:
    out = []
    for c in range(n_counters):
        counts = rng.integers(-300, 300, size=(n_links, 3))
        words = pack_sample_words(counts, np.zeros(n_links, dtype=np.int64))
        for first in range(0, n_links, SNAP_MAX):
            k = min(SNAP_MAX, n_links - first)
            payload = (c & 0xFFFF).to_bytes(2, "little") + first.to_bytes(2, "little") + bytes([k]) \
                + words[first * 5:(first + k) * 5]
            out.append(encode_frame(MsgType.SNAPSHOT, 0, payload))
    return b"".join(out)


def run_stream(data: bytes, n_links: int, chunk: int, n_counters: int) -> dict:
    agg = Aggregator(n_links, deadline_s=1e9, queue_size=n_counters + 1)
    dec = StreamDecoder(batch_samples=True)
    t0 = time.perf_counter()
    for i in range(0, len(data), chunk):
        agg.ingest(dec.feed(data[i:i + chunk]), now=0.0)
    agg.flush(0.0)
    dt = time.perf_counter() - t0
    snaps = agg.drain()
    assert len(snaps) == n_counters and all(s.complete for s in snaps), (len(snaps), agg.stats.summary())
    return {"samples_per_s": round(n_links * n_counters / dt), "seconds": round(dt, 4),
            "snapshots_per_s": round(n_counters / dt, 1)}


def run_batches(data: bytes, n_links: int, chunk: int, n_counters: int) -> tuple[dict, dict]:
    dec = StreamDecoder(batch_samples=True)
    t0 = time.perf_counter()
    events = []
    for i in range(0, len(data), chunk):
        events.extend(dec.feed(data[i:i + chunk]))
    t_dec = time.perf_counter() - t0
    batches = [e for e in events if isinstance(e, SampleBatch)]
    agg = Aggregator(n_links, deadline_s=1e9, queue_size=n_counters + 1)
    t0 = time.perf_counter()
    for b in batches:
        agg.ingest_batch(b.node, b.counter, b.counts, b.status, now=0.0)
    agg.flush(0.0)
    t_agg = time.perf_counter() - t0
    assert agg.stats.complete == n_counters, agg.stats.summary()
    n = n_links * n_counters
    return ({"samples_per_s": round(n / t_agg), "seconds": round(t_agg, 4)},
            {"samples_per_s": round(n / t_dec), "seconds": round(t_dec, 4)})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--counters", type=int, default=0, help="counters per case (default: ~1M samples)")
    ap.add_argument("--chunk", type=int, default=1 << 16, help="bytes per decoder feed (a serial read)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    rng = np.random.Generator(np.random.MT19937(args.seed))
    results = {"chunk_bytes": args.chunk, "cases": {}}
    for spec in ("14x14", "32x32"):
        lat = Lattice.parse(spec)
        n = lat.n_links
        n_counters = args.counters or max(10, 1_000_000 // n)
        pc = per_chip_stream(n, n_counters, rng)
        snap = snapshot_stream(n, n_counters, rng)
        agg_only, dec_only = run_batches(pc, n, args.chunk, n_counters)
        results["cases"][spec] = {
            "n_links": n, "counters": n_counters,
            "per_chip": {"end_to_end": run_stream(pc, n, args.chunk, n_counters),
                         "aggregator_only": agg_only, "decoder_only": dec_only},
            "snapshot": {"end_to_end": run_stream(snap, n, args.chunk, n_counters)},
        }
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
