"""What reading the frames costs the live view's relay (`host.publish.ws_frames.FrameStream`, which
lets it send again a subscribe foxglove-sdk could not place): the server's stream of a 64x64 live
view — one binary message per scene (~450 kB: 16,128 line ends, their colours) and a small text
frame now and then — fed in the 64 KiB reads the relay makes, against passing the same reads on
untouched (the relay before), in the same run. Prints JSON: MB/s and µs per scene.

    .venv/bin/python benchmarks/bench_relay_frames.py [--scenes 400] [--scene-bytes 450000]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from websockets.frames import Frame, Opcode  # noqa: E402

from host.publish.ws_frames import FrameStream  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=400)
    ap.add_argument("--scene-bytes", type=int, default=450_000)
    args = ap.parse_args(argv)
    scene = Frame(Opcode.BINARY, bytes(args.scene_bytes)).serialize(mask=False)
    status = Frame(Opcode.TEXT, b'{"op":"status","level":0,"message":"ok"}').serialize(mask=False)
    stream = b"".join(scene + (status if k % 50 == 0 else b"") for k in range(args.scenes))
    reads = [stream[i:i + (1 << 16)] for i in range(0, len(stream), 1 << 16)]
    out = {}
    for name in ("untouched", "frames_read"):
        fs = FrameStream()
        t0 = time.perf_counter()
        n = 0
        for r in reads:
            if name == "untouched":
                n += len(r)
            else:
                got = fs.feed(r)
                n += len(got[0][1] if len(got) == 1 else b"".join(raw for _, raw in got))
        dt = time.perf_counter() - t0
        assert n == len(stream)
        out[name] = {"mb_per_s": round(len(stream) / dt / 1e6, 1), "us_per_scene": round(dt / args.scenes * 1e6, 1)}
    out["scene_bytes"], out["scenes"], out["loadavg"] = args.scene_bytes, args.scenes, os.getloadavg()[0]
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
