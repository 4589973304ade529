"""`capsheet conformance` against both virtual chips (the Python model and the C firmware through cffi),
on a pty serial port and a python-can virtual bus, through the virtual sheet's own devices; on a
full sheet (the chip under test alone is touched); over a port that damages frames (losses are
reported as the port's, not as chip violations); and the command line.

Where the subject is what the checks and the runner decide (a 6/9-axis chip's §16 checks, the
broadcast skip, a full sheet, a lossy port, a late chip, nodes counted by uid, a 1.2 chip's check 45)
the run is on the simulated clock (`_run_simulated`: in-process, no waiting, the same every run).
Where it is the transport or the real process — every healthy accelerometer chip, Python and C, over
a real pty and a python-can bus, in real time; the command line; the port going away — it is real."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from host.cli import main
from host.conformance import CHECKS, INFORMATIVE, Port, run_checks, select, summary, table
from host.conformance.checks import clauses_covered
from host.conformance.runner import CheckResult
from tests.host.conformance.simulated_runs import simulated_port
from host.transport.ports import MemoryTransport, TransportError
from protocol.messages import Assign, ChipState, Config
from tests.host.conformance.real_runs import real_runs, result  # noqa: F401 (fixture)
from virtual_sheet.devices import MemoryDevice, PtyDevice
from virtual_sheet.sheet import VirtualSheet

ROOT = Path(__file__).resolve().parents[3]


def _run_simulated(sheet, **kw):
    """The checks against ``sheet``'s chips on the simulated clock (`host.conformance.simulated`)."""
    with simulated_port(sheet) as port:
        return run_checks(port, timeout_s=0.3, **kw)


#: the chip checks of §16 (6/9-axis chips): skipped on an accelerometer chip (46, §16.5, is a gateway's)
IMU_CHECKS = {c.number for c in CHECKS if c.clauses[0].startswith("16") and "chip" in c.profiles}
assert len(IMU_CHECKS) == 3


def _healthy(runs, key):
    """The real-time run ``key`` of tests/host/conformance/real_runs.py (made at once with the others)."""
    return [CheckResult(**r) for r in result(runs, key)]


#: the 6/9-axis runs: (transport, sensors)
IMU_RUNS = [("serial", "accel+gyro+mag"), ("can", "accel+gyro")]


@pytest.mark.parametrize("transport", ["serial", "can"])
def test_every_check_passes_on_a_virtual_chip(chip_class, transport, real_runs):
    """The whole suite in real time against a healthy accelerometer chip over a real pty and a python-can
    bus (tests/host/conformance/real_runs.py)."""
    name = "python" if chip_class.__name__ == "ChipModel" else "c"
    results = _healthy(real_runs, f"healthy/{name}/{transport}")
    report = "\n".join(r.line() for r in results)
    assert [r for r in results if r.outcome != "PASS" and r.number not in IMU_CHECKS] == [], report
    # an accelerometer chip: §16 does not apply, said so
    skipped = [r for r in results if r.outcome == "SKIP"]
    assert {r.number for r in skipped} == IMU_CHECKS & {r.number for r in results}
    assert all("no GYRO" in r.detail for r in skipped), report
    # every check of the chip profile ran, except the other transport's own
    assert [r.number for r in results] == [c.number for c in CHECKS if c.transport in (None, transport)
                                           and "chip" in c.profiles]
    n_skip = len(skipped)
    assert summary(results) == f"conformance: {len(results) - n_skip} checks passed, 0 failed, {n_skip} skipped"


@pytest.mark.parametrize("transport, sensors", IMU_RUNS)
def test_every_check_passes_on_a_6_or_9_axis_chip(transport, sensors):
    """The Python chip model as a 6/9-axis chip on a sheet at rest: the §16 checks run and pass too
    (on the simulated clock: the subject is the §16 checks; the transports are the accelerometer runs')."""
    results = _run_simulated(VirtualSheet("flat", "2x2", transport=transport, noise=0.5, sensors=sensors),
                             allow_broadcast=True)
    report = "\n".join(r.line() for r in results)
    assert [r for r in results if r.outcome != "PASS"] == [], report
    assert IMU_CHECKS & {r.number for r in results} == (IMU_CHECKS if transport == "can" else IMU_CHECKS - {44})


def test_broadcast_checks_are_skipped_unless_allowed():
    sheet = VirtualSheet("flat", "2x2", noise=0.5)
    results = _run_simulated(sheet, only=[str(c.number) for c in CHECKS if c.broadcast])
    broadcast = [r for r in results if r.number in {c.number for c in CHECKS if c.broadcast}]
    assert broadcast and all(r.outcome == "SKIP" and "--allow-broadcast" in r.detail for r in broadcast)


