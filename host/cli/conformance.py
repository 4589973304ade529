"""``capsheet conformance``: the command line over `host.conformance` (see its docstring)."""

from __future__ import annotations

import argparse
import sys

from host.cli.transport_args import add_transport_args
from host.conformance import checks as _checks
from host.conformance.checks import CHECKS, CanLink, SerialLink, run_checks, summary

__all__ = ["register", "run"]


def run(args: argparse.Namespace) -> int:
    if args.list:
        for c in CHECKS:
            print(f"{c.number:2d}  {c.clause:10} {c.title}" + (f"  ({c.transport} only)" if c.transport else ""))
        return 0
    if bool(args.port) == bool(args.can):
        print("capsheet conformance: give exactly one of --port PATH or --can IFACE:CHANNEL", file=sys.stderr)
        return 2
    try:
        link = SerialLink(args.port, args.baud) if args.port else CanLink(args.can, fd=args.fd, bitrate=args.bitrate)
    except ConnectionError as exc:
        print(f"capsheet conformance: {exc}", file=sys.stderr)
        return 2
    link.start()
    try:
        only = [o.strip() for o in args.only.split(",")] if args.only else None
        print(f"capsheet conformance: {args.port or args.can} ({link.transport})", flush=True)
        results = run_checks(link, timeout_s=args.timeout, node=args.node, slack_ms=args.slack_ms, only=only,
                             out=sys.stdout)
    finally:
        link.close()
    print(summary(results))
    return 1 if any(r.outcome == "FAIL" for r in results) else 0


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "conformance", help="hold a chip (or gateway) to the protocol spec, clause by clause",
        description=_checks.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_transport_args(p, title="the port the chip is on (exactly one)", several_buses=False)
    p.add_argument("--timeout", type=float, default=0.5, help="seconds to wait for each answer (default 0.5)")
    p.add_argument("--node", type=lambda v: int(v, 0), default=42, help="node id to assign for the run (default 42)")
    p.add_argument("--slack-ms", type=float, default=10.0,
                   help="host-side latency allowed on top of the 2 ms SYNC deadline (default 10)")
    p.add_argument("--only", help="comma-separated check numbers or clause prefixes, e.g. 4.6,5")
    p.add_argument("--list", action="store_true", help="list the checks and exit")
    p.set_defaults(func=run)
    return p
