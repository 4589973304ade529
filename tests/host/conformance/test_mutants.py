"""Every check is shown able to fail: each mutant chip (tests/host/conformance/mutants.py) breaks one
rule and must fail exactly the checks that hold a chip to that rule — no more (the suite does not
blame the wrong clause), no fewer (the rule is checked)."""

from __future__ import annotations

import pytest

from host.conformance import CHECKS, AuditedCanTransport, Port, run_checks
from host.transport import MemoryTransport
from tests.host.conformance.mutants import MUTANTS
from virtual_sheet.devices import CanDevice, MemoryDevice
from virtual_sheet.sheet import VirtualSheet

#: mutant -> the checks it must fail (check numbers: `capsheet conformance --list`)
EXPECTED = {
    "dead_sensor": {23, 24},  # |a| = 0 g at rest; 20 identical samples, none STALE
    "stale_marked_fresh": {24},
    "wrong_crc": {1, 30},  # nothing decodes: not discovered; the framing check blames the chip, not the port
    "counter_off_by_one": {22, 23, 24, 25},  # every check that matches SAMPLEs to SYNCs
    "wrong_byte_order": {22, 23, 24, 25},
    "sync_answered_twice": {22},
    "slow_heartbeat": {10},
    "no_reannounce": {8},
    "wrong_nack_reason": {5, 11, 13, 15, 16, 17, 26},  # every check expecting a NACK
    "ignored_reset": {3, 4, 5, 6, 7, 8},  # every check that needs a fresh BOOT
    "answers_broadcast": {28},
    "ignores_broadcast_start": {29},
    "nacks_chip_types": {14},
    "ack_detail_set": {31},
    "reserved_capability_bit": {2},
    "no_rx_errors": {19},
    "assign_ignores_uid": {6},
    "assigned_id_in_boot": {4},
    "cal_read_nominal": {18},
    "accepts_bad_config": {11},
    "claims_no_multi_range": {12},
    "refuses_repeated_config": {9},
    "start_not_idempotent": {21},
    "streams_after_stop": {27},
    "wrong_priority": {30, 32},  # CAN: the priority audit, and the DBC lookup (priority bits are in its id)
}

#: checks no mutant here can fail, and why (the virtual CAN device drops standard frames before any chip)
NOT_SHOWN = {20: "the virtual CanDevice filters standard-identifier frames before the chips see them"}


def run(name):
    cls, transport, allow_broadcast = MUTANTS[name]
    sheet = VirtualSheet("flat", "2x2", transport=transport, noise=0.5, chip_factory=cls)
    if transport == "serial":
        with MemoryDevice(sheet) as dev:
            port = Port(MemoryTransport(dev.port))
            try:
                return run_checks(port, timeout_s=0.3, allow_broadcast=allow_broadcast)
            finally:
                port.close()
    with CanDevice(sheet) as dev:
        t = AuditedCanTransport(f"virtual:{dev.channels[0]}", reconnect=False)
        port = Port(t)
        try:
            return run_checks(port, timeout_s=0.3, allow_broadcast=allow_broadcast)
        finally:
            port.close()
            t.close()


@pytest.mark.parametrize("name", sorted(MUTANTS))
def test_a_mutant_fails_exactly_its_checks(name):
    results = run(name)
    report = "\n".join(r.line() for r in results)
    assert {r.number for r in results if r.outcome == "FAIL"} == EXPECTED[name], report
    assert not [r for r in results if r.outcome == "LOST"], report  # a chip fault is never blamed on the port


def test_every_check_is_failed_by_some_mutant():
    assert set(EXPECTED) == set(MUTANTS)
    failed = set().union(*EXPECTED.values())
    assert {c.number for c in CHECKS} - failed == set(NOT_SHOWN)


def test_check_20_fails_a_chip_that_answers_foreign_frames():
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
        results = run_checks(port, timeout_s=0.3, only=["20"])
    finally:
        port.close()
        t.close()
        stop.set()
        th.join(timeout=2)
        bus.shutdown()
    report = "\n".join(r.line() for r in results)
    assert [(r.number, r.outcome) for r in results] == [(1, "PASS"), (20, "FAIL")], report
    assert "standard-identifier frame" in results[1].detail
