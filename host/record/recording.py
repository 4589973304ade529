"""Recordings in MCAP (docs/recording.md): what a session receives, aggregates and estimates, in a
file that robotics tools read (Foxglove, the ``mcap`` CLI and libraries, RViz via mcap plugins).

One `Recorder` publishes a session's data on `foxglove.Channel` s of one `foxglove.Context`; its
sinks are an MCAP file (``path``), a live Foxglove WebSocket server (``host.publish.live``), or both, so the
file and the live view carry the very same messages. The writer is foxglove-sdk's (Rust, chunked,
zstd); a chunk is closed every ``flush_interval_s``, so a killed host leaves a file that `read`
(and any MCAP stream reader) reads up to its last finished chunk.

Topics (format ``capsheet-mcap-2``: capsheet's own are protobuf, schemas built by
`host.record.schema` and stored in the file; docs/recording.md has every field):

==========================  =======================  =============================================
topic                       schema                   content
==========================  =======================  =============================================
``/capsheet/raw/bus{N}``    capsheet.v2.RawSerial    wire bytes of bus N as read (serial, pty, memory);
                                                     ``t`` when ingested, ``t_rx`` when read
                            capsheet.v2.RawSerialFrames  the same bytes, valid SAMPLE frames as columns
                                                     (`host.record.compact`; what `Recorder` writes)
                            capsheet.v2.RawCan       CAN frames of bus N as received (one batch)
``/capsheet/sync``          capsheet.v2.Sync         the host opened SYNC ``counter`` at ``t``
``/capsheet/snapshot``      capsheet.v2.Snapshot     counter, the chips' counts (int16; `read`
                                                     converts them with the recorded calibration),
                                                     valid bitmap, status; 6/9-axis chips: gyro
                                                     (rad/s), mag (T), sample_time_s (float32)
``/capsheet/estimate``      capsheet.v2.Estimate     joints (rows, cols, 3) m; ``yaw_std``,
                                                     ``joint_std`` when computed; error vs truth
``/capsheet/contacts``      capsheet.Contacts (JSON) tactile contacts: position, force, radius, id
``/sheet/imu``              capsheet.Imu (JSON)      live view only, 6/9-axis chips: per link gyro
                                                     (rad/s), |gyro| (°/s), mag (µT), the fused
                                                     estimator's magnetometer weights; summaries
``/sheet/scene``            foxglove.SceneUpdate     the lattice as a coloured line list, contacts
``/sheet/joints``           foxglove.PointCloud      the estimated joints (x, y, z float32, m)
``/tf``                     foxglove.FrameTransform  ``world`` -> ``sheet`` (identity)
==========================  =======================  =============================================

Recordings of format ``capsheet-mcap-1`` (JSON channels) are read too. A recording may be a split
set (``run_0000.mcap``, ``run_0001.mcap``, ...: `split_path`, `recording_set`).

Every message's log time is the host's wall clock (ns since the Unix epoch); ``t`` fields inside
are the host's monotonic clock (s), the clock `host.snapshots.snapshot.LatticeSnapshot.timestamp` uses.
Metadata record ``capsheet.session``: lattice, link length, rate, sync mode, transports, versions.
Attachments: ``layout.json`` (uid -> link), ``calibration.json`` (per link offset/sensitivity, the
node map), ``host_calibration.json`` (with ``capsheet host --calibration``: the calibration every recorded
snapshot was corrected with, which replay applies too), and at close ``stats.json`` (the host's final
statistics).

`read` gives numpy arrays back (`Recording`).
"""

from __future__ import annotations

import base64
import json
import platform
import shutil
import struct
import threading
import time
from dataclasses import dataclass, field
from importlib import metadata as _md
from pathlib import Path
from typing import Any, Callable, Iterator

import logging

import numpy as np

from host.publish.live import length_delimited
from protocol.files import loads_json, open_regular

log = logging.getLogger("capsheet.host.record")

__all__ = ["Recorder", "Recording", "read", "read_recording", "iter_snapshots", "SnapshotBatch", "snapshot_count",
           "tap_transport", "versions", "compression_level_for",
           "TOPIC_RAW", "TOPIC_SYNC", "TOPIC_SNAPSHOT", "TOPIC_ESTIMATE", "TOPIC_CONTACTS", "TOPIC_IMU",
           "FORMAT"]

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


def _unarr(d: dict) -> np.ndarray:
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


# --------------------------------------------------------------------------------------------
# Raw taps
# --------------------------------------------------------------------------------------------

def tap_transport(transport, on_raw: Callable[[str, Any], None]) -> Callable:
    """Call ``on_raw(kind, payload)`` with a transport's wire input as it is received: ``kind``
    ``"serial"`` (payload: the bytes read) or ``"can"`` (payload: the frames of one receive, one
    by one: python-can messages, and `host.transport.ports.RawFrame` s for the rows of an SLCAN bus's
    `protocol.can.FrameBlock`). A capture handler (`host.transport.ports.Transport.begin_capture`);
    returned, for `end_capture`. Raises TypeError for an object that is not a transport."""
    begin = getattr(transport, "begin_capture", None)
    if begin is None:
        raise TypeError(f"Cannot record raw input of {type(transport).__name__} {getattr(transport, 'name', '?')!r} "
                        f"(need a host.transport.Transport, which offers begin_capture)")

    def handler(cap) -> None:
        if cap.direction == "rx":
            on_raw(cap.kind, cap.frames(echoes=True) if cap.kind == "can" else cap.raw)
    begin(handler)
    return handler


#: channel metadata key: which sink a channel is for ("file" or "live"); channels without it go to both
SINK_KEY = "capsheet.sink"
#: the file gets the 3D scene (derived from the estimates) at most this often, s
SCENE_FILE_PERIOD_S = 1.0
#: ... and the live estimates at most this often (5/s; `capsheet estimate` makes every one offline), s
ESTIMATE_FILE_PERIOD_S = 0.2
#: zstd level of the chunks: 9 makes a 14x14 145 Hz recording ~10 % smaller than the default (3)
#: for ~2 % of a core (docs/recording.md, "Size")
COMPRESSION_LEVEL = 9
#: ... and of a sheet of more than `LARGE_SHEET_LINKS` links. Every call into the SDK's writer holds
#: the interpreter lock the receive threads and the SYNC thread need; on a 64x64 sheet's raw input
#: at 145 Hz (6 MB/s) level 9 spends ~110 ms a second in those calls, level 3 ~42 ms, for files
#: ~4 % larger (benchmarks/bench_record_compression.py; whole 64x64 recordings ~7 %)
COMPRESSION_LEVEL_LARGE = 3
LARGE_SHEET_LINKS = 2048
#: zstd worker threads (0: the logging call compresses as it goes). With a worker, a chunk's last
#: call waits for the whole chunk to be compressed, holding the interpreter lock (25 ms against
#: 3 ms at level 9, 64x64 raw input, 1 MB chunks), and the total is no smaller (bench as above)
COMPRESSION_THREADS = 0


def compression_level_for(n_links: int) -> int:
    """The zstd level a recording of a sheet of ``n_links`` links is written with."""
    return COMPRESSION_LEVEL_LARGE if int(n_links) > LARGE_SHEET_LINKS else COMPRESSION_LEVEL


def _not_for(sink: str):
    """A sink's channel filter: every channel but those marked for the other sink."""
    return lambda ch: (ch.metadata or {}).get(SINK_KEY) != ("live" if sink == "live" else "file")


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


def _can_flags(m) -> int:
    from host.record import schema as P
    return ((P.CAN_EXT if m.is_extended_id else 0) | (P.CAN_FD if m.is_fd else 0)
            | (P.CAN_ERR if m.is_error_frame else 0) | (P.CAN_RTR if m.is_remote_frame else 0)
            | (P.CAN_BRS if getattr(m, "bitrate_switch", False) else 0))


