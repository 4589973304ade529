"""The C codec (firmware_ref/src/codec.c) against the golden vectors and the Python codec.

Every golden vector — v1.2's IMU frames (docs §16) among them — is reproduced byte for byte by the C
encoder and decoded by the C decoder; random messages encode identically in C and Python and decode
back; arbitrary bytes get the same verdict (message or ErrorReason) from the C and the Python decoders.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cobs import cobs
from hypothesis import given
from hypothesis import strategies as st

from protocol import can as pycan
from protocol import framing
from protocol.crc import crc16_ccitt_false
from protocol.framing import DecodeError, ErrorReason, StreamDecoder
from protocol.messages import (IMU_TYPES, ConfigImu, ImuAccel, ImuGyro, ImuMag, ImuSample, MsgType, Snapshot,
                               SnapshotImu, Sync, provisional_node)
from protocol.state import RULES, Reply
from protocol.vectors import message_from_fields
from tests.strategies import messages

codec = pytest.importorskip("firmware_ref.codec", reason="C firmware extension not built")

VECTORS = Path(__file__).resolve().parents[1] / "vectors"
SERIAL = json.loads((VECTORS / "serial.json").read_text())["vectors"]
CAN = json.loads((VECTORS / "can.json").read_text())["vectors"]
#: every vector, v1.2's IMU frames (§16) included: the C codec speaks them all
C_SERIAL, C_CAN = SERIAL, CAN
_IMU_NAMES = {t.name for t in IMU_TYPES}
assert {v["type"] for v in SERIAL + CAN} >= _IMU_NAMES
SERIAL_ERRORS = json.loads((VECTORS / "serial_errors.json").read_text())["vectors"]


def _msg(v):
    return message_from_fields(v["type"], v["node"], v["fields"])


# ---------------------------------------------------------------------------------------------
# golden vectors
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("v", C_SERIAL, ids=[v["name"] for v in C_SERIAL])
def test_serial_vector_encoded_byte_for_byte_by_c(v):
    assert codec.encode_serial(_msg(v)).hex() == v["hex"]


@pytest.mark.parametrize("v", C_SERIAL, ids=[v["name"] for v in C_SERIAL])
def test_serial_vector_decoded_by_c(v):
    wire = bytes.fromhex(v["hex"])
    assert wire[-1] == 0
    assert codec.decode_frame(wire[:-1]) == _msg(v)
    # and through the byte-at-a-time stream decoder, with idle fill around it
    assert codec.decode_stream(b"\x00" + wire + b"\x00\x00") == [_msg(v)]


@pytest.mark.parametrize("v", C_CAN, ids=[v["name"] for v in C_CAN])
def test_can_vector_encoded_byte_for_byte_by_c(v):
    f = codec.encode_can(_msg(v))
    assert (f"{f.arbitration_id:08X}", f.data.hex(), f.is_fd) == (v["id"], v["data"], v["fd"])


@pytest.mark.parametrize("v", C_CAN, ids=[v["name"] for v in C_CAN])
def test_can_vector_decoded_by_c(v):
    got = codec.decode_can(int(v["id"], 16), bytes.fromhex(v["data"]), is_fd=v["fd"])
    assert got == _msg(v)


@pytest.mark.parametrize("v", SERIAL_ERRORS, ids=[v["name"] for v in SERIAL_ERRORS])
def test_serial_error_vector_gives_the_same_reason_in_c(v):
    wire = bytes.fromhex(v["hex"])
    reason = ErrorReason(v["reason"])
    # the frame alone (without its delimiter) ...
    with pytest.raises(codec.CodecError) as exc:
        codec.decode_frame(wire[:-1])
    assert exc.value.reason is reason
    # ... and the stream, byte by byte: exactly one event, that reason, then a good frame still decodes
    good = framing.encode(Sync(counter=7))
    assert codec.decode_stream(wire + good) == [reason, Sync(counter=7)]


def test_snapshot_vector_pads_fd_with_zeros_and_rejects_non_zero_padding():
    v = next(v for v in CAN if v["type"] == "SNAPSHOT")
    data = bytearray.fromhex(v["data"])
    assert v["fd"] and data[-1] == 0
    data[-1] = 0x55
    with pytest.raises(codec.CodecError) as exc:
        codec.decode_can(int(v["id"], 16), bytes(data), is_fd=True)
    assert exc.value.reason is ErrorReason.BAD_FIELD


# ---------------------------------------------------------------------------------------------
# primitives
# ---------------------------------------------------------------------------------------------

def test_crc_check_value_and_residue():
    assert codec.crc16(b"123456789") == 0x29B1
    assert codec.crc16(b"123456789\x29\xb1") == 0


@given(st.binary(max_size=600))
def test_crc_and_cobs_agree_with_python(data):
    assert codec.crc16(data) == crc16_ccitt_false(data)
    enc = codec.cobs_encode(data)
    assert enc == cobs.encode(data)
    assert codec.cobs_decode(enc) == data


@given(st.binary(max_size=300))
def test_cobs_decode_verdict_agrees_with_python(data):
    try:
        expected = cobs.decode(data)
    except cobs.DecodeError:
        expected = None
    try:
        got = codec.cobs_decode(data)
    except codec.CodecError as exc:
        assert exc.name == "BAD_COBS"
        got = None
    assert got == expected


@given(st.integers(0, 2**64 - 1), st.integers(0, 2**32 - 1))
def test_provisional_node_identical_to_python(uid, salt):
    assert codec.provisional_node(uid, salt) == provisional_node(uid, salt)


def test_provisional_node_doc_example():
    assert codec.provisional_node(0x0123456789ABCDEF) == 0x9112


def test_c_state_table_is_protocol_state_rules():
    """Every (state, host -> chip type) pair: same presence, reply, next state and validate flag."""
    replies = {0: Reply.NONE, 1: Reply.ACK, 2: Reply.SAMPLE, 3: Reply.ANNOUNCE_INFO, 4: Reply.CAL_DATA,
               5: Reply.ACK_THEN_BOOT, 6: Reply.CAL_IMU_DATA}
    from protocol.messages import ChipState
    host_types = [t for t in MsgType if t >= 0x10]
    assert len(host_types) == 12 and MsgType.CONFIG_IMU in host_types and MsgType.CAL_IMU_READ in host_types
    for state in ChipState:
        for t in host_types:
            rule = RULES.get((state, t))
            got = codec.rule_for(state, t)
            if rule is None:
                assert got is None, (state, t)
            else:
                reply, nxt, validate = got
                assert (replies[reply], nxt, validate) == (rule.reply, rule.next_state, rule.validate), (state, t)


# ---------------------------------------------------------------------------------------------
# random messages: C == Python
# ---------------------------------------------------------------------------------------------

@given(messages())
def test_c_serial_encode_equals_python_and_decodes_back(msg):
    wire = framing.encode(msg)
    assert codec.encode_serial(msg) == wire
    assert codec.decode_frame(wire[:-1]) == msg
    assert codec.encode_payload(msg) == msg.payload()
    assert codec.decode_payload(msg.TYPE, msg.node, msg.payload()) == msg


@given(messages(max_snapshot=11), st.sampled_from([None, True]))
def test_c_can_encode_equals_python_and_decodes_back(msg, fd):
    f = pycan.to_can(msg, fd=fd)
    assert codec.encode_can(msg, fd=fd) == f
    assert codec.decode_can(f.arbitration_id, f.data, is_fd=f.is_fd) == msg


def test_classic_can_refuses_a_snapshot_and_serial_refuses_an_oversized_frame():
    snap = Snapshot(0, 1, 0, bytes(5 * 2))
    with pytest.raises(codec.CodecError) as exc:
        codec.encode_can(snap, fd=False)
    assert exc.value.name == "NEEDS_FD"
    with pytest.raises(codec.CodecError) as exc:
        codec.encode_serial(Snapshot(0, 1, 0, bytes(5 * 204)))
    assert exc.value.name == "ARGUMENT"


# ---------------------------------------------------------------------------------------------
# arbitrary input: the C decoder's verdict is the Python decoder's
# ---------------------------------------------------------------------------------------------

def _py_verdict(segment: bytes):
    ev = framing.decode_frame(segment)
    return ev.reason if isinstance(ev, DecodeError) else ev


def _c_verdict(segment: bytes):
    try:
        return codec.decode_frame(segment)
    except codec.CodecError as exc:
        return exc.reason


#: type codes, the IMU ones (§16) and their neighbours drawn more often than their share
_TYPES = st.one_of(st.integers(0, 0x3F), st.sampled_from([0x08, 0x09, 0x0A, 0x0B, 0x0C, 0x0D, 0x0E, 0x0F, 0x19, 0x1A]))


def _imu_payload():
    """Payloads near the IMU types' own sizes (8, 15, 21, 6 + 13·n, 6 + 19·n), format byte 0..3."""
    return st.one_of(st.binary(max_size=24), st.builds(
        lambda head, fmt, n, pad: head[:5] + bytes([fmt]) + pad[:(13 if fmt == 1 else 19) * n],
        st.binary(min_size=5, max_size=5).map(lambda h: h[:4] + bytes([h[4] % 4])), st.integers(0, 3),
        st.integers(0, 3), st.binary(min_size=57, max_size=57)))


