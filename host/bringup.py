"""Bring-up: from any state to streaming; what a bus over its capacity needs (`capacity_remedy`)."""

from __future__ import annotations

import numpy as np

__all__ = ["capacity_remedy"]


def capacity_remedy(kind: str, load: float, rate_hz: float, *, packed: bool, fd: bool = False,
                    bitrate: int | None = None, split: str | None = None, pack: str | None = None,
                    faster: bool = True) -> str:
    """What takes a bus at ``load`` (1.0 = full) back under its capacity, for what is already set:
    packing where it is not on (``pack``: how the command says so, e.g. with the gateways packing
    needs), more gateways or buses (``split``), a faster link (``faster``), or the highest rate
    that fits.

    >>> capacity_remedy("serial", 2.5, 145.0, packed=True, bitrate=12_000_000)
    'use more gateways (a --port each; at least 3), a link faster than 12 Mbaud (--baud), or --rate 58 or lower'
    """
    ways = []
    k = int(np.ceil(load - 1e-9))
    if kind == "serial":
        if not packed:
            ways.append(pack or "--packed (SNAPSHOT frames from the gateway)")
        ways.append(split or f"more gateways (a --port each; at least {k})")
        if faster:
            ways.append("a link faster than " + (f"{bitrate / 1e6:g} Mbaud" if bitrate else "this one") + " (--baud)")
    else:
        if not (fd and packed):
            ways.append(pack or "CAN FD with packed frames (--fd --packed)")
        ways.append(split or f"more buses (a --can each; at least {k})")
    ways.append(f"--rate {int(rate_hz / load):d} or lower")
    return "use " + ", ".join(ways[:-1]) + ", or " + ways[-1]
