"""What the live view's relay reads of the WebSocket frames it passes on (RFC 6455 §5.2), and the
one repair it makes with them.

foxglove-sdk (0.30) sends a channel's ``advertise`` to a client before it records that this client
was told of the channel (``ConnectedClient::advertise_channels``: the message is queued, then the
channel is inserted in the client's map). A ``subscribe`` that the client sends at once and the
server reads in between is answered with the status error ``Unknown channel ID: N`` and dropped,
and the channel stays silent for that client for the whole session. It happens to channels made
while a client is connected (the recorder's ``/sheet/imu``, the contacts, a replay's topics):
measured against channels made 0-0.4 s after the client connected, 8 of 40 sessions lost one
(docs/recording.md, "The live 3D view in Foxglove").

The relay (`host.publish.live.SubprotocolRelay`) sees both directions. `SubscribeRepair` remembers
each connection's subscribes and the channels advertised to it; when the server answers a subscribe
of an advertised channel with that error, the relay sends the same subscribe again a moment later
(up to `RETRIES` times, each counted) instead of passing the error on. Everything else passes
unchanged, in order; binary frames and large ones pass through as they arrive, never buffered whole.
"""

from __future__ import annotations

import json
import os
import re
import struct

__all__ = ["MAX_TEXT_BYTES", "RETRIES", "RETRY_DELAY_S", "FrameStream", "SubscribeRepair", "text_frame"]

OP_TEXT = 0x1
#: a text frame longer than this passes through uninspected (an advertise of many channels with
#: their schemas is the largest the server sends; tens of kB)
MAX_TEXT_BYTES = 4 << 20
#: subscribes sent again for one channel, at most, before the server's error is passed on
RETRIES = 5
#: the first retry's delay, seconds; each next one waits twice as long (0.02 .. 0.32 s)
RETRY_DELAY_S = 0.02
_UNKNOWN = re.compile(r"Unknown channel ID: (\d+)")


