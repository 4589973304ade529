"""A chip against the state table (protocol/state.py RULES), NACK reasons, timers.

Every test that takes the ``chip_class`` fixture (tests/conftest.py) runs once per chip
implementation: the Python model (`virtual_sheet.chip.ChipModel`) and the C reference firmware
through cffi (`firmware_ref.chip.CFirmwareChip`)."""

from __future__ import annotations

import dataclasses

import pytest

from protocol.can import CanFrame, decode_can, make_id, to_can
from protocol.constants import SampleStatus
from protocol.framing import decode_frame, encode, encode_frame
from protocol.messages import (MESSAGE_TYPES, ConfigImu, CalImuRead, CalImuWrite, Ack, Announce, Assign, CalData, CalRead, CalWrite, Capability,
                               ChipState, Config, Direction, GetInfo, Info, MsgType, Nack, NackReason, Reset,
                               Sample, Start, Status, Stop, Sync, provisional_node)
from protocol.vectors import canonical_messages
from protocol.state import ANNOUNCE_PERIOD_S, RULES, Reply
from virtual_sheet.chip import ChipModel

UID = 0x0123456789ABCDEF
NODE = 42
HOST_TYPES = [t for t, c in MESSAGE_TYPES.items() if c.DIRECTION == Direction.HOST_TO_CHIP]
CHIP_TYPES = [t for t, c in MESSAGE_TYPES.items() if c.DIRECTION == Direction.CHIP_TO_HOST]


def sensor(now_s):
    return (10, -20, 1024), 0


def decode_all(frames, transport="serial"):
    if transport == "can":
        return [decode_can(f.arbitration_id, f.data, is_fd=f.is_fd) for f in frames]
    out = []
    for f in frames:
        assert f.endswith(b"\x00") and f.count(b"\x00") == 1
        out.append(decode_frame(f[:-1]))
    return out


class Driver:
    """Talks to one chip in messages, on either transport."""

    def __init__(self, chip_class=ChipModel, transport="serial", **kw):
        self.transport = transport
        self.chip = chip_class(UID, sensor, transport=transport, **kw)
        self.t = 0.0

    def wire(self, msg):
        return to_can(msg) if self.transport == "can" else encode(msg)

    def send(self, msg, *, pass_decoded=False):
        out = self.chip.handle(self.wire(msg), self.t, msg if pass_decoded else None)
        return decode_all(out, self.transport)

    def send_raw(self, frame):
        return decode_all(self.chip.handle(frame, self.t), self.transport)

    def boot(self):
        return decode_all(self.chip.power_on(self.t), self.transport)

    def to_state(self, state):
        self.boot()
        if state == ChipState.BOOT:
            return
        assert self.send(Assign(self.chip.node, new_node=NODE, link=7, uid_low=UID & 0xFFFFFFFF)) == [
            Ack(NODE, MsgType.ASSIGN, 0)]
        if state == ChipState.IDLE:
            return
        assert self.send(Start(NODE)) == [Ack(NODE, MsgType.START, 0)]
        if state == ChipState.FAULT:
            self.chip.fault()
        assert self.chip.state == state


def valid_message(t, node):
    return {
        MsgType.SYNC: lambda: Sync(counter=5),
        MsgType.ASSIGN: lambda: Assign(node, new_node=NODE + 1, link=3, uid_low=UID & 0xFFFFFFFF),
        MsgType.CONFIG: lambda: Config(node, rate_hz=100, range=0, filter=1, heartbeat_ms=500),
        MsgType.START: lambda: Start(node),
        MsgType.STOP: lambda: Stop(node),
        MsgType.GET_INFO: lambda: GetInfo(node),
        MsgType.RESET: lambda: Reset(node),
        MsgType.CAL_WRITE: lambda: CalWrite(node, axis=1, flags=1, offset_q4=-8, sensitivity=1000.0),
        MsgType.CAL_READ: lambda: CalRead(node, axis=2),
        MsgType.CONFIG_IMU: lambda: ConfigImu(node, 0, 4, 1, 0),  # format 0: valid for an accel-only chip
        MsgType.CAL_IMU_WRITE: lambda: CalImuWrite(node, 1, 2, 0, 0, 0.01),  # v1.3: NACK 5 without a gyro
        MsgType.CAL_IMU_READ: lambda: CalImuRead(node, 3, 4),
    }[t]()


# Every (type, addressing) a valid frame can have: SYNC is always broadcast; ASSIGN, CAL_WRITE and
# CAL_READ are always addressed (node 0 does not decode for them).
_ADDRESSINGS = [(t, b) for t in HOST_TYPES for b in (False, True)
                if not (t == MsgType.SYNC and not b)
                and not (b and t in (MsgType.ASSIGN, MsgType.CAL_WRITE, MsgType.CAL_READ, MsgType.CAL_IMU_WRITE,
                                     MsgType.CAL_IMU_READ))]


