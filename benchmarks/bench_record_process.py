"""What recording a 64x64 sheet costs the host's process, written there (`Recorder`) or by a process of
its own (`RecorderProcess`, docs/recording.md "A writer process"), and what the writer process costs.

The input is a packed sheet's wire output per SYNC cut in five reads, as five gateways' ports deliver
it (`bench_record_compression.wire_reads`), and the snapshots an aggregator makes of it; per SYNC
the recorder gets the SYNC, the five reads (each stamped as a host's ingest stamps it) and the
snapshot, as ``capsheet host --record`` hands them over. ``host_ms_per_sync`` is this process's CPU
(``time.process_time``) in those calls, the best of ``--rounds``; ``writer_ms_per_sync`` the writer
process's CPU over the same SYNCs (/proc, from its start-up's end to its end: its file's close
included), the best round's.

    .venv/bin/python benchmarks/bench_record_process.py            # JSON on stdout
    .venv/bin/python benchmarks/bench_record_process.py --syncs 300 --rounds 2
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from bench_record_compression import PORTS, wire_reads  # noqa: E402  (benchmarks/, this script's folder)
from host.record.recording import Recorder  # noqa: E402
from host.record.writer_process import RecorderProcess  # noqa: E402
from host.snapshots.aggregator import Aggregator  # noqa: E402
from protocol.framing import StreamDecoder  # noqa: E402
from protocol.lattice import Lattice  # noqa: E402


def _ticks(pid: int) -> int | None:
    try:
        f = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return int(f[11]) + int(f[12])


def session(lattice: Lattice, n: int):
    reads = wire_reads(f"{lattice.rows}x{lattice.cols}", n)
    dec = StreamDecoder(batch_samples=True, batch_status=True, batch_snapshots=True)
    agg = Aggregator(lattice.n_links, deadline_s=1e9, queue_size=n + 8, n_buses=PORTS)
    for i, r in enumerate(reads):
        agg.ingest(dec.feed(r), i % PORTS, now=i / (PORTS * 145.0))
    return reads, agg.drain()


def one_round(cls, path: str, lattice: Lattice, reads, snaps) -> tuple[float, float | None, int]:
    rec = cls(path, lattice, 0.02)
    pid = getattr(rec, "pid", None)
    w0 = _ticks(pid) if pid else None
    t0 = time.process_time()
    for c, snap in enumerate(snaps):
        rec.sync(c, c / 145.0)
        for j in range(PORTS):
            rec.raw(j, "serial", reads[PORTS * c + j], t=c / 145.0 + 0.001 * j, log_time_ns=c, t_rx=c / 145.0)
        rec.snapshot(snap)
    host = time.process_time() - t0
    last = [w0]
    if pid:  # the writer's CPU, read until it ends (its close included)
        closing = threading.Thread(target=rec.close)
        closing.start()
        while closing.is_alive():
            t = _ticks(pid)
            if t is not None:
                last[0] = t
            time.sleep(0.005)
    else:
        rec.close()
    writer = None if pid is None else (last[0] - w0) / os.sysconf("SC_CLK_TCK")
    return host, writer, os.path.getsize(path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lattice", default="64x64")
    ap.add_argument("--syncs", type=int, default=600, help="SYNCs per round (default 600)")
    ap.add_argument("--rounds", type=int, default=3, help="rounds per way (default 3)")
    args = ap.parse_args(argv)
    if args.syncs < 10 or args.rounds < 1:
        ap.error("need --syncs >= 10 and --rounds >= 1")
    try:
        lattice = Lattice.parse(args.lattice)
    except ValueError as e:
        ap.error(str(e))
    load0 = os.getloadavg()
    reads, snaps = session(lattice, args.syncs)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for name, cls in (("in the host's process", Recorder), ("writer process", RecorderProcess)):
            best = None
            for k in range(args.rounds):
                r = one_round(cls, os.path.join(d, f"{cls.__name__}{k}.mcap"), lattice, reads, snaps)
                if best is None or r[0] < best[0]:
                    best = r
            host, writer, size = best
            rows.append({"way": name, "host_ms_per_sync": round(1e3 * host / len(snaps), 3),
                         "writer_ms_per_sync": None if writer is None else round(1e3 * writer / len(snaps), 3),
                         "file_mb": round(size / 1e6, 2)})
    print(json.dumps({"lattice": args.lattice, "ports": PORTS, "syncs": len(snaps), "rows": rows,
                      "loadavg_before": [round(x, 2) for x in load0],
                      "loadavg": [round(x, 2) for x in os.getloadavg()]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
