"""Chip scenarios (tests/vectors/chip.json): what a chip answers, frame by frame and on a simulated
clock, in every case docs/protocol.md decided (§15, §18 list them). Written out by hand from the
spec — every expected frame below is a literal, not something a chip implementation computed — and
held against every chip implementation (the Python model, the chip array, the C firmware) by
tests/virtual_sheet/test_chip_scenarios.py. A third-party chip runs the JSON the same way.

The format is `FORMAT` (also the ``about`` of chip.json, so the file explains itself).
"""

from __future__ import annotations

from .messages import (message_to_fields, LINK_NONE, Ack, Announce, Assign, CalData, CalRead, CalWrite, Capability, ChipState, Config,
                       ConfigImu, GetInfo, Info, Message, MsgType, Nack, NackReason, Reset, Sample, Start, Status,
                       StatusFlag, Stop, Sync)

__all__ = ["UID", "scenarios", "PROVISIONAL", "FORMAT"]

#: How to run a scenario (the ``about`` of tests/vectors/chip.json).
FORMAT = """\
A scenario is one chip: 'uid', 'capabilities' (INFO bits), no stored calibration (CAL_DATA reports the
nominal offset 0 and sensitivity 1024.0, flags 0), and a sensor that reads 'sensor' ('xyz': counts at
+-2 g; 'status': the conversion's own status bits, STALE and SELF_TEST passing through to the sample)
until a step changes it. At range r the chip reports those counts shifted right by r (floor), as a chip
that implements ranges by scaling a +-2 g reading does (docs/protocol.md §8.3). Run it on a simulated
clock, on each transport of 'transport' ('both': serial and can). Steps, in order, each at time 'at'
(seconds, never decreasing):
  power_on      power the chip on.
  poll          serve the chip's timers at 'at'; what it sends is the step's 'expect'.
  send          a host frame from its fields: 'type', 'node', 'fields' (as in serial.json).
  send_raw      a host frame from its parts: 'version', 'type' (any code), 'node', 'payload' (hex).
                serial: COBS(header + payload + CRC) + 0x00; CAN: the identifier with the type's
                priority (4 for an undefined type) and that version, a classic frame.
  send_wire     serial only: these bytes as they are; split at each 0x00, empty runs skipped.
  sensor        from now on the sensor reads 'xyz' with 'status'.
  sensor_fault  the application tells the chip its sensor stopped answering.
Before every step but power_on and poll the chip's timers are served at 'at' first; what that sends
must be the step's 'timers' (absent: nothing). 'expect' is every frame the chip sends in answer to the
step, in order, as {type, node, fields}; a field not listed is not compared (INFO's firmware version);
a float within 1e-6 relative."""

UID = 0x0123456789ABCDEF
UID_LOW = UID & 0xFFFFFFFF
#: provisional_node(UID, salt) for salt 0..5, written out (docs §3.2's formula; checked by a test)
PROVISIONAL = (0x9112, 0x950E, 0xB8EC, 0xDBEB, 0xFEE7, 0xB6C5)
P0, P1, P2, P3, P4, P5 = PROVISIONAL
N = 42  # the node id the scenarios assign
XYZ = (10, -20, 1024)
_BOTH, _SERIAL = "both", "serial"
_CAPS = int(Capability.MULTI_RANGE | Capability.FILTER)  # no CAL_STORAGE: STATUS flags stay simple


def _m(msg: Message, **omit) -> dict:
    f = message_to_fields(msg)
    if isinstance(msg, Info):  # the firmware version is the implementation's own
        for k in ("fw_major", "fw_minor", "fw_patch"):
            f.pop(k)
    for k in omit:
        f.pop(k)
    return {"type": msg.TYPE.name, "node": msg.node, "fields": f}


def _boot(node: int, caps: int = _CAPS) -> list[dict]:
    return [_m(Announce(node, UID)), _m(Info(node, 0, 0, 0, 1, caps, 12, ChipState.BOOT))]


