"""The C codec (firmware_ref/src/codec.c) against the golden vectors and the Python codec.

Every golden vector is reproduced byte for byte by the C encoder and decoded by the C decoder;
random messages encode identically in C and Python and decode back; arbitrary bytes get the same
verdict (message or ErrorReason) from the C and the Python decoders.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cobs import cobs
from hypothesis import assume, given
from hypothesis import strategies as st

from protocol import can as pycan
from protocol import framing
from protocol.crc import crc16_ccitt_false
from protocol.framing import DecodeError, ErrorReason, StreamDecoder
from protocol.messages import IMU_TYPES, MsgType, Snapshot, Sync, provisional_node
from protocol.state import RULES, Reply
from protocol.vectors import message_from_fields
from tests.strategies import messages

codec = pytest.importorskip("firmware_ref.codec", reason="C firmware extension not built")

VECTORS = Path(__file__).resolve().parents[1] / "vectors"
SERIAL = json.loads((VECTORS / "serial.json").read_text())["vectors"]
CAN = json.loads((VECTORS / "can.json").read_text())["vectors"]
#: the C firmware does not speak v1.2's IMU messages yet (issue 29 point 3): their vectors are held to
#: the Python reference only (tests/protocol), and the random frames below leave their type codes out
_IMU_NAMES = {t.name for t in IMU_TYPES}
C_SERIAL = [v for v in SERIAL if v["type"] not in _IMU_NAMES]
C_CAN = [v for v in CAN if v["type"] not in _IMU_NAMES]
assert len(C_SERIAL) < len(SERIAL) and len(C_CAN) < len(CAN)
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
               5: Reply.ACK_THEN_BOOT}
    from protocol.messages import ChipState
    host_types = [t for t in MsgType if t >= 0x10 and t not in IMU_TYPES]  # CONFIG_IMU: not in C yet
    assert len(host_types) == 9
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


def _imu_segment(segment: bytes) -> bool:
    """A delimited run that decodes to a frame of a v1.2 IMU type (the C firmware does not know them yet)."""
    try:
        raw = cobs.decode(segment)
    except cobs.DecodeError:
        return False
    return len(raw) >= 2 and raw[1] in {int(t) for t in IMU_TYPES}


def _frames(draw_types=st.integers(0, 0x3F).filter(lambda t: t not in {int(t) for t in IMU_TYPES})):
    """Frames a conforming sender never sends: any version, type, node and payload."""
    return st.builds(lambda v, t, n, p: framing.encode_frame(t, n, p, version=v)[:-1],
                     st.sampled_from([1, 1, 1, 2, 0]), draw_types, st.integers(0, 0xFFFF),
                     st.binary(max_size=24))


@given(st.one_of(st.binary(max_size=64), _frames()))
def test_any_frame_gets_the_same_verdict_from_c_and_python(segment):
    segment = segment.replace(b"\x00", b"\x01") if b"\x00" in segment else segment
    assume(not _imu_segment(segment))
    assert _c_verdict(segment) == _py_verdict(segment)


@given(st.lists(st.one_of(st.binary(max_size=40), _frames().map(lambda f: f + b"\x00")), max_size=8))
def test_any_byte_stream_gives_the_same_events_from_c_and_python(chunks):
    data = b"".join(chunks)
    assume(not any(_imu_segment(seg) for seg in data.split(b"\x00")))
    py = StreamDecoder()
    expected = [ev.reason if isinstance(ev, DecodeError) else ev for ev in py.feed(data)]
    assert codec.decode_stream(data) == expected


@given(st.integers(0, 2**29 - 1), st.binary(max_size=64), st.booleans())
def test_any_can_frame_gets_the_same_verdict_from_c_and_python(can_id, data, is_fd):
    assume((can_id >> 20) & 0x3F not in {int(t) for t in IMU_TYPES})
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
