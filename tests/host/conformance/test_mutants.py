"""Every check is shown able to fail, and the suite passes what conforms.

* Each Python mutant (tests/host/conformance/mutants.py) breaks one MUST and must fail exactly the
  checks that hold a node to that rule — no more (the suite does not blame the wrong clause), no fewer
  (the rule is checked) — and the failure names the clause.
* Each C firmware mutant (the -DCAPSHEET_MUTANTS test build) fails the checks of its Python twin (run
  on those checks only: the full-run "no more" property is the Python side's).
* Each gateway mutant fails the gateway profile's check of the rule it breaks.
* The healthy variants pass every check of their profile, once each here; 20 runs in a row are
  `benchmarks/bench_conformance_stability.py`'s job, not the test suite's.

Every run here is on a simulated clock (`host.conformance.simulated`): the chips are models in this
process (Python, or the C firmware through cffi, both driven by the ``now`` they are given), and what
is under test is the checks' verdicts, which a real-time run reaches by waiting. On the simulated
clock a run takes ~0.1-0.4 s of CPU and no waiting where it took ~7-25 s of wall in real time, the
same frames at the same instants on every run: no run is starved by the machine's load, so none is
made again (`_verdict`, before, made a run that failed a timed check beyond its own once more).
`benchmarks/bench_conformance_clock.py` compares every run's verdict on both clocks. The runs over a
real transport, in real time, are tests/host/conformance/test_checks.py's (a pty, python-can),
tests/firmware_ref's (the C firmware over a pty, QEMU) and tests/host/test_matrix.py's.
"""

from __future__ import annotations

import pytest

from host.conformance import CHECKS, AuditedCanTransport, Port, run_checks
from host.conformance.runner import CheckResult
from tests.host.conformance.simulated_runs import simulated_port
from host.transport.ports import MemoryTransport
from tests.host.conformance.mutants import (C_MUTANT_EVIDENCE, C_MUTANT_OPTIONS, C_MUTANTS, GATEWAY_MUTANTS, HEALTHY,
                                            IMU_MUTANTS, MUTANTS)
from virtual_sheet.devices import CanDevice, MemoryDevice
from virtual_sheet.sheet import VirtualSheet

#: mutant -> the checks it must fail (check numbers: `capsheet conformance --list`)
EXPECTED = {
    "dead_sensor": {25, 26},  # |a| = 0 g at rest; no conversion at the new range either
    "frozen_sample": {26},  # the old range's counts, unflagged, after a range change
    "wrong_crc": {1, 39},  # nothing decodes: not discovered; the framing check blames the chip, not the port
    "wrong_crc_sample": {24, 25, 26, 27, 39},  # every SYNC check: §6.2, not "port lost frames"
    "counter_off_by_one": {24, 25, 26, 27},  # every check that matches SAMPLEs to SYNCs
    "wrong_byte_order": {24, 25, 26, 27},
    "sync_answered_twice": {24},
    "slow_heartbeat": {11},
    "no_reannounce": {8, 9},  # no round: no previous id either
    "no_previous_id": {9},
    "wrong_nack_reason": {5, 12, 14, 16, 17, 18, 28, 45},  # every check expecting a NACK (45: §17's NACK 5)
    "ignored_reset": {3, 4, 5, 6, 7, 8, 9, 30},  # every check that needs a fresh BOOT
    "answers_broadcast": {31},
    "nacks_broadcast": {19},
    "ignores_broadcast_start": {32},
    "nacks_chip_types": {15},
    "ack_detail_set": {40},
    "reserved_capability_bit": {2},
    "no_rx_errors": {21},
    "assign_ignores_uid": {6},
    "assigned_id_in_boot": {4, 9},  # never a provisional id: no previous one either
    "uptime_restarts_at_reset": {30},
    "cal_read_nominal": {20},
    "accepts_bad_config": {12},
    "claims_no_multi_range": {13},
    "refuses_repeated_config": {10, 11},  # check 11 sends the same CONFIG three times
    "start_not_idempotent": {23},
    "streams_after_stop": {26, 29},  # still streaming: the range change is refused
    "missed_syncs_counts_wrap": {27},
    "config_while_streaming": {28},
    "wrong_priority": {39, 41},  # CAN: the priority audit, and the DBC lookup (priority bits are in its id)
}

