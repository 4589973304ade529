"""The transport options every subcommand that opens a sheet shares: ``--port``/``--baud`` for a
serial port, ``--can`` (repeatable, or once), ``--fd``, ``--bitrate`` for python-can buses.

One definition, so ``capsheet host``, ``tactile`` and ``conformance`` spell, default and explain
them alike, and open them through the same `host.transport.ports` classes.
"""

from __future__ import annotations

import argparse
import os
import sys

from host.cli.argtypes import OptionGroup, positive_int
from host.transport.ports import CanTransport, SerialTransport, Transport, TransportError

__all__ = ["add_transport_args", "open_transports", "DEFAULT_BAUD"]

#: serial baud rate when ``--baud`` is not given (a 3 Mbaud UART, docs/protocol.md §10)
DEFAULT_BAUD = 3_000_000


def add_transport_args(parser: argparse.ArgumentParser, *, title: str, several_buses: bool = True,
                       ) -> OptionGroup:
    """Add ``--port --baud --can --fd --bitrate`` to ``parser`` in a group called ``title``.

    With ``several_buses`` ``--can`` may be repeated (buses merged into one lattice) and collects a
    list; otherwise it takes one bus and stores a string (or None).
    """
    g = parser.add_argument_group(title)
    if several_buses:
        g.add_argument("--port", action="append", default=[], metavar="PORT",
                       help="serial port: device path or pyserial URL (/dev/ttyUSB0, /dev/pts/5, loop://); "
                            "repeat for a sheet behind several serial gateways, merged into one lattice")
    else:
        g.add_argument("--port", help="serial port: device path or pyserial URL (/dev/ttyUSB0, /dev/pts/5, loop://)")
    g.add_argument("--baud", type=positive_int, default=DEFAULT_BAUD, help=f"serial baud rate (default {DEFAULT_BAUD})")
    if several_buses:
        g.add_argument("--can", action="append", default=[], metavar="IFACE:CHANNEL",
                       help="CAN bus as python-can names it (virtual:bus0, slcan:/dev/pts/6, socketcan:can0); "
                            "repeat for several buses merged into one lattice")
    else:
        g.add_argument("--can", metavar="IFACE:CHANNEL",
                       help="CAN bus as python-can names it (virtual:bus0, slcan:/dev/pts/6, socketcan:can0)")
    g.add_argument("--fd", action="store_true", help="open the CAN bus(es) for CAN FD")
    g.add_argument("--bitrate", type=positive_int, default=None, help="CAN bit rate, where the interface needs one (e.g. 1000000)")
    return g


def _can_specs(args: argparse.Namespace) -> list[str]:
    can = args.can
    if not can:
        return []
    return [can] if isinstance(can, str) else list(can)


def _port_specs(args: argparse.Namespace) -> list[str]:
    port = args.port
    if not port:
        return []
    return [port] if isinstance(port, str) else list(port)


def _same_port(a: str, b: str) -> bool:
    """Two --port values name the same port: equal, or paths (symlinks) to the same device."""
    if a == b:
        return True
    if "://" in a or "://" in b:
        return False
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def _usage(msg: str) -> None:
    print(msg, file=sys.stderr)
    raise SystemExit(2)


def check_ports(args: argparse.Namespace, *, prog: str = "capsheet") -> None:
    """Usage errors in the ports named (one line on stderr, ``SystemExit(2)``): neither or both of
    --port and --can, a port or bus given twice (also two symlinks to one device)."""
    ports, specs = _port_specs(args), _can_specs(args)
    if bool(ports) == bool(specs):
        _usage(f"{prog}: give either --port PATH (repeatable) or --can IFACE:CHANNEL (repeatable), "
                         f"not both")
    for names, what in ((ports, "--port"), (specs, "--can")):
        for i, a in enumerate(names):
            for b in names[:i]:
                if (_same_port(a, b) if what == "--port" else a == b):
                    same = "" if a == b else f" (both are {os.path.realpath(a)})"
                    _usage(f"{prog}: {what} {a} is given twice{same}: each port is one gateway, "
                                     f"name each once")


def open_transports(args: argparse.Namespace, *, prog: str = "capsheet") -> list[Transport]:
    """Open what ``args`` names: one `SerialTransport` per ``--port`` (several serial gateways of
    one sheet), one `CanTransport` per ``--can``; several are merged into one lattice by the host.

    Raises ``SystemExit`` with a one-line message (exit 2) when neither or both are given or a port
    is given twice, and `TransportError` (from the transport) when a port cannot be opened; ports
    already opened are closed first.
    """
    check_ports(args, prog=prog)
    specs = _can_specs(args)
    out: list[Transport] = []
    ports = _port_specs(args)
    if ports:
        try:
            for port in ports:
                out.append(SerialTransport(port, baudrate=args.baud,
                                           reader_process=bool(getattr(args, "reader_processes", False))))
        except TransportError:
            for t in out:
                t.close()
            raise
        return out
    try:
        for spec in specs:
            kw = {"sleep_after_open": 0.1} if spec.startswith(("slcan:", "capsheet_slcan:")) else {}
            out.append(CanTransport(spec, fd=args.fd, bitrate=args.bitrate, **kw))
    except TransportError:
        for t in out:
            t.close()
        raise
    return out


def split_needed(n_links: int, rate_hz: float, *, kind: str, bitrate: float, packed: bool = False,
                 fd: bool = False, start: int = 1, limit: int = 64, fmt: int = 0) -> int | None:
    """The fewest gateways (serial) or buses (CAN), from ``start`` on, that carry ``n_links`` chips at
    ``rate_hz`` when the links are split in near-equal contiguous blocks (`VirtualSheet.split`);
    None if more than ``limit`` would be needed."""
    from protocol.capacity import bus_load
    for k in range(max(1, start), limit + 1):
        if bus_load(-(-n_links // k), rate_hz, kind=kind, bitrate=bitrate, fd=fd, packed=packed, fmt=fmt) <= 1.0:
            return k
    return None
