"""Recordings in MCAP (docs/recording.md): what a session receives, aggregates and estimates, in a
file that robotics tools read (Foxglove, the ``mcap`` CLI and libraries, RViz via mcap plugins).

One `Recorder` publishes a session's data on `foxglove.Channel` s of one `foxglove.Context`; its
sinks are an MCAP file (``path``), a live Foxglove WebSocket server (``host.live``), or both, so the
file and the live view carry the very same messages. The writer is foxglove-sdk's (Rust, chunked,
zstd); a chunk is closed every ``flush_interval_s``, so a killed host leaves a file that `read`
(and any MCAP stream reader) reads up to its last finished chunk.

Topics (capsheet's own are JSON with a JSON Schema, the encoding Foxglove plots natively; bulky
arrays are base64 of little-endian arrays, dtype and shape given in the message):

==========================  ===================  =================================================
topic                       schema               content
==========================  ===================  =================================================
``/capsheet/raw/bus{N}``    capsheet.RawSerial   wire bytes of bus N as read (serial, pty, memory);
                                                 ``t`` when ingested, ``t_rx`` when read
                            capsheet.RawCan      CAN frames of bus N as received (one batch)
``/capsheet/sync``          capsheet.Sync        the host opened SYNC ``counter`` at ``t``
``/capsheet/snapshot``      capsheet.Snapshot    counter, readings (n_links, 3) m/s², valid, status
``/capsheet/estimate``      capsheet.Estimate    joints (rows, cols, 3) m; ``yaw_std`` (n_links,)
                                                 rad and ``joint_std`` (rows, cols, 3) m when the
                                                 estimator provides them; error vs truth if known
``/capsheet/contacts``      capsheet.Contacts    tactile contacts: position, force, radius, id
``/sheet/scene``            foxglove.SceneUpdate the lattice as a coloured line list, contacts
``/sheet/joints``           foxglove.PointCloud  the estimated joints (x, y, z float32, m)
``/tf``                     foxglove.FrameTransform  ``world`` -> ``sheet`` (identity)
==========================  ===================  =================================================

Every message's log time is the host's wall clock (ns since the Unix epoch); ``t`` fields inside
are the host's monotonic clock (s), the clock `host.aggregator.LatticeSnapshot.timestamp` uses.
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
import threading
import time
from dataclasses import dataclass, field
from importlib import metadata as _md
from pathlib import Path
from typing import Any, Callable, Iterator

import logging

import numpy as np

log = logging.getLogger("capsheet.host.record")

__all__ = ["Recorder", "Recording", "read", "read_recording", "iter_snapshots", "SnapshotBatch", "snapshot_count",
           "tap_transport", "versions",
           "TOPIC_RAW", "TOPIC_SYNC", "TOPIC_SNAPSHOT", "TOPIC_ESTIMATE", "TOPIC_CONTACTS", "FORMAT"]

FORMAT = "capsheet-mcap-1"
#: Attachment: the host-side calibration (``capsheet host --calibration``, `host.analysis.calibration`
#: format, rebased to the chips' own) applied to every recorded snapshot; replay applies it too.
HOST_CALIBRATION = "host_calibration.json"
TOPIC_RAW = "/capsheet/raw/bus{}"
TOPIC_SYNC = "/capsheet/sync"
TOPIC_SNAPSHOT = "/capsheet/snapshot"
TOPIC_ESTIMATE = "/capsheet/estimate"
TOPIC_CONTACTS = "/capsheet/contacts"


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
    return np.frombuffer(base64.b64decode(d["data"]), dtype=np.dtype(d["dtype"])).reshape(d["shape"])


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
}


# --------------------------------------------------------------------------------------------
# Raw taps
# --------------------------------------------------------------------------------------------

def tap_transport(transport, on_raw: Callable[[str, Any], None]) -> Callable:
    """Call ``on_raw(kind, payload)`` with a transport's wire input as it is received: ``kind``
    ``"serial"`` (payload: the bytes read) or ``"can"`` (payload: the frames of one receive, one
    by one: python-can messages, and `host.transport.RawFrame` s for the rows of an SLCAN bus's
    `protocol.can.FrameBlock`). A capture handler (`host.transport.Transport.begin_capture`);
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