def _can_frame_dict(m) -> dict:
    """A received frame (python-can message or `host.transport.ports.RawFrame`) as the recording stores it."""
    return {"id": int(m.arbitration_id), "ext": bool(m.is_extended_id), "fd": bool(m.is_fd),
            "err": bool(m.is_error_frame), "rtr": bool(m.is_remote_frame),
            "brs": bool(getattr(m, "bitrate_switch", False)), "ts": float(m.timestamp or 0.0),
            "data": base64.b64encode(bytes(m.data)).decode()}


# --------------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------------

class Recorder:
    """Publish a session (raw input, SYNC, snapshots, estimates, contacts, the 3D scene) to an MCAP
    file and/or a live Foxglove view.

    Parameters
    ----------
    path : str or Path or None
        The MCAP file to write (overwritten). None: no file (e.g. only ``live``).
    lattice : protocol.lattice.Lattice
    link_length : float
        ``L``, metres.
    session : dict, optional
        Facts stored in the ``capsheet.session`` metadata record (rate_hz, sync, transports, mode,
        ...); lattice, link length, versions and start time are added.
    layout, calibration : dict, optional
        Attached as ``layout.json`` / ``calibration.json`` (see `Recorder.session_facts`).
    live : host.live.LiveServer, optional
        A live server on this recorder's context (`host.publish.live.start`); stopped by `close`.
    live_options : dict, optional
        Keyword arguments of `host.publish.live.LiveServer` for the ``live_port`` server
        (``max_clients``, ``allowed_origins``, ``tls_cert``, ``tls_key``).
    colour_by : {"error", "displacement", "links"}
        What colours the lattice in ``/sheet/scene`` (docs/recording.md).
    flush_interval_s : float
        A chunk is closed at least this often (what a killed host can lose).
    chunk_size : int
        Target uncompressed chunk size, bytes.
    split_size : int, optional
        Start the next file once this one holds at least this many bytes (checked at every flush).
    split_duration : float, optional
        Start the next file after this many seconds. With either split, the files are
        ``<stem>_0000<suffix>``, ``<stem>_0001<suffix>``, ... (`split_path`), each a whole
        recording (session metadata, layout, calibration), read alone or as a set (`read`).
    min_free : int
        Bytes that must stay free on the file's disk: checked when the recorder starts (ValueError
        below it, nothing written) and at every flush, where the recording stops cleanly (the file
        closed with its summary, `stopped` says why; the session and the live view go on).
    free_bytes : callable
        ``(directory) -> free bytes`` (default `shutil.disk_usage`; a simulated disk in tests).
    estimate_file_period_s : float
        The file gets at most one estimate per this many seconds (the live view every one; 0:
        every one). A live session records at `ESTIMATE_FILE_PERIOD_S` (docs/recording.md, "Size").
    scene_file_period_s : float
        The same for the 3D scene (derived from the estimates); a live session: `SCENE_FILE_PERIOD_S`.
    on_stop : callable, optional
        ``(reason)``, called once when the recording stops before `close` (the disk filled).
    compression_level : int, optional
        zstd level of the chunks (default `compression_level_for` the lattice's links).
    compression_threads : int
        zstd worker threads (`COMPRESSION_THREADS`).
    compact : bool
        Serial input as ``capsheet.v2.RawSerialFrames`` (`host.record.compact`: valid SAMPLE frames
        as columns, every other byte as it came; the same bytes on reading), else as ``RawSerial``;
        a snapshot's counts as ``counts_planes`` (against each link's running average), else ``counts``.

    Attributes
    ----------
    paths : list of Path
        The files written so far, in order.
    stopped : str or None
        Why the recording stopped before `close`, if it did.
    not_recorded : int
        Messages logged after the recording stopped (they reached the live view only).
    """

    def __init__(self, path, lattice, link_length: float, *, session: dict | None = None,
                 layout: dict | None = None, calibration: dict | None = None, live_port: int | None = None,
                 live_host: str = "127.0.0.1", colour_by: str = "links", flush_interval_s: float = 1.0,
                 chunk_size: int = 1 << 20, split_size: int | None = None, split_duration: float | None = None,
                 min_free: int = 0, free_bytes: Callable[[Path], int] | None = None,
                 on_stop: Callable[[str], None] | None = None,
                 estimate_file_period_s: float = 0.0, scene_file_period_s: float = 0.0,
                 compression_level: int | None = None, compression_threads: int = COMPRESSION_THREADS,
                 live_options: dict | None = None, compact: bool = True) -> None:
        import foxglove
        from foxglove.mcap import MCAPWriteOptions

        from host.publish.live import SceneChannels

        if path is None and live_port is None:
            raise ValueError("Recorder needs a path, a live_port, or both")
        if not (np.isfinite(link_length) and link_length > 0):
            raise ValueError(f"Invalid link_length: {link_length!r} (need a finite value > 0 m)")
        if split_size is not None and not int(split_size) >= 1:
            raise ValueError(f"Invalid split_size: {split_size!r} (need >= 1 byte)")
        if split_duration is not None and not (np.isfinite(split_duration) and split_duration > 0):
            raise ValueError(f"Invalid split_duration: {split_duration!r} (need a finite value > 0 s)")
        self.path = None if path is None else Path(path)
        self.split_size = None if split_size is None else int(split_size)
        self.split_duration = None if split_duration is None else float(split_duration)
        self.split = self.split_size is not None or self.split_duration is not None
        self.min_free = int(min_free)
        self._free_bytes = free_bytes or (lambda d: shutil.disk_usage(d).free)
        self.on_stop = on_stop
        self.paths: list[Path] = []
        self.stopped: str | None = None
        self.not_recorded = 0
        self._file_docs: list[tuple[str, str, Any]] = []  # what every file of a split set repeats
        self.lattice = lattice
        self.link_length = float(link_length)
        self.flush_interval_s = float(flush_interval_s)
        self.counts: dict[str, int] = {}
        self.context = foxglove.Context()
        self._lock = threading.Lock()
        self._io = threading.RLock()  # one message at a time into the writer; a file switch between two
        self.compact = bool(compact)
        self._compactors: dict[Any, tuple[int, Any]] = {}  # bus (or "snapshot") -> (file index, its coder)
        self._last_flush = time.monotonic()
        self._closed = False
        self._writer = None
        self.compression_level = (compression_level_for(lattice.n_links) if compression_level is None
                                  else int(compression_level))
        self._opts = MCAPWriteOptions(chunk_size=int(chunk_size), compression_threads=int(compression_threads),
                                      profile="", compression_level=self.compression_level)
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            free = self._free_bytes(self.path.parent)
            if free < self.min_free:
                raise ValueError(f"only {free / 1e6:.0f} MB free on the disk of {self.path} (need "
                                 f"{self.min_free / 1e6:.0f} MB free to record): nothing recorded")
            self._open_file()
        from host.record import schema as P

        self._pb = P
        fds = P.file_descriptor_set()
        self._schemas = {name: foxglove.Schema(name=name, encoding="protobuf", data=fds) for name in P.NAMES}
        for name in ("capsheet.Contacts", "capsheet.Imu"):
            self._schemas[name] = foxglove.Schema(name=name, encoding="jsonschema", data=json.dumps(SCHEMAS[name]).encode())
        self._channels: dict[str, Any] = {}
        # the 3D scene is derived from the estimates: the live view gets one per estimate, the file
        # at most one per SCENE_FILE_PERIOD_S (docs/recording.md, "Size"), on channels of its own
        self.scene = self.file_scene = None
        if live_port is not None:
            self.scene = SceneChannels(self.context, lattice, colour_by=colour_by,
                                       metadata={SINK_KEY: "live"} if self.path is not None else None)
        if self.path is not None:
            self.file_scene = SceneChannels(self.context, lattice, colour_by=colour_by, metadata={SINK_KEY: "file"})
        self._last_file_scene_ns = None
        self.scene_cut = 0  #: estimates whose scene went to the live view but not the file (rate)
        self.estimate_file_period_s = float(estimate_file_period_s)
        self.scene_file_period_s = float(scene_file_period_s)
        self._last_file_estimate_ns = None
        self.estimates_cut = 0  #: estimates the live view got but the file did not (its rate)
        self._channel(TOPIC_SNAPSHOT, "capsheet.v2.Snapshot")  # advertised from the start (a live
        # client sees them at once)
        if live_port is not None:
            self._channel(TOPIC_ESTIMATE, "capsheet.v2.Estimate", "live" if self.path is not None else None)
        if self.path is not None:
            self._channel(TOPIC_ESTIMATE, "capsheet.v2.Estimate", "file")
        self.session = {"format": FORMAT, "rows": lattice.rows, "cols": lattice.cols, "n_links": lattice.n_links,
                        "link_length_m": self.link_length, "started_unix_s": time.time(),
                        "versions": versions(), **(session or {})}
        if self._writer is not None:
            self._document("metadata", "capsheet.session", {k: json.dumps(v) for k, v in self.session.items()})
            for name, doc in (("layout.json", layout), ("calibration.json", calibration)):
                if doc is not None:
                    self._document("attachment", name, doc)
        self.live = None
        if live_port is not None:
            from host.publish.live import LiveServer
            self.live = LiveServer(self.context, port=live_port, host=live_host,
                                   name=f"capsheet {lattice.rows}x{lattice.cols}", channel_filter=_not_for("file"),
                                   **(live_options or {}))
        for sc in self._scenes():
            sc.log_transform(time.time_ns())

    # -- files ---------------------------------------------------------------------------------
    def _open_file(self) -> None:
        import foxglove

        path = split_path(self.path, len(self.paths)) if self.split else self.path
        self._writer = foxglove.open_mcap(str(path), allow_overwrite=True, context=self.context,
                                          writer_options=self._opts, channel_filter=_not_for("live"))
        self.paths.append(path)
        self._file_t0 = time.monotonic()
        for kind, name, doc in self._file_docs:  # the next file of a set: readable alone
            self._write_doc(kind, name, doc)
        if self.split:
            self._write_doc("metadata", "capsheet.split", {"index": json.dumps(len(self.paths) - 1)})
        if getattr(self, "file_scene", None) is not None:  # the next file of a set: its own frame and scene
            self.file_scene.log_transform(time.time_ns())
            self._last_file_scene_ns = None

    def _document(self, kind: str, name: str, doc) -> None:
        """A metadata record or JSON attachment every file of a split set holds (replacing an
        earlier one of the same name). An attachment is encoded before the writer's lock is taken:
        a 64x64 layout is ~0.1 s of JSON, and the receive threads record snapshots under that lock
        while they hold the feed's (issue 31, stop 44: a following host's first second stalled on it)."""
        if kind != "metadata":
            doc = _json_attachment(doc)
        with self._io:
            self._file_docs = [d for d in self._file_docs if d[:2] != (kind, name)] + [(kind, name, doc)]
            if self._writer is not None:
                self._write_doc(kind, name, doc)

    def _write_doc(self, kind: str, name: str, doc) -> None:
        """Write a document: metadata (str -> str), or an attachment (its JSON bytes, or a dict)."""
        if kind == "metadata":
            self._writer.write_metadata(name, doc)
        else:
            now = time.time_ns()
            self._writer.attach(log_time=now, create_time=now, name=name, media_type="application/json",
                                data=doc if isinstance(doc, bytes) else _json_attachment(doc))

    @property
    def current_path(self) -> Path | None:
        """The file being written (None once stopped or without a file)."""
        return self.paths[-1] if self._writer is not None and self.paths else None

    def _check_files(self) -> None:
        """At a flush: stop on a full disk, else start the next file of a split set when due."""
        path = self.paths[-1]
        try:
            free = self._free_bytes(path.parent)
        except OSError as exc:
            free, why = 0, f"cannot read the free space of {path.parent}: {exc}"
        else:
            why = (f"only {free / 1e6:.0f} MB left free on the disk of {path} (--min-free "
                   f"{self.min_free / 1e6:.0f} MB)")
        if free < self.min_free:
            self._stop(why)
            return
        if self.split_duration is not None and time.monotonic() - self._file_t0 >= self.split_duration:
            self._next_file()
        elif self.split_size is not None and path.stat().st_size >= self.split_size:
            self._next_file()

    def _next_file(self) -> None:
        with self._io:
            self._end_file()
            self._writer.close()
            self._open_file()

    def _end_file(self) -> None:
        self._writer.write_metadata("capsheet.end", {"finished_unix_s": json.dumps(time.time()),
                                                     "counts": json.dumps(self.counts)})

    def _stop(self, reason: str) -> None:
        """Stop recording (the disk is full): close the file with its summary; the live view goes on."""
        with self._io:
            if self._writer is None:
                return
            self.stopped = reason
            try:
                self._end_file()
                self._writer.close()
            except Exception as exc:  # noqa: BLE001 - the SDK's own error types; the file is as far as it got
                log.warning("closing %s: %s", self.paths[-1], exc)
            self._writer = None
        log.warning("recording stopped: %s; %s is readable", reason, self.paths[-1])
        if self.on_stop is not None:
            self.on_stop(reason)

    # -- channels ------------------------------------------------------------------------------
    def _channel(self, topic: str, schema: str, sink: str | None = None):
        """The channel of ``topic``; ``sink`` ``"file"`` / ``"live"``: one that only that sink gets."""
        key = (topic, sink)
        ch = self._channels.get(key)
        if ch is None:
            import foxglove
            with self._lock:
                ch = self._channels.get(key)
                if ch is None:
                    enc = "json" if self._schemas[schema].encoding == "jsonschema" else "protobuf"
                    ch = foxglove.Channel(topic, schema=self._schemas[schema], message_encoding=enc,
                                          context=self.context, metadata=None if sink is None else {SINK_KEY: sink})
                    self._channels[key] = ch
        return ch

    def _log(self, topic: str, schema: str, msg, log_time_ns: int | None = None, sink: str | None = None) -> None:
        """Log ``msg`` (a dict: JSON; a protobuf message: its bytes; bytes: as they are) on ``topic``
        (to ``sink`` only)."""
        if self._closed:
            return
        data = (msg if isinstance(msg, bytes) else json.dumps(msg, separators=(",", ":")).encode()
                if isinstance(msg, dict) else msg.SerializeToString())
        with self._io:
            self._channel(topic, schema, sink).log(data, log_time=time.time_ns() if log_time_ns is None
                                                   else int(log_time_ns))
            if sink == "live":
                return
            if self._writer is None and self.path is not None:
                self.not_recorded += 1
                return
            self.counts[topic] = self.counts.get(topic, 0) + 1
            if self._writer is not None and time.monotonic() - self._last_flush >= self.flush_interval_s:
                self.flush()

    def _scenes(self) -> list:
        return [sc for sc in (self.scene, self.file_scene) if sc is not None]

    # -- what a session publishes ------------------------------------------------------------------
    def tap(self, transports, feed=None) -> None:
        """Record every transport's raw input (its capture, `host.transport.ports.Transport.begin_capture`),
        bus index = position in the list.

        With ``feed`` (the `host.snapshots.feed.SnapshotFeed` the transports' events go into, as
        ``feed.ingest(events, bus)``), a chunk is written when its events are ingested, stamped
        ``t`` = the ``now`` the aggregator decides with (`SnapshotFeed.add_ingest_listener`): the
        order of ingests and of the snapshots emitted is then the recorded order, so a replay makes
        the same snapshots however late the host's threads ran. (``t_rx`` keeps the time the bytes
        were read.) A chunk without a complete frame waits for the next ingest.
        """
        self._pending = {bus: [] for bus in range(len(transports))}
        self._ports = {bus: t.name for bus, t in enumerate(transports)}
        for bus, t in enumerate(transports):
            if feed is None:
                t.begin_capture(lambda cap, bus=bus, name=t.name: cap.direction == "rx" and self.raw(
                    bus, cap.kind, _raw_payload(cap), name, t=cap.timestamp, log_time_ns=int(cap.wall_time * 1e9)))
            else:
                t.begin_capture(lambda cap, bus=bus: cap.direction == "rx" and self._pending[bus].append(
                    (cap.timestamp, int(cap.wall_time * 1e9), cap.kind, _raw_payload(cap))))
        if feed is not None:
            feed.add_ingest_listener(lambda bus, now: self._pending.get(bus) and self._write_pending(bus, now))

    def _write_pending(self, bus: int, t: float | None) -> None:
        pending = self._pending[bus]
        while True:
            try:
                t_rx, wall_ns, kind, payload = pending.pop(0)
            except IndexError:
                return
            self.raw(bus, kind, payload, self._ports.get(bus, ""), t=t_rx if t is None else t,
                     log_time_ns=wall_ns, t_rx=t_rx)

    def raw(self, bus: int, kind: str, payload, port: str = "", t: float | None = None,
            log_time_ns: int | None = None, t_rx: float | None = None) -> None:
        """Wire input of ``bus``: ``kind="serial"`` with bytes, or ``"can"`` with a list of can.Message.
        ``t`` host monotonic s when it was taken in (default now); ``t_rx`` when it was read."""
        t = time.monotonic() if t is None else t
        topic = TOPIC_RAW.format(bus)
        P = self._pb
        t_rx = t if t_rx is None else t_rx
        if kind == "can":
            msg = P.message_class("RawCan")(bus=int(bus), t=float(t), t_rx=float(t_rx))
            for m in payload:
                msg.frames.add(id=int(m.arbitration_id), flags=_can_flags(m), ts=float(m.timestamp or 0.0),
                               data=bytes(m.data))
            self._log(topic, "capsheet.v2.RawCan", msg, log_time_ns)
        elif kind == "serial" and self.compact:
            from host.record.compact import SCHEMA, SerialCompactor
            with self._io:  # a compactor per bus and file: each file of a split set expands alone
                comp = self._coder(bus, SerialCompactor)
                self._log(topic, SCHEMA, comp.encode(payload, bus=int(bus), t=float(t), t_rx=float(t_rx)), log_time_ns)
        elif kind == "serial":
            self._log(topic, "capsheet.v2.RawSerial", P.message_class("RawSerial")(
                bus=int(bus), t=float(t), t_rx=float(t_rx), data=bytes(payload)), log_time_ns)
        else:
            raise ValueError(f"Invalid raw kind: {kind!r} (need 'serial' or 'can')")

    def _coder(self, key, make):
        """The coder of ``key`` for the file being written (a new file starts a new one); under `_io`."""
        index, coder = self._compactors.get(key, (None, None))
        if index != len(self.paths):
            index, coder = self._compactors[key] = (len(self.paths), make())
        return coder

    def sync(self, counter: int, t: float) -> None:
        """The host opened SYNC ``counter`` at host monotonic ``t`` (replay re-opens it there)."""
        self._log(TOPIC_SYNC, "capsheet.v2.Sync", self._pb.message_class("Sync")(counter=int(counter), t=float(t)))

    def tap_sync(self, feed) -> None:
        """Record every counter the host opens (`host.snapshots.feed.SnapshotFeed.add_open_listener`)."""
        feed.add_open_listener(self.sync)

    def snapshot(self, snap) -> None:
        """One `host.snapshots.snapshot.LatticeSnapshot`: its chips' counts when it has them (the readings
        are then the counts converted with the recorded calibration, `read`), else its readings
        as float32."""
        if self._closed:
            return
        valid = np.asarray(snap.valid, dtype=bool)
        msg = self._pb.message_class("Snapshot")(
            counter=int(snap.counter), timestamp=float(snap.timestamp), wall_time=float(snap.wall_time),
            latency_s=float(snap.latency_s), complete=bool(snap.complete), n_links=int(valid.shape[0]),
            valid=np.packbits(valid, bitorder="little").tobytes(),
            status=np.ascontiguousarray(snap.status, dtype=np.uint8).tobytes())
        counts = getattr(snap, "counts", None)
        parts = [packed_sint32(7, np.asarray(counts, dtype=np.int16)) if counts is not None and not self.compact
                 else b"" if counts is not None else packed_float(8, snap.readings)]
        for name, number in (("gyro", 11), ("mag", 12), ("sample_time_s", 13)):  # 6/9-axis chips (§16)
            v = getattr(snap, name, None)
            if v is not None:
                parts.append(packed_float(number, v))
        # the packed fields appended to the rest, wire-encoded: protobuf merges concatenated
        # messages, so this is the same message without parsing 24,192 counts back in and out
        # (a 64x64 snapshot: 0.39 instead of 0.67 ms, in the receive path)
        with self._io:  # the counts' coder per file, as the raw input's
            if counts is not None and self.compact:
                from host.record.compact import CountsCoder
                msg.counts_planes = self._coder("snapshot", CountsCoder).encode(counts, valid)
            self._log(TOPIC_SNAPSHOT, "capsheet.v2.Snapshot", msg.SerializeToString() + b"".join(parts),
                      _wall_ns(snap.wall_time))

    def estimate(self, est, counter: int, timestamp: float, wall_time: float | None = None, *,
                 error_joint: np.ndarray | None = None, error_pct_side: float | None = None,
                 displacement: np.ndarray | None = None, uncertainty: bool = False) -> None:
        """One `host.analysis.estimator.ShapeEstimate` of snapshot ``counter`` (and the 3D scene).

        ``error_joint`` (rows, cols) colours the lattice by error (% of side), ``displacement``
        (rows, cols) m by displacement; else links are coloured by state (valid / missing).
        ``yaw_std`` and ``joint_std`` are recorded when the estimate has computed them already, or
        when ``uncertainty`` asks for them (they are sampled: tens of estimates' worth of CPU).
        """
        t_ns = _wall_ns(wall_time)
        msg = self._pb.message_class("Estimate")(
            counter=int(counter), timestamp=float(timestamp), method=str(getattr(est, "method", "")),
            residual=float(getattr(est, "residual", np.nan)), iterations=int(getattr(est, "iterations", 0)))
        msg.MergeFromString(packed_float(6, est.joints))
        for name in ("yaw_std", "joint_std"):
            if not (uncertainty or name in getattr(est, "__dict__", {})):
                continue  # a lazy property not yet computed: not computed here unasked
            v = getattr(est, name, None)
            if v is not None:
                v = np.asarray(v, dtype=np.float32)
                getattr(msg, name).extend(v.ravel().tolist())
                if name == "joint_std":
                    msg.joint_std_shape.extend(list(v.shape))
        if error_pct_side is not None:
            msg.error_pct_side = float(error_pct_side)
        if self._closed:
            return
        with self._io:  # the live view gets every estimate, the file one per ESTIMATE_FILE_PERIOD_S
            if self.live is not None:
                self._log(TOPIC_ESTIMATE, "capsheet.v2.Estimate", msg, t_ns,
                          sink="live" if self.path is not None else None)
            if self.path is not None:
                last = self._last_file_estimate_ns
                if last is None or not 0 <= t_ns - last < self.estimate_file_period_s * 1e9:
                    self._last_file_estimate_ns = t_ns
                    self._log(TOPIC_ESTIMATE, "capsheet.v2.Estimate", msg, t_ns, sink="file")
                else:
                    self.estimates_cut += 1
        with self._io:
            self._log_scene(est, t_ns, error_joint, displacement)

    def imu(self, snap, est=None) -> None:
        """The live view's IMU channel (`TOPIC_IMU`) for a snapshot of 6/9-axis chips (a
        `host.snapshots.snapshot.LatticeSnapshot` with ``gyro``; nothing without): every link's gyroscope
        and magnetometer, their magnitudes, and with ``est`` (the shape shown with it) its method and,
        for the fused estimator, the magnetometers' weights. Only the live view gets it (the file's
        snapshots carry the axes); called per estimate, so at the live view's rate."""
        gyro = getattr(snap, "gyro", None)
        if gyro is None or self.live is None or self._closed:
            return
        g = np.asarray(gyro, dtype=float)
        have = np.isfinite(g).all(axis=1) & np.asarray(snap.valid, dtype=bool)
        norm = np.degrees(np.linalg.norm(g, axis=1))
        mag = getattr(snap, "mag", None)
        m = None if mag is None else 1e6 * np.asarray(mag, dtype=float)
        motion = getattr(est, "motion", None)
        weight = None if motion is None else getattr(motion, "mag_weight", None)

        def listed(a):  # JSON has no NaN: null where a link had no record
            return [None if not np.isfinite(v) else round(float(v), 6) for v in np.ravel(a)]
        msg = {"counter": int(snap.counter), "timestamp": float(snap.timestamp), "n_links": int(g.shape[0]),
               "links_with_imu": int(have.sum()), "gyro": listed(np.where(have[:, None], g, np.nan)),
               "gyro_norm_dps": listed(np.where(have, norm, np.nan)),
               "gyro_rms_dps": float(np.sqrt(np.mean(norm[have] ** 2))) if have.any() else None,
               "gyro_max_dps": float(norm[have].max()) if have.any() else None,
               "mag": None if m is None else listed(np.where(have[:, None], m, np.nan)),
               "mag_norm_ut": (float(np.linalg.norm(m[have], axis=1).mean()) if m is not None and have.any()
                               else None),
               "mag_weight": None if weight is None else [round(float(v), 4) for v in np.ravel(weight)],
               "method": str(getattr(est, "method", ""))}
        self._log(TOPIC_IMU, "capsheet.Imu", msg, _wall_ns(snap.wall_time), sink="live" if self.path is not None else None)

    def _log_scene(self, est, t_ns: int, error_joint, displacement) -> None:
        valid = np.asarray(est.valid, dtype=bool)
        if self.scene is not None:
            self.scene.log_lattice(est.joints, valid, t_ns, error=error_joint, displacement=displacement)
        if self.file_scene is not None and self._writer is not None:
            last = self._last_file_scene_ns
            if last is None or not 0 <= t_ns - last < self.scene_file_period_s * 1e9:
                self._last_file_scene_ns = t_ns
                self.file_scene.log_lattice(est.joints, valid, t_ns, error=error_joint, displacement=displacement)
            else:
                self.scene_cut += 1

    def contacts(self, counter: int, timestamp: float, contacts: list[dict], wall_time: float | None = None) -> None:
        """Tactile contacts of one frame: dicts with ``id``, ``index`` (i, j), ``position`` (x, y, z) m,
        ``force_n``, ``radius_m``; shown as spheres with their force in ``/sheet/scene``."""
        t_ns = _wall_ns(wall_time)
        self._log(TOPIC_CONTACTS, "capsheet.Contacts", {"counter": int(counter), "timestamp": float(timestamp),
                                                        "contacts": contacts}, t_ns)
        if not self._closed:
            with self._io:
                for sc in self._scenes():
                    sc.log_contacts(contacts, t_ns)

    def add_host_facts(self, host) -> None:
        """After bring-up: metadata ``capsheet.host`` (rate, sync, deadline, transports) and the
        ``layout.json`` / ``calibration.json`` attachments (what replay rebuilds the aggregator from)."""
        if self._writer is None or self._closed:
            return
        session, layout, calibration = self.session_facts(host)
        self.session.update(session)
        self._document("metadata", "capsheet.host", {k: json.dumps(v) for k, v in session.items()})
        docs = [("layout.json", layout), ("calibration.json", calibration)]
        live_cal = host.calibration
        if live_cal is not None:  # `capsheet host --calibration`: what the snapshots were corrected with
            docs.append((HOST_CALIBRATION, live_cal.to_dict()))
        for name, doc in docs:
            self._document("attachment", name, doc)

    # -- lifetime ------------------------------------------------------------------------------
    def flush(self) -> None:
        """Close the current chunk and push it to the OS (a kill after this loses nothing before)."""
        with self._io:
            self._last_flush = time.monotonic()
            if self._writer is None or self._closed:
                return
            try:
                self._writer.flush()
            except Exception as exc:  # noqa: BLE001 - e.g. the disk filled between two checks
                self._stop(f"cannot write {self.paths[-1]}: {exc}")
                return
            self._check_files()

    def close(self, stats: dict | None = None) -> None:
        """Attach ``stats.json`` (if given), write the summary, stop the live server. Idempotent."""
        if self._closed:
            return
        for bus in list(getattr(self, "_pending", {})):
            self._write_pending(bus, None)  # read but never ingested (the session ended)
        with self._io:
            if self._writer is not None:
                if stats is not None:
                    self._write_doc("attachment", "stats.json", stats)
                self._end_file()
            self._closed = True
            if self._writer is not None:
                self._writer.close()
        if self.live is not None:
            self.live.stop()

    def __enter__(self) -> "Recorder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @staticmethod
    def session_facts(host) -> tuple[dict, dict, dict]:
        """``(session, layout, calibration)`` of a `host.session.core.Host` after bring-up."""
        chips = sorted((r for r in host.chips.values() if r.assigned and r.link is not None), key=lambda r: r.link)
        layout = {"format": "capsheet-layout", "version": 1, "rows": host.lattice.rows, "cols": host.lattice.cols,
                  "chips": [{"uid": f"0x{r.uid:016X}", "link": int(r.link)} for r in chips]}
        calibration = {"range_code": int(host.range_code), "units": {"offset": "ADC counts", "sensitivity": "counts/g"},
                       "links": [{"link": int(r.link), "uid": f"0x{r.uid:016X}", "node": int(r.node), "bus": int(r.bus),
                                  "offset": [float(v) for v in r.offset],
                                  "sensitivity": [float(v) for v in r.sensitivity],
                                  "calibrated": bool(r.calibrated)} for r in chips]}
        session = {"rate_hz": host.rate_hz, "sync": host.sync_mode, "deadline_s": host.aggregator.deadline_s,
                   "imu_config": None if getattr(host, "imu_config", None) is None else list(host.imu_config),
                   "transports": [{"name": t.name, "kind": t.capabilities.kind, "fd": t.capabilities.fd,
                                   "bitrate": t.capabilities.bitrate} for t in host.transports]}
        return session, layout, calibration


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


