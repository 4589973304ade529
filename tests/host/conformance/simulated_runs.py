"""The tests' way to a conformance run on the simulated clock: a `VirtualSheet`'s device in manual mode
and a `host.conformance.simulated.SimulatedPort` to it (the wiring docs/conformance.md shows, in one
context manager)."""

from __future__ import annotations

import itertools
from contextlib import contextmanager
from typing import Iterator

from host.conformance import AuditedCanTransport, run_checks
from host.conformance.simulated import SimulatedClock, SimulatedPort
from host.transport.ports import MemoryTransport
from virtual_sheet.devices import CanDevice, MemoryDevice

__all__ = ["simulated_port", "run_simulated"]

_channels = itertools.count()


@contextmanager
def simulated_port(sheet, *, start_s: float = 0.0, **device_kw) -> Iterator[SimulatedPort]:
    """A `SimulatedPort` to ``sheet``'s chips (serial or CAN), the device made, started, and closed at
    exit. ``device_kw`` go to the device (`MemoryDevice` on serial, `CanDevice` on a python-can
    ``virtual`` channel of its own on CAN): ``packed``, ``sync_rate_hz``, ``gateway_class``, ... The
    clock starts at ``start_s``."""
    clock = SimulatedClock(start_s)
    if sheet.transport == "serial":
        device = MemoryDevice(sheet, clock=clock, **device_kw).start()
        transport = MemoryTransport(device.port)
    else:
        device_kw.setdefault("channels", [f"conformance-simulated-{next(_channels)}"])
        device = CanDevice(sheet, clock=clock, **device_kw).start()
        try:
            transport = AuditedCanTransport(f"virtual:{device.channels[0]}", fd=sheet.fd, reconnect=False)
        except BaseException:
            device.stop()
            raise
    port = None
    try:
        port = SimulatedPort(transport, device, clock)
        yield port
    finally:
        if port is not None:
            port.close()
        transport.close()
        device.stop()


def run_simulated(sheet, *, timeout_s: float = 0.3, device_kw: dict | None = None, **run_kw):
    """`run_checks` against ``sheet``'s chips on the simulated clock (``run_kw``: its options)."""
    with simulated_port(sheet, **(device_kw or {})) as port:
        return run_checks(port, timeout_s=timeout_s, **run_kw)