#: gateway mutant -> the gateway profile's checks it must fail
GATEWAY_EXPECTED = {
    "silent_gateway": {33},
    "passes_host_sync": {37},
    "packs_only_answers": {38},
    "acks_chip_commands": {35},
    "gateway_without_status": {36},
    "packing_without_capability": {34},
    "gateway_nacks_broadcast": {19},
    "imu_gateway_leaves_chips_in_format_0": {46},  # §16.5: its chip's link INVALID, the chip's SAMPLE passed on
}

#: §16/§17 mutant (6/9-axis chips) -> the checks it must fail (an IMU_ACCEL first leaves every record incomplete
#: for the host's decoder, so checks 43 and 45 see no record either)
IMU_EXPECTED = {
    "imu_answers_sample": {43, 45},  # 45 sees no record to check the correction in
    "imu_time_without_capability": {43},
    "imu_accepts_bad_config": {42},
    "imu_accel_first": {43, 44, 45},
    "cal_imu_read_nominal": {45},
}
#: the §16 and §17 checks, which only a 6/9-axis mutant fails
IMU_CHECKS = {42, 43, 44, 45}
#: the chip checks no C mutant fails (every §16 and §17 check has one since v1.3's C mutants)
NO_C_MUTANT: set[int] = set()

#: checks no mutant here can fail, and why (the virtual CAN device drops standard frames before any chip)
NOT_SHOWN = {22: "the virtual CanDevice filters standard-identifier frames before the chips see them"}


#: host-side latency allowed on top of the spec's timing tolerances (the CLI's --slack-ms) in a
#: real-time run (`simulated=False`, benchmarks/bench_conformance_clock.py): the chips run in this
#: process's threads, and on a loaded 2-core machine a frame is sometimes handed over 100 ms late — the
#: mutants are about verdicts, none breaks a timing by less than 2x (as the matrix). On the simulated
#: clock there is no host latency: the runs there take the CLI's default (10 ms).
SLACK_MS = 40.0


def _run(sheet, *, allow_broadcast=False, profile="chip", only=None, simulated=True, **dev):
    """The checks against ``sheet``'s device: on the simulated clock (the default), or in real time
    through the device's thread (``simulated=False``: the comparison of the two, and the stability
    benchmark's way)."""
    if simulated:
        with simulated_port(sheet, **dev) as port:
            return run_checks(port, timeout_s=0.3, allow_broadcast=allow_broadcast, profile=profile, only=only)
    if sheet.transport == "serial":
        with MemoryDevice(sheet, **dev) as d:
            port = Port(MemoryTransport(d.port))
            try:
                return run_checks(port, timeout_s=0.3, allow_broadcast=allow_broadcast, profile=profile, only=only,
                                  slack_ms=SLACK_MS)
            finally:
                port.close()
    with CanDevice(sheet, **dev) as d:
        t = AuditedCanTransport(f"virtual:{d.channels[0]}", reconnect=False)
        port = Port(t)
        try:
            return run_checks(port, timeout_s=0.3, allow_broadcast=allow_broadcast, profile=profile, only=only,
                                  slack_ms=SLACK_MS)
        finally:
            port.close()
            t.close()


