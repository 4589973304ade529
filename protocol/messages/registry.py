"""Type code -> message class, the payload decoder, and the fields the vector files write (docs §4, §9)."""

from __future__ import annotations

from dataclasses import fields

import numpy as np

from .base import Message, MsgType, PayloadError, SPEC_VERSION
from .chip_to_host import Ack, Announce, CalData, GatewayInfo, Info, Nack, Sample, Snapshot, Status
from .imu import ImuAccel, ImuGyro, ImuMag, ImuSample, SnapshotImu
from .host_to_chip import Assign, CalRead, CalWrite, Config, ConfigImu, GetInfo, Reset, Start, Stop, Sync
from .cal_imu import CalImuData, CalImuRead, CalImuWrite


#: type code -> message class
MESSAGE_TYPES: dict[int, type[Message]] = {
    cls.TYPE: cls for cls in (Announce, Info, Sample, Status, Ack, Nack, CalData, Snapshot, GatewayInfo,
                              ImuGyro, ImuMag, ImuAccel, ImuSample, SnapshotImu,
                              Sync, Assign, Config, Start, Stop, GetInfo, Reset, CalWrite, CalRead, ConfigImu,
                              CalImuData, CalImuWrite, CalImuRead)
}
assert set(MESSAGE_TYPES) == set(MsgType)
#: the types 1.2 added (docs §16): 6/9-axis chips
IMU_TYPES = frozenset({MsgType.IMU_GYRO, MsgType.IMU_MAG, MsgType.IMU_ACCEL, MsgType.IMU_SAMPLE,
                       MsgType.SNAPSHOT_IMU, MsgType.CONFIG_IMU})


def decode_payload(type_code: int, node: int, payload: bytes) -> Message:
    """Payload -> message. Raises `PayloadError` with reason UNKNOWN_TYPE, BAD_LENGTH or BAD_FIELD."""
    cls = MESSAGE_TYPES.get(type_code)
    if cls is None:
        raise PayloadError("UNKNOWN_TYPE", f"type 0x{type_code:02X} is not defined in protocol "
                                           f"v{SPEC_VERSION[0]}.{SPEC_VERSION[1]}")
    if node == 0xFFFF:
        raise PayloadError("BAD_FIELD", "node 0xFFFF is reserved")
    return cls.from_payload(node, payload)


def message_to_fields(msg: Message) -> dict:
    """A message's fields as the vector files write them (JSON numbers; a SNAPSHOT's arrays as lists)."""
    if isinstance(msg, Snapshot):
        return {"counter": msg.counter, "first_link": msg.first_link,
                "counts": msg.counts.tolist(), "status": msg.status.tolist()}
    if isinstance(msg, SnapshotImu):
        counts, status, time_us, gyro, mag = msg.arrays()
        out = {"counter": msg.counter, "first_link": msg.first_link, "counts": counts.tolist(),
               "status": status.tolist(), "time_us": time_us.tolist(), "gyro": gyro.tolist()}
        if mag is not None:
            out["mag"] = mag.tolist()
        return out
    return {f.name: (None if v is None else float(v) if isinstance(v, float) else int(v))
            for f in fields(msg)[1:] for v in [getattr(msg, f.name)]
            if not (v is None and isinstance(msg, ImuSample))}


def message_from_fields(type_name: str, node: int, values: dict) -> Message:
    """The message `message_to_fields` wrote (type by name, node, fields)."""
    cls = MESSAGE_TYPES[MsgType[type_name]]
    if cls is Snapshot:
        return Snapshot.from_arrays(node, values["counter"], values["first_link"],
                                    np.array(values["counts"]), np.array(values["status"]))
    if cls is SnapshotImu:
        mag = values.get("mag")
        return SnapshotImu.from_arrays(node, values["counter"], values["first_link"], np.array(values["counts"]),
                                       np.array(values["status"]), np.array(values["time_us"]),
                                       np.array(values["gyro"]), None if mag is None else np.array(mag))
    return cls(node, **values)
