"""A conformance run on a simulated clock: the checks against an in-process chip model whose time the
run advances, instead of waiting for it.

A run against a chip mostly waits — for the silences a chip must keep, its heartbeats, its
re-announces — so a whole run takes ~10 s of wall clock for a fraction of a second of work. When
the chip is a model in this process (the virtual sheet's devices in manual mode,
`virtual_sheet.devices.Device` with ``clock=``: the Python chip model, the C firmware through
cffi, a gateway in front), nothing needs to wait: `SimulatedPort` is a `host.conformance.session.Port`
whose clock is a `SimulatedClock`, and whose `next` steps the device to its next event (a chip's
timer, a frame due, the gateway's SYNC) or to the deadline, whichever is first, in the caller's
thread. No reader thread, no sleep: the same run gives the same frames at the same instants on
every run, whatever the machine's load.

The checks are the same functions deciding on the same evidence: every time they read (arrival and
send times, deadlines, their own pauses) is the port's (`Port.now`, `Port.sleep`). What the clock
changes is the latency: the device reads the host's frame at the instant it was sent and its
answer arrives at that instant, so a timing check measures the chip's own timers alone (a chip's
10 ms timer tick, `virtual_sheet.gateway.CHIP_POLL_PERIOD_S`, is the only jitter), with no host or
port latency on top.

Useful to anyone testing a chip model: wrap it in a `VirtualSheet` (``chip_factory=``), give its
device the clock, and run the checks through the port (docs/conformance.md, "On a simulated clock")::

    clock = SimulatedClock()
    device = MemoryDevice(VirtualSheet("flat", "2x2", chip_factory=MyChip), clock=clock).start()
    port = SimulatedPort(MemoryTransport(device.port), device)
    results = run_checks(port)

(On CAN: a `CanDevice` with ``clock=`` and an `AuditedCanTransport` on its ``virtual`` channel.)
The device is anything with ``step()`` (one pass of its loop at the clock's time, never waiting),
a ``clock`` attribute and ``gateways``, each with ``next_deadline()`` (when it next has something to
do): the virtual sheet's devices are.

What a simulated clock cannot show is the transport: a real port's latency, a pty's or a CAN
adapter's behaviour, a chip in another process or on hardware. Those runs keep `Port` over a
real transport.
"""

from __future__ import annotations

from .session import SimulatedClock, SimulatedPort

__all__ = ["SimulatedClock", "SimulatedPort"]
