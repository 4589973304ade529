"""Message set of the capsheet wire protocol (docs/protocol.md §4, §16, §17; the revision is `SPEC_VERSION`).

Every message is a frozen, slotted dataclass that validates itself when built. The *payload* layout
of a message is the same on every transport; serial wraps it in a header + CRC + COBS
(`protocol.framing`), CAN carries it as the frame data with type and node in the identifier
(`protocol.can`). All multi-byte fields are little-endian.

``node`` is the chip a frame comes from (chip -> host) or is addressed to (host -> chip);
``node == 0`` from the host means every chip (broadcast). See docs/protocol.md §3.
"""

from __future__ import annotations

from .base import (PROTOCOL_VERSION, SPEC_VERSION, MsgType, Direction, ChipState, Capability, StatusFlag,
    NackReason, GatewayFlag, SampleFormat, RESERVED_CAPABILITIES, NODE_TO_HOST_TYPES, HOST_TO_NODE_TYPES,
    LINK_NONE, is_node_to_host_type, NODE_BROADCAST, NODE_MAX_ASSIGNED, NODE_PROVISIONAL_MIN,
    NODE_PROVISIONAL_MAX, SAMPLE_WORD_SIZE, MAX_SNAPSHOT_SAMPLES, Message, pack_sample_words,
    unpack_sample_words, unpack_snapshots, PayloadError, provisional_node, TIME_UNKNOWN, IMU_RECORD_SIZE,
    MAX_SERIAL_IMU_RECORDS, ConfigImuFlag, codes_of, MSG_TYPE_CODES, CHIP_STATE_CODES, SAMPLE_FORMAT_CODES,
    NACK_REASON_CODES)
from .chip_to_host import (Announce, Info, Sample, SampleBatch, ImuBatch, Status, StatusBatch, STATUS_STATES,
    Ack, Nack, CalData, Snapshot, SnapshotFrames, GatewayInfo)
from .imu import (ImuGyro, ImuMag, ImuAccel, ImuSample, SnapshotImu, imu_sample_to_can_parts,
    pack_imu_records, unpack_imu_records, unpack_snapshots_imu, imu_saturated)
from .host_to_chip import (Sync, Assign, Config, Start, Stop, GetInfo, Reset, CalWrite, CalRead, ConfigImu)
from .cal_imu import (CalBlock, CAL_BLOCK_SIZE, CalImuData, CalImuWrite, CalImuRead, cal_block_nominal)
from .registry import (MESSAGE_TYPES, message_to_fields, message_from_fields, decode_payload, IMU_TYPES)

__all__ = [
    "PROTOCOL_VERSION", "SPEC_VERSION", "MsgType", "Direction", "ChipState", "Capability", "StatusFlag",
    "NackReason", "GatewayFlag", "SampleFormat", "RESERVED_CAPABILITIES", "NODE_TO_HOST_TYPES", "HOST_TO_NODE_TYPES",
    "LINK_NONE", "is_node_to_host_type",
    "NODE_BROADCAST", "NODE_MAX_ASSIGNED", "NODE_PROVISIONAL_MIN", "NODE_PROVISIONAL_MAX",
    "SAMPLE_WORD_SIZE", "MAX_SNAPSHOT_SAMPLES",
    "Message", "Announce", "Info", "Sample", "SampleBatch", "ImuBatch", "Status", "StatusBatch", "STATUS_STATES", "Ack", "Nack", "CalData", "Snapshot", "SnapshotFrames",
    "GatewayInfo", "Sync", "Assign", "Config", "Start", "Stop", "GetInfo", "Reset", "CalWrite", "CalRead",
    "MESSAGE_TYPES", "message_to_fields", "message_from_fields", "pack_sample_words", "unpack_sample_words", "unpack_snapshots", "PayloadError", "decode_payload",
    "provisional_node",
    "ImuGyro", "ImuMag", "ImuAccel", "ImuSample", "SnapshotImu", "ConfigImu", "TIME_UNKNOWN", "IMU_RECORD_SIZE",
    "MAX_SERIAL_IMU_RECORDS", "ConfigImuFlag", "IMU_TYPES", "imu_sample_to_can_parts", "pack_imu_records", "unpack_imu_records", "unpack_snapshots_imu", "imu_saturated",
    "CalBlock", "CAL_BLOCK_SIZE", "CalImuData", "CalImuWrite", "CalImuRead", "cal_block_nominal",
    "codes_of", "MSG_TYPE_CODES", "CHIP_STATE_CODES", "SAMPLE_FORMAT_CODES", "NACK_REASON_CODES",
]
