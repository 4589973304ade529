"""The live 3D view: the sheet in Foxglove (or any Foxglove WebSocket client), from foxglove-sdk.

`SceneChannels` turns estimates and contacts into Foxglove's own schemas (protobuf, registered by
foxglove-sdk): ``/sheet/scene`` a `foxglove.SceneUpdate` (entity ``lattice``: one line list, two
points per link, coloured per vertex; entity ``contacts``: a sphere per contact, its diameter the
contact's, and a text with its force), ``/sheet/joints`` a `foxglove.PointCloud` of the joints and
``/tf`` a `foxglove.FrameTransform` ``world`` -> ``sheet``. Colours (docs/recording.md):

* ``error`` (demo): joint error vs the virtual truth, % of side, 0 (blue) .. 2 % (red);
* ``displacement`` (tactile): normal displacement from rest, 0 .. max of the frame (blue .. red);
* ``links`` (default, a real sheet): valid links green, missing/invalid links red (drawn along
  the chord between their estimated joints).

`LiveServer` serves a context on ``ws://127.0.0.1:8765`` with the Foxglove WebSocket protocol under
both of its subprotocol names: ``foxglove.sdk.v1`` (the Foxglove app, foxglove-sdk's own clients)
and ``foxglove.websocket.v1`` (Lichtblick, the ``@foxglove/ws-protocol`` client, foxglove_bridge
0.8 era tools). foxglove-sdk serves the first only (0.30, and its main branch: any other offer is
an HTTP 400); the two name one protocol, so a relay in front of it (`SubprotocolRelay`) takes the
connections, offers the SDK's name upstream and answers the client in the name it asked for;
the frames after the handshake pass unchanged. Open it in Foxglove: *Open connection* ->
*Foxglove WebSocket* -> ``ws://localhost:8765``, then add a *3D* panel (fixed frame ``world``) and a
*Plot* panel.
"""

from __future__ import annotations

import errno
import logging
import selectors
import socket
import ssl
import threading
import time

import numpy as np

from host.publish.ws_frames import FrameStream, SubscribeRepair

__all__ = ["SceneChannels", "LiveServer", "tls_context", "MAX_CLIENTS", "log_frame_transform", "varint", "length_delimited", "SubprotocolRelay", "colours", "COLOUR_MODES", "ERROR_FULL_SCALE_PCT",
           "SUBPROTOCOLS", "rewrite_request", "rewrite_response"]

log = logging.getLogger(__name__)

#: the subprotocol foxglove-sdk serves, and the older name of the same protocol v1
SDK_SUBPROTOCOL, WS_V1_SUBPROTOCOL = "foxglove.sdk.v1", "foxglove.websocket.v1"
#: what the live view accepts, in order of preference when a client offers both
SUBPROTOCOLS = (SDK_SUBPROTOCOL, WS_V1_SUBPROTOCOL)

COLOUR_MODES = ("error", "displacement", "links")
#: % of side shown as full red in ``error`` mode
ERROR_FULL_SCALE_PCT = 2.0
_OK = (0.15, 0.75, 0.3, 1.0)
_MISSING = (0.9, 0.1, 0.1, 1.0)


def colours(values: np.ndarray, full_scale: float) -> np.ndarray:
    """RGBA in 0..1 for ``values`` (any shape) on a blue -> red ramp, 0 .. ``full_scale``; NaN grey.

    >>> colours(np.array([0.0, 1.0, np.nan]), 1.0)[:, :3].round(2).tolist()
    [[0.1, 0.2, 0.9], [0.9, 0.15, 0.1], [0.5, 0.5, 0.5]]
    """
    v = np.asarray(values, dtype=float)
    x = np.clip(v / full_scale if full_scale > 0 else np.zeros_like(v), 0.0, 1.0)
    lo, hi = np.array([0.1, 0.2, 0.9]), np.array([0.9, 0.15, 0.1])
    rgb = lo + x[..., None] * (hi - lo)
    rgb = np.where(np.isnan(v)[..., None], 0.5, rgb)
    return np.concatenate([rgb, np.ones(v.shape + (1,))], axis=-1)


