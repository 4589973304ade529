"""A Zenoh subscriber in its own process for tests/host/cli/test_estimate_workers.py: it knows only the
zenoh API and docs/distribution.md (its own decoding, not host.publish's). It takes every snapshot
and every estimate of the sheets named, and prints one JSON line (per sheet, the snapshot counters
and the estimates decoded) when the test says what it waits for and it came: a line ``expect
SHEET=N[,SHEET=N...]`` on stdin (each sheet's hosts published N snapshots, so N estimates are due)
ends it once every sheet named has N estimates. Else, or before, it ends when none came for IDLE
seconds after the first, or SECONDS passed (an estimate that never comes fails the test at its
counts, as before).

    python estimate_checker.py SHEET[,SHEET...] SECONDS IDLE
"""

import json
import os
import struct
import sys
import threading
import time

import numpy as np
import zenoh

sheets, seconds, idle = sys.argv[1].split(","), float(sys.argv[2]), float(sys.argv[3])
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
# docs/distribution.md: without multicast, the machine's sessions meet at tcp/127.0.0.1:7447
conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0", "tcp/127.0.0.1:7447#exit_on_failure=false"]')
conf.insert_json5("connect/endpoints", '["tcp/127.0.0.1:7447"]')
conf.insert_json5("scouting/multicast/enabled", "false")
# ZENOH_CONFIG_OVERRIDE (rmw_zenoh's key=value;... pairs, docs/distribution.md), applied last as capsheet
# applies it: where the test run's sessions meet (tests/zenoh_meeting.py)
for item in filter(None, os.environ.get("ZENOH_CONFIG_OVERRIDE", "").split(";")):
    conf.insert_json5(*(s.strip() for s in item.split("=", 1)))
session = zenoh.open(conf)
HDR = "<4sBBHHIHQdd"
O = struct.calcsize(HDR)
out = {s: {"snapshot": [], "estimate": []} for s in sheets}
bad: list = []
lock = threading.Lock()
last = [None]


def on_sample(sample):
    key, data = str(sample.key_expr), bytes(sample.payload.to_bytes())
    _, sheet, kind = key.split("/")
    try:
        magic, ver, flags, rows, cols, n, _, counter, ts, wall = struct.unpack_from(HDR, data)
        if kind == "snapshot":
            # flags: bit 0 gyro float32 (n, 3), bit 1 mag float32 (n, 3), bit 2 sample time float32 (n,)
            size = O + 14 * n + (12 * n if flags & 1 else 0) + (12 * n if flags & 2 else 0) + (4 * n if flags & 4 else 0)
            assert magic == b"CSNP" and ver == 1 and len(data) == size, key
            gyro = np.frombuffer(data, "<f4", 3 * n, O + 14 * n).reshape(n, 3) if flags & 1 else None
            rec = {"counter": counter, "flags": flags,
                   "gyro_max": None if gyro is None else float(np.nanmax(np.abs(gyro)))}
        else:
            assert magic == b"CEST" and ver == 1 and n == rows * cols, key
            assert len(data) == O + 12 * n + (4 * n if flags & 1 else 0), key
            j = np.frombuffer(data, "<f4", 3 * n, O).reshape(rows, cols, 3)
            estimated = not flags & 2
            link = float(np.median(np.linalg.norm(np.diff(j, axis=1), axis=2))) if estimated else None
            rec = {"counter": counter, "estimated": estimated, "link_m": link, "rows": rows, "cols": cols,
                   "finite": bool(np.isfinite(j).all())}
        with lock:
            out[sheet][kind].append(rec)
            last[0] = time.monotonic()
    except Exception as exc:  # noqa: BLE001 - reported, the test fails on it
        bad.append(f"{key}: {exc!r}")


expected: dict = {}


def read_expectations() -> None:
    """``expect SHEET=N,...`` lines on stdin, until it closes."""
    for line in sys.stdin:
        if line.startswith("expect "):
            pairs = dict(item.split("=", 1) for item in line.split(None, 1)[1].strip().split(","))
            with lock:
                expected.update({k: int(v) for k, v in pairs.items()})


subs = [session.declare_subscriber(f"capsheet/{s}/{k}", on_sample) for s in sheets for k in ("snapshot", "estimate")]
threading.Thread(target=read_expectations, daemon=True).start()
print("ready", flush=True)
end = time.monotonic() + seconds
while time.monotonic() < end:
    with lock:
        if expected and all(len(out[s]["estimate"]) >= n for s, n in expected.items()):
            break
        if last[0] is not None and time.monotonic() - last[0] >= idle:
            break
    time.sleep(0.05)
for s in subs:
    s.undeclare()
session.close()
print(json.dumps({"sheets": out, "bad": bad}), flush=True)
