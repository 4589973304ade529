"""How long a command that talks to chips waits for them, for every command that brings a sheet up
(capsheet host, calibrate, layout, tactile): ``--ack-timeout-ms``, a command's ACK before the
command is sent again, and ``--watchdog-ms``, how long a link may send nothing before it is marked
missing.

Chips answer a command within a SYNC period or two; the defaults suit a sheet on its own port. A
sheet behind a slow gateway, a long CAN bus shared with other traffic, or a virtual sheet on a
machine busy with other work may answer later: there a host with the defaults resends commands
that were answered, gives chips up during bring-up (``no_ack``), and marks links missing that
were only late (``silent``). A user who knows the sheet is slow says so here (docs/host.md)."""

from __future__ import annotations

from host.cli import argtypes as T
from host.session.commands import ACK_TIMEOUT_S, RETRIES as RESENDS, attempt_wait_s

__all__ = ["add_timing_args", "timing_kwargs", "ACK_TIMEOUT_MS"]

#: the default wait for a command's ACK (`host.session.core.Host`'s ``timeout_s``)
ACK_TIMEOUT_MS = 1e3 * ACK_TIMEOUT_S


def _total_wait_s(ack_ms: float) -> float:
    """How long a command round waits in all before it gives a chip up (every attempt's wait)."""
    return sum(attempt_wait_s(ack_ms / 1000, a) for a in range(RESENDS + 1))


def add_timing_args(p, *, deadline: bool = False) -> None:
    """``--ack-timeout-ms`` and ``--watchdog-ms`` in a group of their own (``deadline``: the command
    has ``--deadline-ms``, which the watchdog's default waits out)."""
    g = p.add_argument_group("waiting for chips (a slow gateway, a busy bus or machine)")
    g.add_argument("--ack-timeout-ms", type=T.bounded_float(0.0, 10_000.0, lo_open=True, unit="ms"),
                   default=ACK_TIMEOUT_MS, metavar="MS",
                   help=f"wait this long for a command's ACK before sending it again; {RESENDS} resends, each "
                        f"waiting half as long again as the one before (default {ACK_TIMEOUT_MS:g}: "
                        f"{_total_wait_s(ACK_TIMEOUT_MS):.1f} s before a chip is given up)")
    g.add_argument("--watchdog-ms", type=T.bounded_float(0.0, 60_000.0, lo_open=True, unit="ms"),
                   default=None, metavar="MS",
                   help="mark a link missing (SILENT, not waited for) when no frame came from it for this "
                        "long (default: 500 ms or 20 SYNC periods" + (", or --deadline-ms" if deadline else "")
                        + ", whichever is longest)")


def timing_kwargs(args) -> dict:
    """`host.session.core.Host`'s keyword arguments for what ``add_timing_args`` parsed."""
    kw = {"timeout_s": args.ack_timeout_ms / 1000}
    if args.watchdog_ms is not None:
        kw["watchdog_s"] = args.watchdog_ms / 1000
    return kw