def _frames(draw_types=_TYPES):
    """Frames a conforming sender never sends: any version, type, node and payload."""
    return st.builds(lambda v, t, n, p: framing.encode_frame(t, n, p, version=v)[:-1],
                     st.sampled_from([1, 1, 1, 2, 0]), draw_types, st.integers(0, 0xFFFF),
                     _imu_payload())


@given(st.one_of(st.binary(max_size=64), _frames()))
def test_any_frame_gets_the_same_verdict_from_c_and_python(segment):
    segment = segment.replace(b"\x00", b"\x01") if b"\x00" in segment else segment
    assert _c_verdict(segment) == _py_verdict(segment)


@given(st.lists(st.one_of(st.binary(max_size=40), _frames().map(lambda f: f + b"\x00")), max_size=8))
def test_any_byte_stream_gives_the_same_events_from_c_and_python(chunks):
    data = b"".join(chunks)
    py = StreamDecoder()
    expected = [ev.reason if isinstance(ev, DecodeError) else ev for ev in py.feed(data)]
    assert codec.decode_stream(data) == expected


def _can_ids():
    """Any 29-bit identifier, or one of an IMU type (§16) in version 1."""
    return st.one_of(st.integers(0, 2**29 - 1), st.builds(lambda t, n, p: p << 26 | t << 20 | 1 << 16 | n,
                                                          st.sampled_from([0x0A, 0x0B, 0x0C, 0x0D, 0x0E, 0x19]),
                                                          st.integers(0, 0xFFFF), st.integers(0, 7)))