def _python_mutant_jobs(simulated: bool = True) -> dict:
    """``{key: run(k)}``: every Python chip, IMU and gateway mutant's run (``k``: in real time, a channel
    number of its own for a CAN run, the device's default channel being one name for every bus of this
    process; `simulated_port` gives each run a channel of its own)."""
    def can(transport, k):
        return {"channels": [f"mutant{k}"]} if transport == "can" and not simulated else {}
    jobs = {}
    for name, (cls, transport, allow_broadcast) in MUTANTS.items():
        jobs[f"chip:{name}"] = lambda k, cls=cls, transport=transport, allow_broadcast=allow_broadcast: _run(
            VirtualSheet("flat", "2x2", transport=transport, noise=0.5, chip_factory=cls),
            allow_broadcast=allow_broadcast, simulated=simulated, **can(transport, k))
    for name, (cls, transport, sensors) in IMU_MUTANTS.items():
        jobs[f"imu:{name}"] = lambda k, cls=cls, transport=transport, sensors=sensors: _run(
            VirtualSheet("flat", "2x2", transport=transport, noise=0.5, chip_factory=cls, sensors=sensors),
            simulated=simulated, **can(transport, k))
    for name, (cls, opts) in GATEWAY_MUTANTS.items():
        opts = dict(opts)
        sensors = opts.pop("sensors", "accel")
        jobs[f"gateway:{name}"] = lambda k, cls=cls, opts=opts, sensors=sensors: _run(
            VirtualSheet("flat", "2x2", noise=0.5, sensors=sensors), profile="gateway", gateway_class=cls,
            simulated=simulated, **opts)
    return jobs


def _c_mutant_jobs(simulated: bool = True) -> dict:
    """``{name: run(k)}``: every C firmware mutant on its twin's checks (each chip a C struct of its own)."""
    from firmware_ref.chip import CFirmwareChip

    def job(name, k):
        twin = C_MUTANTS[name]

        def factory(uid, sensor, **kw):
            return CFirmwareChip(uid, sensor, mutant=name, **{**kw, **C_MUTANT_OPTIONS.get(name, {})})
        if twin in IMU_MUTANTS:  # a 6/9-axis chip (§16, §17)
            _cls, transport, sensors = IMU_MUTANTS[twin]
            allow_broadcast = False
        else:
            (_cls, transport, allow_broadcast), sensors = MUTANTS[twin], "accel"
        sheet = VirtualSheet("flat", "2x2", transport=transport, noise=0.5, chip_factory=factory, sensors=sensors)
        # its twin's checks, and check 7 (an ASSIGN: an ACK for the reserved-bits check to look at), and
        # what makes the chip send the frame it breaks (C_MUTANT_EVIDENCE: SYNC for a SAMPLE)
        run = {**EXPECTED, **IMU_EXPECTED}[twin] | {7} | C_MUTANT_EVIDENCE.get(name, set())
        return _run(sheet, allow_broadcast=allow_broadcast, only=[str(n) for n in sorted(run)], simulated=simulated,
                    **({"channels": [f"cmutant{k}"]} if transport == "can" and not simulated else {}))
    return {name: (lambda k, name=name: job(name, k)) for name in C_MUTANTS}


def _results(job) -> list[CheckResult]:
    """The run's results (a run that raised fails the test with what it raised)."""
    return job(0)


def _failed(results):
    return {r.number for r in results if r.outcome == "FAIL"}


def _clause_named(results, number):
    """The failure of ``number`` names a clause the check cites (its own, or §6.2 for a node's CRC)."""
    r = next(x for x in results if x.number == number)
    check = next(c for c in CHECKS if c.number == number)
    return any(f"§{c}" in r.detail or f"§{c}" == r.clause.split("/")[0] for c in check.clauses + ("6.2",))


@pytest.mark.parametrize("name", sorted(MUTANTS))
def test_a_mutant_fails_exactly_its_checks(name):
    results = _results(_python_mutant_jobs()[f"chip:{name}"])
    report = "\n".join(r.line() for r in results)
    assert _failed(results) == EXPECTED[name], report
    assert not [r for r in results if r.outcome == "LOST"], report  # a chip fault is never blamed on the port
    assert all(_clause_named(results, n) for n in EXPECTED[name]), report


