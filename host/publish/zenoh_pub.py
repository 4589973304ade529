"""Publishing a sheet to Zenoh: `ZenohPublisher` (``--publish zenoh[:ENDPOINT]``, docs/distribution.md).

Per sheet, under ``capsheet/<sheet>/``:

* ``snapshot``: every snapshot the host emits, corrected (a `host.snapshots.feed.SnapshotFeed` listener:
  consumers that fall behind never make it skip one), `encode_snapshot`;
* ``estimate``: every shape estimate the session makes (``--live-rate`` per second), joints and,
  when computed (about once a second), their uncertainty, `encode_estimate`;
* ``contacts``: ``capsheet tactile``'s contacts and forces, JSON, one per tactile frame (`contacts`);
* ``health``: the host's summary (completeness, errors, missing links), JSON, about once a second;
* ``info`` (queryable): lattice, link length, layout and calibration, JSON — a late subscriber asks
  for it (``session.get("capsheet/<sheet>/info")``).

The binary payloads are little-endian, a 40-byte header then arrays (docs/distribution.md has the
layout; `decode_snapshot` / `decode_estimate` read them back, checking every size first). Without an
ENDPOINT the session stays on loopback (127.0.0.1 only, no multicast scouting; the processes of one
machine meet at ``tcp/127.0.0.1:7447``); with an ENDPOINT (a Zenoh locator such as
``tcp/10.0.0.2:7447``) client mode, connected to that router; a Zenoh config file for anything else
(TLS, user and password, access control): `host.publish.zenoh_session`.
"""

from __future__ import annotations

import json
import re
import struct
import threading
import time

import numpy as np

__all__ = ["ZenohPublisher", "parse_publish", "PUBLISH_KINDS", "LOCATOR", "encode_snapshot", "encode_estimate", "decode_snapshot",
           "decode_estimate", "encode_no_estimate", "FLAG_UNCERTAINTY", "FLAG_NOT_ESTIMATED", "SNAP_GYRO", "SNAP_MAG",
           "SNAP_SAMPLE_TIME", "KINDS", "HEADER", "PAYLOAD_VERSION", "MAX_PAYLOAD_BYTES", "check_lattice",
           "MAX_INFO_BYTES", "decode_info"]

#: ``(kind, version, rows, cols, n, flags, counter, timestamp, wall_time)``: see docs/distribution.md
HEADER = struct.Struct("<4sBBHHIHQdd")
assert HEADER.size == 40
PAYLOAD_VERSION = 1
KINDS = {"snapshot": b"CSNP", "estimate": b"CEST"}
#: estimate flag: a float32 joint_std (metres) per joint follows the joints
FLAG_UNCERTAINTY = 1
#: estimate flag: the snapshot could not be estimated (no valid link, every reading refused): joints NaN.
#: An estimate worker (`host.workers.distribute`) publishes one for every snapshot it takes, this one included.
FLAG_NOT_ESTIMATED = 2
#: the sheet name: one Zenoh key chunk (no ``/``, no wildcard or reserved characters)
SHEET_NAME = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")
HEALTH_PERIOD_S = 1.0


#: a Zenoh locator: ``<protocol>/<address>:<port>`` (or a unix socket path)
LOCATOR = re.compile(r"^(?:(?:tcp|udp|tls|quic|ws)/\S+:\d{1,5}|unixsock-stream/\S+)$")
#: what ``--publish`` takes: zenoh (capsheet's keys, this module) or ros2 (rmw_zenoh's layout, host/publish/ros2.py)
PUBLISH_KINDS = ("zenoh", "ros2")


def parse_publish(value: str) -> tuple[str, str | None]:
    """``zenoh``, ``ros2``, ``zenoh:ENDPOINT`` or ``ros2:ENDPOINT`` -> ``(kind, endpoint or None)``;
    ValueError otherwise."""
    kind, colon, endpoint = value.partition(":")
    if kind not in PUBLISH_KINDS:
        raise ValueError(f"unknown --publish {value!r}: give zenoh, ros2, zenoh:ENDPOINT or ros2:ENDPOINT "
                         f"(ENDPOINT a Zenoh locator, e.g. tcp/127.0.0.1:7447)")
    if colon and not LOCATOR.match(endpoint):
        raise ValueError(f"bad Zenoh endpoint {endpoint!r} in --publish {value!r}: a locator such as tcp/127.0.0.1:7447")
    return kind, endpoint or None


