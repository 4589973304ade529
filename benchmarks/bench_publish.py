"""The cost of ``--publish zenoh`` on the host's receive thread: encoding a snapshot
(`host.publish.encode_snapshot`) and one ``Publisher.put`` in peer mode on loopback, with one
subscriber process-local peer listening (so the put goes to a transport, not to nothing), per
lattice size. Prints JSON: microseconds per snapshot (median of ``--n`` puts) and payload bytes.

    .venv/bin/python benchmarks/bench_publish.py [--n 2000]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from host.aggregator import LatticeSnapshot  # noqa: F401 -- the type the encoder reads
from host.publish import ZenohPublisher, encode_snapshot, zenoh_config
from protocol.lattice import Lattice


class Snap:  # the fields encode_snapshot reads, as a LatticeSnapshot has them
    def __init__(self, n, rng):
        self.counter, self.timestamp, self.wall_time = 1, 1.0, time.time()
        self.readings = rng.normal(size=(n, 3))
        self.valid = np.ones(n, bool)
        self.status = np.zeros(n, np.uint8)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=2000)
    args = ap.parse_args()
    import zenoh
    rng = np.random.default_rng(1)
    sub_session = zenoh.open(zenoh_config(None))
    got = [0]
    out = {}
    for size in ("14x14", "32x32", "64x64"):
        lat = Lattice.parse(size)
        name = f"bench{size}"
        sub = sub_session.declare_subscriber(f"capsheet/{name}/snapshot", lambda s: got.__setitem__(0, got[0] + 1))
        pub = ZenohPublisher(name, None, lat, 0.01)
        time.sleep(2.0)  # discovery
        snap = Snap(lat.n_links, rng)
        enc, put = [], []
        for k in range(args.n):
            snap.counter = k
            t0 = time.perf_counter()
            encode_snapshot(snap, lat.rows, lat.cols)
            t1 = time.perf_counter()
            pub.snapshot(snap)
            t2 = time.perf_counter()
            enc.append(t1 - t0)
            put.append(t2 - t1)
        time.sleep(1.0)
        out[size] = {"links": lat.n_links, "bytes": len(encode_snapshot(snap, lat.rows, lat.cols)),
                     "encode_us_median": round(1e6 * float(np.median(enc)), 1),
                     "encode_and_put_us_median": round(1e6 * float(np.median(put)), 1),
                     "encode_and_put_us_p99": round(1e6 * float(np.percentile(put, 99)), 1),
                     "published": args.n, "received_by_subscriber": got[0]}
        got[0] = 0
        pub.close()
        sub.undeclare()
    sub_session.close()
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
