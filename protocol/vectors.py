"""Golden test vectors (tests/vectors/*.json): canonical messages and their exact wire bytes on
serial and CAN (serial.json, can.json), damaged serial input (serial_errors.json), edge frames and
the receiver's verdict for each (verdicts.json), and chip scenarios (chip.json). The C firmware and
any chip are held to them (docs §9).

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
from pathlib import Path

import numpy as np

from .can import to_can
from .constants import SampleStatus
from .framing import encode, encode_frame
from .messages import (LINK_NONE, PROTOCOL_VERSION, SPEC_VERSION, Ack, Announce, Assign, CalData, CalRead,
                       CalWrite, Capability, ChipState, Config, GatewayFlag, GatewayInfo, GetInfo, Info, Message,
                       MsgType, Nack, NackReason, Reset, Sample, SampleFormat, Snapshot, Start, Status,
                       StatusFlag, Stop, Sync, message_from_fields, message_to_fields,
                       TIME_UNKNOWN, ConfigImu, ImuAccel, ImuGyro, ImuMag, ImuSample, SnapshotImu,
                       CalBlock, CalImuData, CalImuRead, CalImuWrite)

__all__ = ["canonical_messages", "message_to_fields", "message_from_fields", "build_vectors",
           "error_vectors", "verdict_vectors", "chip_scenarios", "VECTOR_DIR", "write_vectors"]

VECTOR_DIR = Path(__file__).resolve().parent.parent / "tests" / "vectors"


def canonical_messages() -> list[tuple[str, Message]]:
    """At least one vector per type, with edge values (extremes, zeros in the payload for COBS)."""
    snap_counts = np.array([[0, 0, 1024], [-2048, 2047, -1], [1, -1, 0], [100, -200, 300]])
    snap_status = np.array([0, SampleStatus.SATURATED, SampleStatus.INVALID, 0xF])
    return [
        ("announce", Announce(0x9112, uid=0x0123456789ABCDEF)),  # provisional_node(uid, 0), §3.2
        ("announce_assigned", Announce(42, uid=0xFFFFFFFFFFFFFFFF)),
        ("info", Info(42, 1, 2, 3, PROTOCOL_VERSION, Capability.CAN_FD | Capability.SELF_TEST, 12, ChipState.IDLE)),
        ("sample_flat", Sample(1, counter=0, x=0, y=0, z=1024, status=0)),
        ("sample_extremes", Sample(0x7FFF, counter=0xFFFF, x=-2048, y=2047, z=-1, status=SampleStatus.SATURATED)),
        ("sample_all_status", Sample(300, counter=0x1234, x=-5, y=17, z=1000, status=0xF)),
        ("status", Status(42, ChipState.STREAMING, StatusFlag.CAL_VALID | StatusFlag.CONFIGURED, 3, 255, 86400)),
        ("ack_start", Ack(42, MsgType.START, 0)),
        ("nack_bad_state", Nack(42, MsgType.START, NackReason.BAD_STATE)),
        ("cal_data", CalData(42, axis=2, flags=1, offset_q4=-37, sensitivity=1019.25)),
        ("snapshot", Snapshot.from_arrays(0x7FFF, 0xABCD, 360, snap_counts, snap_status)),
        ("gateway_info", GatewayInfo(0x7FFF, GatewayFlag.PACKING | GatewayFlag.SYNC_SOURCE, SampleFormat.ACCEL_12,
                                     0, 364, 145)),
        ("sync", Sync(counter=0)),
        ("sync_wrap", Sync(counter=0xFFFF)),
        ("assign", Assign(0x9112, new_node=1, link=0, uid_low=0x89ABCDEF)),
        ("assign_gateway", Assign(0x9112, new_node=0x7FFF, link=LINK_NONE, uid_low=0x89ABCDEF)),
        ("config", Config(0, rate_hz=145, range=0, filter=1, heartbeat_ms=1000)),
        ("start_broadcast", Start(0)),
        ("stop_one", Stop(7)),
        ("get_info_broadcast", GetInfo(0)),
        ("reset", Reset(7)),
        ("cal_write", CalWrite(7, axis=0, flags=1, offset_q4=16, sensitivity=1024.0)),
        ("cal_read", CalRead(7, axis=1)),
        # new in 1.2 (docs §16): the worked example of §16.1 (node 1, counter 0x0102) and edges
        ("imu_sample_6_axis", ImuSample(1, 0x0102, 0, 0, 1024, 0, -1500, 100, -200, 3000)),
        ("imu_sample_9_axis", ImuSample(1, 0x0102, 0, 0, 1024, 0, -1500, 100, -200, 3000, 8192, -4096, 1)),
        ("imu_sample_extremes", ImuSample(0x7FFF, 0xFFFF, -2048, 2047, -1, SampleStatus.SATURATED, 32767,
                                          -32768, 32767, 0, -32768, 32767, 0)),
        ("imu_sample_invalid", ImuSample(3, 9, 0, 0, 0, SampleStatus.INVALID, TIME_UNKNOWN, 0, 0, 0)),
        ("imu_gyro", ImuGyro(1, 0x0102, 100, -200, 3000)),
        ("imu_mag", ImuMag(1, 0x0102, 8192, -4096, 1)),
        ("imu_accel", ImuAccel(1, 0x02, 0, 0, 1024, 0, -1500)),
        ("snapshot_imu_6_axis", SnapshotImu.from_arrays(0x7FFF, 0xABCD, 360, [[0, 0, 1024], [-2048, 2047, -1]],
                                                        [0, SampleStatus.SATURATED], [-1500, TIME_UNKNOWN],
                                                        [[100, -200, 3000], [-32768, 32767, 1]])),
        ("snapshot_imu_9_axis", SnapshotImu.from_arrays(0x7FFF, 5, 0, [[0, 0, 1024], [1, -1, 0], [0, 0, 0]],
                                                        [0, 0, SampleStatus.INVALID], [120, -7000, TIME_UNKNOWN],
                                                        [[1, 2, 3], [-4, -5, -6], [0, 0, 0]],
                                                        [[8192, -4096, 1], [0, 0, -8192], [0, 0, 0]])),
        ("config_imu", ConfigImu(1, format=SampleFormat.IMU9, gyro_range=3, mag_range=1, flags=0)),
        ("config_imu_fd_broadcast", ConfigImu(0, format=SampleFormat.IMU6, gyro_range=4, mag_range=0, flags=1)),
        # new in 1.3 (docs §17): the worked examples of §17.1 and edges
        ("cal_imu_write_gyro_matrix", CalImuWrite(1, CalBlock.GYRO_MATRIX, 1, 1, 0, -0.00390625)),
        ("cal_imu_write_mag_hard_iron", CalImuWrite(1, CalBlock.MAG_HARD_IRON, 2, 0, 0, 2.5e-05)),
        ("cal_imu_read", CalImuRead(1, CalBlock.GYRO_G_SENS, 8)),
        ("cal_imu_data_gyro_bias", CalImuData(42, CalBlock.GYRO_BIAS, 0, 1, 0, 0.0125)),
        ("cal_imu_data_nominal_identity", CalImuData(42, CalBlock.MAG_MATRIX, 4, 0, 0, 1.0)),
    ]


def _scenario_format() -> str:
    from .scenarios import FORMAT
    return FORMAT


def chip_scenarios() -> list[dict]:
    """The chip scenarios of protocol/scenarios.py (tests/vectors/chip.json)."""
    from .scenarios import scenarios
    return scenarios()


#: the revision of docs/protocol.md the vectors hold an implementation to
_SPEC = f"{SPEC_VERSION[0]}.{SPEC_VERSION[1]}"


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
        "verdicts.json": {"protocol_version": PROTOCOL_VERSION, "spec_version": _SPEC,
                          "about": "edge frames and the verdict of docs/protocol.md §8.1 for each: 'decoded' "
                                   "(type, node, fields) or the reason a receiver reports",
                          "vectors": verdict_vectors()},
        "chip.json": {"protocol_version": PROTOCOL_VERSION, "spec_version": _SPEC,
                      "about": _scenario_format().splitlines(), "scenarios": chip_scenarios()},
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
        # 1029 bytes (not over the run limit) whose last code byte promises 4 bytes that never come: not
        # COBS, although its first 1028 codes alone would decode to more than 1024 bytes — BAD_COBS, not
        # OVERSIZE: the decoded size is only known of valid COBS (§6.3, §8.1 rows 1-2; 1.4's G01)
        {"name": "bad_cobs_of_1029_bytes", "hex": "01" * 1028 + "05" + "00", "reason": "bad_cobs"},
        # a valid run of 1029 bytes that decodes to 1028: OVERSIZE after COBS
        {"name": "oversize_after_cobs", "hex": "01" * 1028 + "01" + "00", "reason": "oversize"},
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


# --------------------------------------------------------------------------------------------
# Receiver verdicts (tests/vectors/verdicts.json): edge frames and what every receiver reports
# --------------------------------------------------------------------------------------------

def _ser(name: str, verdict: str, clause: str, type_code: int, node: int, payload: bytes, *,
         version: int = PROTOCOL_VERSION, msg: Message | None = None) -> dict:
    """A serial edge frame built from its parts (the CRC is right unless the vector says otherwise)."""
    from .crc import crc16_ccitt_false
    from cobs import cobs
    body = bytes([version, type_code]) + node.to_bytes(2, "little") + payload
    body += crc16_ccitt_false(body).to_bytes(2, "big")
    out = {"name": name, "transport": "serial", "hex": (cobs.encode(body) + b"\x00").hex(),
           "frame_size": len(body), "verdict": verdict, "clause": clause}
    if msg is not None:
        out.update(type=msg.TYPE.name, node=msg.node, fields=message_to_fields(msg))
    return out


def _can(name: str, verdict: str, clause: str, can_id: int, data: bytes, *, fd: bool = False,
         extended: bool = True, msg: Message | None = None) -> dict:
    out = {"name": name, "transport": "can", "id": f"{can_id:08X}", "extended": extended, "fd": fd,
           "data": data.hex(), "verdict": verdict, "clause": clause}
    if msg is not None:
        out.update(type=msg.TYPE.name, node=msg.node, fields=message_to_fields(msg))
    return out


def verdict_vectors() -> list[dict]:
    """Edge frames on both transports and the verdict of docs §8.1 for each: ``"decoded"`` (with the
    message's fields) or the ErrorReason a receiver reports. Written out by hand, not derived from
    the decoder, which the tests hold to them (and so the C codec, and any implementation)."""
    import struct
    from .can import make_id
    flat = bytes.fromhex("0000000004")  # the sample word (0, 0, 1024), status 0
    w202 = flat * 202
    f32 = struct.Struct("<f")

    def cal(axis, sens):
        return bytes([axis, 0]) + (0).to_bytes(2, "little") + f32.pack(sens)
    v: list[dict] = [
        # --- limits: 1024 bytes before COBS (§6.3); the serial SNAPSHOT cap follows from it (§4.8)
        _ser("snapshot_202_samples_is_1021_bytes", "decoded", "6.3, 4.8", MsgType.SNAPSHOT, 0x7FFF,
             struct.pack("<HHB", 7, 0, 202) + w202,
             msg=Snapshot.from_arrays(0x7FFF, 7, 0, np.tile([0, 0, 1024], (202, 1)), np.zeros(202, int))),
        _ser("snapshot_203_samples_is_1026_bytes", "oversize", "6.3, 4.8", MsgType.SNAPSHOT, 0x7FFF,
             struct.pack("<HHB", 7, 0, 203) + flat * 203),
        _ser("frame_of_1025_bytes", "oversize", "6.3", MsgType.CONFIG, 5, bytes(1019)),
        _ser("frame_of_1024_bytes_wrong_length", "bad_length", "6.3, 8.1", MsgType.CONFIG, 5, bytes(1018)),
        # --- the order of the checks (§8.1)
        _ser("version_2_and_a_wrong_length", "bad_version", "8.1, 12", MsgType.START, 5, b"\x01", version=2),
        _ser("version_0", "bad_version", "8.1, 12", MsgType.START, 5, b"", version=0),
        _ser("undefined_type_0x2f_host_to_node_range", "unknown_type", "4, 8.1", 0x2F, 5, b""),
        _ser("undefined_type_0x00", "unknown_type", "4, 8.1", 0x00, 5, b""),
        _ser("undefined_type_0x1c", "unknown_type", "4, 8.1", 0x1C, 5, b"\x01\x02"),
        _ser("undefined_type_and_node_ffff", "unknown_type", "8.1", 0x3F, 0xFFFF, b""),
        _ser("node_ffff_and_a_wrong_length", "bad_field", "3.1, 8.1", MsgType.START, 0xFFFF, b"\x01"),
        _ser("node_ffff_valid_payload", "bad_field", "3.1, 8.1", MsgType.SAMPLE, 0xFFFF, bytes(7)),
        # --- addressing rules of single messages
        _ser("sync_addressed_to_a_node", "bad_field", "4.9", MsgType.SYNC, 5, b"\x01\x00"),
        _ser("assign_broadcast", "bad_field", "4.10", MsgType.ASSIGN, 0, struct.pack("<HHI", 1, 0, 0x89ABCDEF)),
        _ser("assign_new_node_0", "bad_field", "4.10", MsgType.ASSIGN, 5, struct.pack("<HHI", 0, 0, 1)),
        _ser("assign_new_node_0x8000", "bad_field", "4.10", MsgType.ASSIGN, 5, struct.pack("<HHI", 0x8000, 0, 1)),
        _ser("assign_link_none_for_a_gateway", "decoded", "4.10, 13.1", MsgType.ASSIGN, 0x9112,
             struct.pack("<HHI", 0x7FFF, LINK_NONE, 0x89ABCDEF),
             msg=Assign(0x9112, new_node=0x7FFF, link=LINK_NONE, uid_low=0x89ABCDEF)),
        _ser("cal_read_broadcast", "bad_field", "4.15", MsgType.CAL_READ, 0, b"\x00"),
        _ser("cal_read_axis_3", "bad_field", "4.15", MsgType.CAL_READ, 5, b"\x03"),
        _ser("cal_write_broadcast", "bad_field", "4.15", MsgType.CAL_WRITE, 0, cal(0, 1024.0)),
        _ser("cal_write_axis_3", "bad_field", "4.7, 4.15", MsgType.CAL_WRITE, 5, cal(3, 1024.0)),
        _ser("cal_write_sensitivity_0", "bad_field", "4.7, 4.15", MsgType.CAL_WRITE, 5, cal(0, 0.0)),
        _ser("cal_write_sensitivity_negative", "bad_field", "4.7, 4.15", MsgType.CAL_WRITE, 5, cal(0, -1024.0)),
        _ser("cal_write_sensitivity_infinite", "bad_field", "4.7, 4.15", MsgType.CAL_WRITE, 5,
             cal(0, float("inf"))),
        _ser("cal_write_sensitivity_nan", "bad_field", "4.7, 4.15", MsgType.CAL_WRITE, 5,
             bytes([0, 0, 0, 0]) + bytes.fromhex("0000c07f")),
        _ser("cal_data_negative_zero_sensitivity", "bad_field", "4.7", MsgType.CAL_DATA, 5,
             bytes([0, 0, 0, 0]) + bytes.fromhex("00000080")),
        # new in 1.3 (§17): CAL_IMU's addressing and value
        _ser("cal_imu_read_broadcast", "bad_field", "17.2", MsgType.CAL_IMU_READ, 0, b"\x00\x00"),
        _ser("cal_imu_read_block_5", "bad_field", "17.1, 17.2", MsgType.CAL_IMU_READ, 5, b"\x05\x00"),
        _ser("cal_imu_read_bias_index_3", "bad_field", "17.1, 17.2", MsgType.CAL_IMU_READ, 5, b"\x01\x03"),
        _ser("cal_imu_read_matrix_index_8", "decoded", "17.1, 17.2", MsgType.CAL_IMU_READ, 5, b"\x03\x08",
             msg=CalImuRead(5, 3, 8)),
        _ser("cal_imu_write_broadcast", "bad_field", "17.2", MsgType.CAL_IMU_WRITE, 0,
             struct.pack("<BBBBf", 0, 0, 0, 0, 1.0)),
        _ser("cal_imu_write_matrix_index_9", "bad_field", "17.1", MsgType.CAL_IMU_WRITE, 5,
             struct.pack("<BBBBf", 0, 9, 0, 0, 1.0)),
        _ser("cal_imu_write_reserved_1", "bad_field", "17.1", MsgType.CAL_IMU_WRITE, 5,
             struct.pack("<BBBBf", 0, 0, 0, 1, 1.0)),
        _ser("cal_imu_write_value_nan", "bad_field", "17.1", MsgType.CAL_IMU_WRITE, 5,
             bytes([0, 0, 0, 0]) + bytes.fromhex("0000c07f")),
        _ser("cal_imu_write_value_infinite", "bad_field", "17.1", MsgType.CAL_IMU_WRITE, 5,
             struct.pack("<BBBBf", 4, 0, 0, 0, float("inf"))),
        _ser("cal_imu_write_negative_and_zero_decode", "decoded", "17.1", MsgType.CAL_IMU_WRITE, 5,
             bytes([2, 0, 0, 0]) + bytes.fromhex("00000080"), msg=CalImuWrite(5, 2, 0, 0, 0, -0.0)),
        _ser("cal_imu_write_short", "bad_length", "17.2", MsgType.CAL_IMU_WRITE, 5, bytes(7)),
        _ser("config_values_out_of_range_decode", "decoded", "4.11, 8.3", MsgType.CONFIG, 5,
             struct.pack("<HBBH", 5000, 7, 9, 100), msg=Config(5, rate_hz=5000, range=7, filter=9, heartbeat_ms=100)),
        _ser("snapshot_count_0", "bad_length", "4.8", MsgType.SNAPSHOT, 0x7FFF, struct.pack("<HHB", 1, 0, 0)),
        _ser("snapshot_count_2_one_word", "bad_length", "4.8", MsgType.SNAPSHOT, 0x7FFF,
             struct.pack("<HHB", 1, 0, 2) + flat),
        _ser("snapshot_last_link_65535", "decoded", "4.8", MsgType.SNAPSHOT, 0x7FFF,
             struct.pack("<HHB", 1, 0xFFFE, 2) + flat * 2,
             msg=Snapshot.from_arrays(0x7FFF, 1, 0xFFFE, np.tile([0, 0, 1024], (2, 1)), np.zeros(2, int))),
        _ser("snapshot_past_link_65535", "bad_field", "4.8", MsgType.SNAPSHOT, 0x7FFF,
             struct.pack("<HHB", 1, 0xFFFF, 2) + flat * 2),
        _ser("info_state_4", "bad_field", "4.2", MsgType.INFO, 5, bytes([1, 0, 0, 1, 0, 0, 12, 4])),
        _ser("status_state_4", "bad_field", "4.4", MsgType.STATUS, 5, bytes([4, 0, 0, 0, 0, 0, 0, 0])),
        _ser("nack_reason_0", "bad_field", "4.6", MsgType.NACK, 5, bytes([0x13, 0])),
        _ser("nack_reason_8", "bad_field", "4.6", MsgType.NACK, 5, bytes([0x13, 8])),
        _ser("gateway_info_past_link_65535", "bad_field", "4.16", MsgType.GATEWAY_INFO, 0x7FFF,
             struct.pack("<BBHHH", 1, 0, 0xFFFF, 2, 0)),
        # --- reserved bits and values are ignored on receipt (§2): the frame decodes
        _ser("ack_detail_1", "decoded", "2, 4.5", MsgType.ACK, 5, bytes([0x13, 1]), msg=Ack(5, 0x13, 1)),
        _ser("info_reserved_capability_bits", "decoded", "2, 4.2", MsgType.INFO, 5,
             bytes([1, 0, 0, 1]) + (0x8001).to_bytes(2, "little") + bytes([12, 1]),
             msg=Info(5, 1, 0, 0, 1, 0x8001, 12, ChipState.IDLE)),
        _ser("gateway_info_reserved_flags_and_format", "decoded", "2, 4.16", MsgType.GATEWAY_INFO, 0x7FFF,
             struct.pack("<BBHHH", 0x81, 3, 10, 4, 0),
             msg=GatewayInfo(0x7FFF, 0x81, 3, 10, 4, 0)),
        _ser("status_unknown_flags", "decoded", "2, 4.4", MsgType.STATUS, 5, bytes([1, 0xF0, 0, 0, 1, 0, 0, 0]),
             msg=Status(5, ChipState.IDLE, 0xF0, 0, 0, 1)),
    ]
    # --- CAN (§7): the same decisions, and the CAN-only ones
    snap11 = struct.pack("<HHB", 3, 0, 11) + flat * 11
    snap1 = struct.pack("<HHB", 3, 0, 1) + flat
    sid = make_id(MsgType.SNAPSHOT, 0x7FFF)
    v += [
        _can("standard_identifier", "bad_field", "7.1", 0x123, b"\x01\x02", extended=False),
        _can("identifier_over_29_bits", "bad_field", "7.1", 1 << 29, b""),
        _can("version_2", "bad_version", "7.1, 12", make_id(MsgType.START, 5, version=2), b""),
        _can("any_priority_is_accepted", "decoded", "7.1", make_id(MsgType.SAMPLE, 1, priority=7),
             bytes(2) + flat, msg=Sample(1, 0, 0, 0, 1024, 0)),
        _can("sync_addressed_to_a_node", "bad_field", "4.9", make_id(MsgType.SYNC, 5), b"\x01\x00"),
        _can("undefined_type_0x1c", "unknown_type", "4, 8.1", make_id(0x1C, 5, priority=4), b""),
        _can("classic_nine_bytes", "bad_length", "7.2", make_id(MsgType.CONFIG, 5), bytes(9)),
        _can("fd_length_nine_is_not_an_fd_length", "bad_length", "7.2", make_id(MsgType.CONFIG, 5), bytes(9),
             fd=True),
        _can("snapshot_on_classic_can", "bad_length", "7.2", sid, snap1),
        _can("snapshot_fd_unpadded", "bad_length", "7.2", sid, snap1, fd=True),
        _can("snapshot_fd_padded", "decoded", "7.2", sid, snap1 + bytes(2), fd=True,
             msg=Snapshot.from_arrays(0x7FFF, 3, 0, np.array([[0, 0, 1024]]), np.zeros(1, int))),
        _can("snapshot_fd_non_zero_padding", "bad_field", "7.2", sid, snap1 + b"\x00\x01", fd=True),
        _can("snapshot_fd_11_samples", "decoded", "7.2, 4.8", sid, snap11 + bytes(4), fd=True,
             msg=Snapshot.from_arrays(0x7FFF, 3, 0, np.tile([0, 0, 1024], (11, 1)), np.zeros(11, int))),
        _can("snapshot_fd_count_12", "bad_length", "7.2, 4.8", sid, struct.pack("<HHB", 3, 0, 12) + flat * 11 + bytes(4),
             fd=True),
        _can("sample_fd_padded_to_8", "bad_length", "7.2", make_id(MsgType.SAMPLE, 1), bytes(2) + flat + b"\x00",
             fd=True),
        _can("gateway_info", "decoded", "4.16", make_id(MsgType.GATEWAY_INFO, 0x7FFF),
             struct.pack("<BBHHH", 1, 0, 0, 364, 0), msg=GatewayInfo(0x7FFF, 1, 0, 0, 364, 0)),
    ]
    return v + _imu_verdict_vectors(flat)


def _imu_verdict_vectors(flat: bytes) -> list[dict]:
    """The IMU frames' edges (docs §16, new in 1.2), bytes built here with struct from §16's tables."""
    import struct
    from .can import make_id
    unknown = struct.pack("<h", TIME_UNKNOWN)
    rec6 = flat + unknown + struct.pack("<hhh", 0, 0, 0)  # 13 bytes: word, time_us, gyro
    rec9 = rec6 + struct.pack("<hhh", 0, 0, 0)  # 19 bytes: + mag

    def snap(count, fmt, rec, first=0):
        return struct.pack("<HHBB", 7, first, count, fmt) + rec * count

    def recs(n, fmt):
        z = np.zeros((n, 3), int)
        return dict(counts=np.tile([0, 0, 1024], (n, 1)), status=np.zeros(n, int), time_us=np.full(n, TIME_UNKNOWN),
                    gyro=z, mag=z if fmt == 2 else None)
    imu = make_id(MsgType.IMU_SAMPLE, 1)
    sid = make_id(MsgType.SNAPSHOT_IMU, 0x7FFF)
    return [
        _ser("imu_sample_6_axis_15_bytes", "decoded", "16.3", MsgType.IMU_SAMPLE, 1, b"\x05\x00" + rec6,
             msg=ImuSample(1, 5, 0, 0, 1024, 0, TIME_UNKNOWN, 0, 0, 0)),
        _ser("imu_sample_9_axis_21_bytes", "decoded", "16.3", MsgType.IMU_SAMPLE, 1, b"\x05\x00" + rec9,
             msg=ImuSample(1, 5, 0, 0, 1024, 0, TIME_UNKNOWN, 0, 0, 0, 0, 0, 0)),
        _ser("imu_sample_16_bytes", "bad_length", "16.3", MsgType.IMU_SAMPLE, 1, b"\x05\x00" + rec6 + b"\x00"),
        _ser("imu_sample_7_bytes_is_not_a_sample", "bad_length", "16.3", MsgType.IMU_SAMPLE, 1, b"\x05\x00" + flat),
        _ser("config_imu_values_out_of_range_decode", "decoded", "16.2", MsgType.CONFIG_IMU, 5, bytes([3, 5, 4, 0xFE]),
             msg=ConfigImu(5, 3, 5, 4, 0xFE)),
        _ser("config_imu_3_bytes", "bad_length", "16.2, 8.1", MsgType.CONFIG_IMU, 5, bytes([1, 3, 0])),
        _ser("snapshot_imu_77_records_is_1013_bytes", "decoded", "16.5, 6.3", MsgType.SNAPSHOT_IMU, 0x7FFF,
             snap(77, 1, rec6), msg=SnapshotImu.from_arrays(0x7FFF, 7, 0, **recs(77, 1))),
        _ser("snapshot_imu_78_records_is_1026_bytes", "oversize", "16.5, 6.3", MsgType.SNAPSHOT_IMU, 0x7FFF,
             snap(78, 1, rec6)),
        _ser("snapshot_imu_53_9_axis_records", "decoded", "16.5, 6.3", MsgType.SNAPSHOT_IMU, 0x7FFF,
             snap(53, 2, rec9), msg=SnapshotImu.from_arrays(0x7FFF, 7, 0, **recs(53, 2))),
        _ser("snapshot_imu_54_9_axis_records", "oversize", "16.5, 6.3", MsgType.SNAPSHOT_IMU, 0x7FFF,
             snap(54, 2, rec9)),
        _ser("snapshot_imu_format_0", "bad_field", "16.5", MsgType.SNAPSHOT_IMU, 0x7FFF, snap(1, 0, rec6)),
        _ser("snapshot_imu_format_3", "bad_field", "16.5", MsgType.SNAPSHOT_IMU, 0x7FFF, snap(1, 3, rec6)),
        _ser("snapshot_imu_count_0", "bad_length", "16.5", MsgType.SNAPSHOT_IMU, 0x7FFF, snap(0, 1, rec6)),
        _ser("snapshot_imu_format_2_with_13_byte_records", "bad_length", "16.5", MsgType.SNAPSHOT_IMU, 0x7FFF,
             struct.pack("<HHBB", 7, 0, 1, 2) + rec6),
        _ser("snapshot_imu_past_link_65535", "bad_field", "16.5", MsgType.SNAPSHOT_IMU, 0x7FFF,
             snap(2, 1, rec6, first=0xFFFF)),
        _ser("imu_gyro_7_bytes", "bad_length", "16.4", MsgType.IMU_GYRO, 1, bytes(7)),
        _ser("imu_accel_decodes_alone", "decoded", "16.4", MsgType.IMU_ACCEL, 1, b"\x05" + flat + unknown,
             msg=ImuAccel(1, 5, 0, 0, 1024, 0, TIME_UNKNOWN)),
        _can("imu_sample_on_classic_can", "bad_length", "16.3, 7.2", imu, b"\x05\x00" + rec6),
        _can("imu_sample_fd_unpadded", "bad_length", "16.3, 7.2", imu, b"\x05\x00" + rec6, fd=True),
        _can("imu_sample_fd_padded_to_16", "decoded", "16.3", imu, b"\x05\x00" + rec6 + b"\x00", fd=True,
             msg=ImuSample(1, 5, 0, 0, 1024, 0, TIME_UNKNOWN, 0, 0, 0)),
        _can("imu_sample_fd_padded_to_24", "decoded", "16.3", imu, b"\x05\x00" + rec9 + b"\x00\x00\x00", fd=True,
             msg=ImuSample(1, 5, 0, 0, 1024, 0, TIME_UNKNOWN, 0, 0, 0, 0, 0, 0)),
        _can("imu_sample_fd_20_bytes", "bad_length", "16.3", imu, b"\x05\x00" + rec6 + bytes(5), fd=True),
        _can("imu_sample_fd_non_zero_padding", "bad_field", "16.3, 7.2", imu, b"\x05\x00" + rec6 + b"\x01", fd=True),
        _can("snapshot_imu_fd_4_records", "decoded", "16.5", sid, snap(4, 1, rec6) + bytes(6), fd=True,
             msg=SnapshotImu.from_arrays(0x7FFF, 7, 0, **recs(4, 1))),
        _can("snapshot_imu_fd_3_9_axis_records", "decoded", "16.5", sid, snap(3, 2, rec9) + bytes(1), fd=True,
             msg=SnapshotImu.from_arrays(0x7FFF, 7, 0, **recs(3, 2))),
        _can("snapshot_imu_fd_count_5", "bad_length", "16.5", sid, snap(5, 1, rec6)[:64], fd=True),
        _can("snapshot_imu_fd_non_zero_padding", "bad_field", "16.5, 7.2", sid, snap(4, 1, rec6) + bytes(5) + b"\x01",
             fd=True),
        _can("imu_gyro_classic", "decoded", "16.4", make_id(MsgType.IMU_GYRO, 1), struct.pack("<Hhhh", 5, -32768, 32767, 0),
             msg=ImuGyro(1, 5, -32768, 32767, 0)),
    ]