def test_a_full_sheet_is_left_as_found():
    """A 3x3 sheet assigned by a host session (one chip at 42, the old default, one at 0x7FFF):
    the run picks a node id nobody uses and touches only the chip under test."""
    sheet = VirtualSheet("flat", "3x3", noise=0.5)
    with simulated_port(sheet) as port:
        dev = port.device
        from protocol.framing import encode
        nodes = list(range(1, len(sheet.chips) + 1))
        nodes[3], nodes[5] = 42, 0x7FFF

        def commission(now):
            for k, c in enumerate(sheet.chips):
                c.handle(encode(Assign(c.node, nodes[k], k, c.uid & 0xFFFFFFFF)), now)
                c.handle(encode(Config(nodes[k], heartbeat_ms=0)), now)
            # chip 0 stays assigned: it is the one under test (the first to answer GET_INFO)
            return [(c.node, c.state, c.link) for c in sheet.chips]
        before = dev.call(commission)
        results = run_checks(port, timeout_s=0.3)
        after = dev.call(lambda now: [(c.node, c.state, c.link) for c in sheet.chips])
    report = "\n".join(r.line() for r in results)
    assert [r for r in results if r.outcome == "FAIL"] == [], report
    d = results[0].detail
    m = re.search(r"the run uses node 0x([0-9A-F]{4})", d)
    assert m and int(m.group(1), 16) not in nodes, d
    assert after[1:] == before[1:]  # every other chip as it was (node, state, link)
    assert after[0][1] == ChipState.BOOT  # the chip under test is left unassigned


def test_a_node_given_that_another_chip_uses_aborts_the_run(capsys):
    sheet = VirtualSheet("flat", "2x2", noise=0.5)
    with PtyDevice(sheet) as dev:
        from protocol.framing import encode

        def assign_second(now):
            c = sheet.chips[1]
            c.handle(encode(Assign(c.node, 42, 1, c.uid & 0xFFFFFFFF)), now)
        dev.call(assign_second)
        code = main(["conformance", "--port", str(dev.path), "--timeout", "0.3", "--node", "42", "--only", "2"])
    assert code == 2
    assert "--node 0x002A is in use by another node" in capsys.readouterr().err


def test_a_lossy_port_is_reported_as_lost_frames_not_as_chip_violations():
    """Bit flips on the way to the host: damaged answers make checks fail once; they are retried
    and reported PASS (after a retry) or LOST — never FAIL."""
    sheet = VirtualSheet("flat", "2x2", noise=0.5, faults="bitflip=3e-4,seed=7")
    with simulated_port(sheet) as port:
        results = run_checks(port, timeout_s=0.3)
        injected = sheet.fault_stats.frames_corrupted
    report = "\n".join(r.line() for r in results)
    assert injected > 0 and port.lost > 0, report
    assert [r for r in results if r.outcome == "FAIL"] == [], report
    retried = [r for r in results if r.attempts > 1]
    assert retried, report  # the damage hit at least one check, which was run again
    for r in retried:
        assert ("port lost" in r.detail) if r.outcome == "PASS" else ("port lost frames" in r.detail), r.line()
    assert all(r.outcome in ("PASS", "LOST", "SKIP") for r in results)


def test_the_port_going_away_raises_the_transport_error():
    """The host's end of the link breaks mid-run (once the first check's result is out): the run ends
    with the transport's error."""
    sheet = VirtualSheet("flat", "2x2", noise=0.5)
    dev = MemoryDevice(sheet).start()
    t = MemoryTransport(dev.port)
    port = Port(t)
    lines = []

    class BreakAfterTheFirstResult:
        def write(self, text):
            if text.strip():
                lines.append(text)
                dev.port.close()

        def flush(self):
            pass
    try:
        with pytest.raises(TransportError):
            run_checks(port, timeout_s=0.3, out=BreakAfterTheFirstResult())
    finally:
        port.close()
        dev.stop()
    # it broke mid-run: after discovery, before the end (a check after the break raised the error)
    assert lines and lines[0].startswith("PASS   1") and len(lines) < len(select(None)), lines


