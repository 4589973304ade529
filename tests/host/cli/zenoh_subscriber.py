"""A Zenoh subscriber in its own process for tests/host/cli/test_publish.py: it knows only the
zenoh API and docs/distribution.md (its own decoding, not host.publish's). Prints one JSON line:
what it received and decoded, then exits: after SECONDS, or sooner when the test says what it waits
for, on stdin (the publisher has ended by then: what is still to come is what it had published):

* ``end``: nothing more (what the test asserts came while the publisher ran);
* ``until KIND=N[,KIND=N...]``: once a message of every KIND named (snapshot, estimate: their
  counter; contacts: its frame) numbered N or later has come.

    python zenoh_subscriber.py SHEET SECONDS MIN_ESTIMATES
"""

import json
import os
import struct
import sys
import threading
import time

import numpy as np
import zenoh

sheet, seconds, min_est = sys.argv[1], float(sys.argv[2]), int(sys.argv[3])
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
out = {"snapshot": [], "estimate": [], "contacts": [], "health": [], "bad": [], "info": None}
HDR = "<4sBBHHIHQdd"  # docs/distribution.md: 40 bytes


def on_sample(sample):
    key, data = str(sample.key_expr), bytes(sample.payload.to_bytes())
    kind = key.rsplit("/", 1)[-1]
    try:
        if kind in ("health", "contacts"):  # JSON
            assert sample.encoding == zenoh.Encoding.APPLICATION_JSON, f"{key}: encoding {sample.encoding}"
            out[kind].append(json.loads(data))
            return
        magic, ver, flags, rows, cols, n, _, counter, ts, wall = struct.unpack_from(HDR, data)
        o = struct.calcsize(HDR)
        if kind == "snapshot":
            assert magic == b"CSNP" and ver == 1 and len(data) == o + 14 * n
            g = np.frombuffer(data, "<f4", 3 * n, o).reshape(n, 3)
            valid = np.frombuffer(data, "u1", n, o + 12 * n)
            out["snapshot"].append({"counter": counter, "n": n, "rows": rows, "cols": cols,
                                    "valid": int(valid.sum()), "norm": float(np.median(np.linalg.norm(g[valid > 0], axis=1)))})
        elif kind == "estimate":
            assert magic == b"CEST" and ver == 1 and n == rows * cols
            j = np.frombuffer(data, "<f4", 3 * n, o).reshape(rows, cols, 3)
            std = np.frombuffer(data, "<f4", n, o + 12 * n) if flags & 1 else None
            assert len(data) == o + 12 * n + (4 * n if flags & 1 else 0)
            d = np.linalg.norm(np.diff(j, axis=1), axis=2)  # the lattice's links along a row
            out["estimate"].append({"counter": counter, "rows": rows, "cols": cols, "link_m": float(np.median(d)),
                                    "std": None if std is None else float(np.nanmax(std))})
    except Exception as exc:  # noqa: BLE001 - reported, the test fails on it
        out["bad"].append(f"{key}: {exc!r}")


told: dict = {}  # "end": True, or "until": {kind: number}


def read_stdin() -> None:
    for line in sys.stdin:
        word, _, rest = line.strip().partition(" ")
        if word == "end":
            told["end"] = True
        elif word == "until":
            told["until"] = {k: int(v) for k, v in (item.split("=", 1) for item in rest.split(","))}


def number(kind: str, item: dict) -> int:
    return item["frame"] if kind == "contacts" else item["counter"]


def done() -> bool:
    if told.get("end"):
        return True
    until = told.get("until")
    return bool(until) and all(any(number(k, x) >= n for x in list(out[k])) for k, n in until.items())


sub = session.declare_subscriber(f"capsheet/{sheet}/**", on_sample)
threading.Thread(target=read_stdin, daemon=True).start()
print("ready", flush=True)
end = time.monotonic() + seconds
while time.monotonic() < end and not done():
    if out["info"] is None and len(out["estimate"]) >= min_est:  # a late asker: after bring-up
        for reply in session.get(f"capsheet/{sheet}/info", timeout=5.0):
            if reply.ok is not None:
                out["info"] = json.loads(bytes(reply.ok.payload.to_bytes()))
    time.sleep(0.05)
sub.undeclare()
session.close()
print(json.dumps(out), flush=True)
