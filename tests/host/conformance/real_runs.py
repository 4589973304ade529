"""The conformance runs in real time, over real transports, that test_checks.py and test_transports.py
read: made at once, in threads (and the command line's runs in processes of their own), once per
test session, whichever workers need them splitting the runs (tests/shared_runs.py).

A run in real time mostly waits for what the spec makes a chip wait for — the silences it must keep,
its heartbeats (100 ms), its re-announces (1 s): ~11 s of wall for ~0.3 s of CPU, whatever the
transport. The two files' runs were two sets one after another (~11 s, then ~14 s, then the two
udp_multicast runs in turn, ~12 s each); here they are one set, ~11-14 s in all.

What each run is for (its subject is the transport, or the real process; what the checks decide on a
chip is tested on the simulated clock, tests/host/conformance/test_mutants.py and test_checks.py):

* ``healthy/{python,c}/{serial,can}``: the whole suite against a healthy accelerometer chip (the
  Python model, the C firmware through cffi) over a real pty and a python-can virtual bus
  (test_checks.py; the Python chip's pty run is also test_transports.py's pty run);
* ``slcan/healthy``: the whole suite over an SLCAN adapter on a pty (test_transports.py);
* ``{pty,slcan}/counter_off_by_one``: the checks a chip that answers SYNC n with counter n + 1 fails
  (24-27), over the transport: what a failing chip's answers give over it (test_transports.py);
* ``udp_multicast``: both of the above over python-can's udp_multicast bus, one after the other in one
  thread that holds the machine-wide bus lock (tests/host/udp_lock.py) for just those runs;
* ``cli/gateway``, ``cli/failing``: ``capsheet conformance`` in a process of its own against a
  virtual sheet's pty in this one: the gateway profile, and a failing chip's exit status
  (test_checks.py).

Every job returns JSON (`shared_runs`): a run's results as dicts, or ``{"error": ...}`` (`shared_runs` records a job that raised; raised again
by the test that reads it), or ``{"skip": ...}`` (no udp_multicast on this machine)."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import threading

import pytest

from host.conformance import AuditedCanTransport, Port, run_checks
from host.transport.ports import CanTransport, SerialTransport
from tests.shared_runs import result_of, session_root, shared_runs
from virtual_sheet.devices import CanDevice, PtyDevice
from virtual_sheet.sheet import VirtualSheet
from virtual_sheet.slcan import SlcanDevice

__all__ = ["real_runs", "result", "COUNTER_CHECKS", "UDP_GROUP", "chip_classes"]

#: the checks a chip that answers SYNC n with counter n + 1 fails (`CounterOffByOne`): the ones its
#: real-transport runs select (the whole suite against it is on the simulated clock, test_transports.py)
COUNTER_CHECKS = ("24", "25", "26", "27")
UDP_GROUP = "239.74.163.2"


def chip_classes() -> dict:
    """``{"python": ChipModel, "c": CFirmwareChip}`` (the C firmware only where its extension was built)."""
    from virtual_sheet.chip import ChipModel
    chips = {"python": ChipModel}
    try:
        from firmware_ref.chip import CFirmwareChip
    except ImportError:  # not built: its tests are skipped (tests/conftest.py's chip_class)
        pass
    else:
        chips["c"] = CFirmwareChip
    return chips


def _sheet(transport: str, chip_factory=None, **kw) -> VirtualSheet:
    return VirtualSheet("flat", "2x2", transport=transport, noise=0.5, chip_factory=chip_factory, **kw)


def _checks(kind: str, chip_factory, k: int, **run_kw) -> list[dict]:
    """The checks (``run_kw``: `run_checks`'s options) against a 2x2 sheet's chip over ``kind``: "pty",
    "can" (python-can virtual, channel of its own), "slcan" (an adapter on a pty) or "udp_multicast"."""
    sheet = _sheet("serial" if kind == "pty" else "can", chip_factory)
    if kind == "pty":
        dev = PtyDevice(sheet).start()
        t = SerialTransport(str(dev.path), reconnect=False)
    elif kind == "can":
        dev = CanDevice(sheet, channels=[f"real-runs-{k}"]).start()
        t = AuditedCanTransport(f"virtual:{dev.channels[0]}", reconnect=False)
    elif kind == "slcan":
        dev = SlcanDevice(sheet).start()
        t = CanTransport(f"slcan:{dev.path}", bitrate=1_000_000, reconnect=False, sleep_after_open=0)
    else:
        dev = CanDevice(sheet, interface="udp_multicast", channels=[UDP_GROUP]).start()
        t = AuditedCanTransport(f"udp_multicast:{UDP_GROUP}", reconnect=False)
    port = None
    try:
        port = Port(t)
        return [dataclasses.asdict(r) for r in run_checks(port, timeout_s=0.3, **run_kw)]
    finally:
        if port is not None:
            port.close()
        t.close()
        dev.stop()


def _udp(k: int) -> dict:
    """The healthy chip's and the counter mutant's udp_multicast runs, under the machine-wide bus lock."""
    from tests.host.conformance.mutants import CounterOffByOne
    from tests.host.udp_lock import udp_multicast_lock
    try:
        import can
        can.Bus(interface="udp_multicast", channel=UDP_GROUP).shutdown()
    except Exception as exc:  # noqa: BLE001 - no multicast route on this machine
        return {"skip": f"udp_multicast not available here: {exc}"}
    with udp_multicast_lock():
        return {"healthy": _checks("udp_multicast", None, k, allow_broadcast=True, slack_ms=40.0),
                "counter_off_by_one": _checks("udp_multicast", CounterOffByOne, k, allow_broadcast=True,
                                              slack_ms=40.0, only=list(COUNTER_CHECKS))}


def _cli(sheet: VirtualSheet, args: list[str], **device_kw) -> dict:
    """``capsheet conformance --port PTY ARGS`` in a process of its own against ``sheet`` on a pty here."""
    with PtyDevice(sheet, **device_kw) as dev:
        p = subprocess.run([sys.executable, "-m", "host.cli", "conformance", "--port", str(dev.path), *args],
                           capture_output=True, text=True, timeout=300)
    return {"code": p.returncode, "stdout": p.stdout, "stderr": p.stderr}


#: runs whose checks run in this process at once. Each has a device thread, a port reader and the runner,
#: all under one GIL: on a loaded machine, with eight at once, the thread that held it was preempted and
#: the others waited — a pty's nine heartbeats read at once, their period 6-16 ms (load 13). Four at once
#: held before; the command line's runs (processes of their own) come on top.
IN_PROCESS_AT_ONCE = 4
_in_process = threading.BoundedSemaphore(IN_PROCESS_AT_ONCE)


def _jobs() -> dict:
    """The runs, the command line's first (they wait in their own processes), then the longest."""
    from tests.host.conformance.mutants import CounterOffByOne
    jobs = {"cli/gateway": lambda k: _cli(_sheet("serial"), ["--timeout", "0.3", "--profile", "gateway",
                                                             "--only", "13.1"], packed=True),
            "cli/failing": lambda k: _cli(_sheet("serial", CounterOffByOne), ["--timeout", "0.3", "--only", "5.1"]),
            "udp_multicast": _udp,
            "slcan/healthy": lambda k: _checks("slcan", None, k, allow_broadcast=True, slack_ms=40.0)}
    for t in ("serial", "can"):  # the default slack (10 ms), as `capsheet conformance` has
        for name, cls in chip_classes().items():
            jobs[f"healthy/{name}/{t}"] = (lambda k, cls=cls, t=t: _checks("pty" if t == "serial" else "can", cls, k,
                                                                          allow_broadcast=True))
    for kind in ("pty", "slcan"):
        jobs[f"{kind}/counter_off_by_one"] = (lambda k, kind=kind: _checks(
            kind, CounterOffByOne, k, allow_broadcast=True, slack_ms=40.0, only=list(COUNTER_CHECKS)))
    return jobs


def _guarded(key, job):
    """``job``, held to `IN_PROCESS_AT_ONCE` unless it is a command-line run (its own process)."""
    def run(k):
        if key.startswith("cli/"):
            return job(k)
        with _in_process:
            return job(k)
    return run


@pytest.fixture(scope="module")
def real_runs(tmp_path_factory) -> dict:
    """``{key: result}`` of every run above (see the module docstring), made once per test session."""
    jobs = {key: _guarded(key, job) for key, job in _jobs().items()}
    return shared_runs(session_root(tmp_path_factory), "conformance-real", jobs, at_once=IN_PROCESS_AT_ONCE + 2)


def result(runs: dict, key: str):
    """The run's result; AssertionError if it raised, pytest.skip if it could not run here."""
    got = result_of(runs, key)
    if isinstance(got, dict) and "skip" in got:
        pytest.skip(got["skip"])
    return got