def _can_data():
    """Any data, or a valid FD length with the padding zero (or not) and IMU-ish heads."""
    return st.one_of(st.binary(max_size=64), st.builds(
        lambda n, head, fmt, nz: (head[:5] + bytes([fmt]) + bytes(n))[:n - 1] + bytes([nz]),
        st.sampled_from([8, 12, 16, 20, 24, 32, 48, 64]), st.binary(min_size=5, max_size=5), st.integers(0, 3),
        st.sampled_from([0, 0, 0, 1])))


@given(_can_ids(), _can_data(), st.booleans())
def test_any_can_frame_gets_the_same_verdict_from_c_and_python(can_id, data, is_fd):
    ev = pycan.decode_can(can_id, data, is_fd=is_fd)
    expected = ev.reason if isinstance(ev, DecodeError) else ev
    try:
        got = codec.decode_can(can_id, data, is_fd=is_fd)
    except codec.CodecError as exc:
        got = exc.reason
    assert got == expected


def test_oversize_run_is_reported_once_and_the_stream_recovers():
    data = b"\x01" * 5000 + b"\x00" + framing.encode(Sync(counter=1))
    assert codec.decode_stream(data) == [ErrorReason.OVERSIZE, Sync(counter=1)]


def test_small_rx_buffer_drops_long_frames_as_oversize_only():
    big = framing.encode(Snapshot(0, 1, 0, bytes(range(50))))
    small = framing.encode(Sync(counter=9))
    assert codec.decode_stream(big + small, cap=15) == [ErrorReason.OVERSIZE, Sync(counter=9)]


