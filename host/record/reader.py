"""Reading a recording (docs/recording.md): `read` (everything, in memory), `iter_snapshots` and
`snapshot_count` (snapshots in batches, bounded memory), for a file or a split set, every format
capsheet wrote (``capsheet-mcap-1`` JSON, ``capsheet-mcap-2`` protobuf, compact raw input). Files
from elsewhere are read within the format's limits (`host.record.mcap_read`)."""

from __future__ import annotations

import base64
import json
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import logging

import numpy as np

from protocol.files import loads_json, open_regular

log = logging.getLogger("capsheet.host.record")

from host.record.channels import (HOST_CALIBRATION, TOPIC_CONTACTS, TOPIC_ESTIMATE, TOPIC_SNAPSHOT, TOPIC_SYNC,
    recording_set, unarr)


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
                    "latency_s": d["latency_s"], "complete": d["complete"], "readings": unarr(d["readings"]),
                    "counts": None, "valid": unarr(d["valid"]).astype(bool), "status": unarr(d["status"])}
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
            out = {"counter": d["counter"], "timestamp": d["timestamp"], "joints": unarr(d["joints"])}
            for name in ("yaw_std", "joint_std"):
                if name in d:
                    out[name] = unarr(d[name])
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
