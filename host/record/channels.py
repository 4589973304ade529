"""A capsheet recording's channels (docs/recording.md): the format's name, the topics, the JSON
schemas of the channels that carry JSON and the arrays inside them, the protobuf packed fields the
writer appends by hand, and the files of a split recording (``run.mcap`` -> ``run_0000.mcap``, ...).
What the writer (`host.record.writer`) and the reader (`host.record.reader`) share."""

from __future__ import annotations

import base64
import platform
from importlib import metadata as _md
from pathlib import Path

import logging

import numpy as np

from host.publish.live import length_delimited

log = logging.getLogger("capsheet.host.record")


FORMAT = "capsheet-mcap-2"
#: what older capsheet wrote (JSON channels); `read`, replay and estimate still read it
FORMAT_V1 = "capsheet-mcap-1"
#: Attachment: the host-side calibration (``capsheet host --calibration``, `host.analysis.calibration`
#: format, rebased to the chips' own) applied to every recorded snapshot; replay applies it too.
HOST_CALIBRATION = "host_calibration.json"
TOPIC_RAW = "/capsheet/raw/bus{}"
TOPIC_SYNC = "/capsheet/sync"
TOPIC_SNAPSHOT = "/capsheet/snapshot"
TOPIC_ESTIMATE = "/capsheet/estimate"
TOPIC_CONTACTS = "/capsheet/contacts"
#: the live view's IMU channel (6/9-axis chips; not in the file, whose snapshots carry the axes)
TOPIC_IMU = "/sheet/imu"


def versions() -> dict:
    """Versions of capsheet and the libraries a recording depends on (strings)."""
    out = {"python": platform.python_version()}
    for dist, key in (("capture-sheet", "capsheet"), ("numpy", "numpy"), ("scipy", "scipy"),
                      ("foxglove-sdk", "foxglove_sdk"), ("mcap", "mcap"), ("python-can", "python_can")):
        try:
            out[key] = _md.version(dist)
        except _md.PackageNotFoundError:
            out[key] = "not installed"
    return out


# --------------------------------------------------------------------------------------------
# array <-> JSON
# --------------------------------------------------------------------------------------------

def _arr(a, dtype: str) -> dict:
    a = np.ascontiguousarray(a, dtype=dtype)
    return {"dtype": np.dtype(dtype).str, "shape": list(a.shape), "data": base64.b64encode(a.tobytes()).decode()}


def unarr(d: dict) -> np.ndarray:
    dtype = np.dtype(d["dtype"])
    if dtype.kind not in "biuf":  # numbers only: never objects, never a dtype sized by the file
        raise ValueError(f"an array of dtype {d['dtype']!r} (need numbers)")
    return np.frombuffer(base64.b64decode(d["data"]), dtype=dtype).reshape(d["shape"])


_ARRAY_SCHEMA = {"type": "object", "properties": {
    "dtype": {"type": "string", "description": "numpy dtype string, little-endian (e.g. '<f4')"},
    "shape": {"type": "array", "items": {"type": "integer"}},
    "data": {"type": "string", "contentEncoding": "base64", "description": "C-order array bytes"}}}


def _schema(title: str, props: dict, description: str) -> dict:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title,
            "description": description, "type": "object", "properties": props}


SCHEMAS: dict[str, dict] = {
    "capsheet.RawSerial": _schema("capsheet.RawSerial", {
        "bus": {"type": "integer"}, "port": {"type": "string"},
        "t": {"type": "number", "description": "host monotonic s when ingested (replay order)"},
        "t_rx": {"type": "number", "description": "host monotonic s when read"},
        "data": {"type": "string", "contentEncoding": "base64", "description": "wire bytes as read (COBS frames)"}},
        "Serial wire input of one bus, as read (docs/protocol.md section 6)"),
    "capsheet.RawCan": _schema("capsheet.RawCan", {
        "bus": {"type": "integer"}, "port": {"type": "string"}, "t": {"type": "number"},
        "frames": {"type": "array", "items": {"type": "object", "properties": {
            "id": {"type": "integer"}, "ext": {"type": "boolean"}, "fd": {"type": "boolean"},
            "err": {"type": "boolean"}, "rtr": {"type": "boolean"}, "brs": {"type": "boolean"},
            "ts": {"type": "number", "description": "python-can timestamp"},
            "data": {"type": "string", "contentEncoding": "base64"}}}}},
        "CAN frames of one bus, one receive batch (docs/protocol.md section 7)"),
    "capsheet.Sync": _schema("capsheet.Sync", {"counter": {"type": "integer"}, "t": {"type": "number"}},
                             "The host opened SYNC counter at t (host monotonic s)"),
    "capsheet.Snapshot": _schema("capsheet.Snapshot", {
        "counter": {"type": "integer"}, "timestamp": {"type": "number"}, "wall_time": {"type": "number"},
        "latency_s": {"type": "number"}, "complete": {"type": "boolean"},
        "readings": _ARRAY_SCHEMA, "valid": _ARRAY_SCHEMA, "status": _ARRAY_SCHEMA},
        "One lattice snapshot: readings (n_links, 3) m/s2 sensor frame, valid (n_links,), status bits"),
    "capsheet.Estimate": _schema("capsheet.Estimate", {
        "counter": {"type": "integer"}, "timestamp": {"type": "number"}, "method": {"type": "string"},
        "residual": {"type": "number"}, "iterations": {"type": "integer"},
        "joints": _ARRAY_SCHEMA, "yaw_std": _ARRAY_SCHEMA, "joint_std": _ARRAY_SCHEMA,
        "error_pct_side": {"type": "number", "description": "mean joint error vs truth, % of side"}},
        "One shape estimate: joints (rows, cols, 3) m, world frame z up"),
    "capsheet.Contacts": _schema("capsheet.Contacts", {
        "counter": {"type": "integer"}, "timestamp": {"type": "number"},
        "contacts": {"type": "array", "items": {"type": "object"}}},
        "Tactile contacts: id, index (i, j), position (m), force_n (N), radius_m"),
    "capsheet.Imu": _schema("capsheet.Imu", {
        "counter": {"type": "integer"}, "timestamp": {"type": "number"}, "n_links": {"type": "integer"},
        "links_with_imu": {"type": "integer", "description": "links whose IMU record came"},
        "gyro": {"type": "array", "items": {"type": ["number", "null"]},
                 "description": "(n_links, 3) rad/s, sensor frame, row-major; null where no record"},
        "gyro_norm_dps": {"type": "array", "items": {"type": ["number", "null"]}, "description": "|gyro| per link, deg/s"},
        "gyro_rms_dps": {"type": ["number", "null"]}, "gyro_max_dps": {"type": ["number", "null"]},
        "mag": {"type": ["array", "null"], "items": {"type": ["number", "null"]},
                "description": "(n_links, 3) microtesla, sensor frame; null without magnetometers"},
        "mag_norm_ut": {"type": ["number", "null"], "description": "mean |mag| over the links, microtesla"},
        "mag_weight": {"type": ["array", "null"], "items": {"type": "number"},
                       "description": "the fused estimator's weight per magnetometer (0: disturbed)"},
        "method": {"type": "string", "description": "the estimator of the shape shown with it"}},
        "6/9-axis chips' axes of one snapshot for the live view (docs/protocol.md section 16)"),
}