def _raw_payload(cap):
    """What `Recorder.raw` records of a received `host.transport.ports.Capture`: the bytes, or every
    frame as received (echoes too: the recording holds the wire)."""
    return cap.frames(echoes=True) if cap.kind == "can" else cap.raw


def _wall_ns(wall_time: float | None) -> int:
    return time.time_ns() if wall_time is None or not np.isfinite(wall_time) else int(round(wall_time * 1e9))


def _json_attachment(doc) -> bytes:
    """A JSON attachment's bytes: a document's top-level keys one a line (people open these
    files), each value compact. json's indenting encoder is pure Python: a 64x64 sheet's layout
    and calibration took it 0.3 s of the interpreter at a following host's start, while five
    receive threads needed it (snapshots lost whole gateways there); the compact values go through
    its C encoder (~20x faster)."""
    enc = json.JSONEncoder(separators=(", ", ": "), default=_jsonable)
    if not isinstance(doc, dict) or not doc:
        return enc.encode(doc).encode()
    lines = [enc.encode({k: None})[1:-7] + ": " + enc.encode(v) for k, v in doc.items()]
    return ("{\n " + ",\n ".join(lines) + "\n}\n").encode()


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return str(o)


# --------------------------------------------------------------------------------------------
# Reader
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Recording:
    """A recording read back (`read`). Arrays are in record order (log time).

    Attributes
    ----------
    session : dict
        The ``capsheet.session`` metadata (rows, cols, n_links, link_length_m, rate_hz, versions...).
    attachments : dict
        name -> parsed JSON (``layout.json``, ``calibration.json``, ``stats.json``).
    counter : ndarray, shape (n,), uint16
        Snapshot SYNC counters.
    timestamp, wall_time, latency_s : ndarray, shape (n,), float64
        Host monotonic s at SYNC, Unix s, SYNC-to-emission s.
    complete : ndarray, shape (n,), bool
    readings : ndarray, shape (n, n_links, 3), float32
        m/s², sensor frame; NaN where not valid.
    valid : ndarray, shape (n, n_links), bool
    status : ndarray, shape (n, n_links), uint8
        `host.snapshots.snapshot.LinkFlag` bits.
    estimates : dict
        ``counter`` (m,), ``timestamp`` (m,), ``joints`` (m, rows, cols, 3) float32 m, and
        ``yaw_std`` / ``joint_std`` (NaN rows for estimates recorded without them) /
        ``error_pct_side`` when recorded.
    raw : dict
        bus -> list of ``(t, kind, payload)``: bytes (serial) or list of frame dicts (CAN).
    sync : ndarray, shape (k, 2)
        ``(counter, t)`` of every SYNC the host opened.
    contacts : list
        ``(counter, timestamp, [contact dicts])`` per tactile frame.
    message_counts : dict
        topic -> messages read.
    truncated : bool
        The file ended before its summary (the writer was killed): read up to the last chunk.
    """

    session: dict
    attachments: dict
    counter: np.ndarray
    timestamp: np.ndarray
    wall_time: np.ndarray
    latency_s: np.ndarray
    complete: np.ndarray
    readings: np.ndarray
    valid: np.ndarray
    status: np.ndarray
    estimates: dict
    raw: dict
    sync: np.ndarray
    contacts: list
    message_counts: dict
    truncated: bool = False
    metadata: dict = field(default_factory=dict)
    #: 6/9-axis chips (docs/protocol.md §16): (n, n_links, 3) rad/s, (n, n_links, 3) T, (n, n_links) s
    #: after the SYNC, float32, NaN where a snapshot had none; None when no snapshot carried them
    gyro: np.ndarray | None = None
    mag: np.ndarray | None = None
    sample_time_s: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.counter.shape[0])

    @property
    def lattice(self):
        from protocol.lattice import Lattice
        return Lattice(int(self.session["rows"]), int(self.session["cols"]))


