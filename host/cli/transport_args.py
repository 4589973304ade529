"""The transport options every subcommand that opens a sheet shares: ``--port``/``--baud`` for a
serial port, ``--can`` (repeatable, or once), ``--fd``, ``--bitrate`` for python-can buses.

One definition, so ``capsheet host``, ``tactile`` and ``conformance`` spell, default and explain
them alike, and open them through the same `host.transport` classes.
"""

from __future__ import annotations

import argparse

from host.transport import CanTransport, SerialTransport, Transport, TransportError

__all__ = ["add_transport_args", "open_transports", "DEFAULT_BAUD"]

#: serial baud rate when ``--baud`` is not given (a 3 Mbaud UART, docs/protocol.md §10)
DEFAULT_BAUD = 3_000_000


def positive_int(text: str) -> int:
    """argparse type: an integer > 0 (bit and baud rates), else a one-line usage error."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: need an integer") from None
    if v <= 0:
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: need > 0")
    return v


def add_transport_args(parser: argparse.ArgumentParser, *, title: str, several_buses: bool = True,
                       ) -> argparse._ArgumentGroup:
    """Add ``--port --baud --can --fd --bitrate`` to ``parser`` in a group called ``title``.

    With ``several_buses`` ``--can`` may be repeated (buses merged into one lattice) and collects a
    list; otherwise it takes one bus and stores a string (or None).
    """
    g = parser.add_argument_group(title)
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


def open_transports(args: argparse.Namespace, *, prog: str = "capsheet") -> list[Transport]:
    """Open what ``args`` names: one `SerialTransport` for ``--port``, one `CanTransport` per ``--can``.

    Raises ``SystemExit`` with a one-line message when neither or both are given, and
    `TransportError` (from the transport) when a port cannot be opened; buses already opened are
    closed first.
    """
    specs = _can_specs(args)
    if bool(args.port) == bool(specs):
        raise SystemExit(f"{prog}: give either --port PATH or --can IFACE:CHANNEL")
    if args.port:
        return [SerialTransport(args.port, baudrate=args.baud)]
    out: list[Transport] = []
    try:
        for spec in specs:
            kw = {"sleep_after_open": 0.1} if spec.startswith("slcan:") else {}
            out.append(CanTransport(spec, fd=args.fd, bitrate=args.bitrate, **kw))
    except TransportError:
        for t in out:
            t.close()
        raise
    return out
