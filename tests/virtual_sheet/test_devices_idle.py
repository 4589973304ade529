"""An idle sheet's device loop sleeps until it has something to do (virtual_sheet/devices.py).

The gateway says when that is (`Gateway.next_deadline`): checked on a simulated clock, polled every
millisecond, that nothing ever comes out before the deadline it gave (a loop that sleeps until then
loses nothing) and that every deadline reached brings something out (no wake-up for nothing) where
the chips' timers are known. A device thread that waits that long is woken at once by a `call`, by
`stop` and by the host's input: shown with a device whose deadlines are infinitely far (without
the wake-ups the thread would sleep for an hour; the tests' bounds only catch a hang). The devices
that cannot be woken (python-can's, the memory links') keep a 20 ms wait.
"""

from __future__ import annotations

import math

import pytest
import serial

from protocol.framing import StreamDecoder, encode
from protocol.messages import Announce, GetInfo, Info
from virtual_sheet.devices import MemoryDevice, PtyDevice
from virtual_sheet.faults import FaultSpec
from virtual_sheet.gateway import CHIP_POLL_PERIOD_S, Gateway
from virtual_sheet.sheet import VirtualSheet


def _by_deadlines(gw, until_s: float, step_s: float = 0.001):
    """Run ``gw`` on a simulated clock, a poll every ``step_s`` until ``until_s``:
    (the steps that had output, the steps a loop sleeping until `next_deadline` would have woken
    at, the steps with output before the deadline given just before them)."""
    out_at, wakes, early = [], [], []
    for i in range(1, int(round(until_s / step_s)) + 1):
        t = i * step_s
        due = gw.next_deadline()
        gw.poll(t)
        n = len(gw.pop_output(t))
        if t >= due:
            wakes.append(t)
        if n:
            out_at.append(t)
            if t < due:
                early.append((t, due))
    return out_at, wakes, early


def _sheet(transport="serial", lattice="3x3", faults=None):
    return VirtualSheet("flat", lattice, noise=0.0, seed=3, transport=transport, faults=faults)


@pytest.mark.parametrize("transport", ["serial", "can"])
@pytest.mark.parametrize("state", ["announcing", "started", "node", "sync-source"])
def test_nothing_comes_out_before_the_gateways_deadline_and_every_deadline_brings_something(transport, state):
    """Announcing chips (a sheet nobody assigned: a re-announce a second), started chips (a STATUS
    heartbeat a second), a gateway node (its own announce and heartbeat), a gateway that drives
    SYNC (its SYNCs and its chips' answers): over 3.5 s, no frame before the deadline, and a
    wake-up only when something comes out — a few dozen instead of a poll tick every 10 ms."""
    sheet = _sheet(transport)
    gw = Gateway(sheet, as_node=state == "node", sync_rate_hz=30.0 if state == "sync-source" else None)
    gw.power_on(0.0)
    gw.pop_output(0.0)  # the power-on announces
    if state in ("started", "sync-source"):
        gw.commission(0.0)
        gw.pop_output(0.0)
    out_at, wakes, early = _by_deadlines(gw, 3.5)
    assert early == []
    assert out_at  # the run shows something
    assert wakes == out_at  # a loop that sleeps until the deadline wakes only to send
    ticks = 3.5 / CHIP_POLL_PERIOD_S
    assert len(wakes) < (ticks / 2 if state == "sync-source" else ticks / 20), len(wakes)


def test_fault_wrapped_chips_and_held_frames_keep_the_poll_tick():
    """Chips with fault wrappers (a chip that dies after a while) and a gateway that holds frames
    back (reordering) act at any poll: their gateway keeps every poll tick as its deadline, and
    still nothing comes out before it."""
    for faults in ("dead_chip=4,dead_after_s=1,seed=2", "reorder=0.2,seed=2"):
        gw = Gateway(_sheet(faults=FaultSpec.parse(faults)), sync_rate_hz=30.0)
        gw.power_on(0.0)
        gw.commission(0.0)
        gw.pop_output(0.0)
        out_at, wakes, early = _by_deadlines(gw, 2.0)
        assert early == [] and out_at, faults
        assert len(wakes) >= 2.0 / CHIP_POLL_PERIOD_S - 1, (faults, len(wakes))  # every tick


def test_the_next_outage_is_a_deadline_of_the_device():
    """The bus goes away at its time even when no gateway has anything to do before."""
    t = [0.0]
    dev = MemoryDevice(_sheet(faults=FaultSpec.parse("outage_at_s=0.25,outage_s=0.1")), clock=lambda: t[0])
    dev.start()
    try:
        dev.step()  # the power-on announces go out; the chips re-announce at 1 s
        assert dev._next_deadline() == 0.25
        t[0] = 0.25
        dev.step()
        assert dev.down and dev.fault_stats.outages == 1
    finally:
        dev.stop()


class _NeverDue:
    """A device with nothing to do until its host speaks or a call comes: every deadline infinitely
    far, and no guard on the wait (an hour)."""

    max_wait_s = 3600.0

    def _next_deadline(self) -> float:
        return math.inf


class _IdlePty(_NeverDue, PtyDevice):
    pass


def test_a_call_and_stop_wake_a_device_waiting_for_nothing():
    dev = _IdlePty(_sheet()).start()
    try:
        for k in range(3):
            assert dev.call(lambda now, k=k: (k, now >= 0.0), timeout_s=30.0) == (k, True)
    finally:
        dev.stop(timeout_s=30.0)  # raises if the thread did not stop
    assert not dev.running


def test_the_hosts_input_wakes_a_device_waiting_for_nothing():
    """GET_INFO from the host: every chip's answer (ANNOUNCE + INFO) comes back at once, although
    the device's deadlines say nothing is due."""
    sheet = _sheet()
    dev = _IdlePty(sheet).start()
    port = serial.Serial(dev.path, timeout=0.1)
    try:
        dec = StreamDecoder()
        port.write(encode(GetInfo(0)))
        got: list = []
        for _ in range(300):  # a hang guard (30 s), not a latency bound
            got += dec.feed(port.read(65536))
            if sum(isinstance(m, Info) for m in got) >= 2 * sheet.n_links:
                break
        # the power-on announces (ANNOUNCE + INFO of every chip), then the answers to GET_INFO
        assert sum(isinstance(m, Info) for m in got) == 2 * sheet.n_links, got
        assert sum(isinstance(m, Announce) for m in got) == 2 * sheet.n_links
    finally:
        port.close()
        dev.stop(timeout_s=30.0)