def _can_frame_dict(m) -> dict:
    """A received frame (python-can message or `host.transport.RawFrame`) as the recording stores it."""
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
        A live server on this recorder's context (`host.live.start`); stopped by `close`.
    colour_by : {"error", "displacement", "links"}
        What colours the lattice in ``/sheet/scene`` (docs/recording.md).
    flush_interval_s : float
        A chunk is closed at least this often (what a killed host can lose).
    chunk_size : int
        Target uncompressed chunk size, bytes.
    """

    def __init__(self, path, lattice, link_length: float, *, session: dict | None = None,
                 layout: dict | None = None, calibration: dict | None = None, live_port: int | None = None,
                 live_host: str = "127.0.0.1", colour_by: str = "links", flush_interval_s: float = 1.0,
                 chunk_size: int = 1 << 20) -> None:
        import foxglove
        from foxglove.mcap import MCAPWriteOptions

        from host.live import SceneChannels

        if path is None and live_port is None:
            raise ValueError("Recorder needs a path, a live_port, or both")
        if not (np.isfinite(link_length) and link_length > 0):
            raise ValueError(f"Invalid link_length: {link_length!r} (need a finite value > 0 m)")
        self.path = None if path is None else Path(path)
        self.lattice = lattice
        self.link_length = float(link_length)
        self.flush_interval_s = float(flush_interval_s)
        self.counts: dict[str, int] = {}
        self.context = foxglove.Context()
        self._lock = threading.Lock()
        self._last_flush = time.monotonic()
        self._closed = False
        self._writer = None
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            opts = MCAPWriteOptions(chunk_size=int(chunk_size), compression_threads=0, profile="")
            self._writer = foxglove.open_mcap(str(self.path), allow_overwrite=True, context=self.context,
                                              writer_options=opts)
        self._schemas = {name: foxglove.Schema(name=name, encoding="jsonschema", data=json.dumps(s).encode())
                         for name, s in SCHEMAS.items()}
        self._channels: dict[str, Any] = {}
        self.scene = SceneChannels(self.context, lattice, colour_by=colour_by)
        for topic, schema in ((TOPIC_SNAPSHOT, "capsheet.Snapshot"), (TOPIC_ESTIMATE, "capsheet.Estimate")):
            self._channel(topic, schema)  # advertised from the start (a live client sees them at once)
        self.session = {"format": FORMAT, "rows": lattice.rows, "cols": lattice.cols, "n_links": lattice.n_links,
                        "link_length_m": self.link_length, "started_unix_s": time.time(),
                        "versions": versions(), **(session or {})}
        if self._writer is not None:
            self._writer.write_metadata("capsheet.session", {k: json.dumps(v) for k, v in self.session.items()})
            now = time.time_ns()
            for name, doc in (("layout.json", layout), ("calibration.json", calibration)):
                if doc is not None:
                    self._writer.attach(log_time=now, create_time=now, name=name, media_type="application/json",
                                        data=json.dumps(doc, indent=1).encode())
        self.live = None
        if live_port is not None:
            from host.live import LiveServer
            self.live = LiveServer(self.context, port=live_port, host=live_host,
                                   name=f"capsheet {lattice.rows}x{lattice.cols}")
        self.scene.log_transform(time.time_ns())

    # -- channels ------------------------------------------------------------------------------
    def _channel(self, topic: str, schema: str):
        ch = self._channels.get(topic)
        if ch is None:
            import foxglove
            with self._lock:
                ch = self._channels.get(topic)
                if ch is None:
                    ch = foxglove.Channel(topic, schema=self._schemas[schema], message_encoding="json",
                                          context=self.context)
                    self._channels[topic] = ch
        return ch

    def _log(self, topic: str, schema: str, msg: dict, log_time_ns: int | None = None) -> None:
        if self._closed:
            return
        self._channel(topic, schema).log(json.dumps(msg, separators=(",", ":")).encode(),
                                         log_time=time.time_ns() if log_time_ns is None else int(log_time_ns))
        self.counts[topic] = self.counts.get(topic, 0) + 1
        if self._writer is not None and time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()

    # -- what a session publishes ------------------------------------------------------------------
    def tap(self, transports, feed=None) -> None:
        """Record every transport's raw input (its capture, `host.transport.Transport.begin_capture`),
        bus index = position in the list.

        With ``feed`` (the `host.feed.SnapshotFeed` the transports' events go into, as
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
        head = {"bus": bus, "port": port, "t": t, "t_rx": t if t_rx is None else t_rx}
        if kind == "can":
            self._log(topic, "capsheet.RawCan", {**head, "frames": [_can_frame_dict(m) for m in payload]},
                      log_time_ns)
        elif kind == "serial":
            self._log(topic, "capsheet.RawSerial", {**head, "data": base64.b64encode(payload).decode()},
                      log_time_ns)
        else:
            raise ValueError(f"Invalid raw kind: {kind!r} (need 'serial' or 'can')")

    def sync(self, counter: int, t: float) -> None:
        """The host opened SYNC ``counter`` at host monotonic ``t`` (replay re-opens it there)."""
        self._log(TOPIC_SYNC, "capsheet.Sync", {"counter": int(counter), "t": float(t)})

    def tap_sync(self, feed) -> None:
        """Record every counter the host opens (`host.feed.SnapshotFeed.add_open_listener`)."""
        feed.add_open_listener(self.sync)

    def snapshot(self, snap) -> None:
        """One `host.aggregator.LatticeSnapshot`."""
        self._log(TOPIC_SNAPSHOT, "capsheet.Snapshot", {
            "counter": int(snap.counter), "timestamp": float(snap.timestamp), "wall_time": float(snap.wall_time),
            "latency_s": float(snap.latency_s), "complete": bool(snap.complete),
            "readings": _arr(snap.readings, "<f4"), "valid": _arr(snap.valid, "|u1"),
            "status": _arr(snap.status, "|u1")}, _wall_ns(snap.wall_time))

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
        msg = {"counter": int(counter), "timestamp": float(timestamp), "method": str(getattr(est, "method", "")),
               "residual": float(getattr(est, "residual", np.nan)), "iterations": int(getattr(est, "iterations", 0)),
               "joints": _arr(est.joints, "<f4")}
        for name in ("yaw_std", "joint_std"):
            if not (uncertainty or name in getattr(est, "__dict__", {})):
                continue  # a lazy property not yet computed: not computed here unasked
            v = getattr(est, name, None)
            if v is not None:
                msg[name] = _arr(v, "<f4")
        if error_pct_side is not None:
            msg["error_pct_side"] = float(error_pct_side)
        self._log(TOPIC_ESTIMATE, "capsheet.Estimate", msg, t_ns)
        if not self._closed:
            self.scene.log_lattice(est.joints, np.asarray(est.valid, dtype=bool), t_ns,
                                   error=error_joint, displacement=displacement)

    def contacts(self, counter: int, timestamp: float, contacts: list[dict], wall_time: float | None = None) -> None:
        """Tactile contacts of one frame: dicts with ``id``, ``index`` (i, j), ``position`` (x, y, z) m,
        ``force_n``, ``radius_m``; shown as spheres with their force in ``/sheet/scene``."""
        t_ns = _wall_ns(wall_time)
        self._log(TOPIC_CONTACTS, "capsheet.Contacts", {"counter": int(counter), "timestamp": float(timestamp),
                                                        "contacts": contacts}, t_ns)
        if not self._closed:
            self.scene.log_contacts(contacts, t_ns)

    def add_host_facts(self, host) -> None:
        """After bring-up: metadata ``capsheet.host`` (rate, sync, deadline, transports) and the
        ``layout.json`` / ``calibration.json`` attachments (what replay rebuilds the aggregator from)."""
        if self._writer is None or self._closed:
            return
        session, layout, calibration = self.session_facts(host)
        self.session.update(session)
        self._writer.write_metadata("capsheet.host", {k: json.dumps(v) for k, v in session.items()})
        now = time.time_ns()
        docs = [("layout.json", layout), ("calibration.json", calibration)]
        live_cal = host.calibration
        if live_cal is not None:  # `capsheet host --calibration`: what the snapshots were corrected with
            docs.append((HOST_CALIBRATION, live_cal.to_dict()))
        for name, doc in docs:
            self._writer.attach(log_time=now, create_time=now, name=name, media_type="application/json",
                                data=json.dumps(doc, indent=1).encode())

    # -- lifetime ------------------------------------------------------------------------------
    def flush(self) -> None:
        """Close the current chunk and push it to the OS (a kill after this loses nothing before)."""
        if self._writer is not None and not self._closed:
            self._writer.flush()
        self._last_flush = time.monotonic()

    def close(self, stats: dict | None = None) -> None:
        """Attach ``stats.json`` (if given), write the summary, stop the live server. Idempotent."""
        if self._closed:
            return
        for bus in list(getattr(self, "_pending", {})):
            self._write_pending(bus, None)  # read but never ingested (the session ended)
        if self._writer is not None:
            if stats is not None:
                now = time.time_ns()
                self._writer.attach(log_time=now, create_time=now, name="stats.json", media_type="application/json",
                                    data=json.dumps(stats, indent=1, default=_jsonable).encode())
            self._writer.write_metadata("capsheet.end", {"finished_unix_s": json.dumps(time.time()),
                                                         "counts": json.dumps(self.counts)})
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
        """``(session, layout, calibration)`` of a `host.session.Host` after bring-up."""
        chips = sorted((r for r in host.chips.values() if r.assigned and r.link is not None), key=lambda r: r.link)
        layout = {"format": "capsheet-layout", "version": 1, "rows": host.lattice.rows, "cols": host.lattice.cols,
                  "chips": [{"uid": f"0x{r.uid:016X}", "link": int(r.link)} for r in chips]}
        calibration = {"range_code": int(host.range_code), "units": {"offset": "ADC counts", "sensitivity": "counts/g"},
                       "links": [{"link": int(r.link), "uid": f"0x{r.uid:016X}", "node": int(r.node), "bus": int(r.bus),
                                  "offset": [float(v) for v in r.offset],
                                  "sensitivity": [float(v) for v in r.sensitivity],
                                  "calibrated": bool(r.calibrated)} for r in chips]}
        session = {"rate_hz": host.rate_hz, "sync": host.sync_mode, "deadline_s": host.aggregator.deadline_s,
                   "transports": [{"name": t.name, "kind": t.capabilities.kind, "fd": t.capabilities.fd,
                                   "bitrate": t.capabilities.bitrate} for t in host.transports]}
        return session, layout, calibration


def _raw_payload(cap):
    """What `Recorder.raw` records of a received `host.transport.Capture`: the bytes, or every
    frame as received (echoes too: the recording holds the wire)."""
    return cap.frames(echoes=True) if cap.kind == "can" else cap.raw


def _wall_ns(wall_time: float | None) -> int:
    return time.time_ns() if wall_time is None or not np.isfinite(wall_time) else int(round(wall_time * 1e9))


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
        `host.aggregator.LinkFlag` bits.
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

    def __len__(self) -> int:
        return int(self.counter.shape[0])

    @property
    def lattice(self):
        from protocol.lattice import Lattice
        return Lattice(int(self.session["rows"]), int(self.session["cols"]))


def _iter_records(f):
    """MCAP records of a file in order, stopping cleanly where a killed writer left off.
    Yields records; returns True (as ``StopIteration.value``) if the file was cut short."""
    import struct

    from mcap.exceptions import McapError
    from mcap.stream_reader import StreamReader

    reader = StreamReader(f, skip_magic=False, emit_chunks=False)
    try:
        for rec in reader.records:
            yield rec
    except (McapError, EOFError, struct.error) as exc:  # a record or chunk cut in the middle
        log.info("%s: cut short (%s); read up to the last whole chunk", getattr(f, "name", "?"), exc)
        return True
    return False


def read(path, *, raw: bool = True) -> Recording:
    """Read a capsheet MCAP recording into numpy arrays (tolerates a file cut short).

    Parameters
    ----------
    path : str or Path
    raw : bool
        Also decode the raw wire input (slower for long recordings).

    Raises
    ------
    ValueError
        The file is not MCAP, or not a capsheet recording (no ``capsheet.session`` metadata).
    """
    from mcap.records import Attachment, Channel, DataEnd, Footer, Message, Metadata, Schema

    path = Path(path)
    with open(path, "rb") as f:
        if f.read(8) != b"\x89MCAP0\r\n":
            raise ValueError(f"{str(path)!r} is not an MCAP file (magic bytes missing)")
        f.seek(0)
        channels: dict[int, str] = {}
        meta: dict[str, dict] = {}
        attachments: dict = {}
        counts: dict[str, int] = {}
        snaps: list[dict] = []
        ests: list[dict] = []
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
            if isinstance(rec, Channel):
                channels[rec.id] = rec.topic
            elif isinstance(rec, Message):
                topic = channels.get(rec.channel_id, "?")
                counts[topic] = counts.get(topic, 0) + 1
                if topic == TOPIC_SNAPSHOT:
                    snaps.append(json.loads(rec.data))
                elif topic == TOPIC_ESTIMATE:
                    ests.append(json.loads(rec.data))
                elif topic == TOPIC_SYNC:
                    d = json.loads(rec.data)
                    syncs.append((d["counter"], d["t"]))
                elif topic == TOPIC_CONTACTS:
                    d = json.loads(rec.data)
                    contacts.append((d["counter"], d["timestamp"], d["contacts"]))
                elif raw and topic.startswith("/capsheet/raw/bus"):
                    d = json.loads(rec.data)
                    if "frames" in d:
                        raws.setdefault(d["bus"], []).append((d["t"], "can", d["frames"]))
                    else:
                        raws.setdefault(d["bus"], []).append((d["t"], "serial", base64.b64decode(d["data"])))
            elif isinstance(rec, Metadata):
                meta[rec.name] = {k: json.loads(v) for k, v in rec.metadata.items()}
            elif isinstance(rec, Attachment):
                try:
                    attachments[rec.name] = json.loads(rec.data)
                except ValueError:
                    attachments[rec.name] = bytes(rec.data)
            elif isinstance(rec, (DataEnd, Footer)):
                ended = True
            elif isinstance(rec, Schema):
                pass
    if "capsheet.session" not in meta:
        if truncated:
            raise ValueError(f"{str(path)!r} was cut short before its 'capsheet.session' metadata: nothing to read")
        raise ValueError(f"{str(path)!r} is not a capsheet recording (no 'capsheet.session' metadata)")
    session = {**meta["capsheet.session"], **meta.get("capsheet.host", {})}
    rows, cols = int(session["rows"]), int(session["cols"])
    b = _snapshot_batch(session, snaps)
    est: dict[str, np.ndarray] = {
        "counter": np.array([e["counter"] for e in ests], dtype=np.uint16),
        "timestamp": np.array([e["timestamp"] for e in ests], dtype=np.float64),
        "joints": (np.stack([_unarr(e["joints"]) for e in ests]) if ests
                   else np.zeros((0, rows, cols, 3), dtype=np.float32))}
    for name in ("yaw_std", "joint_std"):  # NaN rows where an estimate carried none (live: ~1/s)
        have = [_unarr(e[name]) if name in e else None for e in ests]
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
        truncated=truncated, metadata=meta)


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

    def __len__(self) -> int:
        return int(self.counter.shape[0])


