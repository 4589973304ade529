"""The same verdicts whatever carries the frames: the conformance suite against the same chip (a healthy
one, and a mutant that breaks the SYNC counter) over a pty (serial), an SLCAN adapter on a pty and
python-can's udp_multicast bus — the transports a vendor's bench uses. Every check of the chip profile
must reach the same outcome on each, but for the transport's own checks (serial: 21; CAN: 22, 41).

SLCAN hands frames over in blocks and udp_multicast echoes a sender's own frames: the port's audit
reads both through the transport's capture. Over SLCAN the suite is given a plain
`CanTransport` (the `Port` subscribes its own audit), over udp_multicast an `AuditedCanTransport`.

The transport is the subject of the real-time runs (tests/host/conformance/real_runs.py: made at once
with test_checks.py's, ~22 s for both files' where this file's took ~40-50 s): the whole suite against the
healthy chip over each transport (every check passes through it, the timing checks on the host's
clock included), and the four checks the counter mutant fails, over each transport (a failing chip's
answers come through it as FAIL, not LOST or SKIP). The mutant's whole suite — that every other check
still passes and its four fail, on serial and on CAN — is decided by the frames the chip sends, which
the healthy runs show each transport delivers: it runs on the simulated clock
(`test_the_counter_mutant_fails_exactly_its_checks_on_the_simulated_clock`). Its verdict was the same
over all three real transports as on the simulated clock (both kinds) when it moved."""

from __future__ import annotations

import pytest

from host.conformance import CHECKS
from tests.host.cli.test_host import ONE_MULTICAST_BUS
from tests.host.conformance.mutants import CounterOffByOne
from tests.host.conformance.real_runs import COUNTER_CHECKS, real_runs, result  # noqa: F401 (fixture)
from tests.host.conformance.simulated_runs import run_simulated
from virtual_sheet.sheet import VirtualSheet

OWN = {"serial": {21}, "can": {22, 41, 44}}  # a transport's own checks
#: the §16 checks (6/9-axis chips): an accelerometer chip skips them, saying so
IMU_CHECKS = {42, 43, 44}
#: what the counter mutant fails
COUNTER_FAILS = {24, 25, 26, 27}


def _expected(kind, failing=frozenset(), only=None):
    own = OWN["serial" if kind in ("pty", "serial") else "can"]
    common = {c.number for c in CHECKS if "chip" in c.profiles} - OWN["serial"] - OWN["can"]
    numbers = common | own if only is None else {1} | set(only)  # check 1 (discovery) always runs
    return {n: ("FAIL" if n in failing else "SKIP" if n in IMU_CHECKS else "PASS") for n in numbers}


def _outcomes(results):
    return {r["number"]: r["outcome"] for r in results}, "\n".join(
        f"{r['outcome']:4}  {r['number']:2d}  {r['title']}  [{r['detail']}]" for r in results)


def _run(real_runs, kind, chip):
    if kind == "udp_multicast":
        return result(real_runs, "udp_multicast")[chip]
    if (kind, chip) == ("pty", "healthy"):  # the Python chip's pty run is test_checks.py's too
        return result(real_runs, "healthy/python/serial")
    return result(real_runs, f"{kind}/{chip}")


@pytest.mark.parametrize("chip", ["healthy", "counter_off_by_one"])
@pytest.mark.parametrize("kind", ["pty", "slcan", pytest.param("udp_multicast", marks=ONE_MULTICAST_BUS)])
def test_the_same_verdicts_on_every_transport(real_runs, kind, chip):
    """A healthy chip passes every check, a broken one fails the same checks, on each transport."""
    got, report = _outcomes(_run(real_runs, kind, chip))
    if chip == "healthy":
        assert got == _expected(kind), report
    else:
        assert got == _expected(kind, failing=COUNTER_FAILS, only={int(n) for n in COUNTER_CHECKS}), report


@pytest.mark.parametrize("transport", ["serial", "can"])
def test_the_counter_mutant_fails_exactly_its_checks_on_the_simulated_clock(transport):
    """The whole suite against the counter mutant (every check of the chip profile, broadcast ones
    included): the four it breaks fail, every other one passes (or is skipped: §16 on an accelerometer
    chip), as over the real transports."""
    sheet = VirtualSheet("flat", "2x2", transport=transport, noise=0.5, chip_factory=CounterOffByOne)
    results = run_simulated(sheet, allow_broadcast=True)
    got = {r.number: r.outcome for r in results}
    assert got == _expected(transport, failing=COUNTER_FAILS), "\n".join(r.line() for r in results)