def _info(node: int, state: ChipState, caps: int = _CAPS) -> list[dict]:
    return [_m(Announce(node, UID)), _m(Info(node, 0, 0, 0, 1, caps, 12, state))]


def _send(at: float, msg: Message, *expect: Message | list, timers=()) -> dict:
    return _step(at, {"do": "send", **{k: v for k, v in _m(msg).items()}}, expect, timers)


def _raw(at: float, type_code: int, node: int, payload: bytes = b"", *expect, version: int = 1, timers=()) -> dict:
    return _step(at, {"do": "send_raw", "version": version, "type": type_code, "node": node,
                      "payload": payload.hex()}, expect, timers)


def _wire(at: float, data: bytes, *expect, timers=()) -> dict:
    return _step(at, {"do": "send_wire", "hex": data.hex()}, expect, timers)


def _poll(at: float, *expect) -> dict:
    return _step(at, {"do": "poll"}, expect, ())


def _step(at: float, body: dict, expect, timers) -> dict:
    out: list[dict] = []
    for e in expect:
        out += e if isinstance(e, list) else [_m(e)]
    step = {"at": at, **body, "expect": out}
    if timers:
        step["timers"] = [t if isinstance(t, dict) else _m(t) for t in timers]
    return step


def _assigned(at: float = 0.0, caps: int = _CAPS) -> list[dict]:
    """Power on at ``at`` and ASSIGN node 42, link 7, at the same instant: the first STATUS is due at
    ``at + 1`` s (§8.4)."""
    return [{"at": at, "do": "power_on", "expect": _boot(P0, caps)},
            _send(at, Assign(P0, new_node=N, link=7, uid_low=UID_LOW), Ack(N, MsgType.ASSIGN, 0))]


def _streaming(at: float = 0.0, caps: int = _CAPS) -> list[dict]:
    return _assigned(at, caps) + [_send(at, Start(N), Ack(N, MsgType.START, 0))]


def _status(state: ChipState, rx: int = 0, missed: int = 0, up: int = 0, flags: int = 0) -> Status:
    return Status(N, state, flags, rx, missed, up)


