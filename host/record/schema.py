"""capsheet's own recording channels as protobuf (format ``capsheet-mcap-2``, docs/recording.md).

The schemas are built here as a ``FileDescriptorProto`` (no ``protoc`` step, no generated code to
keep in sync); each channel's MCAP schema record is the serialized ``FileDescriptorSet`` with
encoding ``protobuf``, what Foxglove, ``mcap-protobuf-support`` and every MCAP protobuf reader
decode without capsheet. proto2 syntax, for field presence (``error_pct_side`` may be absent) and
``packed`` repeated numbers.

Why protobuf (and not JSON, as ``capsheet-mcap-1`` was): a 14x14 snapshot was ~7 KB of JSON with
base64 arrays of float32; here it is its chips' ADC counts (sint32 zigzag varints, 2 bytes each at
a few g), a bitmap of valid links and the status bytes: ~1.5 KB. Foxglove plots every number field
(``/capsheet/estimate.residual``, ``/capsheet/snapshot.latency_s``); the counts of a recording made
with ``Recorder(compact=True)`` (the default) are byte planes of residuals (``counts_planes``,
`host.record.compact`), which only capsheet's reader turns back into counts.
"""

from __future__ import annotations

from functools import lru_cache

__all__ = ["PACKAGE", "NAMES", "message_class", "file_descriptor_set", "CAN_EXT", "CAN_FD", "CAN_ERR",
           "CAN_RTR", "CAN_BRS"]

PACKAGE = "capsheet.v2"
#: flags bits of a ``capsheet.v2.CanFrame``
CAN_EXT, CAN_FD, CAN_ERR, CAN_RTR, CAN_BRS = 1, 2, 4, 8, 16

# (name, [(field, number, type, label, type_name or None, packed)])
_D, _U32, _S32, _F, _B, _BOOL, _STR, _MSG = "double", "uint32", "sint32", "float", "bytes", "bool", "string", "msg"
_OPT, _REP = "optional", "repeated"

_MESSAGES = [
    ("RawSerial", [("bus", 1, _U32, _OPT), ("t", 2, _D, _OPT), ("t_rx", 3, _D, _OPT), ("data", 4, _B, _OPT)]),
    # the same chunks with their valid SAMPLE frames as columns (`host.record.compact`)
    ("RawSerialFrames", [("bus", 1, _U32, _OPT), ("t", 2, _D, _OPT), ("t_rx", 3, _D, _OPT), ("raw", 4, _B, _OPT),
                         ("gap", 5, _B, _OPT), ("node", 6, _B, _OPT), ("counter", 7, _B, _OPT),
                         ("counts", 8, _B, _OPT), ("status", 9, _B, _OPT)]),
    ("CanFrame", [("id", 1, _U32, _OPT), ("flags", 2, _U32, _OPT), ("ts", 3, _D, _OPT), ("data", 4, _B, _OPT)]),
    ("RawCan", [("bus", 1, _U32, _OPT), ("t", 2, _D, _OPT), ("t_rx", 3, _D, _OPT),
                ("frames", 4, _MSG, _REP, "CanFrame")]),
    ("Sync", [("counter", 1, _U32, _OPT), ("t", 2, _D, _OPT)]),
    ("Snapshot", [("counter", 1, _U32, _OPT), ("timestamp", 2, _D, _OPT), ("wall_time", 3, _D, _OPT),
                  ("latency_s", 4, _D, _OPT), ("complete", 5, _BOOL, _OPT), ("n_links", 6, _U32, _OPT),
                  ("counts", 7, _S32, _REP), ("readings", 8, _F, _REP), ("valid", 9, _B, _OPT),
                  ("status", 10, _B, _OPT),
                  # 6/9-axis chips (docs/protocol.md §16): rad/s, T, s after the SYNC (NaN unknown)
                  ("gyro", 11, _F, _REP), ("mag", 12, _F, _REP), ("sample_time_s", 13, _F, _REP),
                  # counts against each link's running average (`host.record.compact.CountsCoder`)
                  ("counts_planes", 14, _B, _OPT)]),
    ("Estimate", [("counter", 1, _U32, _OPT), ("timestamp", 2, _D, _OPT), ("method", 3, _STR, _OPT),
                  ("residual", 4, _D, _OPT), ("iterations", 5, _U32, _OPT), ("joints", 6, _F, _REP),
                  ("yaw_std", 7, _F, _REP), ("joint_std", 8, _F, _REP), ("joint_std_shape", 9, _U32, _REP),
                  ("error_pct_side", 10, _D, _OPT)]),
]
NAMES = tuple(f"{PACKAGE}.{m[0]}" for m in _MESSAGES if m[0] != "CanFrame")


@lru_cache(maxsize=1)
def _file():
    from google.protobuf import descriptor_pb2 as pb

    types = {_D: pb.FieldDescriptorProto.TYPE_DOUBLE, _U32: pb.FieldDescriptorProto.TYPE_UINT32,
             _S32: pb.FieldDescriptorProto.TYPE_SINT32, _F: pb.FieldDescriptorProto.TYPE_FLOAT,
             _B: pb.FieldDescriptorProto.TYPE_BYTES, _BOOL: pb.FieldDescriptorProto.TYPE_BOOL,
             _STR: pb.FieldDescriptorProto.TYPE_STRING, _MSG: pb.FieldDescriptorProto.TYPE_MESSAGE}
    labels = {_OPT: pb.FieldDescriptorProto.LABEL_OPTIONAL, _REP: pb.FieldDescriptorProto.LABEL_REPEATED}
    fdp = pb.FileDescriptorProto(name="capsheet/v2.proto", package=PACKAGE, syntax="proto2")
    for name, fields in _MESSAGES:
        m = fdp.message_type.add(name=name)
        for spec in fields:
            fname, num, typ, label = spec[:4]
            f = m.field.add(name=fname, number=num, type=types[typ], label=labels[label])
            if typ == _MSG:
                f.type_name = f".{PACKAGE}.{spec[4]}"
            elif label == _REP:
                f.options.packed = True
    return fdp


@lru_cache(maxsize=1)
def _pool():
    from google.protobuf import descriptor_pool

    pool = descriptor_pool.DescriptorPool()
    pool.Add(_file())
    return pool


@lru_cache(maxsize=None)
def message_class(name: str):
    """The message class of ``capsheet.v2.<Name>`` (or a bare ``Name``)."""
    from google.protobuf import message_factory

    full = name if "." in name else f"{PACKAGE}.{name}"
    return message_factory.GetMessageClass(_pool().FindMessageTypeByName(full))


@lru_cache(maxsize=1)
def file_descriptor_set() -> bytes:
    """The serialized ``FileDescriptorSet`` every capsheet protobuf channel's schema record holds."""
    from google.protobuf import descriptor_pb2 as pb

    return pb.FileDescriptorSet(file=[_file()]).SerializeToString()