def _iter_records(f):
    """MCAP records of a file in order, stopping cleanly where a killed writer left off, within
    the bounds `host.record.mcap_read` sets (ValueError beyond them, or for a corrupt record).
    Yields records; returns True (as ``StopIteration.value``) if the file was cut short."""
    from host.record.mcap_read import iter_records

    name = getattr(f, "name", "?")
    truncated = yield from iter_records(f, str(name))
    if truncated:
        log.info("%s: cut short; read up to the last whole record", name)
    return truncated


class _Decoder:
    """Decodes the messages of one capsheet recording's channels, whichever format wrote them:
    ``capsheet-mcap-1`` (JSON) or ``capsheet-mcap-2`` (protobuf, `host.record.schema`)."""

    def __init__(self, name: str = "recording") -> None:
        self.name = name  #: the file, for messages
        self.topic: dict[int, str] = {}
        self.proto: dict[int, Any] = {}  # channel id -> protobuf message class (v2)
        self._expanders: dict[int, Any] = {}  # channel id -> SerialExpander (RawSerialFrames)
        self._counts = None  # the snapshots' CountsCoder (counts_planes)
        self._schemas: dict[int, tuple[str, str]] = {}

    def schema(self, rec) -> None:
        self._schemas[rec.id] = (rec.name, rec.encoding)

    def channel(self, rec) -> None:
        self.topic[rec.id] = rec.topic
        name, enc = self._schemas.get(rec.schema_id, ("", ""))
        if rec.message_encoding == "protobuf" and name.startswith("capsheet.v2."):
            from host.record import schema as P
            self.proto[rec.id] = P.message_class(name)

    def snapshot(self, rec) -> dict:
        cls = self.proto.get(rec.channel_id)
        if cls is None:  # capsheet-mcap-1
            d = json.loads(rec.data)
            return {"counter": d["counter"], "timestamp": d["timestamp"], "wall_time": d["wall_time"],
                    "latency_s": d["latency_s"], "complete": d["complete"], "readings": _unarr(d["readings"]),
                    "counts": None, "valid": _unarr(d["valid"]).astype(bool), "status": _unarr(d["status"])}
        m = cls.FromString(rec.data)
        from host.record.mcap_read import check_snapshot
        n = check_snapshot(m, self.name)  # its arrays' lengths, before any is unpacked by n
        valid = np.unpackbits(np.frombuffer(m.valid, np.uint8), count=n, bitorder="little").astype(bool)
        if m.HasField("counts_planes"):
            from host.record.compact import CountsCoder
            if self._counts is None:
                self._counts = CountsCoder()
            counts = self._counts.decode(m.counts_planes, valid)
        else:
            counts = np.array(m.counts, dtype=np.int16).reshape(n, 3) if len(m.counts) else None
        return {"counter": m.counter, "timestamp": m.timestamp, "wall_time": m.wall_time, "latency_s": m.latency_s,
                "complete": m.complete,
                "counts": counts,
                "readings": np.array(m.readings, dtype=np.float32).reshape(n, 3) if len(m.readings) else None,
                "valid": valid, "status": np.frombuffer(m.status, np.uint8),
                "gyro": np.array(m.gyro, dtype=np.float32).reshape(n, 3) if len(m.gyro) else None,
                "mag": np.array(m.mag, dtype=np.float32).reshape(n, 3) if len(m.mag) else None,
                "sample_time_s": np.array(m.sample_time_s, dtype=np.float32) if len(m.sample_time_s) else None}

    def estimate(self, rec, rows: int, cols: int) -> dict:
        cls = self.proto.get(rec.channel_id)
        if cls is None:
            d = json.loads(rec.data)
            out = {"counter": d["counter"], "timestamp": d["timestamp"], "joints": _unarr(d["joints"])}
            for name in ("yaw_std", "joint_std"):
                if name in d:
                    out[name] = _unarr(d[name])
            if "error_pct_side" in d:
                out["error_pct_side"] = d["error_pct_side"]
            return out
        m = cls.FromString(rec.data)
        out = {"counter": m.counter, "timestamp": m.timestamp,
               "joints": np.array(m.joints, dtype=np.float32).reshape(rows, cols, 3)}
        if len(m.yaw_std):
            out["yaw_std"] = np.array(m.yaw_std, dtype=np.float32)
        if len(m.joint_std):
            out["joint_std"] = np.array(m.joint_std, dtype=np.float32).reshape(tuple(m.joint_std_shape))
        if m.HasField("error_pct_side"):
            out["error_pct_side"] = m.error_pct_side
        return out

    def sync(self, rec) -> tuple[int, float]:
        cls = self.proto.get(rec.channel_id)
        if cls is None:
            d = json.loads(rec.data)
            return d["counter"], d["t"]
        m = cls.FromString(rec.data)
        return m.counter, m.t

    def raw(self, rec) -> tuple[int, float, str, Any]:
        """``(bus, t, kind, payload)``: bytes (serial) or frame dicts (CAN, the v1 layout)."""
        cls = self.proto.get(rec.channel_id)
        if cls is None:
            d = json.loads(rec.data)
            if "frames" in d:
                return d["bus"], d["t"], "can", d["frames"]
            return d["bus"], d["t"], "serial", base64.b64decode(d["data"])
        m = cls.FromString(rec.data)
        if cls.DESCRIPTOR.name == "RawSerial":
            return m.bus, m.t, "serial", bytes(m.data)
        if cls.DESCRIPTOR.name == "RawSerialFrames":
            from host.record.compact import SerialExpander
            return m.bus, m.t, "serial", self._expanders.setdefault(rec.channel_id, SerialExpander()).expand(m)
        from host.record import schema as P
        return m.bus, m.t, "can", [{"id": f.id, "ext": bool(f.flags & P.CAN_EXT), "fd": bool(f.flags & P.CAN_FD),
                                    "err": bool(f.flags & P.CAN_ERR), "rtr": bool(f.flags & P.CAN_RTR),
                                    "brs": bool(f.flags & P.CAN_BRS), "ts": f.ts,
                                    "data": base64.b64encode(f.data).decode()} for f in m.frames]