def scenarios() -> list[dict]:
    """Every scenario, as tests/vectors/chip.json lists it."""
    I, S, F, B = ChipState.IDLE, ChipState.STREAMING, ChipState.FAULT, ChipState.BOOT
    sc: list[dict] = []

    def add(name: str, clause: str, steps: list[dict], *, transport: str = _BOTH, caps: int = _CAPS,
            xyz=XYZ, status: int = 0) -> None:
        sc.append({"name": name, "clause": clause, "transport": transport, "uid": f"0x{UID:016X}",
                   "capabilities": caps, "sensor": {"xyz": list(xyz), "status": status}, "steps": steps})

    # --- §3.2 / §3.3: announce rounds, the salt, the previous provisional id ---------------------
    add("announce_rounds_every_second_and_after_a_late_poll", "3.2, 14", [
        {"at": 0.0, "do": "power_on", "expect": _boot(P0)},
        _poll(0.999),
        _poll(1.0, _boot(P1)),
        _poll(2.5, _boot(P2)),  # late: the next deadline is max(2 + 1, 2.5) = 3
        _poll(2.999),
        _poll(3.0, _boot(P3)),
        _poll(5.5, _boot(P4)),  # over a whole period late: sent once, the next deadline is 5.5 + 1
        _poll(5.5),  # never two back to back
        _poll(6.499),
        _poll(6.5, _boot(P5)),
    ])
    add("assign_to_the_previous_provisional_id_is_taken", "3.3", [
        {"at": 0.0, "do": "power_on", "expect": _boot(P0)},
        _poll(1.0, _boot(P1)),
        _send(1.001, Assign(P0, new_node=N, link=7, uid_low=UID_LOW), Ack(N, MsgType.ASSIGN, 0)),
        _send(1.002, GetInfo(N), _info(N, I)),
    ])
    add("assign_two_rounds_late_is_ignored", "3.3", [
        {"at": 0.0, "do": "power_on", "expect": _boot(P0)},
        _poll(1.0, _boot(P1)),
        _poll(2.0, _boot(P2)),
        _send(2.001, Assign(P0, new_node=N, link=7, uid_low=UID_LOW)),
        _send(2.002, Assign(P1, new_node=N, link=7, uid_low=UID_LOW ^ 1)),  # the previous id, another uid
        _send(2.003, GetInfo(P2), _info(P2, B)),
    ])
    add("only_assign_reaches_the_previous_provisional_id", "3.3", [
        {"at": 0.0, "do": "power_on", "expect": _boot(P0)},
        _poll(1.0, _boot(P1)),
        _send(1.001, GetInfo(P0)),
        _send(1.002, Start(P0)),
    ])
    add("reset_restarts_the_salt_but_not_the_uptime", "3.2, 4.4, 4.14", [
        {"at": 0.0, "do": "power_on", "expect": _boot(P0)},
        _poll(1.0, _boot(P1)),
        _send(1.5, Assign(P1, new_node=N, link=7, uid_low=UID_LOW), Ack(N, MsgType.ASSIGN, 0)),
        _send(5.0, Reset(N), Ack(N, MsgType.RESET, 0), _boot(P0), timers=[_status(I, up=5)]),  # due 2.5: once
        _send(5.0, Assign(P0, new_node=N, link=7, uid_low=UID_LOW), Ack(N, MsgType.ASSIGN, 0)),
        _poll(5.999),
        _poll(6.0, _status(I, up=6)),  # seconds since power-on, not since the RESET
    ])
    # --- §8.4: heartbeat timers ----------------------------------------------------------------------
    add("first_heartbeat_after_assign_and_config_restarts_it", "8.4, 14", [
        {"at": 0.0, "do": "power_on", "expect": _boot(P0)},
        _send(0.5, Assign(P0, new_node=N, link=7, uid_low=UID_LOW), Ack(N, MsgType.ASSIGN, 0)),
        _poll(1.499),
        _poll(1.5, _status(I, up=1)),
        _send(1.6, Config(N, rate_hz=145, range=0, filter=0, heartbeat_ms=200), Ack(N, MsgType.CONFIG, 0)),
        _poll(1.799),
        _poll(1.8, _status(I, up=1, flags=StatusFlag.CONFIGURED)),
        _poll(2.0, _status(I, up=2, flags=StatusFlag.CONFIGURED)),
        _send(2.1, Config(N, rate_hz=145, range=0, filter=0, heartbeat_ms=0), Ack(N, MsgType.CONFIG, 0)),
        _poll(5.0),
        _send(5.0, Reset(N), Ack(N, MsgType.RESET, 0), _boot(P0)),
        _poll(5.999),  # BOOT: no STATUS; the next ANNOUNCE is due at 6
        _poll(6.0, _boot(P1)),
    ])
    # --- §8.1: a broadcast is never NACKed; what rx_errors counts --------------------------------
    add("a_broadcast_is_never_nacked", "8.1, 4.6, 12", caps=0, steps=_assigned(caps=0) + [
        _raw(0.1, MsgType.GET_INFO, 0, version=2),
        _raw(0.1, MsgType.GET_INFO, N, b"", Nack(N, MsgType.GET_INFO, NackReason.BAD_VERSION), version=2),
        _raw(0.1, 0x3F, 0),
        _raw(0.1, 0x3F, N, b"", Nack(N, 0x3F, NackReason.UNKNOWN_COMMAND)),
        _raw(0.1, MsgType.START, 0, b"\x01"),
        _raw(0.1, MsgType.START, N, b"\x01", Nack(N, MsgType.START, NackReason.BAD_LENGTH)),
        _raw(0.1, MsgType.ASSIGN, 0, bytes.fromhex("0100000000000000")),
        _raw(0.1, MsgType.CAL_READ, 0, b"\x00"),
        _send(0.2, Config(0, rate_hz=5000)),
        _send(0.2, Config(N, rate_hz=5000), Nack(N, MsgType.CONFIG, NackReason.BAD_VALUE)),
        _send(0.2, Config(0, range=1)),
        _send(0.2, Config(N, range=1), Nack(N, MsgType.CONFIG, NackReason.UNSUPPORTED)),
        _send(0.2, Config(0, filter=1)),
        _send(0.2, Config(N, filter=1), Nack(N, MsgType.CONFIG, NackReason.UNSUPPORTED)),
        _send(0.3, CalWrite(N, axis=0, flags=1, offset_q4=0, sensitivity=1024.0),
              Nack(N, MsgType.CAL_WRITE, NackReason.UNSUPPORTED)),
        # rx_errors: the 8 frames above addressed to the chip or broadcast that did not decode; the
        # refused CONFIGs decoded. Nothing was applied: CONFIGURED is clear.
        _poll(1.0, _status(I, rx=8, up=1)),
    ])
    add("a_broadcast_refused_by_the_state_table_is_silent", "8.1, 8.2", [
        {"at": 0.0, "do": "power_on", "expect": _boot(P0)},
        _send(0.1, Start(0)),
        _send(0.1, Config(0)),
        _send(0.1, Start(P0), Nack(P0, MsgType.START, NackReason.BAD_STATE)),
    ])
    add("node_to_host_types_are_ignored_and_not_counted", "4, 8.1", _assigned() + [
        _raw(0.1, 0x0A, N),
        _raw(0.1, 0x0F, 0, b"\x01"),
        _raw(0.1, MsgType.GATEWAY_INFO, N, bytes(8)),
        _raw(0.1, MsgType.STATUS, N, bytes(8)),
        _raw(0.1, MsgType.ACK, 0, b"\x13"),  # a wrong length, but another node's type
        _raw(0.1, MsgType.NACK, N, b"\x13\x04", version=2),
        _poll(1.0, _status(I, up=1)),
    ])
    add("frames_for_other_nodes_are_not_counted", "8.1", _assigned() + [
        _raw(0.1, MsgType.START, N + 1, b"\x01"),
        _raw(0.1, MsgType.START, N + 1, version=2),
        _raw(0.1, 0x3F, N + 1),
        _raw(0.1, MsgType.CAL_READ, N + 1, b"\x07"),
        _send(0.1, Start(N + 1)),
        _poll(1.0, _status(I, up=1)),
    ])
    add("damaged_frames_are_counted_and_never_answered", "6.4, 8.1, 4.4", transport=_SERIAL, steps=_assigned() + [
        _wire(0.1, bytes.fromhex("04010301020603012002030387a200")),  # BAD_CRC
        _wire(0.1, bytes.fromhex("0501020300")),  # BAD_COBS
        _wire(0.1, bytes.fromhex("03010200")),  # SHORT
        _wire(0.1, b"\x01" * 1100 + b"\x00"),  # OVERSIZE, once
        _wire(0.1, b"\x00\x00"),  # idle fill: nothing
        _poll(1.0, _status(I, rx=4, up=1)),
    ])
    add("addressed_fields_out_of_range_are_bad_value", "4.9, 4.15, 8.1", _assigned() + [
        _raw(0.1, MsgType.SYNC, N, b"\x01\x00", Nack(N, MsgType.SYNC, NackReason.BAD_VALUE)),
        _raw(0.1, MsgType.CAL_WRITE, N, bytes.fromhex("0300000000008044"), Nack(N, MsgType.CAL_WRITE, NackReason.BAD_VALUE)),
        _raw(0.1, MsgType.CAL_WRITE, N, bytes.fromhex("0000000000000000"), Nack(N, MsgType.CAL_WRITE, NackReason.BAD_VALUE)),
        _raw(0.1, MsgType.CAL_WRITE, N, bytes.fromhex("000000000000c07f"), Nack(N, MsgType.CAL_WRITE, NackReason.BAD_VALUE)),
        _raw(0.1, MsgType.ASSIGN, N, bytes.fromhex("0080000000000000"), Nack(N, MsgType.ASSIGN, NackReason.BAD_VALUE)),
        _poll(1.0, _status(I, rx=5, up=1)),
    ])
    # --- §4.11: a capability for every CONFIG value other than the default ------------------------
    add("range_and_filter_need_their_capability", "4.11", caps=0, steps=_assigned(caps=0) + [
        _send(0.1, Config(N, rate_hz=100, range=1, filter=0, heartbeat_ms=1000),
              Nack(N, MsgType.CONFIG, NackReason.UNSUPPORTED)),
        _send(0.1, Config(N, rate_hz=100, range=0, filter=2, heartbeat_ms=1000),
              Nack(N, MsgType.CONFIG, NackReason.UNSUPPORTED)),
        _send(0.1, Config(N, rate_hz=100, range=4, filter=2, heartbeat_ms=1000),
              Nack(N, MsgType.CONFIG, NackReason.BAD_VALUE)),  # BAD_VALUE before UNSUPPORTED
        _send(0.1, Config(N, rate_hz=100, range=0, filter=0, heartbeat_ms=1000), Ack(N, MsgType.CONFIG, 0)),
    ])
    add("a_range_change_scales_the_next_sample", "4.11, 5.3", _streaming() + [
        _send(0.1, Sync(counter=1), Sample(N, 1, *XYZ, 0)),
        _send(0.1, Stop(N), Ack(N, MsgType.STOP, 0)),
        _send(0.1, Config(N, rate_hz=145, range=1, filter=1, heartbeat_ms=1000), Ack(N, MsgType.CONFIG, 0)),
        _send(0.1, Start(N), Ack(N, MsgType.START, 0)),
        _send(0.1, Sync(counter=2), Sample(N, 2, 5, -10, 512, 0)),
    ])
    # --- §5.1: SYNC counters ------------------------------------------------------------------------
    add("every_sync_frame_is_answered_and_older_counters_move_last", "5.1, 4.4", _streaming() + [
        _send(0.1, Sync(counter=10), Sample(N, 10, *XYZ, 0)),
        _send(0.1, Sync(counter=5), Sample(N, 5, *XYZ, 0)),  # older: adds nothing, last = 5
        _send(0.1, Sync(counter=6), Sample(N, 6, *XYZ, 0)),  # follows 5: no gap
        _send(0.1, Sync(counter=8), Sample(N, 8, *XYZ, 0)),  # 7 missed
        _send(0.1, Sync(counter=8), Sample(N, 8, *XYZ, 0)),  # the same counter again: answered again
        _send(0.1, Sync(counter=0xFFFF), Sample(N, 0xFFFF, *XYZ, 0)),  # 0x7FF6 ahead: older, adds nothing
        _send(0.1, Sync(counter=1), Sample(N, 1, *XYZ, 0)),  # counter 0 missed, across the wrap
        _poll(1.0, _status(S, missed=2, up=1)),
    ])
    add("start_forgets_the_last_counter", "5.1", _streaming() + [
        _send(0.1, Sync(counter=10), Sample(N, 10, *XYZ, 0)),
        _send(0.1, Start(N), Ack(N, MsgType.START, 0)),
        _send(0.1, Sync(counter=20), Sample(N, 20, *XYZ, 0)),
        _poll(1.0, _status(S, missed=0, up=1)),
    ])
    # --- §8.6: FAULT ----------------------------------------------------------------------------------
    add("fault_from_an_invalid_conversion", "8.6, 8.2", _streaming() + [
        {"at": 0.1, "do": "sensor", "xyz": [0, 0, 0], "status": 8, "expect": []},
        _send(0.1, Sync(counter=1), Sample(N, 1, 0, 0, 0, 8)),
        {"at": 0.1, "do": "sensor", "xyz": list(XYZ), "status": 0, "expect": []},  # the sensor is back
        _send(0.1, Sync(counter=2), Sample(N, 2, 0, 0, 0, 8)),  # only RESET leaves FAULT
        _send(0.1, GetInfo(N), _info(N, F)),
        _send(0.1, Stop(N), Ack(N, MsgType.STOP, 0)),
        _send(0.1, Sync(counter=3)),  # stopped: not answered
        _send(0.1, Config(N, rate_hz=145, range=0, filter=0, heartbeat_ms=1000), Ack(N, MsgType.CONFIG, 0)),
        _send(0.1, CalWrite(N, axis=0, flags=0, offset_q4=0, sensitivity=1024.0),
              Nack(N, MsgType.CAL_WRITE, NackReason.BAD_STATE)),
        _send(0.1, CalRead(N, axis=0), CalData(N, 0, 0, 0, 1024.0)),
        _send(0.1, Assign(N, new_node=N, link=8, uid_low=UID_LOW), Ack(N, MsgType.ASSIGN, 0)),
        _send(0.1, Start(N), Ack(N, MsgType.START, 0)),
        _send(0.1, Sync(counter=4), Sample(N, 4, 0, 0, 0, 8)),
        _poll(1.0),  # the CONFIG at 0.1 restarted the heartbeat: due at 1.1
        _send(1.1, Reset(N), Ack(N, MsgType.RESET, 0), _boot(P0),
              timers=[_status(F, up=1, flags=StatusFlag.ADC_FAULT | StatusFlag.CONFIGURED)]),
    ])
    add("fault_reported_by_the_application_in_idle", "8.6", _assigned() + [
        {"at": 0.1, "do": "sensor_fault", "expect": []},
        _send(0.1, GetInfo(N), _info(N, F)),
        _send(0.1, Sync(counter=1)),  # not started
        _send(0.1, Start(N), Ack(N, MsgType.START, 0)),
        _send(0.1, Sync(counter=2), Sample(N, 2, 0, 0, 0, 8)),
    ])
    add("saturated_follows_the_counts_sent", "5.2, 8.6", _streaming() + [
        {"at": 0.1, "do": "sensor", "xyz": [2047, 0, 1024], "status": 0, "expect": []},
        _send(0.1, Sync(counter=1), Sample(N, 1, 2047, 0, 1024, 1)),  # at a rail: SATURATED, set by the chip
        {"at": 0.1, "do": "sensor", "xyz": [100, -2048, 1024], "status": 4, "expect": []},
        _send(0.1, Sync(counter=2), Sample(N, 2, 100, -2048, 1024, 5)),  # STALE passes through
        {"at": 0.1, "do": "sensor", "xyz": [100, 0, 1024], "status": 1, "expect": []},
        _send(0.1, Sync(counter=3), Sample(N, 3, 100, 0, 1024, 0)),  # the ADC's flag without a rail: cleared
        _send(0.1, Stop(N), Ack(N, MsgType.STOP, 0)),
        _send(0.1, Config(N, rate_hz=145, range=1, filter=0, heartbeat_ms=1000), Ack(N, MsgType.CONFIG, 0)),
        _send(0.1, Start(N), Ack(N, MsgType.START, 0)),
        {"at": 0.1, "do": "sensor", "xyz": [2047, 0, 1024], "status": 1, "expect": []},
        _send(0.1, Sync(counter=4), Sample(N, 4, 1023, 0, 512, 0)),  # range 1: 1023 is no rail
        {"at": 0.1, "do": "sensor", "xyz": [2047, 0, 1024], "status": 9, "expect": []},
        _send(0.1, Sync(counter=5), Sample(N, 5, 0, 0, 0, 8)),  # a failed conversion: INVALID alone
    ])
    add("sensor_fault_in_boot_changes_nothing", "8.6", [
        {"at": 0.0, "do": "power_on", "expect": _boot(P0)},
        {"at": 0.1, "do": "sensor_fault", "expect": []},
        _send(0.1, GetInfo(P0), _info(P0, B)),
    ])
    add("a_gateway_assign_is_taken_by_a_chip_too", "4.10", [
        {"at": 0.0, "do": "power_on", "expect": _boot(P0)},
        _send(0.1, Assign(P0, new_node=N, link=LINK_NONE, uid_low=UID_LOW), Ack(N, MsgType.ASSIGN, 0)),
    ])
    _answers_of_1_4(add)
    return sc