def test_select_rejects_unknown_items():
    assert [c.number for c in select(["5"])] == [1, 5]
    assert {c.number for c in select(["4.6"])} >= {1, 12, 16, 19, 31}
    assert [c.number for c in select(["36"], "gateway")] == [33, 36]  # the gateway profile's discovery first
    for bad in ("99", "0", "§13", "4.99"):
        with pytest.raises(ValueError, match="Invalid --only item"):
            select([bad])
    with pytest.raises(ValueError, match="no check 5 in the gateway profile"):
        select(["5"], "gateway")


def test_list_and_usage_errors(capsys):
    assert main(["conformance", "--list"]) == 0
    assert capsys.readouterr().out == table()
    assert main(["conformance"]) == 2
    assert main(["conformance", "--port", "/nonexistent/tty"]) == 2
    assert "Cannot open serial port" in capsys.readouterr().err
    assert main(["conformance", "--port", "loop://", "--only", "99"]) == 2
    assert "there is no check 99" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # a usage error, from the argument's type: one line, exit 2
        main(["conformance", "--port", "loop://", "--node", "0x8000"])
    assert exc.value.code == 2
    assert "--node: invalid value '0x8000': need an assigned node id >= 1 and <= 32767" in capsys.readouterr().err


def test_the_cli_exits_non_zero_on_a_failing_chip(real_runs):
    """``capsheet conformance --only 5.1`` in a process of its own against the counter mutant on a pty
    (tests/host/conformance/real_runs.py, ``cli/failing``)."""
    run = result(real_runs, "cli/failing")
    out = run["stdout"]
    assert run["code"] == 1, out + run["stderr"]
    assert re.search(r"^FAIL\s+24\s+§5\.1.*SYNC 0x0064 answered with counter 0x0065", out, re.M), out
    assert "failed" in out.splitlines()[-1]


# ---- the clause table --------------------------------------------------------------------

def _headings(text: str) -> list[str]:
    return re.findall(r"^#{2,3} (\d+(?:\.\d+)?)\.? ", text, re.M)


def uncovered(headings: list[str]) -> list[str]:
    covered = clauses_covered()  # a section is covered through its subclauses (§3 by §3.1, §3.2)
    return [h for h in headings if h not in INFORMATIVE and not any(c == h or c.startswith(h + ".") for c in covered)]


def test_every_normative_clause_of_the_spec_has_a_check():
    headings = _headings((ROOT / "docs/protocol.md").read_text())
    assert len(headings) > 30 and "4.6" in headings and "8.1" in headings
    assert uncovered(headings) == []
    # and the test can fail: a clause the registry does not know is reported
    assert uncovered(headings + ["19", "4.17"]) == ["19", "4.17"]
    # every clause a check cites exists in the spec
    assert clauses_covered() - set(headings) == set()


def test_docs_conformance_md_is_the_table():
    doc = (ROOT / "docs/conformance.md").read_text()
    assert table() in doc, "regenerate docs/conformance.md: capsheet conformance --list"


def test_a_late_chip_is_reported_against_the_should_not_failed():
    """§5.1's 2 ms reply deadline is a SHOULD: a chip that answers 25 ms late passes, and says so."""
    sheet = VirtualSheet("flat", "2x2", noise=0.5, faults="delay_ms=25")
    results = _run_simulated(sheet, only=["24"])
    sync = results[1]
    assert (sync.number, sync.outcome) == (24, "PASS"), sync.line()
    assert sync.detail.startswith("SHOULD not met: the median SYNC->SAMPLE is over 2 ms"), sync.line()
    assert "(1 with a SHOULD not met)" in summary(results)


def test_nothing_passes_on_zero_evidence():
    """A port nobody serves: discovery fails and every other check is a SKIP saying why — none PASSes
    on nothing (the 1.0 suite said "1 passed, 2 failed": check 31 passed on "0 frames compared")."""
    from virtual_sheet.memport import memory_link
    host_end, _dev_end = memory_link("nobody", timeout=0.1)
    port = Port(MemoryTransport(host_end))
    try:
        results = run_checks(port, timeout_s=0.2, allow_broadcast=True)
    finally:
        port.close()
    report = "\n".join(r.line() for r in results)
    assert (results[0].number, results[0].outcome) == (1, "FAIL"), report
    assert all(r.outcome == "SKIP" for r in results[1:]), report
    assert summary(results) == f"conformance: 0 checks passed, 1 failed, {len(results) - 1} skipped"


