"""``capsheet ports``: which port is my sheet?

Lists every serial port pyserial sees (device, USB vendor:product, serial number, description),
every CAN channel python-can detects, and the paths given (a pty, a symlink); with ``--probe``
asks each, read-only, what answers: chips (how many, their ids), gateway nodes (the links behind
them, packing, SYNC source), sample formats, firmware and protocol versions, at which baud rate
or bit rate (host/transport/discover.py). Nothing but GET_INFO is sent: no chip is assigned,
configured, started, stopped or reset. A port another capsheet session holds is reported as in use
(and by which process) and not probed. The ports are asked at once (a silent port costs one
``--timeout`` for the whole probe, not one each); one line per port, in the listing's order;
``--json`` for programs.

A CAN bus is named as ``--can`` takes it (``socketcan:can0``, ``slcan:/dev/ttyACM0``).

Exit status: 0 a port was listed (with ``--probe``: at least one answered as a sheet); 1 none was
(none answered); 2 a bad value (a PATH that does not exist).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

__all__ = ["register", "run"]


def run(args: argparse.Namespace) -> int:
    from host.transport import discover

    entries = []
    for path in args.paths:
        if _can_spec(path):
            entries.append(discover.PortEntry("can", path, source="argument"))
            continue
        if "://" not in path and not os.path.exists(path):
            print(f"capsheet ports: {path}: no such file or device (a CAN bus is given as IFACE:CHANNEL, "
                  f"e.g. socketcan:can0)", file=sys.stderr)
            return 2
        entries.append(discover.argument_entry(path))
    if not args.paths or args.all:
        given = {os.path.realpath(p) for p in args.paths if not _can_spec(p)}
        entries += [e for e in discover.list_serial() if os.path.realpath(e.name) not in given]
        if not args.no_can:
            entries += discover.list_can()
    answered = 0
    # with --probe every port is asked at once (a silent port costs one --timeout, not one each);
    # the lines still come in the listing's order, each as soon as the ports before it are done
    listed = discover.probe_ports(entries, budget_s=args.timeout) if args.probe else ((e, None) for e in entries)
    for e, probe in listed:
        if args.probe:
            e.probe = probe  # a probe that failed is its own "error" line (probe_ports)
            answered += e.probe.status == "answered"
        if not args.json:
            kind = "CAN" if e.kind == "can" else "serial"
            line = f"{kind:6s} {e.line()}"
            if e.probe is not None:
                line += f" | {e.probe.line()}"
            print(line, flush=True)
    if args.json:
        print(json.dumps({"ports": [e.as_dict() for e in entries], "probed": bool(args.probe),
                          "answered": answered}, indent=1))
    elif not entries:
        print("capsheet ports: no serial port or CAN channel found (give a path to look at one)", file=sys.stderr)
    if args.probe:
        return 0 if answered else 1
    return 0 if entries else 1


def _can_spec(arg: str) -> bool:
    """``IFACE:CHANNEL`` as ``--can`` takes it (``socketcan:can0``, ``slcan:/dev/ttyACM0``), not a path.

    >>> _can_spec("socketcan:can0"), _can_spec("slcan:/dev/ttyACM0"), _can_spec("/dev/pts/3"), _can_spec("loop://")
    (True, True, False, False)
    """
    iface, sep, channel = arg.partition(":")
    return bool(sep and iface and channel and "/" not in iface and not channel.startswith("//"))


def register(subparsers) -> argparse.ArgumentParser:
    from host.cli import argtypes as T
    doc = __doc__.split("\n\n", 1)[1]
    p = subparsers.add_parser(
        "ports", help="list serial ports and CAN channels; --probe: ask each, read-only, what answers",
        description=doc + "\nExamples:\n    capsheet ports\n    capsheet ports --probe\n"
                          "    capsheet ports --probe /tmp/sheet /dev/pts/7 --json\n",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="*", metavar="PATH",
                   help="ports to look at: a device, a pty, a symlink to one, or a CAN bus as IFACE:CHANNEL "
                        "(socketcan:can0, slcan:/dev/ttyACM0); without any, every port the system lists")
    p.add_argument("--all", action="store_true", help="with PATHs: list the system's ports as well")
    p.add_argument("--probe", action="store_true",
                   help="ask each port, read-only (a broadcast GET_INFO, then listen), what answers: chips, "
                        "gateways, formats, versions, baud rate")
    p.add_argument("--timeout", type=T.bounded_float(0.0, 60.0, lo_open=True, unit="s"), default=2.0,
                   help="at most this long per port while probing, s (default 2; a port whose answers "
                        "stop earlier ends earlier); the ports are probed at once, so the whole probe "
                        "takes about one budget")
    p.add_argument("--no-can", action="store_true", help="do not ask python-can for CAN channels")
    p.add_argument("--json", action="store_true", help="print the ports (and probes) as JSON alone on stdout")
    p.set_defaults(func=run)
    return p
