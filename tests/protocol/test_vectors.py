"""Golden vectors: the encoder reproduces tests/vectors/*.json byte for byte, and the decoders
give back exactly the listed fields. The C firmware is held to the same files."""

import json
from pathlib import Path

import cantools
import pytest

from protocol import StreamDecoder, decode_can, encode, to_can
from protocol.crc import crc16_ccitt_false
from protocol.dbc import DBC_PATH, dbc_frame_id, dbc_text, load_database
from protocol.framing import ErrorReason
from protocol.messages import MsgType, Snapshot
from protocol.vectors import build_vectors, message_from_fields, message_to_fields

VECTORS = Path(__file__).resolve().parents[1] / "vectors"
SERIAL = json.loads((VECTORS / "serial.json").read_text())["vectors"]
CAN = json.loads((VECTORS / "can.json").read_text())["vectors"]
ERRORS = json.loads((VECTORS / "serial_errors.json").read_text())["vectors"]


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
    elif vec["type"] == "SNAPSHOT_IMU":  # a multiplexed entry: the format byte picks the record signals
        f = vec["fields"]
        fmt = 2 if "mag" in f else 1
        assert (decoded["counter"], decoded["first_link"], decoded["count"], decoded["format"]) == (
            f["counter"], f["first_link"], len(f["counts"]), fmt)
        for k in range(len(f["counts"])):
            got = [decoded[f"{a}_{fmt}_{k}"] for a in ("x", "y", "z", "status", "time_us", "gx", "gy", "gz")]
            assert got == [*f["counts"][k], f["status"][k], f["time_us"][k], *f["gyro"][k]]
            if fmt == 2:
                assert [decoded[f"m{a}_2_{k}"] for a in "xyz"] == f["mag"][k]
    else:
        assert decoded == pytest.approx(vec["fields"])


# ---- the vectors re-derived independently: the spec's byte tables, `cobs`, binascii.crc_hqx, cantools --

import binascii
import re
import struct

SPEC = (Path(__file__).resolve().parents[2] / "docs/protocol.md").read_text()
_FMT = {"u8": "B", "u16": "H", "u32": "I", "u64": "Q", "i16": "h", "f32": "f"}


def spec_types() -> dict[str, tuple[int, int]]:
    """name -> (type code, CAN priority), from the message table of docs/protocol.md §4."""
    return {name: (int(code, 16), int(prio)) for code, name, prio in
            re.findall(r"^\| (0x[0-9A-F]{2}) \| ([A-Z_]+) \| [^|]+\| [^|]+\| (\d) \|", SPEC, re.M)}


def spec_layouts() -> dict[str, list[tuple[str, str]]]:
    """name -> [(wire type, field)] from the §4.x tables (CAL_WRITE: "the CAL_DATA layout")."""
    out: dict[str, list] = {}
    for sec in re.split(r"^### ", SPEC, flags=re.M)[1:]:
        head, _, body = sec.partition("\n")
        if not head.startswith(("4.", "17.")):  # v1.3's calibration messages are laid out in §17
            continue
        names = re.findall(r"([A-Z][A-Z_]+) \(0x", head)
        rows = re.findall(r"^\| \d+ \| ([a-z0-9·+ ]+?) \| ([a-z_0-9]+)", body, re.M)
        for n in names:
            out.setdefault(n, rows if (rows or "empty" in head) else None)
    return {n: v for n, v in out.items() if v is not None}


def reference_payload(name: str, f: dict) -> bytes:
    """A payload packed by the spec alone: its field tables, §2 (little-endian) and §5.2 (the word)."""
    def word(x, y, z, s):
        return ((x & 0xFFF) | (y & 0xFFF) << 12 | (z & 0xFFF) << 24 | s << 36).to_bytes(5, "little")
    out = b""
    for typ, field in spec_layouts()[name]:
        if typ in _FMT:
            value = len(f["counts"]) if field == "count" else f[field]  # SNAPSHOT's count: n samples
            out += struct.pack("<" + _FMT[typ], value)
        elif field == "sample":  # SAMPLE: "40 bits | sample word"
            out += word(f["x"], f["y"], f["z"], f["status"])
        elif field == "samples":  # SNAPSHOT: "5·n | samples"
            out += b"".join(word(*c, s) for c, s in zip(f["counts"], f["status"]))
        else:
            raise AssertionError(f"{name}: no rule for {typ} {field}")
    return out


V12 = {"IMU_GYRO", "IMU_MAG", "IMU_ACCEL", "IMU_SAMPLE", "SNAPSHOT_IMU", "CONFIG_IMU"}


