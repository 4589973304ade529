"""The same verdicts whatever carries the frames: the conformance suite against the same chip (a healthy
one, and a mutant that breaks the SYNC counter) over a pty (serial), an SLCAN adapter on a pty and
python-can's udp_multicast bus — the transports a vendor's bench uses. Every check of the chip profile
must reach the same outcome on each, but for the transport's own checks (serial: 21; CAN: 22, 41).

SLCAN hands frames over in blocks and udp_multicast echoes a sender's own frames: the port's audit
reads both through the transport's capture. Over SLCAN the suite is given a plain
`CanTransport` (the `Port` subscribes its own audit), over udp_multicast an `AuditedCanTransport`.

The transport is the subject here, so every run is in real time, through a real pty (and an SLCAN
adapter on one, and the UDP bus). The four pty and SLCAN runs are made at once (`pty_and_slcan_runs`):
each mostly waits (~11-14 s of wall for well under a second of CPU), one after another they took
~50 s. The udp_multicast runs take the machine-wide bus lock, one at a time, in their own tests."""

from __future__ import annotations

import pytest

from host.conformance import AuditedCanTransport, CHECKS, Port, run_checks
from host.transport.ports import CanTransport, SerialTransport
from tests.host.cli.cli_runs import udp_bus_lock  # noqa: F401 (fixture)
from tests.host.cli.test_host import ONE_MULTICAST_BUS, _udp_or_skip
from tests.host.conformance.mutants import CounterOffByOne
from tests.shared_runs import session_root, shared_runs
from virtual_sheet.devices import CanDevice, PtyDevice
from virtual_sheet.sheet import VirtualSheet
from virtual_sheet.slcan import SlcanDevice

OWN = {"serial": {21}, "can": {22, 41, 44}}  # a transport's own checks
#: the §16 checks (6/9-axis chips): an accelerometer chip skips them, saying so
IMU_CHECKS = {42, 43, 44}


def _outcomes(kind, chip_class):
    sheet = VirtualSheet("flat", "2x2", transport="serial" if kind == "pty" else "can", noise=0.5,
                         chip_factory=chip_class)
    if kind == "pty":
        dev = PtyDevice(sheet).start()
        t = SerialTransport(str(dev.path), reconnect=False)
    elif kind == "slcan":
        dev = SlcanDevice(sheet).start()
        t = CanTransport(f"slcan:{dev.path}", bitrate=1_000_000, reconnect=False, sleep_after_open=0)
    else:
        _udp_or_skip()
        dev = CanDevice(sheet, interface="udp_multicast", channels=["239.74.163.2"]).start()
        t = AuditedCanTransport("udp_multicast:239.74.163.2", reconnect=False)
    port = Port(t)
    try:
        results = run_checks(port, timeout_s=0.3, allow_broadcast=True, slack_ms=40.0)  # as the matrix
    finally:
        port.close()
        t.close()
        dev.stop()
    return {r.number: r.outcome for r in results}, "\n".join(r.line() for r in results)


def _expected(kind, failing=frozenset()):
    own = OWN["serial" if kind == "pty" else "can"]
    common = {c.number for c in CHECKS if "chip" in c.profiles} - OWN["serial"] - OWN["can"]
    return {n: ("FAIL" if n in failing else "SKIP" if n in IMU_CHECKS else "PASS") for n in common | own}


#: the chips run on every transport: a healthy one, and one that breaks the SYNC counter
CHIPS = {"healthy": None, "counter_off_by_one": CounterOffByOne}
#: the transports whose runs are made at once (`pty_and_slcan_runs`)
AT_ONCE_KINDS = ("pty", "slcan")


@pytest.fixture(scope="module")
def pty_and_slcan_runs(tmp_path_factory) -> dict:
    """``{"KIND/CHIP": {"outcomes": [[number, outcome], ...], "report": text} or {"error"}}``: the pty and
    SLCAN runs made at once in threads, each with its own sheet and pty, once per test session whichever
    workers need them (tests/shared_runs.py)."""
    def job(kind, chip):
        def run(_k):
            try:
                got, report = _outcomes(kind, CHIPS[chip])
            except Exception as exc:  # noqa: BLE001 - raised again by the run's own test
                return {"error": f"{type(exc).__name__}: {exc}"}
            return {"outcomes": sorted(got.items()), "report": report}
        return run
    jobs = {f"{kind}/{chip}": job(kind, chip) for kind in AT_ONCE_KINDS for chip in CHIPS}
    return shared_runs(session_root(tmp_path_factory), "conformance-transports", jobs, at_once=len(jobs))


@pytest.mark.parametrize("chip,failing", [("healthy", set()), ("counter_off_by_one", {24, 25, 26, 27})],
                         ids=list(CHIPS))
@pytest.mark.parametrize("kind", ["pty", "slcan", pytest.param("udp_multicast", marks=ONE_MULTICAST_BUS)])
def test_the_same_verdicts_on_every_transport(request, kind, chip, failing):
    """A healthy chip passes every check, a broken one fails the same checks, on each transport."""
    if kind == "udp_multicast":
        request.getfixturevalue("udp_bus_lock")
        got, report = _outcomes(kind, CHIPS[chip])
    else:
        run = request.getfixturevalue("pty_and_slcan_runs")[f"{kind}/{chip}"]
        if "error" in run:
            raise AssertionError(f"{kind}/{chip}: the conformance run raised {run['error']}")
        got, report = {n: outcome for n, outcome in run["outcomes"]}, run["report"]
    assert got == _expected(kind, failing=failing), report