def split_path(path, index: int) -> Path:
    """File ``index`` of a split recording: ``run.mcap`` -> ``run_0000.mcap``, ``run_0001.mcap``, ..."""
    path = Path(path)
    return path.with_name(f"{path.stem}_{int(index):04d}{path.suffix}")


def recording_set(path) -> list[Path]:
    """The files of a recording: ``path`` itself if it exists, else the split set it names
    (``run.mcap`` -> ``run_0000.mcap``, ``run_0001.mcap``, ... as far as they go, in order).
    Raises FileNotFoundError when there is neither."""
    path = Path(path)
    if path.exists():
        return [path]
    out = []
    while split_path(path, len(out)).exists():
        out.append(split_path(path, len(out)))
    if not out:
        raise FileNotFoundError(f"{str(path)!r} does not exist (nor {split_path(path, 0).name}, a split set)")
    return out


def packed_sint32(number: int, values) -> bytes:
    """Field ``number`` of packed repeated ``sint32`` ``values`` (integers within int32), wire-encoded
    (zigzag varints) with numpy: what ``msg.<field>.extend(values.tolist())`` makes, for
    ``msg.MergeFromString`` (a 64x64 snapshot's 24,192 counts: ~0.1 ms instead of ~0.7 ms, in the
    receive path under the feed's lock).

    >>> from host.record.schema import message_class
    >>> m = message_class("Snapshot")(); m.MergeFromString(packed_sint32(7, [0, -1, 1, -64, 64, -32768, 32767]))
    14
    >>> list(m.counts)
    [0, -1, 1, -64, 64, -32768, 32767]
    """
    v = np.asarray(values).ravel()
    if v.size == 0:
        return b""
    v = v.astype(np.int32, copy=False)
    z = ((v << 1) ^ (v >> 31)).view(np.uint32)  # zigzag
    cols = max(1, (int(z.max()).bit_length() + 6) // 7)
    grid = np.empty((v.size, cols), dtype=np.uint8)
    more = np.empty(v.size, dtype=bool)
    for k in range(cols):
        grid[:, k] = (z >> (7 * k)) & 0x7F
        if k + 1 < cols:
            np.greater_equal(z, 1 << (7 * (k + 1)), out=more)
            grid[:, k] |= more.view(np.uint8) << 7
    if cols == 1:
        payload = grid.tobytes()
    else:
        n_bytes = 1 + sum((z >= (1 << (7 * k))).view(np.uint8).astype(np.intp) for k in range(1, cols))
        payload = grid[np.arange(cols) < n_bytes[:, None]].tobytes()
    return length_delimited(number, payload)


def packed_float(number: int, values) -> bytes:
    """Field ``number`` of packed repeated ``float`` ``values``, wire-encoded (little-endian
    float32), for ``msg.MergeFromString``: what ``extend(values.tolist())`` makes, without the list.

    >>> from host.record.schema import message_class
    >>> m = message_class("Estimate")(); m.MergeFromString(packed_float(6, [0.5, -2.0]))
    10
    >>> list(m.joints)
    [0.5, -2.0]
    """
    payload = np.ascontiguousarray(np.asarray(values, dtype="<f4").ravel()).tobytes()
    if not payload:
        return b""
    return length_delimited(number, payload)