class _Counts:
    """Counts -> readings exactly as the recording host converted and corrected them: the
    aggregator's `protocol.constants.counts_to_si` with ``calibration.json``'s offsets and
    sensitivities (nominal for links without a chip), then ``host_calibration.json``'s correction
    (`host.snapshots.feed.corrected`), one snapshot at a time."""

    def __init__(self, n_links: int, attachments: dict) -> None:
        from host.record.mcap_read import check_chip_calibration
        from protocol.constants import nominal_sensitivity
        cal = attachments.get("calibration.json") or {}
        check_chip_calibration(cal, n_links, "recording")
        self.off = np.zeros((n_links, 3))
        self.sens = np.full((n_links, 3), nominal_sensitivity(int(cal.get("range_code", 0))))
        for c in cal.get("links", []):
            self.off[int(c["link"])] = c["offset"]
            self.sens[int(c["link"])] = c["sensitivity"]
        self.correction = None
        host_cal = attachments.get(HOST_CALIBRATION)
        if host_cal is not None:
            from host.analysis.calibration import Calibration
            self.correction = Calibration.from_dict(host_cal, HOST_CALIBRATION).apply

    def __call__(self, counts: np.ndarray, valid: np.ndarray) -> np.ndarray:
        from protocol.constants import counts_to_si
        r = counts_to_si(counts.astype(np.float64), self.off, self.sens)
        r[~valid] = np.nan
        if self.correction is not None:
            r = np.asarray(self.correction(r), dtype=np.float64)
        return r


