"""``capsheet view --config robot.toml``: several sheets' estimates, from Zenoh, in one live 3D scene.

    capsheet view --config robot.toml                # ws://localhost:8765 in Foxglove or Lichtblick

Every sheet the config names (docs/distribution.md "Several sheets in one view"; `host.publish.robot`) is
subscribed at ``capsheet/<sheet>/estimate`` (what its host, or an estimate worker, publishes) and drawn
in its own frame, named as the sheet, placed in the config's fixed frame (``world`` by default) by
its pose: ``/tf`` carries one `foxglove.FrameTransform` per sheet (about once a second), and each
sheet has ``/<sheet>/scene`` (the lattice, `foxglove.SceneUpdate`) and ``/<sheet>/joints``
(`foxglove.PointCloud`), as the one-sheet live view has ``/sheet/...`` (host/publish/live.py). In Foxglove:
a 3D panel, display frame the fixed frame. The newest estimate of each sheet is drawn up to
``--rate`` times per second; every one received is counted.

Every payload is checked before use (sizes, lattice, counts: `host.publish.zenoh_pub.decode_estimate`);
one that is not a sheet's estimate is counted and named in the summary, never drawn.

Exit status: 0 when every sheet of the config sent estimates, 1 when one never did (named), sent
only payloads that were refused, or when no Zenoh endpoint is reachable; 2 for a usage error or a
bad config (one line naming the key).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time

__all__ = ["register", "run"]

PROG = "capsheet view"
#: how often each sheet's transform is sent again (late clients get it), seconds
TF_PERIOD_S = 1.0


def register(subparsers) -> None:
    from host.cli import argtypes as T
    from host.cli.subscribe import add_zenoh_config_arg, subscribe_arg
    p = subparsers.add_parser("view", help="several sheets' estimates from Zenoh in one live 3D scene (robot.toml)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", required=True, metavar="ROBOT.toml",
                   help="the robot: [[sheet]] tables with name, translation (m) and rotation (quaternion x, y, z, w) "
                        "or rpy_deg; optional [view] frame, port, rate, endpoint (docs/distribution.md)")
    p.add_argument("--subscribe", metavar="zenoh[:ENDPOINT]", type=subscribe_arg, default=None,
                   help="where the estimates are: zenoh (peer mode on loopback only: 127.0.0.1, no multicast) or "
                        "zenoh:ENDPOINT (a router); default the config's [view] endpoint, else loopback only")
    p.add_argument("--port", type=T.tcp_port, default=None,
                   help="the live view's TCP port on localhost (default the config's, else 8765; 0: a free one)")
    p.add_argument("--rate", type=T.bounded_float(0.0, 1000.0, lo_open=True, unit="per s"), default=None,
                   help="scene updates per sheet per second (default the config's, else 20)")
    p.add_argument("--duration", type=T.duration, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("-q", "--quiet", action="store_true", help="only the summary at the end")
    add_zenoh_config_arg(p)
    from host.cli.record_args import add_live_server_args
    add_live_server_args(p, p)
    p.set_defaults(func=run)


def run(args) -> int:
    from host.publish.robot import load_robot
    try:
        robot = load_robot(args.config)
    except ValueError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    import foxglove
    import numpy as np
    from foxglove.channels import FrameTransformChannel

    from host.cli.record_args import live_options
    from host.cli.subscribe import open_session
    from host.publish.live import LiveServer, SceneChannels, log_frame_transform
    from host.publish.zenoh_pub import MAX_PAYLOAD_BYTES, decode_estimate
    from host.publish.zenoh_session import describe
    from protocol.lattice import Lattice

    endpoint = args.subscribe[1] if args.subscribe is not None else robot.endpoint
    port = args.port if args.port is not None else (robot.port if robot.port is not None else 8765)
    rate = args.rate or robot.rate or 20.0
    try:
        session = open_session(endpoint, getattr(args, "zenoh_config", None))
    except ValueError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 1
    context = foxglove.Context()
    # every channel before the server starts (`SceneChannels.use_lattice` says why): the lattice of
    # each sheet comes with its first estimate
    tf = FrameTransformChannel("/tf", context=context)
    poses = {p.name: p for p in robot.sheets}
    scenes = {p.name: SceneChannels(context, None, prefix=f"/{p.name}", frame_id=p.name, tf=tf)
              for p in robot.sheets}
    try:
        server = LiveServer(context, port=port, name="capsheet view", **live_options(args))
    except OSError as exc:
        session.close()
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 1

    def on_term(signum, frame):  # noqa: ARG001
        raise KeyboardInterrupt
    try:
        signal.signal(signal.SIGTERM, on_term)
    except ValueError:
        pass

    lock = threading.Lock()
    newest: dict[str, bytes] = {}
    received = {p.name: 0 for p in robot.sheets}
    drawn = {p.name: 0 for p in robot.sheets}
    not_estimated = {p.name: 0 for p in robot.sheets}
    bad = {p.name: 0 for p in robot.sheets}  # payloads refused: counted, the last reason kept
    last_bad: dict[str, str] = {}

    def on_sample(sample) -> None:  # Zenoh's thread: keep the newest only
        sheet = str(sample.key_expr).split("/")[1]
        size = len(sample.payload)
        with lock:
            received[sheet] += 1
            if size > MAX_PAYLOAD_BYTES:  # refused before it is copied
                bad[sheet] += 1
                last_bad[sheet] = f"a payload of {size} bytes, more than the largest sheet's {MAX_PAYLOAD_BYTES}"
                return
        data = bytes(sample.payload.to_bytes())
        with lock:
            newest[sheet] = data

    subs = [session.declare_subscriber(f"capsheet/{p.name}/estimate", on_sample) for p in robot.sheets]
    print(f"{PROG}: {len(robot.sheets)} sheets ({', '.join(poses)}) in frame {robot.frame}, from Zenoh "
          f"({describe(endpoint, getattr(args, 'zenoh_config', None))}); live 3D view on {server.url} (Foxglove: Open connection -> "
          f"Foxglove WebSocket -> {server.url}; a 3D panel, display frame {robot.frame})", file=sys.stderr, flush=True)
    t0 = time.monotonic()
    end = None if args.duration is None else t0 + args.duration
    last_tf = -np.inf
    interrupted = False
    try:
        while end is None or time.monotonic() < end:
            time.sleep(1.0 / rate)
            now_ns = time.time_ns()
            if time.monotonic() - last_tf >= TF_PERIOD_S:
                last_tf = time.monotonic()
                for p in robot.sheets:
                    log_frame_transform(tf, now_ns, robot.frame, p.name, p.translation, p.rotation)
            with lock:
                batch = list(newest.items())
                newest.clear()
            for sheet, payload in batch:
                try:  # sizes, lattice and counts checked before anything is allocated or drawn
                    e = decode_estimate(payload)
                except ValueError as exc:
                    bad[sheet] += 1
                    last_bad[sheet] = str(exc)
                    continue
                if not e["estimated"]:
                    not_estimated[sheet] += 1
                    continue
                sc = scenes[sheet]
                if sc.lattice is None or (sc.lattice.rows, sc.lattice.cols) != (e["rows"], e["cols"]):
                    sc.use_lattice(Lattice(e["rows"], e["cols"]))
                J = np.asarray(e["joints"], dtype=float)
                ends = np.asarray(sc.lattice.endpoints)
                ok = np.isfinite(J.reshape(-1, 3)).all(axis=1)
                sc.log_lattice(J, ok[ends[:, 0]] & ok[ends[:, 1]], now_ns)
                drawn[sheet] += 1
    except KeyboardInterrupt:
        interrupted = True
    finally:
        for s in subs:
            s.undeclare()
        session.close()
        server.stop()
    code = 0
    for p in robot.sheets:
        n = received[p.name]
        line = (f"{PROG}: sheet {p.name}: {n} estimates received, {drawn[p.name]} drawn"
                + (f", {not_estimated[p.name]} not estimated by their worker" if not_estimated[p.name] else "")
                + (f", {bad[p.name]} bad payload(s) refused (the last: {last_bad[p.name]})" if bad[p.name] else ""))
        if n == 0:
            line += f" -- nothing from capsheet/{p.name}/estimate (its host or worker not running?)"
            code = 1
        elif bad[p.name] and not drawn[p.name]:
            line += " -- none could be drawn"
            code = 1
        print(line, file=sys.stderr)
    print(f"{PROG}: {time.monotonic() - t0:.1f} s{' (interrupted)' if interrupted else ''}, "
          f"{server.connections} client connection(s)", file=sys.stderr)
    return code