@pytest.mark.parametrize("name", sorted(IMU_MUTANTS))
def test_an_imu_mutant_fails_exactly_its_checks(name):
    results = _results(_python_mutant_jobs()[f"imu:{name}"])
    report = "\n".join(r.line() for r in results)
    assert _failed(results) == IMU_EXPECTED[name], report
    assert not [r for r in results if r.outcome == "LOST"], report
    assert all(_clause_named(results, n) for n in IMU_EXPECTED[name]), report


def test_every_check_is_failed_by_some_mutant():
    assert set(EXPECTED) == set(MUTANTS) and set(GATEWAY_EXPECTED) == set(GATEWAY_MUTANTS)
    assert set(IMU_EXPECTED) == set(IMU_MUTANTS) and set().union(*IMU_EXPECTED.values()) == IMU_CHECKS
    failed = set().union(*EXPECTED.values(), *GATEWAY_EXPECTED.values(), *IMU_EXPECTED.values())
    assert {c.number for c in CHECKS} - failed == set(NOT_SHOWN)


def test_every_c_mutant_has_a_python_twin():
    pytest.importorskip("firmware_ref._capsheet_fw_mutants", reason="the C mutant build is not there")
    from firmware_ref.chip import C_MUTANTS as BUILT
    assert set(C_MUTANTS) == set(BUILT)
    assert set(C_MUTANTS.values()) <= set(MUTANTS) | set(IMU_MUTANTS)


def test_every_chip_check_is_failed_by_some_c_mutant():
    """The C firmware, too, has a broken build for every check of the chip profile."""
    chip = {c.number for c in CHECKS if "chip" in c.profiles}
    covered = set().union(*({**EXPECTED, **IMU_EXPECTED}[twin] for twin in C_MUTANTS.values()))
    assert chip - covered == set(NOT_SHOWN) | NO_C_MUTANT


@pytest.mark.parametrize("name", sorted(C_MUTANTS))
def test_a_c_firmware_mutant_fails_the_checks_of_its_twin(name):
    pytest.importorskip("firmware_ref._capsheet_fw_mutants", reason="the C mutant build is not there")
    expected = {**EXPECTED, **IMU_EXPECTED}[C_MUTANTS[name]]
    results = _results(_c_mutant_jobs()[name])
    report = "\n".join(r.line() for r in results)
    assert _failed(results) == expected, report
    assert all(_clause_named(results, n) for n in expected), report


@pytest.mark.parametrize("name", sorted(GATEWAY_MUTANTS))
def test_a_gateway_mutant_fails_its_check(name):
    results = _results(_python_mutant_jobs()[f"gateway:{name}"])
    report = "\n".join(r.line() for r in results)
    assert _failed(results) == GATEWAY_EXPECTED[name], report
    assert not [r for r in results if r.outcome == "LOST"], report


def _healthy_jobs(simulated: bool = True) -> dict:
    """``{name: run(k)}``: every healthy variant's run (all on serial: a memory link of its own), and a
    packing gateway's run of the gateway profile as well (``{"chip": results, "gateway": results}``)."""
    def job(name, k):
        sheet_kw, dev_kw = HEALTHY[name]
        sheet_kw = dict(sheet_kw)
        lattice = sheet_kw.pop("lattice", "2x2")
        out = {"chip": _run(VirtualSheet("flat", lattice, **sheet_kw), allow_broadcast=True, simulated=simulated,
                            **dev_kw)}
        if dev_kw.get("packed"):
            out["gateway"] = _run(VirtualSheet("flat", lattice, **sheet_kw), profile="gateway", simulated=simulated,
                                  **dev_kw)
        return out
    return {name: (lambda k, name=name: job(name, k)) for name in HEALTHY}