class SceneChannels:
    """The 3D channels of one context (`foxglove.Context`) for a lattice.

    Parameters
    ----------
    context : foxglove.Context
    lattice : protocol.lattice.Lattice or None
        None: the channels are made now, the lattice given later (`use_lattice`); nothing is drawn
        before it.
    colour_by : {"error", "displacement", "links"}
    metadata : dict, optional
        Channel metadata (`host.record.recording.Recorder` marks which sink a set of channels is for).
    prefix, frame_id : str
        The topics are ``<prefix>/scene`` and ``<prefix>/joints``, drawn in frame ``frame_id``
        (one sheet: ``/sheet`` and ``sheet``; ``capsheet view``: each sheet's name).
    tf : foxglove.channels.FrameTransformChannel, optional
        The ``/tf`` channel, shared by the sheets of one scene (default: a channel of its own).
    """

    def __init__(self, context, lattice, colour_by: str = "links", metadata: dict | None = None, *,
                 prefix: str = "/sheet", frame_id: str = "sheet", tf=None) -> None:
        import foxglove
        from foxglove.channels import FrameTransformChannel, PointCloudChannel
        from foxglove.messages import SceneUpdate

        if colour_by not in COLOUR_MODES:
            raise ValueError(f"Invalid colour_by: {colour_by!r} (need one of {COLOUR_MODES})")
        self.lattice = lattice
        self.colour_by = colour_by
        self.frame_id = frame_id
        # a plain channel with the SDK's own SceneUpdate schema (what its SceneUpdateChannel
        # advertises: same name, encoding and descriptor set), so that it takes bytes: the lattice is
        # encoded with numpy (`_LineListScene`), the contacts with the SDK's `encode()`
        self.scene = foxglove.Channel(f"{prefix}/scene", message_encoding="protobuf",
                                      schema=SceneUpdate.get_schema(), context=context, metadata=metadata)
        self.cloud = PointCloudChannel(f"{prefix}/joints", context=context, metadata=metadata)
        self.tf = tf if tf is not None else FrameTransformChannel("/tf", context=context, metadata=metadata)
        self.lattice = None
        if lattice is not None:
            self.use_lattice(lattice)

    def use_lattice(self, lattice) -> None:
        """Draw ``lattice`` from now on (the channels stay: a client subscribed to them keeps them).

        `capsheet view` makes its channels before its server starts and learns each sheet's lattice
        from its first estimate: foxglove-sdk advertises a channel made while a client is connected
        before it records it as advertised to that client, so a client that subscribes at once may be
        told "Unknown channel ID" and get nothing on it (docs/recording.md, "The live 3D view")."""
        self.lattice = lattice
        self._ends = np.asarray(lattice.endpoints)
        self._lines = _LineListScene(2 * self._ends.shape[0])

    def log_transform(self, t_ns: int, translation=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0, 1.0),
                      parent: str = "world") -> None:
        """``parent`` -> this sheet's frame: ``translation`` metres, ``rotation`` a unit quaternion (x, y, z, w)."""
        log_frame_transform(self.tf, t_ns, parent, self.frame_id, translation, rotation)

    def link_colours(self, valid: np.ndarray, error: np.ndarray | None = None,
                     displacement: np.ndarray | None = None) -> np.ndarray:
        """RGBA per line-list vertex, shape (2 * n_links, 4), for the configured mode."""
        a, b = self._ends[:, 0], self._ends[:, 1]
        if self.colour_by == "error" and error is not None:
            per_joint = colours(np.asarray(error, dtype=float).ravel(), ERROR_FULL_SCALE_PCT)
        elif self.colour_by == "displacement" and displacement is not None:
            d = np.abs(np.asarray(displacement, dtype=float).ravel())
            per_joint = colours(d, float(np.nanmax(d)) if np.isfinite(d).any() and np.nanmax(d) > 0 else 1.0)
        else:
            per_joint = None
        if per_joint is None:
            c = np.where(np.asarray(valid, dtype=bool)[:, None], _OK, _MISSING)
            return np.repeat(c, 2, axis=0)
        out = np.empty((2 * a.shape[0], 4))
        out[0::2], out[1::2] = per_joint[a], per_joint[b]
        out[0::2][~valid] = out[1::2][~valid] = _MISSING  # missing links stay visible, in red
        return out

    def log_lattice(self, joints: np.ndarray, valid: np.ndarray, t_ns: int, *, error=None, displacement=None) -> None:
        """The lattice (line list) and the joints (point cloud) of one estimate; joints (rows, cols, 3) m.

        The line list's 2 points and 2 colours per link go out as protobuf bytes made with numpy
        (`_LineListScene`): on a 64x64 sheet (16,128 of each) one SDK object per point held the
        interpreter lock ~15 ms a call, the bytes take ~0.15 ms (docs/recording.md)."""
        from foxglove.messages import (PackedElementField, PackedElementFieldNumericType, PointCloud,
                                       Timestamp)

        if self.lattice is None or not (self.scene.has_sinks() or self.cloud.has_sinks()):
            return
        P = np.asarray(joints, dtype=float).reshape(-1, 3)
        ts = _ts(t_ns, Timestamp)  # first: a time the SDK's Timestamp refuses logs nothing
        if self.scene.has_sinks():
            cols = self.link_colours(np.asarray(valid, dtype=bool), error, displacement)
            self.scene.log(self._lines.encode(P[self._ends.ravel()], cols, t_ns, self.frame_id),
                           log_time=t_ns)
        f32 = PackedElementFieldNumericType.Float32
        self.cloud.log(PointCloud(timestamp=ts, frame_id=self.frame_id, point_stride=12,
                                  fields=[PackedElementField(name=n, offset=4 * k, type=f32)
                                          for k, n in enumerate("xyz")],
                                  data=P.astype("<f4").tobytes()), log_time=t_ns)

    def log_contacts(self, contacts: list[dict], t_ns: int) -> None:
        """Contacts as spheres (diameter 2 radius, at least 5 mm) with a text label ``#id F N``."""
        from foxglove.messages import (Color, Pose, Quaternion, SceneEntity, SceneUpdate, SpherePrimitive,
                                       TextPrimitive, Timestamp, Vector3)

        if not self.scene.has_sinks():
            return
        spheres, texts = [], []
        for c in contacts:
            if c.get("position") is None:  # e.g. a true contact known only by its lattice index
                continue
            x, y, z = (float(v) for v in c["position"])
            d = max(0.005, 2 * float(c.get("radius_m", 0.0)))
            pose = Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(x=0, y=0, z=0, w=1))
            spheres.append(SpherePrimitive(pose=pose, size=Vector3(x=d, y=d, z=d),
                                           color=Color(r=1.0, g=0.6, b=0.0, a=0.8)))
            tpose = Pose(position=Vector3(x=x, y=y, z=z + d), orientation=Quaternion(x=0, y=0, z=0, w=1))
            texts.append(TextPrimitive(pose=tpose, billboard=True, font_size=14, scale_invariant=True,
                                       color=Color(r=1, g=1, b=1, a=1),
                                       text=f"#{c.get('id', '?')} {float(c['force_n']):.2f} N"))
        msg = SceneUpdate(entities=[SceneEntity(timestamp=_ts(t_ns, Timestamp), frame_id=self.frame_id,
                                                id="contacts", spheres=spheres, texts=texts)])
        self.scene.log(msg.encode(), log_time=t_ns)  # a plain channel: bytes


