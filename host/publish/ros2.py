"""ROS 2 without ROS: a sheet's data as ROS 2 messages, published over Zenoh the way rmw_zenoh lays
them out (``--publish ros2[:ENDPOINT]``) and recorded to a ROS 2-profile MCAP (``--record-ros2``).

No ROS install is needed: this module parses the ``.msg`` definitions (the standard ones it uses are
below, capsheet's own are ``msgs/capsheet_msgs/msg/*.msg``), computes their REP-2011 type hashes
(``RIHS01_<sha256>``), encodes CDR (little-endian, with the 4-byte encapsulation header) with numpy,
and speaks rmw_zenoh's key expressions, sample attachment and liveliness tokens (rmw_zenoh's
docs/design.md, followed as of ros2/rmw_zenoh commit 99a6a2bd; docs/distribution.md says what is
published where).

Per sheet ``<sheet>``, a node ``/capsheet/<sheet>`` publishes

* ``/capsheet/<sheet>/snapshot``  ``capsheet_msgs/msg/LatticeSnapshot`` (every snapshot)
* ``/capsheet/<sheet>/joints``    ``sensor_msgs/msg/PointCloud2`` (x, y, z, std float32 per joint;
  rows x cols, organised)
* ``/capsheet/<sheet>/surface``   ``visualization_msgs/msg/Marker`` (TRIANGLE_LIST over the joints)
* ``/capsheet/<sheet>/contacts``  ``capsheet_msgs/msg/Contacts`` (``capsheet tactile``)
* ``/capsheet/<sheet>/info``      ``std_msgs/msg/String``: JSON, lattice, layout and calibration
  (transient local, keep last 1: a late subscriber gets the newest, as ``/tf_static``)
* ``/diagnostics``                ``diagnostic_msgs/msg/DiagnosticArray`` (the host's health, ~1/s)

and, when the chips have gyroscopes (6/9-axis sheets), per link ``k`` (`imu_topics`: ``link_000`` ..,
the link's index in the lattice's order, zero-padded) one sensor per topic as REP 145 names them:

* ``/capsheet/<sheet>/link_<k>/imu/data``  ``sensor_msgs/msg/Imu`` (every snapshot the link sent an
  IMU record in; frame_id ``capsheet_<sheet>_link_<k>``; orientation from the fused estimator, or
  ``orientation_covariance[0] = -1`` without it)
* ``/capsheet/<sheet>/link_<k>/imu/mag``   ``sensor_msgs/msg/MagneticField`` (9-axis chips)

declared at the first snapshot with IMU records.
"""

from __future__ import annotations

import json
import os
import re
import struct
import threading
import time
from pathlib import Path

import numpy as np

from host.publish.ros2_types import (CDR_LE_HEADER, MSGS_DIR, Cdr, MsgType, TypeRegistry,  # noqa: F401 -- ros2's names
                                     dds_type_name, registry, rihs01)

__all__ = ["MsgType", "TypeRegistry", "registry", "rihs01", "Cdr", "Ros2Encoder", "Ros2Publisher",
           "Ros2Recorder", "Ros2Outputs", "topic_keyexpr", "liveliness_keyexpr", "qos_keyexpr", "dds_type_name",
           "mangle", "attachment", "publisher_gid", "ROS_NAME", "TOPICS", "SENSOR_QOS", "DEFAULT_QOS",
           "domain_id", "CDR_LE_HEADER", "KEYEXPR_DEFAULT_QOS", "LATCHED_QOS", "imu_topics", "IMU_TYPE", "MAG_TYPE"]

# -- what is published -----------------------------------------------------------------------------
#: topic (relative to the node's namespace ``/capsheet/<sheet>``, or absolute) -> type
TOPICS = {
    "snapshot": "capsheet_msgs/msg/LatticeSnapshot",
    "joints": "sensor_msgs/msg/PointCloud2",
    "surface": "visualization_msgs/msg/Marker",
    "contacts": "capsheet_msgs/msg/Contacts",
    "info": "std_msgs/msg/String",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}
IMU_TYPE, MAG_TYPE = "sensor_msgs/msg/Imu", "sensor_msgs/msg/MagneticField"


def imu_topics(n_links: int) -> list[str]:
    """The links' names, ``link_000`` .. (zero-padded to at least 3 digits: the same width on a
    sheet, so names sort in the lattice's order); a link's topics are ``<name>/imu/data`` and
    ``<name>/imu/mag``, its frame ``capsheet_<sheet>_<name>``."""
    width = max(3, len(str(max(n_links - 1, 0))))
    return [f"link_{k:0{width}d}" for k in range(n_links)]