def _header(kind: str, rows: int, cols: int, n: int, flags: int, counter: int, timestamp: float,
            wall_time: float) -> bytes:
    wall = float(wall_time) if wall_time is not None and np.isfinite(wall_time) else float("nan")
    return HEADER.pack(KINDS[kind], PAYLOAD_VERSION, flags, rows, cols, n, 0, int(counter) & (2**64 - 1),
                       float(timestamp), wall)


#: snapshot flags: what follows ``status`` (6/9-axis chips, docs/protocol.md §16), each float32
SNAP_GYRO, SNAP_MAG, SNAP_SAMPLE_TIME = 1, 2, 4


def encode_snapshot(snap, rows: int, cols: int) -> bytes:
    """Header (n = links), then readings float32 (n, 3) in m/s² (specific force, sensor frame), then
    valid uint8 (n,), status uint8 (n,); then, for 6/9-axis chips, by the flags: gyro float32 (n, 3)
    rad/s (`SNAP_GYRO`), mag float32 (n, 3) tesla (`SNAP_MAG`), sample_time_s float32 (n,) seconds
    after the SYNC (`SNAP_SAMPLE_TIME`), NaN where a link sent no IMU record."""
    n = int(snap.readings.shape[0])
    flags, extra = 0, []
    for bit, name in ((SNAP_GYRO, "gyro"), (SNAP_MAG, "mag"), (SNAP_SAMPLE_TIME, "sample_time_s")):
        v = getattr(snap, name, None)
        if v is not None:
            flags |= bit
            extra.append(np.ascontiguousarray(v, dtype="<f4").tobytes())
    return b"".join((_header("snapshot", rows, cols, n, flags, snap.counter, snap.timestamp, snap.wall_time),
                     np.ascontiguousarray(snap.readings, dtype="<f4").tobytes(),
                     np.ascontiguousarray(snap.valid, dtype=np.uint8).tobytes(),
                     np.ascontiguousarray(snap.status, dtype=np.uint8).tobytes(), *extra))


def encode_estimate(est, counter: int, timestamp: float, wall_time: float, *, uncertainty: bool) -> bytes:
    """Header (rows, cols of the joint grid, n = joints), joints float32 (n, 3) metres, then with
    flag 1 joint_std float32 (n,) metres."""
    joints = np.asarray(est.joints)
    rows, cols = joints.shape[:2]
    parts = [_header("estimate", rows, cols, rows * cols, FLAG_UNCERTAINTY if uncertainty else 0, counter,
                     timestamp, wall_time), np.ascontiguousarray(joints, dtype="<f4").tobytes()]
    if uncertainty:
        parts.append(np.ascontiguousarray(est.joint_std, dtype="<f4").tobytes())
    return b"".join(parts)


def encode_no_estimate(rows: int, cols: int, counter: int, timestamp: float, wall_time: float) -> bytes:
    """An estimate payload saying the snapshot ``counter`` could not be estimated: flag
    `FLAG_NOT_ESTIMATED`, joints NaN."""
    n = rows * cols
    return _header("estimate", rows, cols, n, FLAG_NOT_ESTIMATED, counter, timestamp, wall_time) + \
        np.full(3 * n, np.nan, dtype="<f4").tobytes()


def _max_links() -> int:
    from host.cli.argtypes import MAX_LINKS  # --lattice's limit: node ids 1..0x7FFF
    return MAX_LINKS


#: the largest payload a receiver takes: a snapshot of `--lattice`'s largest sheet (32,767 links)
#: with gyroscopes, magnetometers and sample times, 42 bytes a link (an estimate is smaller: at most
#: 21,846 joints, 16 bytes each). Larger ones are refused before they are copied.
MAX_PAYLOAD_BYTES = HEADER.size + 42 * 0x7FFF
#: an ``info`` answer (JSON) is read only up to this size
MAX_INFO_BYTES = 1 << 20


def check_lattice(rows: int, cols: int) -> None:
    """ValueError unless ``rows`` x ``cols`` joints is a lattice ``--lattice`` takes: each side at
    least 2, at most 32,767 links (`host.cli.argtypes.MAX_LINKS`)."""
    if rows < 2 or cols < 2:
        raise ValueError(f"a {rows}x{cols} lattice: a sheet has at least 2x2 joints")
    links = rows * (cols - 1) + cols * (rows - 1)
    if links > _max_links():
        raise ValueError(f"a {rows}x{cols} lattice has {links:,} links, more than a sheet's {_max_links():,}")