def _answers_of_1_4(add) -> None:
    """What 1.4 decided about a chip (docs §18 lists the questions; each scenario names its answer)."""
    I = ChipState.IDLE
    stored = _CAPS | int(Capability.CAL_STORAGE)
    # G03: only an ASSIGN that decodes is taken at the previous id; an undecodable one may be another node's
    add("an_undecodable_assign_to_the_previous_id_is_ignored_and_not_counted", "3.3, 8.1, 18 G03", [
        {"at": 0.0, "do": "power_on", "expect": _boot(P0)},
        _poll(1.0, _boot(P1)),
        _raw(1.001, MsgType.ASSIGN, P0, bytes([N, 0, 7, 0]) + UID_LOW.to_bytes(4, "little")[:3]),  # 7 bytes
        _send(1.002, Assign(P1, new_node=N, link=7, uid_low=UID_LOW), Ack(N, MsgType.ASSIGN, 0)),
        _poll(2.002, _status(I, rx=0, up=2)),
    ])
    # G04: power-on and RESET start a round with no round before it
    add("after_reset_the_id_before_it_is_no_previous_id", "3.3, 4.14, 18 G04", [
        {"at": 0.0, "do": "power_on", "expect": _boot(P0)},
        _poll(1.0, _boot(P1)),
        _send(1.001, Reset(P1), Ack(P1, MsgType.RESET, 0), _boot(P0)),
        _send(1.002, Assign(P1, new_node=N, link=7, uid_low=UID_LOW)),  # the round before RESET: ignored
        _send(1.003, Assign(P0, new_node=N, link=7, uid_low=UID_LOW), Ack(N, MsgType.ASSIGN, 0)),
    ])
    # G11: CONFIGURED is part of the configuration RESET forgets
    add("reset_clears_configured", "4.4, 4.14, 18 G11", _assigned() + [
        _send(0.1, Config(N, rate_hz=145, range=0, filter=0, heartbeat_ms=1000), Ack(N, MsgType.CONFIG, 0)),
        _poll(1.1, _status(I, up=1, flags=int(StatusFlag.CONFIGURED))),
        _send(1.2, Reset(N), Ack(N, MsgType.RESET, 0), _boot(P0)),
        _send(1.2, Assign(P0, new_node=N, link=7, uid_low=UID_LOW), Ack(N, MsgType.ASSIGN, 0)),
        _poll(2.2, _status(I, up=2)),
    ])
    # G13: the stored flag says where the value in use came from, not whether it equals the stored one
    add("a_write_without_store_clears_the_stored_flag_even_for_the_same_value", "4.7, 8.3, 18 G13",
        _assigned(caps=stored) + [
            _send(0.1, CalWrite(N, axis=0, flags=1, offset_q4=-8, sensitivity=1000.0), Ack(N, MsgType.CAL_WRITE, 0)),
            _send(0.1, CalRead(N, axis=0), CalData(N, 0, 1, -8, 1000.0)),
            _send(0.1, CalWrite(N, axis=0, flags=0, offset_q4=-8, sensitivity=1000.0), Ack(N, MsgType.CAL_WRITE, 0)),
            _send(0.1, CalRead(N, axis=0), CalData(N, 0, 0, -8, 1000.0)),
            _send(0.2, Reset(N), Ack(N, MsgType.RESET, 0), _boot(P0, stored)),
            _send(0.2, Assign(P0, new_node=N, link=7, uid_low=UID_LOW), Ack(N, MsgType.ASSIGN, 0)),
            _send(0.2, CalRead(N, axis=0), CalData(N, 0, 1, -8, 1000.0)),  # the stored value is back, flagged
        ], caps=stored)
    # G14: a failure found in BOOT is not kept; the chip finds it (or not) again when it converts
    add("a_sensor_fault_in_boot_is_forgotten_and_found_at_the_next_conversion", "8.6, 18 G14", [
        {"at": 0.0, "do": "power_on", "expect": _boot(P0)},
        {"at": 0.1, "do": "sensor_fault", "expect": []},
        _send(0.1, Assign(P0, new_node=N, link=7, uid_low=UID_LOW), Ack(N, MsgType.ASSIGN, 0)),
        _send(0.1, GetInfo(N), _info(N, I)),
        _send(0.1, Start(N), Ack(N, MsgType.START, 0)),
        _send(0.1, Sync(counter=1), Sample(N, 1, *XYZ, 0)),  # the sensor answers: no FAULT
        {"at": 0.1, "do": "sensor", "xyz": [10, -20, 1024], "status": 8, "expect": []},
        _send(0.1, Sync(counter=2), Sample(N, 2, 0, 0, 0, 8)),  # it does not: INVALID, FAULT from here
        _send(0.1, GetInfo(N), _info(N, ChipState.FAULT)),
    ])
    # G16: a STALE sample repeats the last conversion as the chip sends it at the range in force
    add("a_stale_sample_after_a_range_change_is_the_last_conversion_at_the_new_range", "5.3, 18 G16",
        _assigned() + [
            _send(0.1, Config(N, rate_hz=145, range=1, filter=0, heartbeat_ms=1000), Ack(N, MsgType.CONFIG, 0)),
            _send(0.1, Start(N), Ack(N, MsgType.START, 0)),
            {"at": 0.1, "do": "sensor", "xyz": [10, -20, 1024], "status": 4, "expect": []},
            _send(0.1, Sync(counter=1), Sample(N, 1, 5, -10, 512, 4)),
            # G12: the calibration is in ±2 g counts whatever the range: the nominal 1024, not rescaled
            _send(0.1, CalRead(N, axis=2), CalData(N, 2, 0, 0, 1024.0)),
        ])
    # G17: every run of up to 15 bytes between delimiters is decoded, so a wrong length there is NACK 2
    add("a_config_of_8_bytes_in_15_bytes_on_the_wire_is_nacked_bad_length", "8.7, 8.1, 18 G17",
        _assigned() + [
            _raw(0.1, MsgType.CONFIG, N, bytes([145, 0, 0, 0, 0xE8, 0x03, 0, 0]), Nack(N, MsgType.CONFIG, NackReason.BAD_LENGTH)),
            _poll(1.0, _status(I, rx=1, up=1)),
        ])
    # G22: a broadcast CONFIG_IMU acts on every chip as CONFIG does; refused, it is answered by nothing
    add("a_broadcast_config_imu_is_acted_on_and_acked", "16.2, 8.2, 18 G22", _assigned() + [
        _send(0.1, ConfigImu(0, 0, 2, 1, 0), Ack(N, MsgType.CONFIG_IMU, 0)),
        _send(0.1, ConfigImu(0, 1, 3, 0, 0)),  # format 1 without GYRO: UNSUPPORTED, silent when broadcast
        _send(0.1, ConfigImu(N, 1, 3, 0, 0), Nack(N, MsgType.CONFIG_IMU, NackReason.UNSUPPORTED)),
        _send(0.1, ConfigImu(0, 0, 5, 0, 0)),  # gyro_range 5: BAD_VALUE, silent when broadcast
    ])
