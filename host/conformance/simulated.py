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

Useful to anyone testing a chip model: wrap it in a `VirtualSheet` (``chip_factory=``), and::

    from host.conformance import run_checks
    from host.conformance.simulated import simulated_port

    with simulated_port(VirtualSheet("flat", "2x2", chip_factory=MyChip)) as port:
        results = run_checks(port)

What a simulated clock cannot show is the transport: a real port's latency, a pty's or a CAN
adapter's behaviour, a chip in another process or on hardware. Those runs keep `Port` over a
real transport.
"""

from __future__ import annotations

import itertools
from contextlib import contextmanager
from typing import Iterator

from host.transport.ports import MemoryTransport, Transport

from .session import AuditedCanTransport, Port

__all__ = ["SimulatedClock", "SimulatedPort", "simulated_port"]

#: when the device names no later event (it is down in an outage), time moves on by its loop's poll period
_IDLE_STEP_S = 0.01
_channels = itertools.count()


class SimulatedClock:
    """Seconds that move only when the run moves them (`advance_to`); call it for the time.

    Pass the same clock to the device (``clock=``) and to `SimulatedPort`."""

    def __init__(self, start_s: float = 0.0) -> None:
        self.t = float(start_s)

    def __call__(self) -> float:
        return self.t

    def advance_to(self, t: float) -> None:
        """Move to ``t`` (never back: an earlier ``t`` leaves the clock where it is)."""
        if t > self.t:
            self.t = float(t)

    def __repr__(self) -> str:
        return f"SimulatedClock({self.t:.6f})"


class SimulatedPort(Port):
    """A `Port` on a simulated clock, over the host's end of an in-process device in manual mode.

    Parameters
    ----------
    transport : Transport
        The host's end of ``device``: a `MemoryTransport` over ``device.port`` (serial), or an
        `AuditedCanTransport` on the device's python-can ``virtual`` channel. Read without waiting.
    device : virtual_sheet.devices.Device
        Built with ``clock=`` ``clock`` and started (manual mode: no thread; the port runs it with
        ``device.step()``).
    clock : SimulatedClock, optional
        Default: ``device.clock``, which must then be a `SimulatedClock`.

    ``steps``: how many times the port stepped the device (a run's cost, the same on every run).
    """

    def __init__(self, transport: Transport, device, clock: SimulatedClock | None = None) -> None:
        clock = device.clock if clock is None else clock
        if not isinstance(clock, SimulatedClock):
            raise ValueError(f"Invalid clock {clock!r}: a SimulatedPort needs a SimulatedClock (the device's, "
                             f"given as clock= when it was built)")
        if device.clock is not clock:
            raise ValueError("the device runs on another clock: build it with clock= the port's SimulatedClock")
        self.clock = clock
        self.device = device
        self.steps = 0
        super().__init__(transport)

    def _start_reader(self) -> None:  # the caller's thread reads, in `_pump`
        pass

    def now(self) -> float:
        return self.clock.t

    def _pump(self) -> None:
        """Step the device at the clock's time (it reads what the host sent, serves its timers, sends
        what is due) and queue everything the transport then holds, as arrived now."""
        self.device.step()
        self.steps += 1
        while True:
            events = self.transport.recv(0.0)  # TransportError propagates, as the reader thread's does
            if self._went_away():
                raise self.error
            if not events:
                return
            self._take(events, self.clock.t)

    def _next_event(self) -> float:
        """When the device next has something to do (after the clock's time)."""
        now = self.clock.t
        t = min(gw.next_deadline() for gw in self.device.gateways)
        return t if t > now else now + _IDLE_STEP_S

    def next(self, deadline: float):
        """The next ``(arrival_time, Message | DecodeError)``, or None at ``deadline``: the device runs
        from one event to the next until something arrives or the clock reaches ``deadline``."""
        while True:
            if self.error is not None:
                raise self.error
            self._pump()
            if self._q:
                return self._q.popleft()
            if self.clock.t >= deadline:
                return None
            self.clock.advance_to(min(deadline, self._next_event()))

    def sleep(self, seconds: float) -> None:
        """Run the device for ``seconds`` of the clock; what arrives meanwhile is queued, at its time."""
        end = self.clock.t + max(0.0, seconds)
        while True:
            self._pump()
            if self.clock.t >= end:
                return
            self.clock.advance_to(min(end, self._next_event()))

    def drain(self) -> None:
        self._pump()
        self._q.clear()

    def close(self) -> None:
        self._stop.set()
        self.transport.end_capture(self.audit)


@contextmanager
def simulated_port(sheet, *, start_s: float = 0.0, **device_kw) -> Iterator[SimulatedPort]:
    """A `SimulatedPort` to ``sheet``'s chips (a `virtual_sheet.sheet.VirtualSheet`, serial or CAN),
    the device made, started, and closed at exit.

    ``device_kw`` go to the device (`MemoryDevice` on serial, `CanDevice` on a python-can ``virtual``
    channel of its own on CAN): ``packed``, ``sync_rate_hz``, ``gateway_class``, ... The clock
    starts at ``start_s``."""
    from virtual_sheet.devices import CanDevice, MemoryDevice

    clock = SimulatedClock(start_s)
    if sheet.transport == "serial":
        device = MemoryDevice(sheet, clock=clock, **device_kw).start()
        transport: Transport = MemoryTransport(device.port)
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