def log_frame_transform(tf, t_ns: int, parent: str, child: str, translation=(0.0, 0.0, 0.0),
                        rotation=(0.0, 0.0, 0.0, 1.0)) -> None:
    """One `foxglove.FrameTransform` ``parent`` -> ``child`` on the channel ``tf``: ``translation``
    metres, ``rotation`` a unit quaternion (x, y, z, w)."""
    from foxglove.messages import FrameTransform, Quaternion, Timestamp, Vector3
    (tx, ty, tz), (qx, qy, qz, qw) = (float(v) for v in translation), (float(v) for v in rotation)
    tf.log(FrameTransform(timestamp=_ts(t_ns, Timestamp), parent_frame_id=parent, child_frame_id=child,
                          translation=Vector3(x=tx, y=ty, z=tz), rotation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
           log_time=t_ns)


def _ts(t_ns: int, Timestamp):
    return Timestamp(int(t_ns // 1_000_000_000), int(t_ns % 1_000_000_000))


# -- foxglove.SceneUpdate with one line list, encoded with numpy ------------------------------------
#: The field numbers of the lattice's SceneUpdate, from the schema foxglove-sdk ships
#: (`foxglove.messages.SceneUpdate.get_schema()`, a FileDescriptorSet; tests/host/
#: test_scene_encoding.py checks each against it). Timestamp is google.protobuf.Timestamp.
_FIELDS = {
    "SceneUpdate.entities": 2,
    "SceneEntity.timestamp": 1, "SceneEntity.frame_id": 2, "SceneEntity.id": 3, "SceneEntity.lines": 11,
    "Timestamp.seconds": 1, "Timestamp.nanos": 2,
    "LinePrimitive.type": 1, "LinePrimitive.thickness": 3, "LinePrimitive.scale_invariant": 4,
    "LinePrimitive.points": 5, "LinePrimitive.colors": 7,
    "Point3.x": 1, "Point3.y": 2, "Point3.z": 3,
    "Color.r": 1, "Color.g": 2, "Color.b": 3, "Color.a": 4,
}
#: `foxglove.LinePrimitive.Type` LINE_LIST
_LINE_LIST = 2
_VARINT, _I64, _LEN = 0, 1, 2  # wire types: int64, int32, enum, bool; double; message, string


def _tag(field: str, wire: int) -> int:
    return (_FIELDS[field] << 3) | wire  # every field number here < 16: a one-byte tag


def varint(n: int) -> bytes:
    """A protobuf varint (a negative int64 as its two's complement, 10 bytes)."""
    n &= (1 << 64) - 1
    out = bytearray()
    while n >= 0x80:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def length_delimited(number: int, payload: bytes) -> bytes:
    """Field ``number`` (wire type 2: bytes, string, message, packed) holding ``payload``."""
    return varint((number << 3) | 2) + varint(len(payload)) + payload


def _len_field(field: str, payload: bytes) -> bytes:
    return length_delimited(_FIELDS[field], payload)


def _doubles(*names: str) -> np.dtype:
    """One element of a repeated message field, the message's fields ``names`` all double: the
    field's tag, the length (one byte) and each field's tag and little-endian value; packed, no
    padding. ``names`` are the dtype's names 3, 5, 7, ..."""
    return np.dtype([("tag", "u1"), ("len", "u1")]
                    + [f for name in names for f in ((f"tag_{name}", "u1"), (name, "<f8"))])


_POINT3, _COLOR = _doubles("x", "y", "z"), _doubles("r", "g", "b", "a")
_LINE_HEAD = (bytes([_tag("LinePrimitive.type", _VARINT), _LINE_LIST])
              + bytes([_tag("LinePrimitive.thickness", _I64)]) + np.float64(2.0).astype("<f8").tobytes()
              + bytes([_tag("LinePrimitive.scale_invariant", _VARINT), 1]))


class _LineListScene:
    """`foxglove.SceneUpdate` bytes of one entity holding one line list (thickness 2, scale
    invariant) of ``n`` points with per-vertex colours: the message the SDK's objects encode to
    (``LinePrimitive(points=[Point3(...)], colors=[Color(...)])``), made with numpy.

    Every field of every point and colour is written (8 bytes each: the sub-messages all have the
    length of `_POINT3` / `_COLOR`, their tags written once), -0.0 as +0.0 (the SDK omits it: it
    decodes as +0.0). The line list's bytes live in a buffer kept between calls (a fresh 1 MB
    buffer a call costs as much again in page faults as the encoding); a lock keeps two threads
    from filling it at once."""

    def __init__(self, n: int) -> None:
        self.n = int(n)
        h, p = len(_LINE_HEAD), self.n * _POINT3.itemsize
        self._line = np.empty(h + p + self.n * _COLOR.itemsize, np.uint8)
        self._line[:h] = np.frombuffer(_LINE_HEAD, np.uint8)
        self._points = self._line[h:h + p].view(_POINT3)
        self._colors = self._line[h + p:].view(_COLOR)
        for rec, field, message in ((self._points, "LinePrimitive.points", "Point3"),
                                    (self._colors, "LinePrimitive.colors", "Color")):
            names = rec.dtype.names[3::2]
            rec["tag"], rec["len"] = _tag(field, _LEN), 9 * len(names)  # < 128: a one-byte length
            for name in names:
                rec[f"tag_{name}"] = _tag(f"{message}.{name}", _I64)
        self._lock = threading.Lock()

    def encode(self, points: np.ndarray, colors: np.ndarray, t_ns: int, frame_id: str,
               entity_id: str = "lattice") -> bytes:
        """``points`` (n, 3) m, ``colors`` (n, 4) RGBA; the entity stamped ``t_ns``."""
        points, colors = np.asarray(points, dtype=float), np.asarray(colors, dtype=float)
        if points.shape != (self.n, 3) or colors.shape != (self.n, 4):
            raise ValueError(f"need points ({self.n}, 3) and colors ({self.n}, 4), "
                             f"got {points.shape} and {colors.shape}")
        s, ns = int(t_ns // 1_000_000_000), int(t_ns % 1_000_000_000)
        ts = ((bytes([_tag("Timestamp.seconds", _VARINT)]) + varint(s) if s else b"")
              + (bytes([_tag("Timestamp.nanos", _VARINT)]) + varint(ns) if ns else b""))
        n_line = len(self._line)
        entity = (_len_field("SceneEntity.timestamp", ts)  # present, even if zero (as the SDK)
                  + (_len_field("SceneEntity.frame_id", frame_id.encode()) if frame_id else b"")
                  + (_len_field("SceneEntity.id", entity_id.encode()) if entity_id else b"")
                  + bytes([_tag("SceneEntity.lines", _LEN)]) + varint(n_line))
        head = bytes([_tag("SceneUpdate.entities", _LEN)]) + varint(len(entity) + n_line) + entity
        with self._lock:
            for rec, values in ((self._points, points), (self._colors, colors)):
                for k, name in enumerate(rec.dtype.names[3::2]):
                    np.add(values[:, k], 0.0, out=rec[name])  # + 0.0: -0.0 -> +0.0
            return b"".join([head, self._line.data])


# -- the handshake, sans I/O: bytes in, bytes out ---------------------------------------------------

#: an HTTP request or response head longer than this is refused (a client cannot make us buffer more)
MAX_HEAD_BYTES = 64 << 10
_PROTO = b"sec-websocket-protocol"


def _offered(head: bytes) -> list[str]:
    out: list[str] = []
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == _PROTO:
            out += [v.strip() for v in value.decode("latin-1").split(",") if v.strip()]
    return out


def _set_protocol(head: bytes, value: str) -> bytes:
    """``head`` (ending in the blank line) with every Sec-WebSocket-Protocol line replaced by one."""
    lines = head.split(b"\r\n")
    kept = [ln for ln in lines[1:] if ln and ln.partition(b":")[0].strip().lower() != _PROTO]
    return b"\r\n".join([lines[0], *kept, b"Sec-WebSocket-Protocol: " + value.encode("latin-1"), b"", b""])


def rewrite_request(head: bytes) -> tuple[bytes, str | None]:
    """A client's handshake head for foxglove-sdk: a client that offers only the protocol's older name
    (``foxglove.websocket.v1``) is offered upstream under the SDK's (``foxglove.sdk.v1``). Returns the
    head to send upstream and the name to answer the client in (None: the head passes unchanged).

    >>> h = b"GET / HTTP/1.1\\r\\nHost: x\\r\\nSec-WebSocket-Protocol: foxglove.websocket.v1\\r\\n\\r\\n"
    >>> up, answer = rewrite_request(h)
    >>> answer, b"Sec-WebSocket-Protocol: foxglove.sdk.v1" in up
    ('foxglove.websocket.v1', True)
    """
    offered = _offered(head)
    if SDK_SUBPROTOCOL in offered or WS_V1_SUBPROTOCOL not in offered:
        return head, None  # the SDK's own name (or nothing we could serve): the SDK answers
    return _set_protocol(head, SDK_SUBPROTOCOL), WS_V1_SUBPROTOCOL


def rewrite_response(head: bytes, answer: str | None) -> bytes:
    """foxglove-sdk's handshake answer, in the name the client asked for (`rewrite_request`)."""
    if answer is None or SDK_SUBPROTOCOL not in _offered(head):
        return head
    return _set_protocol(head, answer)


def _read_head(sock: socket.socket) -> tuple[bytes, bytes]:
    """(head up to and including the blank line, bytes after it) from ``sock``; ValueError if the
    peer closes first or the head exceeds `MAX_HEAD_BYTES`."""
    buf = b""
    while b"\r\n\r\n" not in buf:
        if len(buf) > MAX_HEAD_BYTES:
            raise ValueError("handshake head too long")
        chunk = sock.recv(4096)
        if not chunk:
            raise ValueError("closed during the handshake")
        buf += chunk
    k = buf.index(b"\r\n\r\n") + 4
    return buf[:k], buf[k:]


#: clients served at once by default (``--live-max-clients``): a live view has a few viewers
MAX_CLIENTS = 16
#: accept() errors that mean "out of descriptors or memory for now", not "the socket is gone":
#: the relay waits `ACCEPT_BACKOFF_S` and accepts again (the pending client is answered once a
#: descriptor is free)
_TRANSIENT_ACCEPT = {errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM, errno.ECONNABORTED, errno.EPROTO,
                     errno.EPERM, errno.EAGAIN}
ACCEPT_BACKOFF_S = 0.1


def _http_error(status: str, why: str) -> bytes:
    body = (why + "\n").encode()
    return (f"HTTP/1.1 {status}\r\nContent-Type: text/plain\r\nContent-Length: {len(body)}\r\n"
            f"Connection: close\r\n\r\n").encode() + body


def _origin(head: bytes) -> str | None:
    """The request's Origin header (None when it has none: not a browser)."""
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"origin":
            return value.strip().decode("latin-1")
    return None


class SubprotocolRelay:
    """Accept WebSocket clients on ``(host, port)`` and relay each to ``upstream`` (foxglove-sdk's
    server), translating the subprotocol name in the handshake (`rewrite_request`,
    `rewrite_response`); afterwards bytes pass both ways unchanged, but for one repair: a subscribe
    that foxglove-sdk answered "Unknown channel ID" for a channel it had just advertised is sent again
    (`host.publish.ws_frames`, counted in ``resubscribed``). One thread accepts, one thread
    per connection relays, at most ``max_clients`` at once (a further client is answered HTTP 503).

    Out of file descriptors (EMFILE) or memory, the accept loop waits `ACCEPT_BACKOFF_S` and tries
    again (counted in ``accept_errors``): the port never stays open unanswered.

    ``allowed_origins``: when given, a browser's handshake whose ``Origin`` is not one of them is
    answered HTTP 403 (a web page the viewer opens elsewhere cannot read the sheet through the
    viewer's browser); a client that sends no Origin (not a browser) is served. ``tls``: an
    `ssl.SSLContext` (server side): clients connect with ``wss://``.

    Raises OSError when ``(host, port)`` cannot be bound (in use)."""

    def __init__(self, host: str, port: int, upstream: tuple[str, int], *, max_clients: int = MAX_CLIENTS,
                 allowed_origins=None, tls: ssl.SSLContext | None = None) -> None:
        if int(max_clients) < 1:
            raise ValueError(f"Invalid max_clients: {max_clients!r} (need >= 1)")
        self.upstream = upstream
        self.max_clients = int(max_clients)
        self.allowed_origins = None if allowed_origins is None else frozenset(allowed_origins)
        self.tls = tls
        self._sock = socket.create_server((host, int(port)))
        self._sock.settimeout(0.2)
        self.port = int(self._sock.getsockname()[1])
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._open: set[socket.socket] = set()
        self._active = 0
        self.connections = 0  #: clients accepted
        self.translated = 0  #: of those, answered as ``foxglove.websocket.v1``
        self.refused = {"busy": 0, "origin": 0, "tls": 0}  #: clients turned away, by reason
        self.accept_errors = 0  #: accept() calls that failed for want of descriptors or memory
        #: subscribes sent again after the server answered "Unknown channel ID" (`host.publish.ws_frames`)
        self.resubscribed = 0
        #: of those errors, passed on to the client after `ws_frames.RETRIES` tries
        self.unknown_channels_passed = 0
        self.last_accept_error = ""
        self._threads: list[threading.Thread] = []
        self._accept = threading.Thread(target=self._accept_loop, name="capsheet-live-relay", daemon=True)
        self._accept.start()

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError as exc:
                if self._stop.is_set() or exc.errno not in _TRANSIENT_ACCEPT:
                    return  # closed by `stop`
                self.accept_errors += 1
                self.last_accept_error = str(exc)
                time.sleep(ACCEPT_BACKOFF_S)  # the client waits in the backlog; a descriptor may free up
                continue
            self.connections += 1
            with self._lock:
                busy = self._active >= self.max_clients
                if not busy:
                    self._active += 1
            if busy:
                self.refused["busy"] += 1
                self._turn_away(client, _http_error("503 Service Unavailable",
                                                    f"capsheet live view: {self.max_clients} clients already"))
                continue
            th = threading.Thread(target=self._serve, args=(client,), name="capsheet-live-conn", daemon=True)
            with self._lock:
                self._open.add(client)
                self._threads = [t for t in self._threads if t.is_alive()] + [th]
            try:
                th.start()
            except RuntimeError as exc:  # no thread to be had: this client only
                self.last_accept_error = str(exc)
                with self._lock:
                    self._open.discard(client)
                    self._active -= 1
                client.close()

    @staticmethod
    def _turn_away(client: socket.socket, answer: bytes) -> None:
        try:
            client.settimeout(1.0)
            client.sendall(answer)
        except OSError:
            pass
        finally:
            client.close()

    def _serve(self, client: socket.socket) -> None:
        try:
            self._relay(client)
        finally:
            with self._lock:
                self._active -= 1

    def _relay(self, client: socket.socket) -> None:
        up = None
        try:
            client.settimeout(10.0)
            if self.tls is not None:
                raw = client
                try:
                    client = self.tls.wrap_socket(raw, server_side=True)
                except (OSError, ValueError):
                    self.refused["tls"] += 1
                    with self._lock:
                        self._open.discard(raw)
                    raw.close()
                    return
                with self._lock:
                    self._open.discard(raw)
                    self._open.add(client)
            head, rest = _read_head(client)
            origin = _origin(head)
            if self.allowed_origins is not None and origin is not None and origin not in self.allowed_origins:
                self.refused["origin"] += 1
                client.sendall(_http_error("403 Forbidden", f"capsheet live view: origin {origin} not allowed"))
                return
            head, answer = rewrite_request(head)
            up = socket.create_connection(self.upstream, timeout=10.0)
            with self._lock:
                self._open.add(up)
            up.sendall(head)
            early = rest  # the client's first frames, if they came with its request: read by `_pump`
            resp, rest = _read_head(up)
            if answer is not None:
                self.translated += 1
            client.sendall(rewrite_response(resp, answer))
            client.settimeout(None)
            up.settimeout(None)
            # the server's first frames (its serverInfo and advertise) often come in the same read as
            # its HTTP answer: they go through `_pump` too, so that the advertise is seen
            self._pump(client, up, {client: early, up: rest})
        except (OSError, ValueError) as exc:
            if not self._stop.is_set():
                log.info("live view connection ended: %s", exc)
        finally:
            for s in (client, up):
                if s is not None:
                    with self._lock:
                        self._open.discard(s)
                    try:
                        s.close()
                    except OSError:
                        pass

    def _pump(self, a: socket.socket, b: socket.socket, first: dict | None = None) -> None:
        """Bytes both ways (``a`` the client, ``b`` the server) until either side closes (or `stop`);
        a subscribe the server could not place is sent again (`host.publish.ws_frames`)."""
        other = {a: b, b: a}
        streams = {a: FrameStream(), b: FrameStream()}
        repair = SubscribeRepair()

        def relay(s, data: bytes) -> None:
            now = time.monotonic()
            out = []
            for text, raw in streams[s].feed(data):
                if text is not None:
                    if s is a:
                        repair.from_client(text)
                    elif not repair.from_server(text, now):
                        continue
                out.append(raw)
            if out:
                other[s].sendall(out[0] if len(out) == 1 else b"".join(out))

        try:
            for s, data in (first or {}).items():  # bytes read with the handshake (``first[socket]``)
                if data:
                    relay(s, data)
            with selectors.DefaultSelector() as sel:
                sel.register(a, selectors.EVENT_READ)
                sel.register(b, selectors.EVENT_READ)
                while not self._stop.is_set():
                    due = repair.next_due()
                    wait = 0.2 if due is None else min(0.2, max(0.0, due - time.monotonic()))
                    # a TLS socket may hold decrypted bytes the selector cannot see
                    buffered = [s for s in (a, b) if isinstance(s, ssl.SSLSocket) and s.pending()]
                    ready = buffered or [key.fileobj for key, _ in sel.select(wait)]
                    for s in ready:
                        try:
                            data = s.recv(1 << 16)
                        except ssl.SSLWantReadError:
                            continue
                        if not data:
                            return
                        relay(s, data)
                    if repair.due and streams[a].at_boundary:  # never inside a frame of the client's
                        again = repair.take_due(time.monotonic())
                        if again:
                            b.sendall(b"".join(again))
        finally:
            with self._lock:
                self.resubscribed += repair.resubscribed
                self.unknown_channels_passed += repair.given_up

    def stop(self) -> None:
        self._stop.set()
        self._sock.close()
        with self._lock:
            open_, threads = list(self._open), list(self._threads)
        for s in open_:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        self._accept.join(2.0)
        for th in threads:
            th.join(2.0)


def tls_context(cert: str | None, key: str | None) -> ssl.SSLContext | None:
    """A server-side `ssl.SSLContext` from a PEM certificate and key (None when neither is given);
    ValueError (one line, naming the file) when only one is given or they do not load."""
    if cert is None and key is None:
        return None
    if cert is None or key is None:
        raise ValueError("the live view's TLS needs both a certificate and its key")
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise ValueError(f"the live view's TLS certificate {cert} / key {key}: "
                         f"{getattr(exc, 'strerror', None) or exc.args[-1] if exc.args else exc}") from None
    return ctx


class LiveServer:
    """A Foxglove WebSocket server for one context, on localhost by default: foxglove-sdk's server
    on a free loopback port, behind a `SubprotocolRelay` on ``port`` that serves both subprotocol
    names (`SUBPROTOCOLS`, module docstring).

    Parameters
    ----------
    context : foxglove.Context
    port : int
        TCP port; 0 picks a free one (see `port`).
    host : str
        Interface to listen on; the default serves this machine only.
    channel_filter : callable, optional
        ``(foxglove.ChannelDescriptor) -> bool``: the channels the view gets (default all).
    max_clients : int
        Clients served at once (`SubprotocolRelay`); more are answered HTTP 503.
    allowed_origins : iterable of str, optional
        Browser origins served (e.g. ``https://app.foxglove.dev``); default any.
    tls_cert, tls_key : str, optional
        PEM certificate (chain) and private key: serve ``wss://`` (both or neither). The TLS is the
        relay's (Python's ssl); foxglove-sdk's own server stays on loopback behind it.

    Raises OSError when the port is in use or the server cannot start, ValueError for a bad value
    (a certificate that does not load is named).
    """

    def __init__(self, context, port: int = 8765, host: str = "127.0.0.1", name: str = "capsheet",
                 channel_filter=None, *, max_clients: int = MAX_CLIENTS, allowed_origins=None,
                 tls_cert: str | None = None, tls_key: str | None = None) -> None:
        import foxglove

        if not 0 <= int(port) <= 65535:
            raise ValueError(f"Invalid port: {port!r} (need 0..65535)")
        tls = tls_context(tls_cert, tls_key)
        try:
            self._server = foxglove.start_server(name=name, host="127.0.0.1", port=0, context=context,
                                                 channel_filter=channel_filter)
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own error types
            raise OSError(f"Cannot start the live view: {exc}") from exc
        try:
            self._relay = SubprotocolRelay(host, int(port), ("127.0.0.1", int(self._server.port)),
                                           max_clients=max_clients, allowed_origins=allowed_origins, tls=tls)
        except OSError as exc:  # the port is in use
            self._server.stop()
            raise OSError(f"Cannot start the live view on {host}:{port}: {exc}") from exc
        self.host = host
        self.port = self._relay.port

    @property
    def url(self) -> str:
        scheme = "wss" if self._relay.tls is not None else "ws"
        return f"{scheme}://{'localhost' if self.host in ('127.0.0.1', '::1') else self.host}:{self.port}"

    @property
    def connections(self) -> int:
        """Clients that connected (through the relay)."""
        return self._relay.connections

    @property
    def relay(self) -> SubprotocolRelay:
        """The relay clients connect to: its counts (``refused``, ``accept_errors``)."""
        return self._relay

    def stop(self) -> None:
        self._relay.stop()
        self._server.stop()