@pytest.mark.parametrize("transport", ["serial", "can"])
@pytest.mark.parametrize("state", list(ChipState))
@pytest.mark.parametrize("msg_type,broadcast", _ADDRESSINGS)
def test_every_state_and_type_follows_the_rules(chip_class, transport, state, msg_type, broadcast):
    d = Driver(chip_class, transport)
    d.to_state(state)
    node = d.chip.node
    msg = valid_message(msg_type, 0 if broadcast else node)
    replies = d.send(msg)
    rule = RULES.get((state, msg_type))
    if rule is None:
        assert replies == ([] if broadcast else [Nack(node, msg_type, NackReason.BAD_STATE)])
        assert d.chip.state == state
        return
    expect_state = rule.next_state if rule.next_state is not None else state
    assert d.chip.state == expect_state
    if msg_type in (MsgType.CAL_IMU_WRITE, MsgType.CAL_IMU_READ):  # §17.2: this chip has no gyro, no mag
        assert replies == [Nack(node, msg_type, NackReason.UNSUPPORTED)]
    elif rule.reply is Reply.NONE:
        assert replies == []
    elif rule.reply is Reply.ACK:
        new_node = msg.new_node if msg_type == MsgType.ASSIGN else node
        assert replies == [Ack(new_node, msg_type, 0)]
        assert d.chip.node == new_node
    elif rule.reply is Reply.SAMPLE:
        status = SampleStatus.INVALID if state == ChipState.FAULT else 0
        xyz = (0, 0, 0) if state == ChipState.FAULT else (10, -20, 1024)
        assert replies == [Sample(node, 5, *xyz, status)]
    elif rule.reply is Reply.ANNOUNCE_INFO:
        assert [type(m) for m in replies] == [Announce, Info]
        assert replies[0] == Announce(node, UID) and replies[1].state == state
    elif rule.reply is Reply.CAL_DATA:
        assert replies == [CalData(node, 2, 1, 0, 1024.0)]
    elif rule.reply is Reply.ACK_THEN_BOOT:
        prov = provisional_node(UID, 0)
        assert replies[0] == Ack(node, msg_type, 0)
        assert [type(m) for m in replies[1:]] == [Announce, Info]
        assert replies[1].node == prov and d.chip.node == prov and d.chip.link is None
    else:  # pragma: no cover
        pytest.fail(f"unhandled reply {rule.reply}")


@pytest.mark.parametrize("state", list(ChipState))
@pytest.mark.parametrize("msg_type", CHIP_TYPES)
def test_chip_to_host_frames_are_ignored(chip_class, state, msg_type):
    d = Driver(chip_class)
    d.to_state(state)
    msg = next(m for _n, m in canonical_messages() if m.TYPE == msg_type)
    assert d.send(dataclasses.replace(msg, node=d.chip.node)) == []
    assert d.send(dataclasses.replace(msg, node=0)) == []


def test_decoded_argument_gives_the_same_answers():  # a Python-model fast path only
    chip_class = ChipModel
    a, b = Driver(chip_class), Driver(chip_class)
    for d in (a, b):
        d.to_state(ChipState.STREAMING)
    for msg in (Sync(counter=1), GetInfo(0), Config(NODE), CalRead(NODE, axis=0), Stop(NODE)):
        assert a.send(msg) == b.send(msg, pass_decoded=True)


# ------------------------------------------------------------------ NACK reasons

@pytest.mark.parametrize("transport", ["serial", "can"])
def test_nack_reasons(chip_class, transport):
    d = Driver(chip_class, transport)
    d.to_state(ChipState.IDLE)
    c = d.chip

    def raw(type_code, node, payload, version=1):
        if transport == "can":
            return CanFrame(make_id(type_code, node, priority=4, version=version), payload, False)
        return encode_frame(type_code, node, payload, version=version)

    assert d.send_raw(raw(0x3F, NODE, b"")) == [Nack(NODE, 0x3F, NackReason.UNKNOWN_COMMAND)]
    assert d.send_raw(raw(0x3F, 0, b"")) == []  # broadcast: silent
    assert d.send_raw(raw(MsgType.START, NODE, b"\x01")) == [Nack(NODE, MsgType.START, NackReason.BAD_LENGTH)]
    assert d.send_raw(raw(MsgType.CAL_READ, NODE, b"\x03")) == [Nack(NODE, MsgType.CAL_READ, NackReason.BAD_VALUE)]
    for cfg in (Config(NODE, range=4), Config(NODE, filter=4), Config(NODE, rate_hz=0), Config(NODE, rate_hz=4001)):
        assert d.send(cfg) == [Nack(NODE, MsgType.CONFIG, NackReason.BAD_VALUE)], cfg
    assert d.send(Config(NODE, rate_hz=4000, range=3)) == [Ack(NODE, MsgType.CONFIG, 0)]
    assert d.send(Config(0, range=4)) == []  # broadcast: never a NACK (§8.1), and nothing applied
    assert d.send_raw(raw(MsgType.START, NODE, b"", version=2)) == [Nack(NODE, MsgType.START, NackReason.BAD_VERSION)]
    assert d.send_raw(raw(MsgType.START, 0, b"", version=2)) == []  # broadcast: silent
    assert d.send_raw(raw(MsgType.START, NODE + 1, b"", version=2)) == []
    # every frame addressed to the chip or broadcast that did not decode: unknown x2, length, field,
    # version x2 (not the one for another node)
    assert c.rx_errors == 6
    assert d.send(Start(NODE + 1)) == []  # someone else's
    assert d.send(Assign(NODE, new_node=3, link=0, uid_low=0xDEADBEEF)) == []  # uid mismatch: silent