def decode_info(payload: bytes) -> dict:
    """An ``info`` answer: a JSON object of at most `MAX_INFO_BYTES`; ValueError otherwise (nesting
    too deep for the JSON reader included)."""
    if len(payload) > MAX_INFO_BYTES:
        raise ValueError(f"an info answer of {len(payload)} bytes, more than {MAX_INFO_BYTES}")
    try:
        doc = json.loads(payload)
    except (ValueError, RecursionError) as exc:
        raise ValueError(f"an info answer that is not JSON: {str(exc)[:80] or 'nested too deep'}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"an info answer that is a JSON {type(doc).__name__}, not an object")
    return doc


def _decode_header(payload: bytes, kind: str) -> dict:
    if len(payload) < HEADER.size:
        raise ValueError(f"payload of {len(payload)} bytes: shorter than the {HEADER.size}-byte header")
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise ValueError(f"payload of {len(payload)} bytes: more than the largest sheet's {MAX_PAYLOAD_BYTES}")
    magic, version, flags, rows, cols, n, _, counter, ts, wall = HEADER.unpack_from(payload)
    if magic != KINDS[kind] or version != PAYLOAD_VERSION:
        raise ValueError(f"not a capsheet {kind} v{PAYLOAD_VERSION} payload (magic {magic!r}, version {version})")
    check_lattice(rows, cols)
    return {"flags": flags, "rows": rows, "cols": cols, "n": n, "counter": counter, "timestamp": ts,
            "wall_time": wall}


def decode_snapshot(payload: bytes) -> dict:
    """`encode_snapshot` read back: header fields and ``readings`` (n, 3), ``valid``, ``status``, and
    ``gyro`` (n, 3), ``mag`` (n, 3), ``sample_time_s`` (n,) (each None when the flags say it is absent).
    ValueError (nothing allocated) for a payload whose size, lattice (`check_lattice`) or link count
    is not what its header says."""
    h = _decode_header(payload, "snapshot")
    n, flags = h["n"], h["flags"]
    links = h["rows"] * (h["cols"] - 1) + h["cols"] * (h["rows"] - 1)
    if n != links:
        raise ValueError(f"snapshot of {n} links for a {h['rows']}x{h['cols']} lattice of {links}")
    size = HEADER.size + 14 * n + sum(w * n for bit, w in ((SNAP_GYRO, 12), (SNAP_MAG, 12), (SNAP_SAMPLE_TIME, 4))
                                      if flags & bit)
    if len(payload) != size:
        raise ValueError(f"snapshot of {n} links (flags {flags}) is {size} bytes, got {len(payload)}")
    o = HEADER.size
    h["readings"] = np.frombuffer(payload, "<f4", 3 * n, o).reshape(n, 3)
    h["valid"] = np.frombuffer(payload, np.uint8, n, o + 12 * n).astype(bool)
    h["status"] = np.frombuffer(payload, np.uint8, n, o + 13 * n)
    o += 14 * n
    for bit, name, width in ((SNAP_GYRO, "gyro", 3), (SNAP_MAG, "mag", 3), (SNAP_SAMPLE_TIME, "sample_time_s", 1)):
        h[name] = None
        if flags & bit:
            v = np.frombuffer(payload, "<f4", width * n, o)
            h[name] = v.reshape(n, 3) if width == 3 else v
            o += 4 * width * n
    return h


def decode_estimate(payload: bytes) -> dict:
    """`encode_estimate` read back: header fields, ``joints`` (rows, cols, 3), ``joint_std`` or None.
    ValueError (nothing allocated) as `decode_snapshot`."""
    h = _decode_header(payload, "estimate")
    n, unc = h["n"], bool(h["flags"] & FLAG_UNCERTAINTY)
    size = HEADER.size + 12 * n + (4 * n if unc else 0)
    if len(payload) != size or n != h["rows"] * h["cols"]:
        raise ValueError(f"estimate of {h['rows']}x{h['cols']} joints is {size} bytes, got {len(payload)}")
    o = HEADER.size
    h["joints"] = np.frombuffer(payload, "<f4", 3 * n, o).reshape(h["rows"], h["cols"], 3)
    h["joint_std"] = (np.frombuffer(payload, "<f4", n, o + 12 * n).reshape(h["rows"], h["cols"])
                      if unc else None)
    h["estimated"] = not h["flags"] & FLAG_NOT_ESTIMATED
    return h


def zenoh_config(endpoint: str | None, config_file: str | None = None):
    """The session's `zenoh.Config`: loopback only without ``endpoint``, a client of ``endpoint``
    otherwise, or a Zenoh config file (`host.publish.zenoh_session`)."""
    from host.publish.zenoh_session import session_config
    return session_config(endpoint, config_file)


class ZenohPublisher:
    """One sheet's Zenoh outputs (module docstring).

    Parameters
    ----------
    sheet : str
        The sheet's name, one key chunk (`SHEET_NAME`).
    endpoint : str or None
        A Zenoh locator to connect to (client mode), or None (peer mode on loopback).
    lattice : protocol.lattice.Lattice
    link_length : float
    info : dict, optional
        Extra facts for the ``info`` queryable (the session's mode ...).
    config_file : str, optional
        A Zenoh config file (``--zenoh-config``; `host.publish.zenoh_session`).

    Raises ValueError for a config that cannot be used, OSError when the session cannot be opened.
    """

    def __init__(self, sheet: str, endpoint: str | None, lattice, link_length: float, *,
                 info: dict | None = None, config_file: str | None = None) -> None:
        if not SHEET_NAME.match(sheet):
            raise ValueError(f"bad sheet name {sheet!r}: 1-64 of A-Z a-z 0-9 _ . - (one Zenoh key chunk)")
        import zenoh
        self.sheet, self.endpoint = sheet, endpoint
        self.prefix = f"capsheet/{sheet}"
        self.lattice = lattice
        self._lock = threading.Lock()
        self._info = {"format": "capsheet-zenoh", "version": PAYLOAD_VERSION, "sheet": sheet,
                      "rows": lattice.rows, "cols": lattice.cols, "links": lattice.n_links,
                      "link_length_m": float(link_length), "layout": None, "calibration": None,
                      "session": dict(info or {}),
                      "keys": {k: f"{self.prefix}/{k}" for k in ("snapshot", "estimate", "contacts", "health", "info")}}
        self.counts = {"snapshot": 0, "estimate": 0, "contacts": 0, "health": 0, "info": 0}
        self._last_health = -np.inf
        from host.publish.zenoh_session import open_session
        self.session = open_session(endpoint, config_file)
        self._pub = {k: self.session.declare_publisher(f"{self.prefix}/{k}")
                     for k in ("snapshot", "estimate", "contacts", "health")}
        self._queryable = self.session.declare_queryable(f"{self.prefix}/info", self._reply_info)

    def _reply_info(self, query) -> None:
        # nothing of the query is read (payload, parameters, attachment): whoever asks, however,
        # gets the same bounded document
        with self._lock:
            doc = json.dumps(self._info)
            self.counts["info"] += 1
        query.reply(f"{self.prefix}/info", doc.encode(), encoding="application/json")

    def describe(self, layout: dict | None, calibration: dict | None, session: dict | None = None) -> None:
        """The facts the ``info`` queryable answers with, after bring-up."""
        with self._lock:
            self._info["layout"] = layout
            self._info["calibration"] = calibration
            if session:
                self._info["session"].update(session)

    def snapshot(self, snap) -> None:
        """A feed listener: every emitted, corrected snapshot."""
        self._pub["snapshot"].put(encode_snapshot(snap, self.lattice.rows, self.lattice.cols))
        self.counts["snapshot"] += 1

    def estimate(self, est, snap, *, uncertainty: bool) -> None:
        self._pub["estimate"].put(encode_estimate(est, snap.counter, snap.timestamp, snap.wall_time,
                                                  uncertainty=uncertainty))
        self.counts["estimate"] += 1

    def contacts(self, frame: int, t_s: float | None, wall_time: float, total_force_n: float,
                 contacts: list[dict]) -> None:
        """One tactile frame's contacts (``capsheet tactile``) as JSON: ``frame`` (its number in the
        session), ``t_s``, ``wall_time`` (Unix s), ``total_force_n`` and ``contacts``, each ``id``,
        ``index`` (lattice row, col), ``position`` (m), ``force_n``, ``depth_m``, ``area_m2``,
        ``radius_m`` (docs/distribution.md)."""
        doc = {"sheet": self.sheet, "frame": int(frame), "t_s": None if t_s is None else float(t_s),
               "wall_time": float(wall_time), "total_force_n": float(total_force_n), "contacts": contacts}
        self._pub["contacts"].put(json.dumps(doc).encode(), encoding="application/json")
        self.counts["contacts"] += 1

    def health(self, doc: dict, *, force: bool = False) -> None:
        """The host's summary as JSON, at most once per `HEALTH_PERIOD_S` (always with ``force``)."""
        now = time.monotonic()
        if not force and now - self._last_health < HEALTH_PERIOD_S:
            return
        self._last_health = now
        self._pub["health"].put(json.dumps({"sheet": self.sheet, "wall_time": time.time(), **doc},
                                           default=str).encode(), encoding="application/json")
        self.counts["health"] += 1

    def close(self) -> None:
        try:
            self._queryable.undeclare()
            for p in self._pub.values():
                p.undeclare()
        finally:
            self.session.close()