def _attachment(rec):
    try:
        return loads_json(rec.data, rec.name)  # nesting bounded
    except ValueError:
        return bytes(rec.data)


def _paths(path) -> list[Path]:
    if isinstance(path, (list, tuple)):
        if not path:
            raise ValueError("no recording given (an empty list of files)")
        return [Path(p) for p in path]
    return recording_set(path)


def read(path, *, raw: bool = True) -> Recording:
    """Read a capsheet MCAP recording into numpy arrays (tolerates a file cut short); either
    format (``capsheet-mcap-2``, or ``-1`` of older capsheet). A split recording (``--split-size``,
    ``--split-duration``) is read whole from its files in order: give them as a list, or the name
    they were recorded under (``run.mcap`` for ``run_0000.mcap``, ``run_0001.mcap``, ...).

    Parameters
    ----------
    path : str or Path, or a list of them
    raw : bool
        Also decode the raw wire input (slower for long recordings).

    Raises
    ------
    ValueError
        The file is not MCAP, or not a capsheet recording (no ``capsheet.session`` metadata).
    """
    parts = [_read_one(p, raw=raw) for p in _paths(path)]
    return parts[0] if len(parts) == 1 else _concat(parts)


def _concat(parts: list[Recording]) -> Recording:
    """Consecutive files of a split recording as one."""
    first, last = parts[0], parts[-1]
    est: dict = {}
    for k in first.estimates:
        if all(k in p.estimates for p in parts):
            est[k] = np.concatenate([p.estimates[k] for p in parts])
    raw: dict[int, list] = {}
    for p in parts:
        for bus, chunks in p.raw.items():
            raw.setdefault(bus, []).extend(chunks)
    counts: dict[str, int] = {}
    for p in parts:
        for t, n in p.message_counts.items():
            counts[t] = counts.get(t, 0) + n
    cat = lambda name: np.concatenate([getattr(p, name) for p in parts])  # noqa: E731

    def cat_imu(name):
        if all(getattr(p, name) is None for p in parts):
            return None
        return np.concatenate([getattr(p, name) if getattr(p, name) is not None else
                               np.full((len(p),) + next(getattr(q, name) for q in parts
                                                        if getattr(q, name) is not None).shape[1:], np.nan, np.float32)
                               for p in parts])
    return Recording(session=first.session, attachments={k: v for p in parts for k, v in p.attachments.items()},
                     counter=cat("counter"), timestamp=cat("timestamp"), wall_time=cat("wall_time"),
                     latency_s=cat("latency_s"), complete=cat("complete"), readings=cat("readings"),
                     valid=cat("valid"), status=cat("status"), estimates=est, raw=raw, sync=cat("sync"),
                     contacts=[c for p in parts for c in p.contacts], message_counts=counts,
                     truncated=any(p.truncated for p in parts), metadata={**first.metadata, **last.metadata},
                     gyro=cat_imu("gyro"), mag=cat_imu("mag"), sample_time_s=cat_imu("sample_time_s"))


