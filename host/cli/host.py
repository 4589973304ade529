"""``capsheet host``: connect to a sheet, discover and assign its chips, stream, show a live status
line and record snapshots (docs/host.md).

    capsheet host --port /dev/pts/5 --lattice 14x14 --layout sheet.csv --rate 100 --record run.mcap --live
    capsheet host --can virtual:bus0 --can virtual:bus1 --lattice 14x14 --duration 10
    capsheet host --can slcan:/dev/pts/6 --bitrate 1000000 --auto-assign

The Python API is `host.session.Host` (re-exported here).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time

from host.session import Host, Layout
from host.cli.record_args import SessionOutputs, add_record_args
from host.cli.transport_args import add_transport_args, open_transports
from host.transport import TransportError

__all__ = ["register", "run", "Host", "Layout", "open_transports"]


def register(subparsers) -> None:
    p = subparsers.add_parser("host", help="talk to a sheet: discover, assign, stream, record",
                              description=__doc__.split("\n\n")[0],
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    add_transport_args(p, title="transports (one --port, or one or more --can)")
    p.add_argument("--lattice", default="14x14", help="joints ROWSxCOLS (default 14x14)")
    p.add_argument("--layout", help="uid -> link file (CSV 'uid,link' or JSON; docs/host.md)")
    p.add_argument("--auto-assign", action="store_true",
                   help="without --layout: place chips on links in uid order (positions arbitrary)")
    p.add_argument("--rate", type=float, default=100.0, help="SYNC rate in Hz (default 100)")
    p.add_argument("--sync", choices=("drive", "follow"), default="drive",
                   help="drive SYNC from the host (default) or follow a gateway's SYNC")
    p.add_argument("--deadline-ms", type=float, default=None, help="wait this long for missing links")
    p.add_argument("--calibration", metavar="CAL_JSON",
                   help="apply this calibration (capsheet calibrate) to every snapshot, and check chip "
                        "health on still stretches (docs/calibration.md)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--discover-s", type=float, default=0.5, help="discovery window per round (s)")
    p.add_argument("--json", action="store_true", help="print the final statistics as JSON")
    p.add_argument("-q", "--quiet", action="store_true", help="no live status line")
    add_record_args(p, can_log=True, link_length=True)  # --record --live --live-rate --can-log --link-length
    p.set_defaults(func=run)


def _status_line(host: Host, t0: float, n0: int) -> str:
    st = host.aggregator.stats
    dt = max(1e-9, time.monotonic() - t0)
    rate = (st.emitted - n0) / dt
    done = st.complete / max(1, st.emitted)
    errors = sum(t.stats.error_count for t in host.transports)
    return (f"\r{st.emitted:7d} snapshots {rate:7.1f}/s  complete {100 * done:5.1f}%  "
            f"late {st.late}  dup {st.duplicates}  unknown {st.unknown}  dropped {st.dropped}  "
            f"errors {errors}  silent {len(host.silent_links)}   ")


def run(args) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    layout = Layout.load(args.layout) if args.layout else None
    from host.cli.calibrate import load_calibration_arg, snapshot_corrector
    cal = load_calibration_arg(args.calibration, args.lattice, "capsheet host")
    if layout is None and not args.auto_assign:
        print("capsheet host: no --layout given; auto-assigning chips in uid order (positions arbitrary). "
              "Pass --auto-assign to silence this.", file=sys.stderr)
    try:
        transports = open_transports(args)
    except TransportError as exc:
        print(f"capsheet host: {exc}", file=sys.stderr)
        return 1
    host = Host(transports, args.lattice, layout=layout, rate_hz=args.rate, sync=args.sync,
                deadline_s=None if args.deadline_ms is None else args.deadline_ms / 1000)
    out = SessionOutputs(args, host.lattice, args.link_length, mode="host", colour_by="links",
                         prog="capsheet host")
    out.attach(host)
    writer = out if out.active else None
    stats: dict | None = None
    try:
        with host:
            summary = host.bring_up(args.discover_s)
            print(f"capsheet host: {summary['discovered']} chips found, {summary['assigned']} assigned, "
                  f"{summary['configured']} configured, {summary['calibrated']} calibrated, "
                  f"{summary['started']} started on {', '.join(t.name for t in transports)}", file=sys.stderr)
            if cal is not None:
                from host.health import HealthChecker
                host.snapshot_filter = snapshot_corrector(host, cal)
                host.health = HealthChecker(host.lattice.rows, host.lattice.cols)
            out.describe(host)
            t0, n0, last = time.monotonic(), host.aggregator.stats.emitted, 0.0
            end = None if args.duration is None else t0 + args.duration
            while end is None or time.monotonic() < end:
                snap = host.get(0.1)
                if snap is not None and writer is not None:
                    writer.snapshot(snap)
                now = time.monotonic()
                if not args.quiet and now - last >= 0.5:
                    print(_status_line(host, t0, n0), end="", file=sys.stderr, flush=True)
                    last = now
            host.stop()
            for snap in host.aggregator.drain():
                if writer is not None:
                    writer.snapshot(snap)
            if not args.quiet:
                print(_status_line(host, t0, n0), file=sys.stderr)
            stats = host.stats
    except KeyboardInterrupt:
        stats = host.stats
        print("", file=sys.stderr)
    finally:
        if writer is not None:
            writer.close(stats=stats)
    if args.json:
        print(json.dumps(stats, default=str, indent=1))
    return 0