def _unmask(payload: bytes, key: bytes) -> bytes:
    n = len(payload)
    k = int.from_bytes((key * (n // 4 + 1))[:n], "big") if n else 0
    return (int.from_bytes(payload, "big") ^ k).to_bytes(n, "big") if n else b""


class FrameStream:
    """Splits one direction's bytes into what passes through and whole text frames.

    `feed` returns ``(text, raw)`` pairs in stream order: ``text`` is the (unmasked) payload of a
    whole unfragmented, uncompressed text frame of at most `MAX_TEXT_BYTES`, ``raw`` its bytes as they came;
    ``text`` None: ``raw`` is other bytes (headers and payloads of other frames), to pass on as they
    are. Bytes of an incomplete text frame wait for the rest."""

    def __init__(self, max_text: int = MAX_TEXT_BYTES) -> None:
        self.max_text = int(max_text)
        self._buf = bytearray()
        self._skip = 0  # payload bytes of the current frame still to pass through

    def feed(self, data: bytes) -> list[tuple[bytes | None, bytes]]:
        out: list[tuple[bytes | None, bytes]] = []
        if self._skip and not self._buf:  # inside a large frame: its bytes pass without a copy
            n = min(self._skip, len(data))
            self._skip -= n
            out.append((None, data[:n] if n < len(data) else data))
            data = data[n:]
        self._buf += data
        while self._buf:
            if self._skip:
                n = min(self._skip, len(self._buf))
                out.append((None, bytes(self._buf[:n])))
                del self._buf[:n]
                self._skip -= n
                continue
            head = self._header()
            if head is None:
                break
            fin, opcode, hlen, length, key = head
            if fin and opcode == OP_TEXT and length <= self.max_text:
                if len(self._buf) < hlen + length:
                    break
                raw = bytes(self._buf[:hlen + length])
                del self._buf[:hlen + length]
                payload = raw[hlen:]
                out.append((_unmask(payload, key) if key else payload, raw))
            else:
                out.append((None, bytes(self._buf[:hlen])))
                del self._buf[:hlen]
                self._skip = length
        return out

    @property
    def at_boundary(self) -> bool:
        """Nothing of a frame is pending: a frame of our own may go in here."""
        return not self._skip and not self._buf

    def _header(self):
        b = self._buf
        if len(b) < 2:
            return None
        # a frame with an RSV bit (permessage-deflate's compressed frames) is not read: foxglove-sdk
        # negotiates no extension, so its frames never have one
        fin, opcode = bool(b[0] & 0x80) and not b[0] & 0x70, b[0] & 0x0F
        masked, n = bool(b[1] & 0x80), b[1] & 0x7F
        hlen = 2
        if n == 126:
            if len(b) < 4:
                return None
            n, hlen = struct.unpack_from(">H", b, 2)[0], 4
        elif n == 127:
            if len(b) < 10:
                return None
            n, hlen = struct.unpack_from(">Q", b, 2)[0], 10
        key = b""
        if masked:
            if len(b) < hlen + 4:
                return None
            key = bytes(b[hlen:hlen + 4])
            hlen += 4
        return fin, opcode, hlen, n, key


def text_frame(text: str) -> bytes:
    """A client's (masked, RFC 6455 §5.3) text frame of ``text``."""
    payload = text.encode()
    n = len(payload)
    head = bytes([0x80 | OP_TEXT]) + (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n)
                                      if n < 1 << 16 else bytes([0x80 | 127]) + struct.pack(">Q", n))
    key = os.urandom(4)
    return head + key + _unmask(payload, key)


def _json(text: bytes):
    try:
        doc = json.loads(text)
    except ValueError:
        return None
    return doc if isinstance(doc, dict) else None


class SubscribeRepair:
    """One connection's subscribes and advertised channels, and the subscribes to send again
    (module docstring). Sans-I/O: the relay feeds it the text frames and the time.

    ``resubscribed`` counts the subscribes sent again; ``given_up`` the errors passed on after
    `RETRIES` tries."""

    def __init__(self) -> None:
        self.advertised: set[int] = set()
        self.subscriptions: dict[int, int] = {}  # channel id -> subscription id
        self.tries: dict[int, int] = {}
        self.due: list[tuple[float, int]] = []  # (when, channel id)
        self.resubscribed = 0
        self.given_up = 0

    def from_client(self, text: bytes) -> None:
        doc = _json(text)
        if doc is None:
            return
        if doc.get("op") == "subscribe":
            for s in doc.get("subscriptions") or ():
                if isinstance(s, dict) and isinstance(s.get("channelId"), int) and isinstance(s.get("id"), int):
                    self.subscriptions[s["channelId"]] = s["id"]
        elif doc.get("op") == "unsubscribe":
            gone = set(doc.get("subscriptionIds") or ())
            for ch in [c for c, i in self.subscriptions.items() if i in gone]:
                del self.subscriptions[ch]

    def from_server(self, text: bytes, now: float) -> bool:
        """False: hold this frame back (a subscribe will be sent again instead)."""
        doc = _json(text)
        if doc is None:
            return True
        op = doc.get("op")
        if op == "advertise":
            for c in doc.get("channels") or ():
                if isinstance(c, dict) and isinstance(c.get("id"), int):
                    self.advertised.add(c["id"])
        elif op == "unadvertise":
            for c in doc.get("channelIds") or ():
                self.advertised.discard(c)
                self.subscriptions.pop(c, None)
        elif op == "status":
            m = _UNKNOWN.search(str(doc.get("message", "")))
            if m:
                ch = int(m.group(1))
                if ch in self.advertised and ch in self.subscriptions:
                    k = self.tries.get(ch, 0)
                    if k < RETRIES:
                        self.tries[ch] = k + 1
                        self.due.append((now + RETRY_DELAY_S * (1 << k), ch))
                        return False
                    self.given_up += 1
        return True

    def next_due(self) -> float | None:
        return min(t for t, _ in self.due) if self.due else None

    def take_due(self, now: float) -> list[bytes]:
        """The subscribe frames (masked, for the server) due at ``now``."""
        ready = [ch for t, ch in self.due if t <= now]
        self.due = [(t, ch) for t, ch in self.due if t > now]
        out = []
        for ch in ready:
            sub = self.subscriptions.get(ch)
            if sub is None or ch not in self.advertised:  # unsubscribed or gone meanwhile
                continue
            self.resubscribed += 1
            out.append(text_frame(json.dumps({"op": "subscribe", "subscriptions": [{"id": sub, "channelId": ch}]},
                                             separators=(",", ":"))))
        return out