@pytest.mark.parametrize("name", sorted(HEALTHY))
def test_a_healthy_variant_passes_every_check(name):
    sheet_kw, dev_kw = HEALTHY[name]
    sheet_kw = dict(sheet_kw)
    run = _healthy_jobs()[name](0)
    results = run["chip"]
    report = "\n".join(r.line() for r in results)
    assert [r for r in results if r.outcome not in ("PASS", "SKIP")] == [], report
    skipped = {r.number for r in results if r.outcome == "SKIP"}
    imu = sheet_kw.get("sensors", "accel") != "accel"
    # nothing is skipped but what cannot run here: the CAN check, and chosen counters behind a SYNC source,
    # §16's checks on accelerometer chips, and the records' own checks behind a packing gateway (§16.5)
    assert skipped <= ({27} if dev_kw.get("sync_rate_hz") else set()) | (IMU_CHECKS if not imu else {43, 44, 45}), \
        report
    # the checks of the samples (24-27) read them from whatever the gateway packs: SNAPSHOT or SNAPSHOT_IMU
    assert {24, 25, 26} <= {r.number for r in results if r.outcome == "PASS"}, report
    if dev_kw.get("packed"):  # and the gateway itself passes its profile
        results = run["gateway"]
        report = "\n".join(r.line() for r in results)
        assert [r for r in results if r.outcome not in ("PASS", "SKIP")] == [], report
        # 38 packs SAMPLEs, 46 IMU records (§16.5): a gateway does one of them
        assert {r.number for r in results if r.outcome == "SKIP"} <= \
            ({37} if not dev_kw.get("sync_rate_hz") else set()) | ({38} if imu else {46}), report


@pytest.mark.parametrize("sensors", ["accel+gyro", "accel+gyro+mag"])
def test_a_gateway_packing_imu_records_passes_the_gateway_profile(sensors):
    """The virtual gateway of a 6/9-axis sheet (SNAPSHOT_IMU, §16.5) passes every gateway check: check 46
    (its packing) passes, 38 (SAMPLE packing) and 37 (not a SYNC source) are skipped."""
    results = _run(VirtualSheet("flat", "2x2", noise=0.5, sensors=sensors), profile="gateway", packed=True)
    report = "\n".join(r.line() for r in results)
    assert [r for r in results if r.outcome not in ("PASS", "SKIP")] == [], report
    assert {r.number for r in results if r.outcome == "SKIP"} == {37, 38}, report
    assert next(r for r in results if r.number == 46).outcome == "PASS", report


def test_check_22_fails_a_chip_that_answers_foreign_frames():
    """The virtual CanDevice filters standard-identifier frames, so this mutant sits on the bus itself:
    a chip model behind a python-can virtual bus that NACKs every standard frame it hears."""
    import threading
    import time

    import can

    from protocol.can import CanFrame, to_can
    from protocol.messages import Nack, NackReason
    from virtual_sheet.chip import ChipModel

    channel = f"conformance-foreign-{id(object())}"
    chip = ChipModel(0x1122334455667788, lambda now: ((0, 0, 1024), 0), transport="can")
    bus = can.Bus(interface="virtual", channel=channel)
    stop = threading.Event()
    t0 = time.monotonic()

    def send(frames):
        for f in frames:
            bus.send(can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True, is_fd=f.is_fd))

    def serve():
        send(chip.power_on(0.0))
        while not stop.is_set():
            m = bus.recv(0.005)
            now = time.monotonic() - t0
            if m is not None and not m.is_extended_id:
                send([to_can(Nack(chip.node, 0x3F, NackReason.UNKNOWN_COMMAND))])
            elif m is not None:
                send(chip.handle(CanFrame(m.arbitration_id, bytes(m.data), m.is_fd), now))
            send(chip.poll(now))

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    t = AuditedCanTransport(f"virtual:{channel}", reconnect=False)
    port = Port(t)
    try:
        results = run_checks(port, timeout_s=0.3, only=["22"])
    finally:
        port.close()
        t.close()
        stop.set()
        th.join(timeout=2)
        bus.shutdown()
    report = "\n".join(r.line() for r in results)
    assert [(r.number, r.outcome) for r in results] == [(1, "PASS"), (22, "FAIL")], report
    assert "standard-identifier frame" in results[1].detail
