"""Every receiver against tests/vectors/verdicts.json: edge frames and the verdict docs/protocol.md
§8.1 gives each (written out by hand in protocol/vectors.py, not derived from a decoder). The
receivers: the Python frame decoder, its stream decoder (whole, byte by byte), the CAN decoder, and
the C firmware's frame decoder, stream decoder and CAN decoder (cffi)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from protocol.can import decode_can
from protocol.framing import DecodeError, ErrorReason, StreamDecoder, decode_frame
from protocol.vectors import build_vectors, message_from_fields

VECTORS = json.loads((Path(__file__).resolve().parents[1] / "vectors" / "verdicts.json").read_text())["vectors"]
SERIAL = [v for v in VECTORS if v["transport"] == "serial"]
CAN = [v for v in VECTORS if v["transport"] == "can"]


def _c():
    pytest.importorskip("firmware_ref._capsheet_fw", reason="C firmware extension not built")
    from firmware_ref import codec
    return codec


def _verdict(result) -> str | object:
    if isinstance(result, DecodeError):
        return result.reason.value
    return "decoded"


def _expected_msg(v):
    return message_from_fields(v["type"], v["node"], v["fields"])


def _check(v, result) -> None:
    assert _verdict(result) == v["verdict"], f"{v['name']} (§{v['clause']}): got {result}"
    if v["verdict"] == "decoded":
        assert result == _expected_msg(v)


def test_the_checked_in_verdicts_are_the_generated_ones():
    assert json.loads(json.dumps(build_vectors()["verdicts.json"])) == \
        json.loads((Path(__file__).resolve().parents[1] / "vectors" / "verdicts.json").read_text())


def test_the_vectors_cover_both_transports_and_every_verdict():
    assert {v["verdict"] for v in SERIAL} >= {"decoded", "oversize", "bad_version", "unknown_type", "bad_length",
                                              "bad_field"}
    assert {v["verdict"] for v in CAN} >= {"decoded", "bad_version", "unknown_type", "bad_length", "bad_field"}


@pytest.mark.parametrize("v", SERIAL, ids=[v["name"] for v in SERIAL])
def test_python_frame_decoder(v):
    _check(v, decode_frame(bytes.fromhex(v["hex"])[:-1]))


@pytest.mark.parametrize("v", SERIAL, ids=[v["name"] for v in SERIAL])
@pytest.mark.parametrize("chunk", [None, 1])
def test_python_stream_decoder(v, chunk):
    dec = StreamDecoder()
    data = bytes.fromhex(v["hex"])
    events = dec.feed(data) if chunk is None else [e for i in range(len(data)) for e in dec.feed(data[i:i + 1])]
    assert len(events) == 1, events
    _check(v, events[0])


@pytest.mark.parametrize("v", CAN, ids=[v["name"] for v in CAN])
def test_python_can_decoder(v):
    _check(v, decode_can(int(v["id"], 16), bytes.fromhex(v["data"]), is_extended_id=v["extended"], is_fd=v["fd"]))


@pytest.mark.parametrize("v", SERIAL, ids=[v["name"] for v in SERIAL])
def test_c_frame_and_stream_decoders(v):
    codec = _c()
    data = bytes.fromhex(v["hex"])
    try:
        got = codec.decode_frame(data[:-1])
    except codec.CodecError as exc:
        got = DecodeError(exc.reason, exc.name)
    _check(v, got)
    (ev,) = codec.decode_stream(data)  # the C stream decoder with a buffer of every frame the spec allows
    # an event is a message or an ErrorReason (CAL_IMU_* messages have a field `value` too)
    _check(v, DecodeError(ev, "") if isinstance(ev, ErrorReason) else ev)


@pytest.mark.parametrize("v", CAN, ids=[v["name"] for v in CAN])
def test_c_can_decoder(v):
    codec = _c()
    try:
        got = codec.decode_can(int(v["id"], 16), bytes.fromhex(v["data"]), is_extended_id=v["extended"], is_fd=v["fd"])
    except codec.CodecError as exc:
        got = DecodeError(exc.reason, exc.name)
    _check(v, got)


def test_a_wrong_verdict_is_caught():
    v = dict(next(x for x in SERIAL if x["name"] == "snapshot_203_samples_is_1026_bytes"), verdict="decoded")
    with pytest.raises(AssertionError):
        _check(v, decode_frame(bytes.fromhex(v["hex"])[:-1]))
