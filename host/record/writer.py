"""Writing a recording (docs/recording.md): `Recorder` (raw input through each transport's capture,
SYNCs, snapshots, estimates, contacts, the 3D scene; split files; the live view beside it) and
`tap_transport`. The channels it writes are `host.record.channels`'."""

from __future__ import annotations

import base64
import json
import shutil
import threading
import time
from pathlib import Path
from typing import Any, Callable

import logging

import numpy as np


log = logging.getLogger("capsheet.host.record")

from host.record.channels import (FORMAT, HOST_CALIBRATION, SCHEMAS, TOPIC_CONTACTS, TOPIC_ESTIMATE, TOPIC_IMU,
    TOPIC_RAW, TOPIC_SNAPSHOT, TOPIC_SYNC, packed_float, packed_sint32, split_path, versions)


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
#: ~4 % larger (benchmarks/bench_record_compression.py; whole 64x64 recordings ~7 %). Level 1: the
#: compression alone ~0.09 ms per SYNC of that input against ~0.26 at level 3 (a third), for a raw
#: channel ~2 % larger (0.757 of the input against 0.742: the counts' noise does not compress)
COMPRESSION_LEVEL_LARGE = 1
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
        while they hold the feed's (a following host's first second stalled on it)."""
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
        self._tap = InputTap(transports, feed, self.raw)  # `raw` records no port name: the bus index says it

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
        extra = []
        for name, number in (("gyro", 11), ("mag", 12), ("sample_time_s", 13)):  # 6/9-axis chips (§16)
            v = getattr(snap, name, None)
            if v is not None:
                extra.append(packed_float(number, v))
        extra = b"".join(extra)
        # the packed fields appended to the rest, wire-encoded: protobuf merges concatenated
        # messages, so this is the same message without parsing 24,192 counts back in and out
        # (a 64x64 snapshot: 0.39 instead of 0.67 ms, in the receive path)
        # the file holds the counts compact (docs/recording.md, "Size") unless a live view shares
        # the channel: a live client (Foxglove, a plot of the counts) reads them plain, as every
        # protobuf reader does, and one context takes one channel per topic
        compact = counts is not None and self.compact and self.path is not None and self.live is None
        plain = b""
        if not compact:  # (made only when it is written: a 64x64 snapshot's is ~1 ms)
            plain = (packed_sint32(7, np.asarray(counts, dtype=np.int16)) if counts is not None
                     else packed_float(8, snap.readings))
        with self._io:  # the counts' coder per file, as the raw input's
            if compact:
                from host.record.compact import CountsCoder
                msg.counts_planes = self._coder("snapshot", CountsCoder).encode(counts, valid)
            self._log(TOPIC_SNAPSHOT, "capsheet.v2.Snapshot", msg.SerializeToString() + plain + extra,
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
        live_cal = host.calibration  # `capsheet host --calibration`: what the snapshots were corrected with
        self.add_facts(session, layout, calibration, None if live_cal is None else live_cal.to_dict())

    def add_facts(self, session: dict, layout: dict, calibration: dict, live_cal: dict | None = None) -> None:
        """`add_host_facts` from facts already taken (`session_facts`; a writer process gets them from
        the host's process): the metadata, the attachments, and ``live_cal`` (the live calibration's
        dict) if any."""
        if self._writer is None or self._closed:
            return
        self.session.update(session)
        self._document("metadata", "capsheet.host", {k: json.dumps(v) for k, v in session.items()})
        docs = [("layout.json", layout), ("calibration.json", calibration)]
        if live_cal is not None:
            docs.append((HOST_CALIBRATION, live_cal))
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
        if getattr(self, "_tap", None) is not None:
            self._tap.flush()  # read but never ingested (the session ended)
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


class InputTap:
    """Every transport's received input (its capture, `host.transport.ports.Transport.begin_capture`)
    handed to ``write(bus, kind, payload, t=, log_time_ns=, t_rx=)``, bus index = position in the list:
    as read without ``feed``; with it, each chunk when its events are ingested (`Recorder.tap` says
    why), and `flush` hands over what was read but never ingested."""

    def __init__(self, transports, feed, write) -> None:
        self._write = write
        self._pending: dict[int, list] = {bus: [] for bus in range(len(transports))}
        for bus, t in enumerate(transports):
            if feed is None:
                t.begin_capture(lambda cap, bus=bus: cap.direction == "rx" and write(
                    bus, cap.kind, _raw_payload(cap), t=cap.timestamp, log_time_ns=int(cap.wall_time * 1e9),
                    t_rx=None))
            else:
                t.begin_capture(lambda cap, bus=bus: cap.direction == "rx" and self._pending[bus].append(
                    (cap.timestamp, int(cap.wall_time * 1e9), cap.kind, _raw_payload(cap))))
        if feed is not None:
            feed.add_ingest_listener(self._ingested)

    def _ingested(self, bus: int, now: float | None) -> None:
        pending = self._pending.get(bus)
        while pending:
            t_rx, wall_ns, kind, payload = pending.pop(0)
            self._write(bus, kind, payload, t=t_rx if now is None else now, log_time_ns=wall_ns, t_rx=t_rx)

    def flush(self) -> None:
        for bus in self._pending:
            self._ingested(bus, None)


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
