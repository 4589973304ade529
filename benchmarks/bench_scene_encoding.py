"""The 3D scene's lattice at 64x64: `host.publish.live.SceneChannels.log_lattice` as it is (the line list's
SceneUpdate bytes made with numpy, `host.publish.live._LineListScene`) against the SDK's objects it replaced
(one `Point3` and one `Color` per line end, `tests.host.publish.test_scene_encoding.object_log_lattice`),
each into an MCAP sink, in the same run. Every call holds the interpreter lock the host's receive
and SYNC threads need. Prints JSON: the median of ``--calls`` calls per colouring.

    .venv/bin/python benchmarks/bench_scene_encoding.py [--lattice 64x64] [--calls 20]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import foxglove  # noqa: E402
import numpy as np  # noqa: E402
from foxglove.channels import SceneUpdateChannel  # noqa: E402

from host.publish.live import SceneChannels  # noqa: E402
from protocol.lattice import Lattice  # noqa: E402
from tests.host.publish.test_scene_encoding import T_NS, object_log_lattice, sample  # noqa: E402


def median_ms(lat: Lattice, colour_by: str, objects: bool, n_calls: int) -> float:
    J, valid, error, _ = sample(lat, 11)
    ctx = foxglove.Context()
    with tempfile.TemporaryDirectory() as d, foxglove.open_mcap(os.path.join(d, "t.mcap"), context=ctx):
        sc = SceneChannels(ctx, lat, colour_by=colour_by)
        if objects:
            sc.scene = SceneUpdateChannel("/sheet/scene_objects", context=ctx)

            def call(t):
                object_log_lattice(sc, J, valid, t, error=error)
        else:
            def call(t):
                sc.log_lattice(J, valid, t, error=error)
        for k in range(3):  # warm-up
            call(T_NS + k)
        ts = []
        for k in range(n_calls):
            t0 = time.perf_counter()
            call(T_NS + 3 + k)
            ts.append(time.perf_counter() - t0)
    return round(float(np.median(ts)) * 1e3, 2)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lattice", default="64x64", help="joints, ROWSxCOLS (default 64x64)")
    ap.add_argument("--calls", type=int, default=20, help="timed calls per case (default 20)")
    args = ap.parse_args(argv)
    if args.calls < 1:
        ap.error(f"--calls must be >= 1, not {args.calls}")
    try:
        lat = Lattice.parse(args.lattice)
    except ValueError as e:
        ap.error(str(e))
    rows = [{"colour_by": c, "numpy_ms": median_ms(lat, c, False, args.calls),
             "sdk_objects_ms": median_ms(lat, c, True, args.calls)} for c in ("links", "error")]
    print(json.dumps({"lattice": args.lattice, "calls": args.calls, "rows": rows,
                      "loadavg": [round(x, 2) for x in os.getloadavg()]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