#: a ROS 2 name token (topics, nodes): what a sheet's name must be for --publish ros2
ROS_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,63}$")
# rmw_qos_profile_t values: reliability 1 reliable / 2 best effort, durability 1 transient local /
# 2 volatile, history 1 keep last / 2 keep all
#: the sensor-data profile (rmw_qos_profile_sensor_data): best effort, volatile, keep last 5
SENSOR_QOS = {"reliability": 2, "durability": 2, "history": 1, "depth": 5}
#: rmw_qos_profile_default: reliable, volatile, keep last 10
DEFAULT_QOS = {"reliability": 1, "durability": 2, "history": 1, "depth": 10}
#: rmw_zenoh's own defaults (its qos.cpp), the values ``qos_to_keyexpr`` leaves empty: reliable,
#: volatile, keep last 42; deadline, lifespan and liveliness lease infinite, liveliness automatic
KEYEXPR_DEFAULT_QOS = {"reliability": 1, "durability": 2, "history": 1, "depth": 42}
#: reliable, transient local, keep last 1 (as /tf_static): what a late subscriber is sent
LATCHED_QOS = {"reliability": 1, "durability": 1, "history": 1, "depth": 1}
_QOS_OF = {"/diagnostics": DEFAULT_QOS, "info": LATCHED_QOS}
#: rmw_zenoh's heartbeat period for a reliable, transient-local publisher (sample miss detection), s
MISS_HEARTBEAT_S = 0.5
#: PointField.FLOAT32
_FLOAT32 = 7
_POINT_FIELDS = (("x", 0), ("y", 4), ("z", 8), ("std", 12))


def domain_id(environ=os.environ) -> int:
    """``ROS_DOMAIN_ID`` (0 when unset), as ROS 2 reads it: 0..232."""
    raw = environ.get("ROS_DOMAIN_ID", "").strip()
    if raw == "":
        return 0
    if not raw.isdigit() or int(raw) > 232:
        raise ValueError(f"ROS_DOMAIN_ID={raw!r}: need an integer 0..232")
    return int(raw)


def mangle(name: str) -> str:
    """rmw_zenoh's mangled name: every ``/`` replaced by ``%`` (``""`` -> ``%``)."""
    return name.replace("/", "%") if name else "%"


def qos_keyexpr(qos: dict) -> str:
    """rmw_zenoh's compact QoS (``qos_to_keyexpr``): ``reliability:durability:history,depth:
    deadline_s,ns:lifespan_s,ns:liveliness,lease_s,ns``, a value left empty where it is rmw_zenoh's
    default (`KEYEXPR_DEFAULT_QOS`; deadline, lifespan and liveliness are always the defaults here)."""
    d = KEYEXPR_DEFAULT_QOS
    part = [str(qos[k]) if qos[k] != d[k] else "" for k in ("reliability", "durability", "history", "depth")]
    return f"{part[0]}:{part[1]}:{part[2]},{part[3]}:,:,:,,"


def topic_keyexpr(domain: int, topic: str, type_name: str) -> str:
    """``<domain_id>/<fully qualified name without its leading />/<DDS type name>/<RIHS01 hash>``."""
    return f"{domain}/{topic.strip('/')}/{dds_type_name(type_name)}/{rihs01(type_name)}"


def liveliness_keyexpr(domain: int, zid: str, node_id: int, entity_id: int, kind: str, namespace: str,
                       node: str, topic: str | None = None, type_name: str | None = None,
                       qos: dict | None = None) -> str:
    """``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|...>/<enclave>/<namespace>/<node>``
    (+ ``/<mangled topic>/<DDS type>/<hash>/<qos>`` for a publisher); enclave unset (``%``)."""
    key = f"@ros2_lv/{domain}/{zid}/{node_id}/{entity_id}/{kind}/%/{mangle(namespace)}/{node}"
    if topic is not None:
        key += f"/{mangle(topic)}/{dds_type_name(type_name)}/{rihs01(type_name)}/{qos_keyexpr(qos)}"
    return key


def publisher_gid(liveliness_key: str) -> bytes:
    """rmw_zenoh's entity GID: XXH3-128 of the entity's liveliness key expression, its low 64 bits
    then its high 64 bits, each little-endian."""
    import xxhash
    return xxhash.xxh3_128_intdigest(liveliness_key.encode()).to_bytes(16, "little")


