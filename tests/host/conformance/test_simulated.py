"""The conformance run on a simulated clock (host/conformance/simulated.py): the device stepped from
one event to the next, no waiting, no thread, the same run every time, exact counts and times."""

from __future__ import annotations

import re
import time

import pytest

from host.conformance import run_checks
from host.conformance.simulated import SimulatedClock, SimulatedPort
from tests.host.conformance.simulated_runs import simulated_port
from host.transport.ports import MemoryTransport
from protocol.messages import Announce, Info
from protocol.state import ANNOUNCE_PERIOD_S
from tests.host.conformance.mutants import SlowHeartbeat
from virtual_sheet.devices import MemoryDevice
from virtual_sheet.gateway import CHIP_POLL_PERIOD_S
from virtual_sheet.sheet import VirtualSheet


def _lines(results) -> list[str]:
    return [r.line() for r in results]


@pytest.mark.parametrize("transport", ["serial", "can"])
def test_a_simulated_run_waits_on_its_clock_never_on_the_machines(transport, monkeypatch):
    """Every wait of a whole run (the silences, heartbeats, re-announces, the checks' own pauses) is
    the simulated clock's: a `time.sleep` anywhere in the run fails it, and the clock has moved on by
    the re-announce check's three periods at least."""
    def no_sleep(s):
        raise AssertionError(f"time.sleep({s}) during a run on the simulated clock")
    monkeypatch.setattr(time, "sleep", no_sleep)
    with simulated_port(VirtualSheet("flat", "2x2", transport=transport, noise=0.5)) as port:
        results = run_checks(port, timeout_s=0.3, allow_broadcast=True)
        elapsed = port.now()
    assert [r for r in results if r.outcome not in ("PASS", "SKIP")] == [], "\n".join(_lines(results))
    assert elapsed >= 3 * ANNOUNCE_PERIOD_S


def test_the_same_run_twice_is_the_same_run():
    """Deterministic: the same results, word for word (periods, counts, sample values), at the same
    simulated instants, in the same number of device steps."""
    runs = []
    for _ in range(2):
        with simulated_port(VirtualSheet("flat", "2x2", noise=0.5), packed=True) as port:
            results = run_checks(port, timeout_s=0.3, allow_broadcast=True)
            runs.append((_lines(results), port.now(), port.steps))
    assert runs[0] == runs[1]


def test_timers_are_measured_exactly():
    """No host or port latency on the simulated clock: the heartbeat period the check measures is the
    chip's own: 100 ms for a conforming chip; for one at twice the period 200 ms, to the chips' 10 ms
    timer tick (the mutant's next STATUS is due 200 ms after the tick that sent the last)."""
    with simulated_port(VirtualSheet("flat", "2x2", noise=0.5)) as port:
        (_, hb) = run_checks(port, timeout_s=0.3, only=["11"])
    assert hb.outcome == "PASS" and "period 100.0 ms over 9 heartbeats" in hb.detail, hb.line()
    with simulated_port(VirtualSheet("flat", "2x2", noise=0.5, chip_factory=SlowHeartbeat)) as port:
        (_, hb) = run_checks(port, timeout_s=0.3, only=["11"])
    period = re.search(r"period ([0-9.]+) ms", hb.detail)
    assert hb.outcome == "FAIL" and period, hb.line()
    assert 200.0 <= float(period.group(1)) <= 200.0 + 1000 * CHIP_POLL_PERIOD_S, hb.line()


def test_next_and_sleep_move_the_clock_to_the_event_or_the_deadline():
    """After power-on (at 0) each of the 4 unassigned chips re-announces every second: in 3.5 s of
    the clock exactly 3 rounds of ANNOUNCE + INFO arrive, each at its round's second (to the chips'
    10 ms timer tick); `next` returns None at its deadline exactly, `sleep` moves the clock exactly."""
    with simulated_port(VirtualSheet("flat", "2x2", noise=0.5)) as port:
        boot = []
        while (item := port.next(0.0)) is not None:
            boot.append(item)
        assert len(boot) == 8 and port.now() == 0.0  # ANNOUNCE + INFO of each chip at power-on
        got = []
        while (item := port.next(3.5)) is not None:
            got.append(item)
        assert port.now() == 3.5
        assert [type(m) for _, m in got] == [Announce, Info] * 12
        rounds = sorted({round(t, 6) for t, _ in got})
        assert len(rounds) == 3
        for k, t in enumerate(rounds, start=1):
            assert k * ANNOUNCE_PERIOD_S <= t <= k * ANNOUNCE_PERIOD_S + CHIP_POLL_PERIOD_S + 1e-9
        port.sleep(0.25)
        assert port.now() == 3.75
        assert port.next(3.75) is None and port.now() == 3.75


def test_a_port_and_a_device_on_different_clocks_are_refused():
    sheet = VirtualSheet("flat", "2x2", noise=0.5)
    with MemoryDevice(sheet) as dev:  # real time: its own thread
        t = MemoryTransport(dev.port)
        with pytest.raises(ValueError, match="needs a SimulatedClock"):
            SimulatedPort(t, dev)
        with pytest.raises(ValueError, match="runs on another clock"):
            SimulatedPort(t, dev, SimulatedClock())
        t.close()


def test_the_clock_never_goes_back():
    c = SimulatedClock(2.0)
    c.advance_to(1.0)
    assert c() == 2.0
    c.advance_to(2.5)
    assert c() == 2.5


def test_the_checks_read_no_clock_but_the_ports():
    """A check that read `time.monotonic` or slept with `time.sleep` would wait in real time on the
    simulated clock (and measure the machine, not the chip): the checks import no clock at all."""
    from pathlib import Path

    from tests.test_architecture import imports_of
    checks = Path(__file__).resolve().parents[3] / "host/conformance/checks"
    clocks = {"time", "datetime", "threading"}
    bad = {p.name: sorted(m for m in imports_of(p) if m.split(".")[0] in clocks) for p in sorted(checks.glob("*.py"))}
    assert {k: v for k, v in bad.items() if v} == {}