def _read_one(path, *, raw: bool = True) -> Recording:
    """`_read_unchecked`, every malformed record one ValueError (`host.record.mcap_read.malformed`)."""
    from host.record.mcap_read import malformed, malformed_errors
    try:
        return _read_unchecked(path, raw=raw)
    except malformed_errors() as exc:
        raise malformed(path, exc) from None


def _read_unchecked(path, *, raw: bool = True) -> Recording:
    from mcap.records import Attachment, Channel, DataEnd, Footer, Message, Metadata, Schema

    path = Path(path)
    with open_regular(path, "a recording (.mcap)") as f:
        if f.read(8) != b"\x89MCAP0\r\n":
            raise ValueError(f"{str(path)!r} is not an MCAP file (magic bytes missing)")
        f.seek(0)
        dec = _Decoder(str(path))
        meta: dict[str, dict] = {}
        attachments: dict = {}
        counts: dict[str, int] = {}
        snaps: list[dict] = []
        ests: list = []
        raws: dict[int, list] = {}
        syncs: list[tuple[int, float]] = []
        contacts: list = []
        ended = False
        gen = _iter_records(f)
        while True:
            try:
                rec = next(gen)
            except StopIteration as stop:
                truncated = bool(stop.value) or not ended
                break
            if isinstance(rec, Message):
                topic = dec.topic.get(rec.channel_id, "?")
                counts[topic] = counts.get(topic, 0) + 1
                if topic == TOPIC_SNAPSHOT:
                    snaps.append(dec.snapshot(rec))
                elif topic == TOPIC_ESTIMATE:
                    ests.append(rec)  # decoded once the lattice is known
                elif topic == TOPIC_SYNC:
                    syncs.append(dec.sync(rec))
                elif topic == TOPIC_CONTACTS:
                    d = loads_json(rec.data, f"{path}: {TOPIC_CONTACTS}")
                    contacts.append((d["counter"], d["timestamp"], d["contacts"]))
                elif raw and topic.startswith("/capsheet/raw/bus"):
                    bus, t, kind, payload = dec.raw(rec)
                    raws.setdefault(bus, []).append((t, kind, payload))
            elif isinstance(rec, Channel):
                dec.channel(rec)
            elif isinstance(rec, Schema):
                dec.schema(rec)
            elif isinstance(rec, Metadata):
                meta[rec.name] = {k: loads_json(v, f"{path}: metadata {rec.name}") for k, v in rec.metadata.items()}
            elif isinstance(rec, Attachment):
                attachments[rec.name] = _attachment(rec)
            elif isinstance(rec, (DataEnd, Footer)):
                ended = True
    if "capsheet.session" not in meta:
        if truncated:
            raise ValueError(f"{str(path)!r} was cut short before its 'capsheet.session' metadata: nothing to read")
        raise ValueError(f"{str(path)!r} is not a capsheet recording (no 'capsheet.session' metadata)")
    session = {**meta["capsheet.session"], **meta.get("capsheet.host", {})}
    from host.record.mcap_read import check_session
    rows, cols, _ = check_session(session, path)  # before anything is sized by the lattice
    ests = [dec.estimate(e, rows, cols) for e in ests]
    b = _snapshot_batch(session, snaps, _Counts(int(session["n_links"]), attachments))
    est: dict[str, np.ndarray] = {
        "counter": np.array([e["counter"] for e in ests], dtype=np.uint16),
        "timestamp": np.array([e["timestamp"] for e in ests], dtype=np.float64),
        "joints": (np.stack([e["joints"] for e in ests]) if ests
                   else np.zeros((0, rows, cols, 3), dtype=np.float32))}
    for name in ("yaw_std", "joint_std"):  # NaN rows where an estimate carried none (live: ~1/s)
        have = [e.get(name) for e in ests]
        shape = next((v.shape for v in have if v is not None), None)
        if shape is not None:
            est[name] = np.stack([v if v is not None else np.full(shape, np.nan, np.float32) for v in have])
    if ests and all("error_pct_side" in e for e in ests):
        est["error_pct_side"] = np.array([e["error_pct_side"] for e in ests])
    return Recording(
        session=session, attachments=attachments,
        counter=b.counter, timestamp=b.timestamp, wall_time=b.wall_time,
        latency_s=np.array([s["latency_s"] for s in snaps], dtype=np.float64),
        complete=np.array([s["complete"] for s in snaps], dtype=bool),
        readings=b.readings, valid=b.valid, status=b.status, estimates=est, raw=raws,
        sync=np.array(syncs, dtype=np.float64).reshape(-1, 2), contacts=contacts, message_counts=counts,
        truncated=truncated, metadata=meta, gyro=b.gyro, mag=b.mag, sample_time_s=b.sample_time_s)