def snapshot_count(path) -> int | None:
    """How many snapshots a cleanly closed recording holds (from its summary, without reading the
    data), or None when the file has no summary (a killed writer)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except (McapError, OSError, EOFError, ValueError):
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

    Raises
    ------
    ValueError
        Not MCAP, not a capsheet recording, or ``batch`` < 1.
    """
    from mcap.records import Channel, Message, Metadata

    if int(batch) < 1:
        raise ValueError(f"batch must be >= 1, got {batch!r}")
    path = Path(path)
    with open(path, "rb") as f:
        if f.read(8) != b"\x89MCAP0\r\n":
            raise ValueError(f"{str(path)!r} is not an MCAP file (magic bytes missing)")
        f.seek(0)
        snap_channels: set[int] = set()
        session: dict | None = None
        pending: list[dict] = []
        for rec in _iter_records(f):
            if isinstance(rec, Message):
                if rec.channel_id in snap_channels:
                    pending.append(json.loads(rec.data))
                    if session is not None and len(pending) >= batch:
                        yield _snapshot_batch(session, pending)
                        pending = []
            elif isinstance(rec, Channel):
                if rec.topic == TOPIC_SNAPSHOT:
                    snap_channels.add(rec.id)
            elif isinstance(rec, Metadata) and rec.name == "capsheet.session":
                session = {k: json.loads(v) for k, v in rec.metadata.items()}
    if session is None:
        raise ValueError(f"{str(path)!r} is not a capsheet recording, or was cut short before its "
                         f"'capsheet.session' metadata (nothing to read)")
    for k in range(0, len(pending), batch):
        yield _snapshot_batch(session, pending[k:k + batch])


def _snapshot_batch(session: dict, snaps: list[dict]) -> SnapshotBatch:
    n, n_links = len(snaps), int(session["n_links"])
    readings = np.empty((n, n_links, 3), dtype=np.float32)
    valid = np.empty((n, n_links), dtype=bool)
    status = np.empty((n, n_links), dtype=np.uint8)
    for k, s in enumerate(snaps):
        readings[k] = _unarr(s["readings"])
        valid[k] = _unarr(s["valid"]).astype(bool)
        status[k] = _unarr(s["status"])
    return SnapshotBatch(session, np.array([s["counter"] for s in snaps], dtype=np.uint16),
                         np.array([s["timestamp"] for s in snaps], dtype=np.float64),
                         np.array([s["wall_time"] for s in snaps], dtype=np.float64), readings, valid, status)


#: the name docs and older code used
read_recording = read
