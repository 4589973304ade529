"""Golden test vectors (tests/vectors/*.json): canonical messages and their exact wire bytes on
serial and CAN. The C firmware and any chip are held to these bytes (docs §9).

``capsheet protocol vectors --write`` regenerates the files; a test fails if the encoder and the
checked-in files ever disagree, so a change of wire format cannot slip through unnoticed.

JSON layout (``serial.json``; ``can.json`` has ``id``, ``data`` and ``fd`` instead of ``hex``)::

    {"protocol_version": 1, "vectors": [
        {"name": "sample_basic", "type": "SAMPLE", "node": 5,
         "fields": {"counter": 1, "x": 0, ...}, "hex": "..."}, ...]}

Snapshot fields are ``counter``, ``first_link``, ``counts`` (list of [x, y, z]) and ``status``.
"""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path

import numpy as np

from .can import to_can
from .constants import SampleStatus
from .framing import encode, encode_frame
from .messages import (MESSAGE_TYPES, PROTOCOL_VERSION, Ack, Announce, Assign, CalData, CalRead, CalWrite,
                       Capability, ChipState, Config, GetInfo, Info, Message, MsgType, Nack, NackReason,
                       Reset, Sample, Snapshot, Start, Status, StatusFlag, Stop, Sync)

__all__ = ["canonical_messages", "message_to_fields", "message_from_fields", "build_vectors",
           "error_vectors", "VECTOR_DIR", "write_vectors"]

VECTOR_DIR = Path(__file__).resolve().parent.parent / "tests" / "vectors"


def canonical_messages() -> list[tuple[str, Message]]:
    """At least one vector per type, with edge values (extremes, zeros in the payload for COBS)."""
    snap_counts = np.array([[0, 0, 1024], [-2048, 2047, -1], [1, -1, 0], [100, -200, 300]])
    snap_status = np.array([0, SampleStatus.SATURATED, SampleStatus.INVALID, 0xF])
    return [
        ("announce", Announce(0x8123, uid=0x0123456789ABCDEF)),
        ("announce_assigned", Announce(42, uid=0xFFFFFFFFFFFFFFFF)),
        ("info", Info(42, 1, 2, 3, PROTOCOL_VERSION, Capability.CAN_FD | Capability.SELF_TEST, 12, ChipState.IDLE)),
        ("sample_flat", Sample(1, counter=0, x=0, y=0, z=1024, status=0)),
        ("sample_extremes", Sample(0x7FFF, counter=0xFFFF, x=-2048, y=2047, z=-1, status=SampleStatus.SATURATED)),
        ("sample_all_status", Sample(300, counter=0x1234, x=-5, y=17, z=1000, status=0xF)),
        ("status", Status(42, ChipState.STREAMING, StatusFlag.CAL_VALID | StatusFlag.CONFIGURED, 3, 255, 86400)),
        ("ack_start", Ack(42, MsgType.START, 0)),
        ("nack_bad_state", Nack(42, MsgType.START, NackReason.BAD_STATE)),
        ("cal_data", CalData(42, axis=2, flags=1, offset_q4=-37, sensitivity=1019.25)),
        ("snapshot", Snapshot.from_arrays(0, 0xABCD, 360, snap_counts, snap_status)),
        ("sync", Sync(counter=0)),
        ("sync_wrap", Sync(counter=0xFFFF)),
        ("assign", Assign(0x8123, new_node=1, link=0, uid_low=0x89ABCDEF)),
        ("config", Config(0, rate_hz=145, range=0, filter=1, heartbeat_ms=1000)),
        ("start_broadcast", Start(0)),
        ("stop_one", Stop(7)),
        ("get_info_broadcast", GetInfo(0)),
        ("reset", Reset(7)),
        ("cal_write", CalWrite(7, axis=0, flags=1, offset_q4=16, sensitivity=1024.0)),
        ("cal_read", CalRead(7, axis=1)),
    ]


def message_to_fields(msg: Message) -> dict:
    if isinstance(msg, Snapshot):
        return {"counter": msg.counter, "first_link": msg.first_link,
                "counts": msg.counts.tolist(), "status": msg.status.tolist()}
    return {f.name: (float(v) if isinstance(v, float) else int(v))
            for f in fields(msg)[1:] for v in [getattr(msg, f.name)]}


def message_from_fields(type_name: str, node: int, values: dict) -> Message:
    cls = MESSAGE_TYPES[MsgType[type_name]]
    if cls is Snapshot:
        return Snapshot.from_arrays(node, values["counter"], values["first_link"],
                                    np.array(values["counts"]), np.array(values["status"]))
    return cls(node, **values)


def build_vectors() -> dict[str, dict]:
    serial, can = [], []
    for name, msg in canonical_messages():
        base = {"name": name, "type": msg.TYPE.name, "node": msg.node, "fields": message_to_fields(msg)}
        serial.append({**base, "hex": encode(msg).hex()})
        f = to_can(msg)
        can.append({**base, "id": f"{f.arbitration_id:08X}", "data": f.data.hex(), "fd": f.is_fd})
    return {
        "serial.json": {"protocol_version": PROTOCOL_VERSION, "framing": "COBS, 0x00 delimiter, CRC-16/CCITT-FALSE MSB first",
                        "vectors": serial},
        "can.json": {"protocol_version": PROTOCOL_VERSION, "identifier": "29-bit: priority[28:26] type[25:20] version[19:16] node[15:0]",
                     "vectors": can},
        "serial_errors.json": {"protocol_version": PROTOCOL_VERSION, "vectors": error_vectors()},
    }


def error_vectors() -> list[dict]:
    """Damaged serial input and the error reason a receiver must report for it."""
    good = encode(Sample(1, 7, 1, 2, 3, 0))
    body = bytearray(good)
    body[5] ^= 0x01  # a payload bit: CRC fails
    out = [
        {"name": "bad_crc", "hex": bytes(body).hex(), "reason": "bad_crc"},
        {"name": "bad_version", "hex": encode_frame(MsgType.SAMPLE, 1, Sample(1, 7, 1, 2, 3).payload(), version=2).hex(),
         "reason": "bad_version"},
        {"name": "unknown_type", "hex": encode_frame(0x3F, 1, b"").hex(), "reason": "unknown_type"},
        {"name": "bad_length", "hex": encode_frame(MsgType.SAMPLE, 1, b"\x01\x02\x03").hex(), "reason": "bad_length"},
        {"name": "bad_field", "hex": encode_frame(MsgType.NACK, 1, bytes([0x13, 0xEE])).hex(), "reason": "bad_field"},
        {"name": "short", "hex": "03010200", "reason": "short"},
        {"name": "bad_cobs", "hex": "05010203" + "00", "reason": "bad_cobs"},
        {"name": "oversize", "hex": "01" * 1100 + "00", "reason": "oversize"},
    ]
    return out


def write_vectors(directory: Path = VECTOR_DIR) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for fname, content in build_vectors().items():
        path = directory / fname
        path.write_text(json.dumps(content, indent=1) + "\n")
        written.append(path)
    return written
