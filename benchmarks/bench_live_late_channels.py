"""Channels made while a live-view client is connected: how many sessions would lose one.

foxglove-sdk advertises such a channel before it records it as advertised to the client, so a
subscribe sent at once can be answered "Unknown channel ID" and dropped (host/publish/ws_frames.py).
Each session: a `host.publish.live.LiveServer`, the npm `@foxglove/ws-protocol` client under node
(tests/host/publish/node/ws_protocol_client.js) connecting, 4 channels made 0-0.4 s later (seeded),
each logged at 20 Hz until the client has 3 messages of each. Run twice in the same run: the relay
as it is (it sends such a subscribe again) and with that repair switched off (the relay before),
where a session counts as lost when the client was told "Unknown channel ID" (the client itself then
subscribes again, so that it ends). Prints JSON.

    .venv/bin/python benchmarks/bench_live_late_channels.py [--sessions 40] [--seed 1]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import foxglove  # noqa: E402
from foxglove.messages import SceneUpdate  # noqa: E402

from host.publish import ws_frames  # noqa: E402
from host.publish.live import LiveServer  # noqa: E402
from tests.host.publish.test_live_node import CLIENT_JS, NODE_MODULES  # noqa: E402


def session(rng: random.Random) -> tuple[bool, int, bool]:
    """(client told "Unknown channel ID", subscribes the relay sent again, client got everything)."""
    ctx = foxglove.Context()
    srv = LiveServer(ctx, port=0)
    topics = [f"/s{i}/scene" for i in range(4)]
    cl = subprocess.Popen(["node", str(CLIENT_JS), srv.url, json.dumps(topics), "3", "10"], stdout=subprocess.PIPE,
                          text=True, env=dict(os.environ, NODE_PATH=str(NODE_MODULES)))
    time.sleep(rng.uniform(0.0, 0.4))
    chans = []
    for t in topics:
        chans.append(foxglove.Channel(t, message_encoding="protobuf", schema=SceneUpdate.get_schema(), context=ctx))
        time.sleep(rng.uniform(0.0, 0.01))
    end = time.monotonic() + 11
    while cl.poll() is None and time.monotonic() < end:
        for c in chans:
            if c.has_sinks():
                c.log(b"", log_time=time.time_ns())
        time.sleep(0.05)
    out, _ = cl.communicate(timeout=15)
    srv.stop()
    doc = json.loads(out.strip().splitlines()[-1])
    return bool(doc["resubscribed"]), srv.relay.resubscribed, cl.returncode == 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    res = {}
    repair = ws_frames.SubscribeRepair.from_server
    for name in ("relay_before", "relay"):
        ws_frames.SubscribeRepair.from_server = repair if name == "relay" else (lambda self, text, now: True)
        rng = random.Random(args.seed)
        told = resent = ended = 0
        for _ in range(args.sessions):
            t, r, ok = session(rng)
            told, resent, ended = told + t, resent + r, ended + ok
        res[name] = {"sessions": args.sessions, "told_unknown_channel": told, "relay_resubscribed": resent,
                     "client_got_everything": ended}
    ws_frames.SubscribeRepair.from_server = repair
    res["loadavg"] = os.getloadavg()[0]
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
