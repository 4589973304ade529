"""The host's ingest at 64x64: a packed sheet's wire bytes through the stream decoder
and the aggregator, with the compiled scan (protocol/_kernel/stream.c) and without, in one run.

The input is the wire output of a virtual sheet whose gateway sends packed SNAPSHOTs and passes its
chips' STATUS heartbeats on (`bench_virtual.Rig`; `Gateway.pop_wire` per SYNC, each SYNC's bytes cut
in five reads, as five gateways' ports deliver them). Three ways are timed on the same reads:

* ``before``: the Python decoder the host ran until the scan was compiled:
  numpy per fast frame kind, one `Snapshot` object per SNAPSHOT frame (`decode_frame`),
  `unpack_snapshots` in the aggregator (with today's `StreamDecoder.feed`, which decodes a held
  partial frame and the read after it in one pass: the old feed took 1.65 ms per SYNC here);
* ``python``: the same code with ``batch_snapshots`` (runs of SNAPSHOT as one `SnapshotFrames`):
  what a host without a C compiler runs now;
* ``compiled``: the compiled scan, what a host runs now.

Each reports CPU ms per SYNC for the decoder alone and for decoder + aggregator (every snapshot
complete), and the share of one core that is at 145 SYNC/s; best of ``--rounds``.

    .venv/bin/python benchmarks/bench_ingest.py                 # 64x64, JSON on stdout
    .venv/bin/python benchmarks/bench_ingest.py --lattice 32x32 --syncs 100
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from host.snapshots.aggregator import Aggregator  # noqa: E402
from protocol.framing import NATIVE_SCAN, StreamDecoder  # noqa: E402
from protocol.lattice import Lattice  # noqa: E402
from bench_record_compression import PORTS, wire_reads  # noqa: E402  (benchmarks/, this script's folder)
from bench_virtual import RATE_HZ  # noqa: E402

WAYS = {"before": dict(batch_snapshots=False, native=False),
        "python": dict(batch_snapshots=True, native=False),
        "compiled": dict(batch_snapshots=True, native=True)}


def decoder(way: str) -> StreamDecoder:
    return StreamDecoder(batch_samples=True, batch_status=True, **WAYS[way])


def time_decoder(reads: list[bytes], way: str) -> float:
    dec = decoder(way)
    t0 = time.process_time()
    for r in reads:
        dec.feed(r)
    return time.process_time() - t0


def time_ingest(reads: list[bytes], way: str, n_links: int, n_syncs: int) -> tuple[float, int]:
    dec = decoder(way)
    agg = Aggregator(n_links, deadline_s=1e9, queue_size=n_syncs + 8, n_buses=PORTS)
    t0 = time.process_time()
    for i, r in enumerate(reads):
        agg.ingest(dec.feed(r), i % PORTS, now=0.0)
    agg.flush(0.0)
    dt = time.process_time() - t0
    return dt, sum(1 for s in agg.drain() if s.complete)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lattice", default="64x64", help="joints ROWSxCOLS (default 64x64)")
    ap.add_argument("--syncs", type=int, default=200, help="SYNCs of input (default 200)")
    ap.add_argument("--rounds", type=int, default=5, help="rounds; the best of each way is reported (default 5)")
    args = ap.parse_args(argv)
    try:
        lat = Lattice.parse(args.lattice)
    except ValueError as exc:
        ap.error(str(exc))
    if args.syncs < 2 or args.rounds < 1:
        ap.error("--syncs must be at least 2 and --rounds at least 1")
    ways = [w for w in WAYS if w != "compiled" or NATIVE_SCAN]
    reads = wire_reads(args.lattice, args.syncs)
    best = {w: {"decoder": float("inf"), "ingest": float("inf")} for w in ways}
    complete = {}
    for _ in range(args.rounds):
        for w in ways:
            best[w]["decoder"] = min(best[w]["decoder"], time_decoder(reads, w))
            dt, complete[w] = time_ingest(reads, w, lat.n_links, args.syncs)
            best[w]["ingest"] = min(best[w]["ingest"], dt)
    out = {"lattice": args.lattice, "links": lat.n_links, "syncs": args.syncs, "reads_per_sync": PORTS,
           "bytes_per_sync": round(sum(map(len, reads)) / args.syncs), "rate_hz": RATE_HZ,
           "compiled_scan_built": NATIVE_SCAN, "ways": {}}
    for w in ways:
        dec_ms, ing_ms = (1e3 * best[w][k] / args.syncs for k in ("decoder", "ingest"))
        out["ways"][w] = {"decoder_ms_per_sync": round(dec_ms, 3), "ingest_ms_per_sync": round(ing_ms, 3),
                          "ingest_core_pct_at_rate": round(ing_ms * RATE_HZ / 10, 1),
                          "complete_snapshots": complete[w]}
    if NATIVE_SCAN:
        b, c = out["ways"]["before"], out["ways"]["compiled"]
        out["ingest_speedup_compiled_vs_before"] = round(b["ingest_ms_per_sync"] / c["ingest_ms_per_sync"], 2)
        out["decoder_speedup_compiled_vs_before"] = round(b["decoder_ms_per_sync"] / c["decoder_ms_per_sync"], 2)
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