def reference_v12(name: str, f: dict) -> bytes:
    """A v1.2 payload packed from docs §16 alone: §16.1's record (the §5.2 word, time_us i16, 3 × i16
    gyroscope, 3 × i16 magnetometer in format 2), §16.2-§16.5's tables."""
    def word(x, y, z, s):
        return ((x & 0xFFF) | (y & 0xFFF) << 12 | (z & 0xFFF) << 24 | s << 36).to_bytes(5, "little")

    def record(c, s, t, g, m):
        return word(*c, s) + struct.pack("<h3h", t, *g) + (struct.pack("<3h", *m) if m is not None else b"")
    if name == "CONFIG_IMU":
        return struct.pack("<4B", f["format"], f["gyro_range"], f["mag_range"], f["flags"])
    if name == "IMU_GYRO":
        return struct.pack("<H3h", f["counter"], f["gx"], f["gy"], f["gz"])
    if name == "IMU_MAG":
        return struct.pack("<H3h", f["counter"], f["mx"], f["my"], f["mz"])
    if name == "IMU_ACCEL":
        return struct.pack("<B", f["counter_lo"]) + word(f["x"], f["y"], f["z"], f["status"]) + struct.pack("<h", f["time_us"])
    if name == "IMU_SAMPLE":
        mag = [f["mx"], f["my"], f["mz"]] if "mx" in f else None
        return struct.pack("<H", f["counter"]) + record((f["x"], f["y"], f["z"]), f["status"], f["time_us"],
                                                       (f["gx"], f["gy"], f["gz"]), mag)
    if name == "SNAPSHOT_IMU":
        mags = f.get("mag", [None] * len(f["counts"]))
        return struct.pack("<HHBB", f["counter"], f["first_link"], len(f["counts"]), 2 if "mag" in f else 1) + b"".join(
            record(*r) for r in zip(f["counts"], f["status"], f["time_us"], f["gyro"], mags))
    raise AssertionError(name)


def reference_wire(vec) -> bytes:
    code, _prio = spec_types()[vec["type"]]
    pack = reference_v12 if vec["type"] in V12 else reference_payload
    frame = bytes([1, code]) + vec["node"].to_bytes(2, "little") + pack(vec["type"], vec["fields"])
    return cobs.encode(frame + binascii.crc_hqx(frame, 0xFFFF).to_bytes(2, "big")) + b"\x00"


from cobs import cobs  # noqa: E402


def test_the_spec_tables_cover_every_message_type():
    assert set(spec_types()) == {t.name for t in MsgType}
    # v1.2's IMU types are laid out in §16 (the record table, the classic-CAN frame table), packed
    # by `reference_v12` below from those tables' words
    assert set(spec_layouts()) | V12 == {t.name for t in MsgType}
    for name in V12:
        assert re.search(rf"\b{name} \(0x", SPEC.partition("\n## 16. ")[2]), name
    assert spec_layouts()["CAL_WRITE"] == spec_layouts()["CAL_DATA"]
    assert spec_layouts()["CAL_IMU_WRITE"] == spec_layouts()["CAL_IMU_DATA"]
    assert [f for _, f in spec_layouts()["CAL_IMU_DATA"]] == ["block", "index", "flags", "reserved", "value"]
    assert spec_layouts()["START"] == []


@pytest.mark.parametrize("vec", SERIAL, ids=lambda v: v["name"])
def test_serial_vector_rederived_from_the_spec(vec):
    assert reference_wire(vec).hex() == vec["hex"]


def test_the_reference_sees_a_wrong_vector():
    vec = dict(next(v for v in SERIAL if v["type"] == "CONFIG"))
    vec["fields"] = dict(vec["fields"], heartbeat_ms=vec["fields"]["heartbeat_ms"] + 1)
    assert reference_wire(vec).hex() != next(v for v in SERIAL if v["type"] == "CONFIG")["hex"]


@pytest.mark.parametrize("vec", CAN, ids=lambda v: v["name"])
def test_can_vector_rederived_by_cantools_and_the_spec(vec):
    code, prio = spec_types()[vec["type"]]
    assert int(vec["id"], 16) == prio << 26 | code << 20 | 1 << 16 | vec["node"]  # §7.1
    db = cantools.database.load_file(str(DBC_PATH))
    entry = db.get_message_by_frame_id(int(vec["id"], 16) & 0x1FFF0000)
    f = dict(vec["fields"])
    if vec["type"] == "SNAPSHOT":
        counts, status = f.pop("counts"), f.pop("status")
        f["count"] = len(counts)
        for k, ((x, y, z), s) in enumerate(zip(counts, status)):
            f.update({f"x_{k}": x, f"y_{k}": y, f"z_{k}": z, f"status_{k}": s})
        for k in range(len(counts), 11):
            f.update({f"x_{k}": 0, f"y_{k}": 0, f"z_{k}": 0, f"status_{k}": 0})
    if vec["type"] == "IMU_SAMPLE" and "mx" not in f:  # a 6-axis record: the 9-axis entry's mag is the padding
        f.update(mx=0, my=0, mz=0)
    if vec["type"] == "SNAPSHOT_IMU":
        fmt = 2 if "mag" in f else 1
        counts, status, time_us, gyro, mag = (f.pop(k, None) for k in ("counts", "status", "time_us", "gyro", "mag"))
        f.update(count=len(counts), format=fmt)
        n_max = 4 if fmt == 1 else 3
        for k in range(n_max):
            c, s, t, g = (counts[k], status[k], time_us[k], gyro[k]) if k < len(counts) else ([0] * 3, 0, 0, [0] * 3)
            f.update({f"x_{fmt}_{k}": c[0], f"y_{fmt}_{k}": c[1], f"z_{fmt}_{k}": c[2], f"status_{fmt}_{k}": s,
                      f"time_us_{fmt}_{k}": t, f"gx_{fmt}_{k}": g[0], f"gy_{fmt}_{k}": g[1], f"gz_{fmt}_{k}": g[2]})
            if fmt == 2:
                m = mag[k] if k < len(counts) else [0] * 3
                f.update({f"mx_2_{k}": m[0], f"my_2_{k}": m[1], f"mz_2_{k}": m[2]})
    data = entry.encode(f, scaling=False, padding=False, strict=False) if f or entry.signals else b""
    want = bytes.fromhex(vec["data"])
    assert data[:len(want)] == want and not any(data[len(want):])
