"""The CAN database (DBC) of protocol v1, generated from the message definitions (docs §7.3).

Every capsheet message has one DBC entry whose frame id is the message's identifier for node 0.
The node id sits in the low 16 bits of every identifier, so a tool looks a frame up with
``arbitration_id & DBC_ID_MASK`` — the same trick J1939 databases use for the source address.

``protocol/capsheet.dbc`` is this module's output, checked in for tools that want a file; a test
keeps the two identical (`capsheet protocol dbc --write` regenerates it).
"""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

from .can import CAN_CLASSIC_MTU, CAN_FD_MTU, MAX_FD_IMU_RECORDS, MAX_FD_SNAPSHOT_SAMPLES, make_id
from .messages import (IMU_RECORD_SIZE, MESSAGE_TYPES, Direction, ImuAccel, ImuSample, MsgType, Sample, SampleFormat,
                       Snapshot, SnapshotImu)

__all__ = ["DBC_PATH", "DBC_ID_MASK", "build_database", "dbc_text", "dbc_frame_id", "load_database", "write_dbc"]

DBC_PATH = Path(__file__).with_name("capsheet.dbc")
DBC_ID_MASK = 0x1FFF0000  #: keep priority, type and version; drop the node

_FORMAT_BITS = {"B": (8, False, False), "H": (16, False, False), "I": (32, False, False),
                "Q": (64, False, False), "h": (16, True, False), "f": (32, True, True)}


def dbc_frame_id(arbitration_id: int) -> int:
    """The DBC frame id to look up for a received identifier."""
    return arbitration_id & DBC_ID_MASK


def _sample_signals(prefix: str, start: int):
    from cantools.database import Signal
    out = []
    for name, off, length, signed in (("x", 0, 12, True), ("y", 12, 12, True), ("z", 24, 12, True),
                                      ("status", 36, 4, False)):
        out.append(Signal(f"{name}{prefix}", start + off, length, byte_order="little_endian",
                          is_signed=signed, unit="counts" if name != "status" else None))
    return out


def _i16(name: str, start: int, unit: str = "counts", **kw):
    from cantools.database import Signal
    return Signal(name, start, 16, byte_order="little_endian", is_signed=True, unit=unit, **kw)


def _record_signals(suffix: str, start: int, fmt: int, **kw):
    """One IMU record (docs §16.1) at bit ``start``: the accel word, time_us, gyro, and mag for format 2."""
    sigs = _sample_signals(suffix, start)
    for sig in sigs:
        for k, v in kw.items():
            setattr(sig, k, v)
    sigs.append(_i16(f"time_us{suffix}", start + 40, "us", **kw))
    sigs += [_i16(f"g{a}{suffix}", start + 56 + 16 * i, **kw) for i, a in enumerate("xyz")]
    if fmt == SampleFormat.IMU9:
        sigs += [_i16(f"m{a}{suffix}", start + 104 + 16 * i, **kw) for i, a in enumerate("xyz")]
    return sigs


def _signals(cls):
    from cantools.database import Signal
    from cantools.database.conversion import BaseConversion
    if cls is ImuAccel:
        return ([Signal("counter_lo", 0, 8, byte_order="little_endian")] + _sample_signals("", 8)
                + [_i16("time_us", 48, "us")])
    if cls is ImuSample:  # the 9-axis layout; a 6-axis frame (16 bytes) ends after gz
        return [Signal("counter", 0, 16, byte_order="little_endian")] + _record_signals("", 16, SampleFormat.IMU9)
    if cls is SnapshotImu:  # the records' layout follows the format byte: a multiplexed message
        sigs = [Signal("counter", 0, 16, byte_order="little_endian"),
                Signal("first_link", 16, 16, byte_order="little_endian"),
                Signal("count", 32, 8, byte_order="little_endian"),
                Signal("format", 40, 8, byte_order="little_endian", is_multiplexer=True)]
        for fmt in (SampleFormat.IMU6, SampleFormat.IMU9):
            size = IMU_RECORD_SIZE[fmt] * 8
            for k in range(MAX_FD_IMU_RECORDS[fmt]):
                sigs += _record_signals(f"_{int(fmt)}_{k}", 48 + size * k, fmt, multiplexer_ids=[int(fmt)],
                                        multiplexer_signal="format")
        return sigs
    if cls is Sample:
        return [Signal("counter", 0, 16, byte_order="little_endian")] + _sample_signals("", 16)
    if cls is Snapshot:
        sigs = [Signal("counter", 0, 16, byte_order="little_endian"),
                Signal("first_link", 16, 16, byte_order="little_endian"),
                Signal("count", 32, 8, byte_order="little_endian")]
        for k in range(MAX_FD_SNAPSHOT_SAMPLES):
            sigs += _sample_signals(f"_{k}", 40 + 40 * k)
        return sigs
    sigs, bit = [], 0
    for f, ch in zip(fields(cls)[1:], cls.payload_struct().format.lstrip("<")):
        length, signed, is_float = _FORMAT_BITS[ch]
        sigs.append(Signal(f.name, bit, length, byte_order="little_endian", is_signed=signed,
                           conversion=BaseConversion.factory(is_float=is_float)))
        bit += length
    return sigs


def build_database():
    """A ``cantools.database.can.Database`` with one message per MsgType."""
    from cantools.database import Database, Message, Node
    from cantools.database.can.formats.dbc import DbcSpecifics
    from cantools.database.can.formats.dbc.dbc_attribute import DbcAttribute as Attribute
    from cantools.database.can.formats.dbc.dbc_attribute_definition import DbcAttributeDefinition as AttributeDefinition
    messages = []
    for code in MsgType:
        cls = MESSAGE_TYPES[code]
        sender = "HOST" if cls.DIRECTION == Direction.HOST_TO_CHIP else (
            "GATEWAY" if cls in (Snapshot, SnapshotImu) else "CHIP")
        fd = cls in (Snapshot, SnapshotImu, ImuSample)
        layout = cls.payload_struct()
        size = (24 if cls is ImuSample else CAN_FD_MTU) if fd else (
            layout.size if layout is not None else cls.SIZE)
        assert size <= (CAN_FD_MTU if fd else CAN_CLASSIC_MTU)
        messages.append(Message(frame_id=make_id(code, 0), name=code.name, length=size,
                                signals=_signals(cls), is_extended_frame=True, is_fd=fd,
                                senders=[sender], comment=(cls.__doc__ or "").strip().splitlines()[0]))
    # BusType "CAN FD" makes cantools write VFrameFormat, so tools see SNAPSHOT as an FD frame.
    bus_type = AttributeDefinition("BusType", default_value="CAN", kind=None, type_name="STRING")
    specifics = DbcSpecifics(attributes={"BusType": Attribute("CAN FD", bus_type)},
                             attribute_definitions={"BusType": bus_type})
    return Database(messages=messages, nodes=[Node("HOST"), Node("CHIP"), Node("GATEWAY")], version="1",
                    dbc_specifics=specifics, frame_id_mask=DBC_ID_MASK)


def dbc_text() -> str:
    """The DBC file's text (cantools writes CRLF line ends; keep them)."""
    return build_database().as_dbc_string()


def load_database():
    """The checked-in DBC loaded with cantools, node bits masked: look frames up by their raw id."""
    import cantools
    return cantools.database.load_file(str(DBC_PATH), frame_id_mask=DBC_ID_MASK)


def write_dbc(path: Path = DBC_PATH) -> Path:
    path.write_bytes(dbc_text().encode())
    return path