def attachment(sequence: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The attachment of every rmw_zenoh sample: int64 sequence number, int64 source timestamp
    (ns since the Unix epoch), both little-endian, then the GID's length (one byte, 16) and the GID."""
    return struct.pack("<qqB", sequence, source_timestamp_ns, len(gid)) + gid


def _stamp_ns(wall_time) -> int:
    """A snapshot's Unix time in ns; now when it is unknown."""
    if wall_time is None or not np.isfinite(wall_time):
        return time.time_ns()
    return int(round(float(wall_time) * 1e9))


class Ros2Encoder:
    """CDR payloads of one sheet's messages (module docstring). ``frame_id`` ``capsheet_<sheet>``."""

    def __init__(self, sheet: str, rows: int, cols: int) -> None:
        self.sheet, self.rows, self.cols = sheet, rows, cols
        self.frame_id = f"capsheet_{sheet}"
        cells = np.arange((rows - 1) * (cols - 1))
        i, j = np.divmod(cells, max(cols - 1, 1))
        a, b, c, d = i * cols + j, (i + 1) * cols + j, i * cols + j + 1, (i + 1) * cols + j + 1
        #: joint indices of the surface's triangles, two per cell: (a, b, c) and (b, d, c)
        self.triangles = np.stack([np.stack([a, b, c], 1), np.stack([b, d, c], 1)], 1).reshape(-1).astype(np.intp)
        self._surface_tail: bytes | None = None
        self._templates: dict[tuple[int, int], tuple[np.ndarray, int]] = {}

    def snapshot(self, snap) -> tuple[bytes, int]:
        stamp = _stamp_ns(snap.wall_time)
        w = Cdr()
        w.header(stamp, self.frame_id)
        w.u64(snap.counter)
        w.f64(float(snap.timestamp))
        w.u16(self.rows)
        w.u16(self.cols)
        w.seq(snap.readings, "<f4")
        w.seq(np.asarray(snap.valid, bool), "u1")
        w.seq(snap.status, "u1")
        return w.bytes(), stamp

    def joints(self, joints: np.ndarray, joint_std, stamp: int) -> bytes:
        rows, cols = joints.shape[:2]
        pts = np.empty((rows, cols, 4), "<f4")
        pts[..., :3] = joints
        pts[..., 3] = np.nan if joint_std is None else joint_std
        w = Cdr()
        w.header(stamp, self.frame_id)
        w.u32(rows)
        w.u32(cols)
        w.u32(len(_POINT_FIELDS))
        for name, off in _POINT_FIELDS:
            w.string(name)
            w.u32(off)
            w.u8(_FLOAT32)
            w.u32(1)
        w.bool(False)  # is_bigendian
        w.u32(16)  # point_step
        w.u32(16 * cols)  # row_step
        w.seq(np.frombuffer(pts.tobytes(), np.uint8), "u1")  # data
        w.bool(bool(np.isfinite(joints).all()))  # is_dense
        return w.bytes()

    def surface(self, joints: np.ndarray, stamp: int) -> bytes:
        """A Marker TRIANGLE_LIST: two triangles per lattice cell, metres, in ``frame_id``. The
        points (most of the message) are gathered once and joined, not copied through the writer."""
        w = Cdr()
        w.header(stamp, self.frame_id)
        w.string(self.sheet)  # ns
        w.i32(0)  # id
        w.i32(11)  # type TRIANGLE_LIST
        w.i32(0)  # action ADD
        w.f64(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)  # pose: position, orientation (identity)
        w.f64(1.0, 1.0, 1.0)  # scale
        w.f32(0.35, 0.6, 0.85, 1.0)  # color
        w.i32(0)  # lifetime: forever
        w.u32(0)
        w.bool(False)  # frame_locked
        w.u32(len(self.triangles))  # points: their count, then 8-aligned float64 x, y, z each
        w.align(8)
        flat = np.ascontiguousarray(joints, "<f8").reshape(-1, 3)
        points = np.take(flat, self.triangles, axis=0).tobytes()
        if self._surface_tail is None:  # the fields after the points: the same every time (the
            t = Cdr()  # points end 8-aligned, so the tail's padding never changes)
            t.u32(0)  # colors
            t.string("")  # texture_resource
            t.header(0, "")  # texture: CompressedImage
            t.string("")
            t.u32(0)
            t.u32(0)  # uv_coordinates
            t.string("")  # text
            t.string("")  # mesh_resource
            t.string("")  # mesh_file
            t.u32(0)
            t.bool(False)  # mesh_use_embedded_materials
            self._surface_tail = t.bytes()[len(CDR_LE_HEADER):]
        return b"".join((w.buf, points, self._surface_tail))

    def contacts(self, frame: int, stamp: int, contacts, total_force_n: float) -> bytes:
        w = Cdr()
        w.header(stamp, self.frame_id)
        w.u64(frame)
        w.f64(float(total_force_n))
        w.u32(len(contacts))
        for c in contacts:
            w.i32(int(c.id))
            w.f64(float(c.index[0]), float(c.index[1]), *[float(v) for v in c.position],
                  float(c.force_n), float(c.depth_m), float(c.area_m2), float(np.max(c.axes_m)))
        return w.bytes()

    def _link_template(self, n_links: int, n_floats: int) -> tuple[np.ndarray, int]:
        """Every link's message of ``n_floats`` float64 after its header, all zero but the CDR header
        and the link's frame_id (one row each; every frame_id has the same length, so every field is
        at the same offset in every row): ``(rows, offset of the floats)``."""
        key = (n_links, n_floats)
        if key not in self._templates:
            names = imu_topics(n_links)
            w = Cdr()
            w.header(0, f"{self.frame_id}_{names[0]}")
            w.align(8)
            off = len(w.buf)
            rows = np.zeros((n_links, off + 8 * n_floats), np.uint8)
            rows[:, :len(w.buf)] = np.frombuffer(w.bytes(), np.uint8)
            ids = np.frombuffer("".join(f"{self.frame_id}_{n}" for n in names).encode(), np.uint8)
            width = len(ids) // n_links  # the frame_id's bytes start after stamp (8) and length (4)
            rows[:, 16:16 + width] = ids.reshape(n_links, width)
            rows.setflags(write=False)
            self._templates[key] = (rows, off)
        return self._templates[key]

    def _link_messages(self, n_links: int, links: np.ndarray, stamps_ns: np.ndarray, floats: np.ndarray) -> np.ndarray:
        rows, off = self._link_template(n_links, floats.shape[1])
        out = rows[links]  # a copy
        sec, nsec = np.divmod(np.asarray(stamps_ns, np.int64), 1_000_000_000)
        out[:, 4:8].view("<i4")[:, 0] = sec
        out[:, 8:12].view("<u4")[:, 0] = nsec
        out[:, off:].view("<f8")[:] = floats
        return out

    def imu(self, n_links: int, links: np.ndarray, stamps_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
            quat: np.ndarray | None, orientation_cov: np.ndarray | None, gyro_var: float,
            accel_var: float) -> np.ndarray:
        """``sensor_msgs/msg/Imu`` of the links ``links`` (one row of CDR bytes each): angular
        velocity (rad/s) and linear acceleration (the accelerometer's specific force, m/s², +g up at
        rest as REP 145 has it), both in the link's frame, diagonal covariances ``gyro_var`` (rad/s)²,
        ``accel_var`` (m/s²)²; orientation (x, y, z, w: link frame -> the sheet's frame) with its
        3 x 3 covariance (rad², about the sheet's axes), or unknown: ``orientation_covariance[0] = -1``."""
        m = len(links)
        f = np.zeros((m, 37))
        if quat is None:
            f[:, 3] = 1.0  # the identity, flagged unknown
            f[:, 4] = -1.0
        else:
            f[:, 0:4] = quat
            f[:, 4:13] = np.asarray(orientation_cov, float).reshape(m, 9)
        f[:, 13:16] = gyro
        f[:, [16, 20, 24]] = gyro_var
        f[:, 25:28] = accel
        f[:, [28, 32, 36]] = accel_var
        return self._link_messages(n_links, links, stamps_ns, f)

    def magnetic_field(self, n_links: int, links: np.ndarray, stamps_ns: np.ndarray, mag: np.ndarray,
                       mag_var: float) -> np.ndarray:
        """``sensor_msgs/msg/MagneticField`` of the links ``links``: tesla, link frame, diagonal
        covariance ``mag_var`` T²."""
        f = np.zeros((len(links), 12))
        f[:, 0:3] = mag
        f[:, [3, 7, 11]] = mag_var
        return self._link_messages(n_links, links, stamps_ns, f)

    def string(self, text: str) -> bytes:
        """A ``std_msgs/msg/String``."""
        w = Cdr()
        w.string(text)
        return w.bytes()

    def diagnostics(self, doc: dict, stamp: int) -> bytes:
        """The host's summary (`host.session.core.Host.summary`) as one DiagnosticStatus: level WARN
        when links are missing or under 99 % of the snapshots were complete, else OK; every
        summary key a KeyValue (JSON for what is not a string)."""
        pct = doc.get("complete_snapshots_pct")
        level = 1 if doc.get("missing_links") or (doc.get("snapshots") and isinstance(pct, (int, float))
                                                   and pct < 99.0) else 0
        w = Cdr()
        w.header(stamp, "")
        w.u32(1)
        w.u8(level)
        w.string(f"capsheet: {self.sheet}")
        missing = len(doc.get("missing_links") or [])
        w.string("ok" if level == 0 else f"{pct}% complete snapshots, {missing} links missing")
        w.string(self.frame_id)
        items = sorted(doc.items())
        w.u32(len(items))
        for k, v in items:
            w.string(str(k))
            w.string(v if isinstance(v, str) else json.dumps(v, default=str))
        return w.bytes()


class Ros2Publisher:
    """A sheet's node on Zenoh as rmw_zenoh lays it out: a Zenoh session (one ROS 2 context), the
    node's liveliness token, per topic a publisher on its key expression and its liveliness token,
    each sample with rmw_zenoh's attachment.

    Parameters
    ----------
    sheet : str
        `ROS_NAME`: the node is ``/capsheet/<sheet>``.
    endpoint : str or None
        None: peer mode on loopback only (`host.publish.zenoh_session`: 127.0.0.1, no multicast
        scouting, the machine's sessions meeting at ``tcp/127.0.0.1:7447``, rmw_zenohd's port). A
        locator: peer mode connected to that router, as an rmw_zenoh session is.
    domain : int
        ``ROS_DOMAIN_ID``.
    config_file : str, optional
        A Zenoh config file (``--zenoh-config``) instead.
    """

    def __init__(self, sheet: str, endpoint: str | None, *, domain: int = 0, config_file: str | None = None) -> None:
        if not ROS_NAME.match(sheet):
            raise ValueError(f"sheet name {sheet!r} is not a ROS 2 name (--publish ros2): 1-64 of "
                             f"A-Z a-z 0-9 _, starting with a letter")
        from host.publish.zenoh_session import open_session
        self.sheet, self.endpoint, self.domain = sheet, endpoint, domain
        self.namespace, self.node = "/capsheet", sheet
        # without ENDPOINT loopback only; with it rmw_zenoh's default session: a peer connected to the
        # router, listening on loopback, no multicast scouting (host.publish.zenoh_session)
        self.session = open_session(endpoint, config_file, ros2=True)
        self.zid = str(self.session.info.zid())
        node_key = liveliness_keyexpr(domain, self.zid, 0, 0, "NN", self.namespace, self.node)
        self.tokens = [self.session.liveliness().declare_token(node_key)]
        self.keys: dict[str, str] = {}
        self.liveliness: dict[str, str] = {"node": node_key}
        self._pub, self._gid, self._seq = {}, {}, {}
        self._lock = threading.Lock()
        for topic, typ in TOPICS.items():
            self.declare(topic, typ)

    def declare(self, topic: str, typ: str) -> None:
        """A publisher of ``typ`` on ``topic`` (relative to the node's namespace, or absolute) and
        its liveliness token; its entity id the next of the node's."""
        import zenoh

        domain, eid = self.domain, len(self._pub) + 1
        fq = self.fq(topic)
        qos = _QOS_OF.get(topic, SENSOR_QOS)
        key = topic_keyexpr(domain, fq, typ)
        lv = liveliness_keyexpr(domain, self.zid, 0, eid, "MP", self.namespace, self.node, fq, typ, qos)
        rel = zenoh.Reliability.BEST_EFFORT if qos["reliability"] == 2 else zenoh.Reliability.RELIABLE
        if qos["durability"] == 1:  # transient local: as rmw_zenoh, an advanced publisher with a cache
            import zenoh.ext as zx  # of `depth` samples, detectable by late subscribers, heartbeats
            pub = zx.declare_advanced_publisher(
                self.session, key, reliability=rel, congestion_control=zenoh.CongestionControl.DROP,
                cache=zx.CacheConfig(qos["depth"]), publisher_detection=True,
                sample_miss_detection=(zx.MissDetectionConfig(sporadic_heartbeat=MISS_HEARTBEAT_S)
                                       if qos["reliability"] == 1 else None))
        else:
            pub = self.session.declare_publisher(key, reliability=rel, congestion_control=zenoh.CongestionControl.DROP)
        with self._lock:
            self._pub[topic] = pub
            self.tokens.append(self.session.liveliness().declare_token(lv))
            self.keys[topic], self.liveliness[topic] = key, lv
            self._gid[topic], self._seq[topic] = publisher_gid(lv), 0

    def fq(self, topic: str) -> str:
        """A topic's fully qualified name."""
        return topic if topic.startswith("/") else f"{self.namespace}/{self.node}/{topic}"

    def write(self, topic: str, payload: bytes, stamp_ns: int) -> None:  # noqa: ARG002 -- a sink's signature
        with self._lock:
            self._seq[topic] += 1
            att = attachment(self._seq[topic], time.time_ns(), self._gid[topic])
            self._pub[topic].put(payload, attachment=att)

    def write_many(self, topics: list[str], payloads: list[bytes]) -> None:
        """Several samples (a snapshot's links), one lock and one source timestamp for all."""
        now = time.time_ns()
        with self._lock:
            for topic, payload in zip(topics, payloads):
                seq = self._seq[topic] = self._seq[topic] + 1
                self._pub[topic].put(payload, attachment=attachment(seq, now, self._gid[topic]))

    def close(self) -> None:
        try:
            for p in self._pub.values():
                p.undeclare()
            for t in self.tokens:
                t.undeclare()
        finally:
            self.session.close()


class Ros2Recorder:
    """``--record-ros2``: the same CDR messages in a ROS 2-profile MCAP (schema encoding ``ros2msg``,
    message encoding ``cdr``, each channel's ``offered_qos_profiles`` and ``topic_type_hash`` as
    rosbag2 writes them), so ``ros2 bag``, rosbags and Foxglove read it."""

    def __init__(self, path, sheet: str) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        self._file = open(self.path, "wb")  # noqa: SIM115 -- closed in close()
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library="capsheet --record-ros2")
        self._lock = threading.Lock()
        self._channels: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        self.sheet = sheet
        self.counts: dict[str, int] = {}
        #: topic -> type: `TOPICS` and what `add_topic` added (the links' IMU topics)
        self.types = dict(TOPICS)
        reg = registry()
        self._schemas = {t: self._writer.register_schema(t, "ros2msg", reg.msgdef(t).encode())
                         for t in sorted(set(TOPICS.values()))}

    def add_topic(self, topic: str, typ: str) -> None:
        with self._lock:
            self.types[topic] = typ
            if typ not in self._schemas:
                self._schemas[typ] = self._writer.register_schema(typ, "ros2msg", registry().msgdef(typ).encode())

    def _channel(self, topic: str, fq: str) -> int:
        if topic not in self._channels:
            typ = self.types[topic]
            qos = _QOS_OF.get(topic, SENSOR_QOS)
            profile = (f"- history: {qos['history']}\n  depth: {qos['depth']}\n  reliability: {qos['reliability']}\n"
                       f"  durability: {qos['durability']}\n  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n"
                       f"  lifespan:\n    sec: 2147483647\n    nsec: 4294967295\n  liveliness: 1\n"
                       f"  liveliness_lease_duration:\n    sec: 2147483647\n    nsec: 4294967295\n"
                       f"  avoid_ros_namespace_conventions: false\n")
            self._channels[topic] = self._writer.register_channel(
                fq, "cdr", self._schemas[typ],
                metadata={"offered_qos_profiles": profile, "topic_type_hash": rihs01(typ)})
            self._seq[topic] = 0
        return self._channels[topic]

    def write(self, topic: str, payload: bytes, stamp_ns: int, fq: str) -> None:
        with self._lock:
            ch = self._channel(topic, fq)
            self._seq[topic] += 1
            self._writer.add_message(ch, log_time=time.time_ns(), publish_time=int(stamp_ns), data=payload,
                                     sequence=self._seq[topic] & 0xFFFFFFFF)
            self.counts[topic] = self.counts.get(topic, 0) + 1

    def close(self) -> None:
        with self._lock:
            self._writer.finish()
            self._file.close()