# ---------------------------------------------------------------------------------------------
# v1.2 IMU messages (docs §16): C == Python on random ones
# ---------------------------------------------------------------------------------------------

_i16 = st.integers(-32768, 32767)
_acc = st.integers(-2048, 2047)
_u16 = st.integers(0, 0xFFFF)
_node = st.integers(0, 0xFFFE)


@st.composite
def _snapshot_imu(draw, max_count):
    fmt = draw(st.sampled_from([1, 2]))
    n = draw(st.integers(1, max_count[fmt]))
    rec = draw(st.binary(min_size=(13 if fmt == 1 else 19) * n, max_size=(13 if fmt == 1 else 19) * n))
    return SnapshotImu(draw(_node), draw(_u16), draw(st.integers(0, 0x10000 - n)), fmt, rec)


def imu_messages(max_count=None):
    """Any valid v1.2 IMU message (records of a SNAPSHOT_IMU capped per format: serial 77 / 53)."""
    max_count = max_count or {1: 77, 2: 53}
    return st.one_of(
        st.builds(ImuSample, _node, _u16, _acc, _acc, _acc, st.integers(0, 15), _i16, _i16, _i16, _i16),
        st.builds(ImuSample, _node, _u16, _acc, _acc, _acc, st.integers(0, 15), _i16, _i16, _i16, _i16, _i16, _i16,
                  _i16),
        st.builds(ImuGyro, _node, _u16, _i16, _i16, _i16),
        st.builds(ImuMag, _node, _u16, _i16, _i16, _i16),
        st.builds(ImuAccel, _node, st.integers(0, 255), _acc, _acc, _acc, st.integers(0, 15), _i16),
        _snapshot_imu(max_count),
        st.builds(ConfigImu, _node, st.integers(0, 255), st.integers(0, 255), st.integers(0, 255), st.integers(0, 255)),
    )


@given(imu_messages())
def test_c_serial_encodes_imu_messages_as_python_and_decodes_them_back(msg):
    wire = framing.encode(msg)
    assert codec.encode_serial(msg) == wire
    assert codec.decode_frame(wire[:-1]) == msg
    assert codec.decode_stream(wire) == [msg]
    assert codec.encode_payload(msg) == msg.payload()
    assert codec.decode_payload(msg.TYPE, msg.node, msg.payload()) == msg


@given(imu_messages(max_count={1: 4, 2: 3}), st.sampled_from([None, True, False]))
def test_c_can_encodes_imu_messages_as_python_and_decodes_them_back(msg, fd):
    if fd is False and len(msg.payload()) > 8:  # IMU_SAMPLE, SNAPSHOT_IMU: CAN FD only (§16.3, §16.5)
        with pytest.raises(codec.CodecError) as exc:
            codec.encode_can(msg, fd=False)
        assert exc.value.name == "NEEDS_FD"
        return
    f = pycan.to_can(msg, fd=fd)
    assert codec.encode_can(msg, fd=fd) == f
    assert codec.decode_can(f.arbitration_id, f.data, is_fd=f.is_fd) == msg


def test_imu_sample_fd_lengths_and_padding_are_held_to_section_16_3():
    v = next(v for v in CAN if v["type"] == "IMU_SAMPLE" and v["fd"])
    cid, data = int(v["id"], 16), bytes.fromhex(v["data"])
    assert len(data) in (16, 24) and data[-1] == 0
    for bad, reason in ((data[:-1] + b"\x01", ErrorReason.BAD_FIELD), (data + bytes(4), ErrorReason.BAD_LENGTH),
                        (data[:12], ErrorReason.BAD_LENGTH)):
        with pytest.raises(codec.CodecError) as exc:
            codec.decode_can(cid, bad, is_fd=True)
        assert exc.value.reason is reason, bad.hex()
    with pytest.raises(codec.CodecError) as exc:  # a classic frame cannot carry it
        codec.decode_can(cid, data[:8], is_fd=False)
    assert exc.value.reason is ErrorReason.BAD_LENGTH