def _imu_arrays(snaps: list[dict], n_links: int) -> dict:
    """The recorded IMU axes as arrays over the snapshots (NaN rows where one had none), or None."""
    out = {}
    for name, shape in (("gyro", (n_links, 3)), ("mag", (n_links, 3)), ("sample_time_s", (n_links,))):
        have = [s.get(name) for s in snaps]
        if any(v is not None for v in have):
            out[name] = np.stack([v if v is not None else np.full(shape, np.nan, np.float32) for v in have])
    return out


@dataclass
class SnapshotBatch:
    """Consecutive recorded snapshots (`iter_snapshots`): arrays with a leading axis of ``len(batch)``."""

    session: dict  #: the ``capsheet.session`` metadata (rows, cols, n_links, link_length_m, ...)
    counter: np.ndarray  #: (b,) uint16
    timestamp: np.ndarray  #: (b,) float64, host monotonic s
    wall_time: np.ndarray  #: (b,) float64, unix s
    readings: np.ndarray  #: (b, n_links, 3) float32, m/s^2
    valid: np.ndarray  #: (b, n_links) bool
    status: np.ndarray  #: (b, n_links) uint8
    #: 6/9-axis chips (docs/protocol.md §16), as `Recording`'s: (b, n_links, 3) rad/s, (b, n_links, 3) T,
    #: (b, n_links) s after the SYNC, float32, NaN where a snapshot had none; None when none in the batch had them
    gyro: np.ndarray | None = None
    mag: np.ndarray | None = None
    sample_time_s: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.counter.shape[0])


def snapshot_count(path) -> int | None:
    """How many snapshots a cleanly closed recording holds (from its summary, without reading the
    data), or None when the file has no summary (a killed writer). A split set: the sum over its
    files (None if any has no summary)."""
    counts = [_snapshot_count_one(p) for p in _paths(path)]
    return None if any(c is None for c in counts) else sum(counts)


def _snapshot_count_one(path) -> int | None:
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    try:
        with open_regular(path, "a recording (.mcap)") as f:
            summary = make_reader(f).get_summary()
    except (McapError, OSError, EOFError, ValueError, struct.error, KeyError, UnicodeDecodeError, MemoryError):
        return None
    if summary is None or summary.statistics is None:
        return None
    ids = [c.id for c in summary.channels.values() if c.topic == TOPIC_SNAPSHOT]
    return sum(summary.statistics.channel_message_counts.get(i, 0) for i in ids)


def iter_snapshots(path, batch: int = 256) -> Iterator[SnapshotBatch]:
    """The recorded snapshots of a capsheet MCAP, ``batch`` at a time, as the file is read: a long
    recording is never in memory whole, and its first batches can be worked on while the rest is
    read (``capsheet estimate``). The same snapshots, in the same order, as `read` (a file cut short
    included); raw input, estimates and contacts are skipped.

    A split set (``path`` a list, or the name it was recorded under) is read file after file.

    Raises
    ------
    ValueError
        Not MCAP, not a capsheet recording, or ``batch`` < 1.
    """
    if int(batch) < 1:
        raise ValueError(f"batch must be >= 1, got {batch!r}")
    for p in _paths(path):
        yield from _iter_snapshots_one(p, batch)


def _iter_snapshots_one(path, batch: int) -> Iterator[SnapshotBatch]:
    """`_iter_snapshots_unchecked`, every malformed record one ValueError."""
    from host.record.mcap_read import malformed, malformed_errors
    try:
        yield from _iter_snapshots_unchecked(path, batch)
    except malformed_errors() as exc:
        raise malformed(path, exc) from None


def _iter_snapshots_unchecked(path, batch: int) -> Iterator[SnapshotBatch]:
    from mcap.records import Attachment, Channel, Message, Metadata, Schema

    path = Path(path)
    with open_regular(path, "a recording (.mcap)") as f:
        if f.read(8) != b"\x89MCAP0\r\n":
            raise ValueError(f"{str(path)!r} is not an MCAP file (magic bytes missing)")
        f.seek(0)
        dec = _Decoder(str(path))
        snap_channels: set[int] = set()
        session: dict | None = None
        attachments: dict = {}
        conv = None
        pending: list[dict] = []
        for rec in _iter_records(f):
            if isinstance(rec, Message):
                if rec.channel_id in snap_channels:
                    pending.append(dec.snapshot(rec))
                    # counts wait for the calibration (attached after bring-up) before they convert
                    if (session is not None and len(pending) >= batch
                            and (pending[-1]["counts"] is None or "calibration.json" in attachments)):
                        conv = conv or _Counts(int(session["n_links"]), attachments)
                        yield _snapshot_batch(session, pending, conv)
                        pending = []
            elif isinstance(rec, Channel):
                dec.channel(rec)
                if rec.topic == TOPIC_SNAPSHOT:
                    snap_channels.add(rec.id)
            elif isinstance(rec, Schema):
                dec.schema(rec)
            elif isinstance(rec, Attachment) and rec.name in ("calibration.json", HOST_CALIBRATION):
                attachments[rec.name] = _attachment(rec)
                conv = None
            elif isinstance(rec, Metadata) and rec.name == "capsheet.session":
                session = {k: loads_json(v, f"{path}: metadata capsheet.session") for k, v in rec.metadata.items()}
                from host.record.mcap_read import check_session
                check_session(session, path)  # before anything is sized by the lattice
    if session is None:
        raise ValueError(f"{str(path)!r} is not a capsheet recording, or was cut short before its "
                         f"'capsheet.session' metadata (nothing to read)")
    conv = conv or _Counts(int(session["n_links"]), attachments)
    for k in range(0, len(pending), batch):
        yield _snapshot_batch(session, pending[k:k + batch], conv)


def _snapshot_batch(session: dict, snaps: list[dict], conv: "_Counts") -> SnapshotBatch:
    n, n_links = len(snaps), int(session["n_links"])
    readings = np.empty((n, n_links, 3), dtype=np.float32)
    valid = np.empty((n, n_links), dtype=bool)
    status = np.empty((n, n_links), dtype=np.uint8)
    for k, s in enumerate(snaps):
        if np.shape(s["valid"]) != (n_links,) or np.shape(s["status"]) != (n_links,):
            raise ValueError(f"a snapshot of {np.shape(s['valid'])[0] if np.ndim(s['valid']) else '?'} links in a "
                             f"recording of {n_links}")
        valid[k] = s["valid"]
        status[k] = s["status"]
        readings[k] = s["readings"] if s["counts"] is None else conv(s["counts"], s["valid"])
    return SnapshotBatch(session, np.array([s["counter"] for s in snaps], dtype=np.uint16),
                         np.array([s["timestamp"] for s in snaps], dtype=np.float64),
                         np.array([s["wall_time"] for s in snaps], dtype=np.float64), readings, valid, status,
                         **_imu_arrays(snaps, n_links))


#: the name docs and older code used
read_recording = read
