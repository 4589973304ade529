"""The recorder's compression at 64x64: what each zstd level and worker-thread setting costs the
threads that log, and how long one logging call holds the interpreter lock.

The input is the wire output of a 64x64 virtual sheet sending packed SNAPSHOTs (`Gateway.pop_wire`
per SYNC, as five gateways' reads: each SYNC's bytes cut in five), logged with `Recorder.raw` into a
real recording, one call per read, 145 reads per port and second of data. Beside the logging
thread a second thread sleeps 1 ms at a time and notes how late it wakes: a logging call that
holds the interpreter lock keeps it waiting (what the host's SYNC thread does).

    .venv/bin/python benchmarks/bench_record_compression.py            # JSON on stdout
    .venv/bin/python benchmarks/bench_record_compression.py --seconds 2

Per setting: ``log_ms_per_s`` (time in the logging calls per second of data: the share of a core
they take from the logging threads, with the interpreter lock held), ``max_call_ms``,
``calls_over_2ms``, the sleeper's ``max_wait_ms`` and the file's size over the input's.
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

import numpy as np  # noqa: E402

from host.record.recording import Recorder, compression_level_for  # noqa: E402
from protocol.framing import encode  # noqa: E402
from protocol.lattice import Lattice  # noqa: E402
from protocol.messages import Sync  # noqa: E402
from bench_virtual import RATE_HZ, Rig  # noqa: E402  (benchmarks/, this script's folder)

PORTS = 5
#: (zstd level, worker threads): the settings compared; the first was capsheet's default before
#: the 64x64 sheet's work, the last is its default for a sheet this size
SETTINGS = [(9, 1), (9, 0), (3, 1), (3, 0), (1, 0)]


def wire_reads(lattice: str, n_syncs: int) -> list[bytes]:
    """The gateway's output for ``n_syncs`` SYNCs at `RATE_HZ`, each cut in `PORTS` reads (a
    commissioned, streaming sheet: `bench_virtual.Rig`)."""
    rig = Rig(lattice, True, "array")
    gw, t, reads = rig.gw, rig.t, []
    for k in range(n_syncs):
        t += 1 / RATE_HZ
        gw.feed(encode(Sync(counter=(rig.counter + k) & 0xFFFF)), t)
        gw.poll(t)
        data, _ = gw.pop_wire(t)
        cut = np.linspace(0, len(data), PORTS + 1).astype(int)
        reads += [data[a:b] for a, b in zip(cut[:-1], cut[1:])]
    return reads


def measure(reads: list[bytes], lattice: Lattice, level: int, threads: int, seconds: float) -> dict:
    waits: list[float] = []
    stop = threading.Event()

    def sleeper():
        while not stop.is_set():
            a = time.perf_counter()
            time.sleep(0.001)
            waits.append(time.perf_counter() - a - 0.001)

    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "r.mcap")
        rec = Recorder(path, lattice, 0.01, compression_level=level, compression_threads=threads)
        th = threading.Thread(target=sleeper, daemon=True)
        th.start()
        calls, n_in = [], 0
        n = int(seconds * RATE_HZ * PORTS)
        for i in range(n):
            data = reads[i % len(reads)]
            a = time.perf_counter()
            rec.raw(i % PORTS, "serial", data)
            calls.append(time.perf_counter() - a)
            n_in += len(data)
            if i % PORTS == PORTS - 1:
                time.sleep(0.001)  # the sleeper gets the lock between SYNCs
        rec.close()
        stop.set()
        th.join()
        size = os.path.getsize(path)
    c = np.array(calls) * 1e3
    return {"zstd_level": level, "compression_threads": threads,
            "log_ms_per_s": round(float(c.sum()) / seconds, 1), "max_call_ms": round(float(c.max()), 2),
            "calls_over_2ms": int((c > 2).sum()), "max_wait_ms": round(1e3 * max(waits), 2),
            "input_mb_per_s": round(n_in / seconds / 1e6, 2), "size_ratio": round(size / n_in, 3)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lattice", default="64x64")
    ap.add_argument("--seconds", type=float, default=4.0, help="seconds of data per setting (default 4)")
    args = ap.parse_args(argv)
    if not args.seconds > 0:
        ap.error(f"--seconds must be > 0, not {args.seconds}")
    sys.setswitchinterval(0.0005)  # as capsheet host
    try:
        lattice = Lattice.parse(args.lattice)
    except ValueError as e:
        ap.error(str(e))
    load0 = os.getloadavg()
    reads = wire_reads(args.lattice, 145)
    rows = [measure(reads, lattice, level, threads, args.seconds) for level, threads in SETTINGS]
    print(json.dumps({"lattice": args.lattice, "ports": PORTS, "rate_hz": RATE_HZ,
                      "default_level": compression_level_for(lattice.n_links), "rows": rows,
                      "loadavg_before": [round(x, 2) for x in load0],
                      "loadavg": [round(x, 2) for x in os.getloadavg()]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