def test_rx_errors_count_every_undecodable_frame_and_saturate(chip_class):
    d = Driver(chip_class)
    d.to_state(ChipState.IDLE)
    for _ in range(300):
        assert d.send_raw(b"\x05\x01\x02\x03\x00") == []
    assert d.chip.rx_errors == 255


def test_unsupported_without_capabilities(chip_class):
    d = Driver(chip_class, capabilities=Capability.NONE)
    d.to_state(ChipState.IDLE)
    assert d.send(Config(NODE, range=1)) == [Nack(NODE, MsgType.CONFIG, NackReason.UNSUPPORTED)]
    assert d.send(CalWrite(NODE, axis=0, flags=1)) == [Nack(NODE, MsgType.CAL_WRITE, NackReason.UNSUPPORTED)]
    assert d.send(CalWrite(NODE, axis=0, flags=0, offset_q4=5, sensitivity=900.0)) == [Ack(NODE, MsgType.CAL_WRITE, 0)]
    assert d.send(CalRead(NODE, axis=0)) == [CalData(NODE, 0, 0, 5, 900.0)]


def test_range_scales_the_counts(chip_class):
    d = Driver(chip_class)
    d.to_state(ChipState.STREAMING)
    assert d.send(Stop(NODE)) == [Ack(NODE, MsgType.STOP, 0)]
    d.send(Config(NODE, range=2))
    d.send(Start(NODE))
    assert d.send(Sync(counter=9)) == [Sample(NODE, 9, 10 >> 2, -20 >> 2, 1024 >> 2, 0)]


# ------------------------------------------------------------------ timers and counters

def test_boot_announces_then_reannounces_with_a_new_salt_until_assigned(chip_class):
    d = Driver(chip_class)
    boot = d.boot()
    assert boot[0] == Announce(provisional_node(UID, 0), UID) and isinstance(boot[1], Info)
    assert d.chip.poll(ANNOUNCE_PERIOD_S * 0.5) == []
    again = decode_all(d.chip.poll(ANNOUNCE_PERIOD_S))
    assert again[0] == Announce(provisional_node(UID, 1), UID)
    d.t = 1.0
    d.send(Assign(d.chip.node, new_node=NODE, link=0, uid_low=UID & 0xFFFFFFFF))
    assert d.chip.poll(1.9) == []  # assigned: no ANNOUNCE; heartbeat after 1 s
    hb = decode_all(d.chip.poll(2.0 + 1.01))
    assert len(hb) == 1 and isinstance(hb[0], Status) and hb[0].state == ChipState.IDLE


def test_heartbeat_period_follows_config_and_reports_counters(chip_class):
    d = Driver(chip_class)
    d.to_state(ChipState.STREAMING)
    d.send(Config(0, heartbeat_ms=0))
    assert d.chip.state == ChipState.STREAMING  # CONFIG is not allowed while streaming
    d.send(Stop(NODE))
    d.send(Config(NODE, heartbeat_ms=200))
    d.send(Start(NODE))
    for c in (0, 1, 5, 5, 6, 0xFFFF, 0):  # gap of 3 after 1; a repeat and wraparound add nothing
        d.send(Sync(counter=c))
    out = []
    t = 0.0
    while t < 1.0:
        t += 0.05
        out += decode_all(d.chip.poll(t))
    assert len(out) == 5 and all(isinstance(m, Status) for m in out)
    assert out[-1].missed_syncs == 3
    d.send(Config(NODE))
    assert d.chip.state == ChipState.STREAMING


def test_missed_syncs_counts_gaps_and_saturates(chip_class):
    d = Driver(chip_class)
    d.to_state(ChipState.STREAMING)
    for c in (10, 11, 14, 14, 15):
        d.send(Sync(counter=c))
    assert d.chip.missed_syncs == 2
    for c in (100, 400):
        d.send(Sync(counter=c))
    assert d.chip.missed_syncs == 255
    d.send(Start(NODE))  # a new stream: the last counter is forgotten
    assert d.chip.last_counter is None


def test_invalid_sensor_sample_puts_the_chip_in_fault(chip_class):
    chip = chip_class(UID, lambda t: ((0, 0, 0), SampleStatus.INVALID))
    chip.power_on(0.0)
    chip.handle(encode(Assign(chip.node, new_node=NODE, link=1, uid_low=UID & 0xFFFFFFFF)), 0.0)
    chip.handle(encode(Start(NODE)), 0.0)
    (s,) = decode_all(chip.handle(encode(Sync(counter=1)), 0.0))
    assert s.status == SampleStatus.INVALID and chip.state == ChipState.FAULT
    (st,) = decode_all(chip.handle(encode(Stop(NODE)), 0.0))
    assert st == Ack(NODE, MsgType.STOP, 0) and chip.state == ChipState.FAULT
    assert chip.handle(encode(Sync(counter=2)), 0.0) == []  # stopped: silent
