"""``capsheet conformance``: the command line over `host.conformance` (see its docstring).

Exit status: 0 every check run passed (or was skipped), 1 the chip failed a check, 2 usage error or
the port cannot be opened, 3 no check failed but some were inconclusive (the port lost frames) or
the port went away during the run.
"""

from __future__ import annotations

import argparse
import sys

import host.conformance as _conf
from host.cli.transport_args import add_transport_args
from host.conformance import CHECKS, AuditedCanTransport, Port, exit_code, run_checks, select, summary, table
from host.conformance.session import RunAborted
from host.transport.ports import PortInUseError, SerialTransport, TransportError

__all__ = ["register", "run"]


def run(args: argparse.Namespace) -> int:
    if args.list:
        print(table(), end="")
        return 0
    if bool(args.port) == bool(args.can):
        print("capsheet conformance: give exactly one of --port PATH or --can IFACE:CHANNEL", file=sys.stderr)
        return 2
    only = [o.strip() for o in args.only.split(",")] if args.only else None
    try:
        select(only, args.profile)
    except ValueError as exc:
        print(f"capsheet conformance: {exc}", file=sys.stderr)
        return 2
    try:
        if args.port:
            transport = SerialTransport(args.port, baudrate=args.baud, reconnect=False)
        else:
            transport = AuditedCanTransport(args.can, fd=args.fd, bitrate=args.bitrate, reconnect=False)
    except TransportError as exc:  # a port in use by another session: 1, as every command says it
        print(f"capsheet conformance: {exc}", file=sys.stderr)
        return 1 if isinstance(exc, PortInUseError) else 2
    port = Port(transport)
    try:
        print(f"capsheet conformance: {args.port or args.can} ({port.kind}), {args.profile} profile", flush=True)
        results = run_checks(port, timeout_s=args.timeout, node=args.node, uid=args.uid, slack_ms=args.slack_ms,
                             only=only, allow_broadcast=args.allow_broadcast, attempts=args.attempts,
                             out=sys.stdout, profile=args.profile)
    except TransportError as exc:
        print(f"capsheet conformance: {exc}", file=sys.stderr)
        return 3
    except RunAborted as exc:
        print(f"capsheet conformance: {exc}", file=sys.stderr)
        return 2
    finally:
        port.close()
        transport.close()
    print(summary(results))
    return exit_code(results)


def register(subparsers) -> argparse.ArgumentParser:
    from host.cli import argtypes as T
    p = subparsers.add_parser(
        "conformance", help="hold a chip or a gateway to the protocol spec, clause by clause",
        description=(_conf.__doc__ or "") + "\n" + (__doc__.split("\n\n", 1)[1] if __doc__ else "")
        + "\nExamples:\n    capsheet conformance --port /dev/ttyUSB0\n    capsheet conformance --can socketcan:can0"
          " --only 4.6,5\n    capsheet conformance --list\n",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    add_transport_args(p, title="the port the chip is on (exactly one)", several_buses=False)
    p.add_argument("--timeout", type=T.bounded_float(0.0, 60.0, lo_open=True, unit="s"), default=0.5, help="seconds the chip must stay silent where it should not answer; an expected answer is "
                        "awaited max(1 s, 3 x this) and ends as soon as it arrives (default 0.5)")
    p.add_argument("--node", type=T.int_range(1, 0x7FFF, what="an assigned node id"), default=None,
                   help="node id to assign for the run (default: the highest id no chip was heard from)")
    p.add_argument("--uid", type=T.int_range(0, 2 ** 64 - 1, what="a 64-bit uid"), default=None,
                   help="the node under test, by uid (default: the first of the profile's kind to answer a "
                        "broadcast GET_INFO)")
    p.add_argument("--profile", choices=("chip", "gateway"), default="chip",
                   help="hold a chip to the spec (default; directly or behind any gateway), or the first gateway "
                        "node (docs/protocol.md §13)")
    p.add_argument("--slack-ms", type=T.bounded_float(0.0, 10_000.0, unit="ms"), default=10.0,
                   help="host-side latency allowed on top of the 2 ms SYNC deadline (a SHOULD) and the "
                        "heartbeat/re-announce periods, ms (default 10)")
    p.add_argument("--only", help=f"comma-separated check numbers (1..{len(CHECKS)}, of the profile) or clause "
                                  f"prefixes, e.g. 4.6,5")
    p.add_argument("--allow-broadcast", action="store_true",
                   help="also run the checks that broadcast START/STOP (they address every chip on the port)")
    p.add_argument("--attempts", type=T.int_range(1, 9), default=3, metavar="N",
                   help="tries per check when the port lost frames (default 3)")
    p.add_argument("--list", action="store_true", help="print the clause table (docs/conformance.md) and exit")
    p.set_defaults(func=run)
    return p