class Ros2Outputs:
    """One sheet's ROS 2 outputs: each message encoded once (`Ros2Encoder`), then published
    (`Ros2Publisher`, ``--publish ros2``) and/or recorded (`Ros2Recorder`, ``--record-ros2``)."""

    def __init__(self, sheet: str, lattice, *, publish: bool = False, endpoint: str | None = None,
                 record=None, domain: int = 0, config_file: str | None = None) -> None:
        if not ROS_NAME.match(sheet):
            raise ValueError(f"sheet name {sheet!r} is not a ROS 2 name (--publish ros2, --record-ros2): "
                             f"1-64 of A-Z a-z 0-9 _, starting with a letter")
        missing = sorted(set(TOPICS.values()) - set(registry().types))
        if missing:  # capsheet_msgs are read from the repository (an editable install, `make`)
            raise OSError(f"message definitions {', '.join(missing)} not found (capsheet_msgs is read from "
                          f"{MSGS_DIR}: install capsheet from its repository with `make`)")
        self.encoder = Ros2Encoder(sheet, lattice.rows, lattice.cols)
        self.namespace = f"/capsheet/{sheet}"
        self.publisher = Ros2Publisher(sheet, endpoint, domain=domain, config_file=config_file) if publish else None
        try:
            self.recorder = Ros2Recorder(record, sheet) if record else None
        except BaseException:
            if self.publisher is not None:
                self.publisher.close()
            raise
        self.counts = {t: 0 for t in TOPICS}
        self.counts.update(imu=0, mag=0)  # the links' Imu and MagneticField messages, all links
        #: topic -> type: `TOPICS` and, once IMU records come, the links' topics (`imu_topics`)
        self.types = dict(TOPICS)
        self._imu_links: list[str] | None = None
        self._mag_declared = False
        #: messages a sink could not take (`_out`), and the last reason
        self.failed = {"publish": 0, "record": 0}
        self.last_error = {"publish": "", "record": ""}
        self._last_health = -np.inf

    def fq(self, topic: str) -> str:
        return topic if topic.startswith("/") else f"{self.namespace}/{topic}"

    def _out(self, topic: str, payload: bytes, stamp: int, count_as: str | None = None) -> None:
        """To each sink. A sink that fails (a closed Zenoh session, a full disk) is counted in
        `failed` with its last error, never raised into the host's receive thread; a recording that
        failed once takes no more (counted too)."""
        if self.publisher is not None:
            try:
                self.publisher.write(topic, payload, stamp)
            except Exception as exc:  # noqa: BLE001 -- zenoh.ZError and kin: counted, reported at close
                self.failed["publish"] += 1
                self.last_error["publish"] = f"{type(exc).__name__}: {exc}"
        if self.recorder is not None and not self.failed["record"]:
            try:
                self.recorder.write(topic, payload, stamp, self.fq(topic))
            except Exception as exc:  # noqa: BLE001 -- OSError, a closed writer: counted, reported at close
                self.failed["record"] += 1
                self.last_error["record"] = f"{type(exc).__name__}: {exc}"
        elif self.recorder is not None:
            self.failed["record"] += 1
        self.counts[count_as or topic] += 1

    def snapshot(self, snap) -> None:
        """A feed listener: every emitted, corrected snapshot."""
        payload, stamp = self.encoder.snapshot(snap)
        self._out("snapshot", payload, stamp)

    def estimate(self, est, snap=None, *, uncertainty: bool = False, wall_time=None) -> None:
        joints = np.asarray(est.joints)
        stamp = _stamp_ns(snap.wall_time if snap is not None else wall_time)
        self._out("joints", self.encoder.joints(joints, est.joint_std if uncertainty else None, stamp), stamp)
        self._out("surface", self.encoder.surface(joints, stamp), stamp)

    def contacts(self, frame: int, contacts, total_force_n: float, wall_time=None) -> None:
        stamp = _stamp_ns(wall_time)
        self._out("contacts", self.encoder.contacts(frame, stamp, contacts, total_force_n), stamp)

    def _declare_links(self, n_links: int, mag: bool) -> None:
        names = imu_topics(n_links)
        want = [(f"{n}/imu/data", IMU_TYPE) for n in names] + ([(f"{n}/imu/mag", MAG_TYPE) for n in names] if mag else [])
        for topic, typ in want:
            if topic in self.types:
                continue
            self.types[topic] = typ
            if self.publisher is not None:
                self.publisher.declare(topic, typ)
            if self.recorder is not None:
                self.recorder.add_topic(topic, typ)
        self._imu_links = names
        self._imu_data = [f"{n}/imu/data" for n in names]
        self._imu_mag = [f"{n}/imu/mag" for n in names]
        self._mag_declared = self._mag_declared or mag

    def imu(self, snap, motion=None, orientation_cov=None, noise=None) -> None:
        """A snapshot of 6/9-axis chips (``snap.gyro`` not None) as one ``sensor_msgs/msg/Imu`` per
        link that sent an IMU record (and a ``sensor_msgs/msg/MagneticField`` with ``snap.mag``),
        each stamped at the link's own sample time (the SYNC's plus ``sample_time_s``).
        ``motion``: the fused estimator's `host.analysis.motion.MotionEstimate` of this snapshot
        (its ``frames`` give the orientations) and ``orientation_cov`` (n_links, 3, 3) rad²; None:
        the orientation is unknown. ``noise``: the white noise per axis per sample the covariances
        say (attributes ``accel_noise_mps2``, ``gyro_noise_rps``, ``mag_noise_t``; default
        `host.analysis.motion.FusedConfig`'s, the datasheets' figures the fused estimator assumes)."""
        gyro = getattr(snap, "gyro", None)
        if gyro is None:
            return
        if noise is None:
            from host.analysis.motion import FusedConfig
            noise = FusedConfig()
        n = len(snap.valid)
        mag = getattr(snap, "mag", None)
        if self._imu_links is None or len(self._imu_links) != n or (mag is not None and not self._mag_declared):
            self._declare_links(n, mag is not None)
        ok = np.asarray(snap.valid, bool) & np.isfinite(gyro).all(1) & np.isfinite(snap.readings).all(1)
        links = np.flatnonzero(ok)
        if not len(links):
            return
        base = _stamp_ns(snap.wall_time)
        st = getattr(snap, "sample_time_s", None)
        offs = np.zeros(n) if st is None else np.where(np.isfinite(st), st, 0.0)
        stamps = base + np.round(offs[links] * 1e9).astype(np.int64)
        quat = ocov = None
        if motion is not None:
            from scipy.spatial.transform import Rotation
            quat = Rotation.from_matrix(np.asarray(motion.frames)[links]).as_quat()  # x, y, z, w
            ocov = (np.full((len(links), 3, 3), np.nan) if orientation_cov is None
                    else np.asarray(orientation_cov)[links])
        rows = self.encoder.imu(n, links, stamps, np.asarray(gyro)[links], np.asarray(snap.readings)[links], quat, ocov,
                                float(noise.gyro_noise_rps) ** 2, float(noise.accel_noise_mps2) ** 2)
        self._out_many([self._imu_data[k] for k in links], rows, stamps, "imu")
        if mag is not None:
            okm = np.isfinite(np.asarray(mag)[links]).all(1)
            mrows = self.encoder.magnetic_field(n, links[okm], stamps[okm], np.asarray(mag)[links[okm]],
                                                float(noise.mag_noise_t) ** 2)
            self._out_many([self._imu_mag[k] for k in links[okm]], mrows, stamps[okm], "mag")

    def _out_many(self, topics: list[str], rows: np.ndarray, stamps: np.ndarray, count_as: str) -> None:
        """`_out` for a snapshot's links at once (one row of CDR bytes each); failures counted alike."""
        payloads = [r.tobytes() for r in rows]
        if self.publisher is not None:
            try:
                self.publisher.write_many(topics, payloads)
            except Exception as exc:  # noqa: BLE001 -- as _out
                self.failed["publish"] += 1
                self.last_error["publish"] = f"{type(exc).__name__}: {exc}"
        if self.recorder is not None:
            for topic, payload, stamp in zip(topics, payloads, stamps.tolist()):
                if self.failed["record"]:
                    self.failed["record"] += 1
                    continue
                try:
                    self.recorder.write(topic, payload, stamp, self.fq(topic))
                except Exception as exc:  # noqa: BLE001 -- as _out
                    self.failed["record"] += 1
                    self.last_error["record"] = f"{type(exc).__name__}: {exc}"
        self.counts[count_as] += len(topics)

    def info(self, doc: dict) -> None:
        """The sheet's facts (lattice, layout, calibration ...) as JSON on the latched ``info`` topic."""
        stamp = time.time_ns()
        self._out("info", self.encoder.string(json.dumps(doc, default=str)), stamp)

    def health(self, doc: dict, *, force: bool = False, period_s: float = 1.0) -> None:
        now = time.monotonic()
        if not force and now - self._last_health < period_s:
            return
        self._last_health = now
        stamp = time.time_ns()
        self._out("/diagnostics", self.encoder.diagnostics(doc, stamp), stamp)

    def close(self) -> None:
        try:
            if self.publisher is not None:
                self.publisher.close()
        finally:
            if self.recorder is not None:
                try:
                    self.recorder.close()
                except OSError as exc:  # the file could not be finished (a full disk): counted, reported
                    self.failed["record"] += 1
                    self.last_error["record"] = f"{type(exc).__name__}: {exc}"
