"""Golden vectors: the encoder reproduces tests/vectors/*.json byte for byte, and the decoders
give back exactly the listed fields. The C firmware is held to the same files."""

import json
from pathlib import Path

import cantools
import pytest

from protocol import StreamDecoder, decode_can, encode, to_can
from protocol.crc import CRC_CHECK, crc16_ccitt_false, crc16_rows
from protocol.dbc import DBC_PATH, dbc_frame_id, dbc_text, load_database
from protocol.framing import ErrorReason
from protocol.messages import MsgType, Snapshot
from protocol.vectors import build_vectors, message_from_fields, message_to_fields

VECTORS = Path(__file__).resolve().parents[1] / "vectors"
SERIAL = json.loads((VECTORS / "serial.json").read_text())["vectors"]
CAN = json.loads((VECTORS / "can.json").read_text())["vectors"]
ERRORS = json.loads((VECTORS / "serial_errors.json").read_text())["vectors"]


def test_crc_check_value_from_the_catalogue():
    assert crc16_ccitt_false(b"123456789") == CRC_CHECK == 0x29B1
    # residue: the CRC over data + its own CRC (MSB first) is zero
    assert crc16_ccitt_false(b"123456789\x29\xb1") == 0


def test_vectorised_crc_agrees_with_binascii_row_by_row():
    import numpy as np
    rng = np.random.Generator(np.random.MT19937(7))
    rows = rng.integers(0, 256, size=(200, 13), dtype=np.uint8)
    assert crc16_rows(rows).tolist() == [crc16_ccitt_false(r.tobytes()) for r in rows]


def test_checked_in_vectors_match_the_encoder():
    built = build_vectors()
    for name, content in built.items():
        assert json.loads((VECTORS / name).read_text()) == json.loads(json.dumps(content)), name


def test_every_message_type_has_a_vector_on_both_transports():
    assert {v["type"] for v in SERIAL} == {t.name for t in MsgType}
    assert {v["type"] for v in CAN} == {t.name for t in MsgType}


@pytest.mark.parametrize("vec", SERIAL, ids=lambda v: v["name"])
def test_serial_vector_encodes_and_decodes(vec):
    msg = message_from_fields(vec["type"], vec["node"], vec["fields"])
    assert encode(msg).hex() == vec["hex"]
    events = StreamDecoder().feed(bytes.fromhex(vec["hex"]))
    assert events == [msg]
    assert message_to_fields(events[0]) == vec["fields"]


@pytest.mark.parametrize("vec", CAN, ids=lambda v: v["name"])
def test_can_vector_encodes_and_decodes(vec):
    msg = message_from_fields(vec["type"], vec["node"], vec["fields"])
    frame = to_can(msg)
    assert (f"{frame.arbitration_id:08X}", frame.data.hex(), frame.is_fd) == (vec["id"], vec["data"], vec["fd"])
    assert decode_can(int(vec["id"], 16), bytes.fromhex(vec["data"]), is_fd=vec["fd"]) == msg


@pytest.mark.parametrize("vec", ERRORS, ids=lambda v: v["name"])
def test_serial_error_vector_reports_its_reason(vec):
    dec = StreamDecoder()
    events = dec.feed(bytes.fromhex(vec["hex"]))
    assert [e.reason for e in events] == [ErrorReason(vec["reason"])]
    assert dec.stats.errors[ErrorReason(vec["reason"])] == 1


def test_a_literal_sample_frame():
    # SAMPLE from node 1, counter 0, (0, 0, 1024), status 0: header 01 03 0100, payload 0000 00 00 00 00 04 (z = 0x400 at bits 24..35),
    # CRC, then COBS and the delimiter. Written out by hand from docs/protocol.md §6.
    frame = bytes.fromhex("01030100" "0000" "0000000004")
    frame += crc16_ccitt_false(frame).to_bytes(2, "big")
    from cobs import cobs
    wire = cobs.encode(frame) + b"\x00"
    vec = next(v for v in SERIAL if v["name"] == "sample_flat")
    assert wire.hex() == vec["hex"]


def test_checked_in_dbc_is_the_generated_one():
    assert DBC_PATH.read_bytes().decode() == dbc_text()


def test_dbc_lookup_by_raw_identifier_masks_the_node():
    db = load_database()
    from protocol import Sample
    for node in (1, 0x1234, 0xFFFE):
        frame = to_can(Sample(node, 1, 2, 3, 4, 0))
        assert dbc_frame_id(frame.arbitration_id) != frame.arbitration_id
        assert db.get_message_by_frame_id(frame.arbitration_id).name == "SAMPLE"


@pytest.mark.parametrize("vec", CAN, ids=lambda v: v["name"])
def test_cantools_decodes_our_frames_field_by_field(vec):
    db = cantools.database.load_file(str(DBC_PATH))  # plain load: tools without the mask
    msg = message_from_fields(vec["type"], vec["node"], vec["fields"])
    frame = to_can(msg)
    entry = db.get_message_by_frame_id(dbc_frame_id(frame.arbitration_id))
    assert entry.name == vec["type"]
    assert entry.is_extended_frame and entry.is_fd == frame.is_fd
    decoded = entry.decode(frame.data, decode_choices=False, allow_truncated=True)
    if isinstance(msg, Snapshot):
        assert decoded["counter"] == msg.counter and decoded["first_link"] == msg.first_link
        assert decoded["count"] == msg.count
        for k, ((x, y, z), s) in enumerate(zip(msg.counts.tolist(), msg.status.tolist())):
            assert (decoded[f"x_{k}"], decoded[f"y_{k}"], decoded[f"z_{k}"], decoded[f"status_{k}"]) == (x, y, z, s)
    else:
        assert decoded == pytest.approx(vec["fields"])