def test_nodes_heard_are_counted_by_uid():
    """12 chips re-announcing from new provisional ids every second are 12 chips, not one per node id
    (the 1.0 suite reported 363 to 2,006 "nodes" on a 364-chip sheet)."""
    sheet = VirtualSheet("flat", "3x3", noise=0.5)
    with simulated_port(sheet) as port:
        port.sleep(1.2)  # a re-announce round: every chip speaks from a second provisional id
        results = run_checks(port, timeout_s=0.3, only=["1"])
    assert results[0].outcome == "PASS" and "12 chip(s) and 0 gateway(s) answered (by uid)" in results[0].detail, \
        results[0].line()


def test_the_gateway_profile_from_the_command_line(real_runs):
    """``capsheet conformance --profile gateway --only 13.1`` in a process of its own against a packing
    gateway on a pty (tests/host/conformance/real_runs.py, ``cli/gateway``); a chip check refused in it."""
    run = result(real_runs, "cli/gateway")
    out = run["stdout"]
    assert run["code"] == 0, out + run["stderr"]
    assert "gateway profile" in out.splitlines()[0] and re.search(r"^PASS\s+33\s+§13\.1", out, re.M), out
    assert main(["conformance", "--port", "loop://", "--profile", "gateway", "--only", "5"]) == 2


def test_the_announce_and_heartbeat_periods_ignore_one_event_read_late():
    """Checks 8 and 9 time a node's free-running deadlines from the host; one event the host read
    late (the busy-core stability run: re-announces at 1.003 then 1.143 s) must not fail a healthy
    node, while a node whose own period is off must."""
    from host.conformance.checks import theil_sen_period
    late = [0.0, 1.003, 2.146, 3.001]  # boot, then the second re-announce read 143 ms late
    assert abs(theil_sen_period(late) - 1.0) <= 0.06
    # the mean of the first two periods, as the check used to take, fails the same node
    assert abs((late[2] - late[0]) / 2 - 1.0) > 0.06
    slow = [0.0, 1.1, 2.2, 3.3]                          # a chip whose own clock runs 10 % slow
    assert abs(theil_sen_period(slow) - 1.0) > 0.06
    slow_and_late = [0.0, 1.1, 2.35, 3.3]
    assert abs(theil_sen_period(slow_and_late) - 1.1) < 0.02
    with pytest.raises(ValueError, match="at least 2"):
        theil_sen_period([1.0])


class _ChipV12:
    """A chip of protocol 1.2 (docs/protocol.md §17.2, §8.1): CAL_IMU_WRITE (0x1A) and CAL_IMU_READ (0x1B)
    are undefined types to it, answered NACK 1 UNKNOWN_COMMAND when addressed to it. ``write_known``: a
    broken one that knows CAL_IMU_WRITE but not CAL_IMU_READ."""

    write_known = False

    @classmethod
    def factory(cls, base):
        from protocol.messages import MsgType, Nack, NackReason

        class Chip(base):
            def handle(self, frame, now_s, decoded=None):
                msg = self.decode(frame) if decoded is None else decoded
                t = getattr(msg, "TYPE", None)
                if t == MsgType.CAL_IMU_READ or (t == MsgType.CAL_IMU_WRITE and not cls.write_known):
                    return [self._out(Nack(self.node, t, NackReason.UNKNOWN_COMMAND))] if msg.node == self.node else []
                return super().handle(frame, now_s, decoded)
        return Chip


class _HalfV12(_ChipV12):
    write_known = True


@pytest.mark.parametrize("sensors", ["accel", "accel+gyro"])
def test_check_45_skips_a_chip_of_1_2_that_answers_nack_1_and_fails_one_that_knows_half(sensors):
    """§17.2: a 1.2 chip (accelerometer-only or 6-axis) answers the 1.3 types NACK 1 UNKNOWN_COMMAND; the wire
    has no minor version, so that is conforming and check 45 is skipped, saying why — not failed. A chip that
    knows CAL_IMU_WRITE but answers CAL_IMU_READ NACK 1 is neither: it fails."""
    from virtual_sheet.chip import ChipModel
    for kind, outcome in ((_ChipV12, "SKIP"), (_HalfV12, "FAIL")):
        sheet = VirtualSheet("flat", "2x2", noise=0.5, sensors=sensors, chip_factory=kind.factory(ChipModel))
        results = _run_simulated(sheet, only=["45"])
        r = next(x for x in results if x.number == 45)
        assert r.outcome == outcome, "\n".join(x.line() for x in results)
        if outcome == "SKIP":
            assert "NACK 1 UNKNOWN_COMMAND: a chip of protocol 1.2 or earlier" in r.detail
        else:
            assert "knows both types or neither" in r.detail
