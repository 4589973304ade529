"""Serial wire input stored by its information: the raw channel's compact form (docs/recording.md, "Size").

A SAMPLE frame on the wire is 15 bytes (COBS of header + counter + sample word + CRC, and the 0x00
delimiter, docs/protocol.md §4.3 and §6); once sensor noise makes every CRC different, zstd cannot
shrink it. What cannot be recomputed is the node, the counter, three 12-bit counts and four status
bits: the version, type, CRC and COBS bytes follow from them. So a chunk of serial bytes as read is
stored as a ``capsheet.v2.RawSerialFrames`` message:

* every 15-byte span ``<14 COBS bytes> 0x00`` of the chunk that is a SAMPLE frame whose re-encoding
  from its fields (`SerialCompactor`) gives the very same 15 bytes becomes one row of columns, each
  a ``bytes`` field of little-endian numbers stored plane by plane (all the rows' lowest bytes, then
  the next: zstd codes each plane apart, and the high bytes of small numbers are all alike):
  ``gap`` (uint32: the chunk's raw bytes before this frame since the previous row's), ``node``
  (uint16: minus the previous row's node, modulo 2**16), ``counter`` (uint16: minus the same node's
  previous counter + 1, modulo 2**16: 0 for a node answering every SYNC), ``counts`` (uint16 × 3:
  each count minus a prediction from the same node's earlier counts, see below, zigzag-coded) and
  ``status`` (one byte per row);
* every other byte — damaged frames, other message types, a frame cut by the chunk's edge, a frame
  a chip encoded differently (any frame whose re-encoding differs) — is kept as it came, in ``raw``,
  in order.

`SerialExpander` rebuilds the chunk byte for byte. Exactness never depends on the chip encoding as
this module does: a frame is stored as columns only when the compactor has rebuilt its 14 bytes
from the fields it stores (CRC and COBS computed afresh) and found them equal to the original.
Snapshots' counts are stored against the same kind of running average (`CountsCoder`).

The prediction of a node's count is an integer exponential average of its earlier counts in this
file, ``ref16`` (16 × counts): prediction ``(ref16 + 8) >> 4``, then ``ref16 += (16 c - ref16) >> 3``;
a node's first count in a file is predicted 0 and sets ``ref16 = 16 c``. On a still sheet with 1 %
g of noise this leaves 5.5 bits per count against 5.9 for the difference from the previous count
(it averages the noise instead of doubling it); a moving sheet costs a little more either way.

State (previous node, each node's counter and average) runs from chunk to chunk of one bus within
one file and starts afresh with each file of a split recording, so each file reads alone: the
recorder makes a new `SerialCompactor` per bus and file, the reader a new `SerialExpander`.

Sans-I/O: bytes and numbers in, bytes out; no clock, no file.
"""

from __future__ import annotations

import numpy as np

from protocol.crc import crc16_rows
from protocol.messages import PROTOCOL_VERSION, MsgType

__all__ = ["SCHEMA", "FRAME_SPAN", "has_frame_span", "SerialCompactor", "SerialExpander", "CountsCoder", "CompactError"]

#: the channel's schema (`host.record.schema`)
SCHEMA = "capsheet.v2.RawSerialFrames"
#: a SAMPLE on the wire: 14 COBS bytes and the 0x00 delimiter
FRAME_SPAN = 15
_ENC = FRAME_SPAN - 1  # 14 COBS bytes
_BODY = _ENC - 1  # 13 bytes: version, type, node (2), counter (2), sample word (5), CRC (2)
_NODES = 1 << 16
_SHIFT = 3  # the average's weight: 1/8 of each new count


class CompactError(ValueError):
    """A ``RawSerialFrames`` message that does not expand: its columns disagree in length or value."""


# -- COBS of a 13-byte body, vectorised over rows (docs/protocol.md §6.1) -----------------------------

def _cobs_decode_rows(enc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Decode ``(n, 14)`` COBS rows without zeros into ``(n, 13)`` bodies; ``ok`` (n,) where the code
    chain lands exactly on the row's end (it ran past it otherwise)."""
    n = enc.shape[0]
    rows = np.arange(n)
    padded = np.zeros((n, _ENC + 2), dtype=np.int64)  # past the end: code 0, the chain stops there
    padded[:, :_ENC] = enc
    is_code = np.zeros((n, _ENC + 2), dtype=bool)
    pos = np.zeros(n, dtype=np.int64)
    while True:
        is_code[rows, pos] = True
        step = padded[rows, pos]
        if not step.any():
            break
        pos = np.minimum(pos + step, _ENC + 1)
    body = enc[:, 1:].copy()
    body[is_code[:, 1:_ENC]] = 0
    return body, pos == _ENC


_OUT_POS = np.arange(_ENC)


def _cobs_encode_rows(body: np.ndarray) -> np.ndarray:
    """COBS of ``(n, 13)`` bodies: ``(n, 14)`` rows (no 254-byte blocks at this length). The code at
    place 0 and at each zero's place is the distance to the next zero's place or the end (14)."""
    n = body.shape[0]
    is_code = np.ones((n, _ENC), dtype=bool)
    is_code[:, 1:] = body == 0
    z = np.where(is_code, _OUT_POS, _ENC)
    z[:, 0] = _ENC
    # next[:, p]: the first code place after p (or the end)
    nxt = np.empty((n, _ENC), dtype=np.int64)
    nxt[:, :-1] = np.minimum.accumulate(z[:, :0:-1], axis=1)[:, ::-1]
    nxt[:, -1] = _ENC
    out = np.empty((n, _ENC), dtype=np.uint8)
    out[:, 1:] = body
    return np.where(is_code, (nxt - _OUT_POS).astype(np.uint8), out)


_SHIFTS = np.array([0, 12, 24], dtype=np.int64)


def _bodies(node, counter, xyz, status) -> np.ndarray:
    """The ``(n, 13)`` SAMPLE frame bodies of these fields, CRC included (docs/protocol.md §4.3, §6)."""
    n = node.shape[0]
    b = np.empty((n, _BODY), dtype=np.uint8)
    b[:, 0] = PROTOCOL_VERSION
    b[:, 1] = int(MsgType.SAMPLE)
    b[:, 2:6] = np.stack([node, counter], axis=1).astype("<u2").view(np.uint8)
    word = ((xyz & 0xFFF) << _SHIFTS).sum(axis=1) | (status.astype(np.int64) << 36)  # x, y, z, status: 40 bits
    b[:, 6:11] = word.astype("<u8").view(np.uint8).reshape(n, 8)[:, :5]
    crc = crc16_rows(b[:, :11])
    b[:, 11], b[:, 12] = crc >> 8, crc & 0xFF
    return b


def _fields(body: np.ndarray):
    """node, counter (int64 (n,)), counts (int64 (n, 3), 12-bit signed), status (n,) of bodies."""
    n = body.shape[0]
    nc = np.ascontiguousarray(body[:, 2:6]).view("<u2").astype(np.int64)
    w = np.zeros((n, 8), dtype=np.uint8)
    w[:, :5] = body[:, 6:11]
    word = w.view("<u8").astype(np.int64)  # (n, 1)
    xyz = (word >> _SHIFTS) & 0xFFF
    xyz -= (xyz & 0x800) << 1
    return nc[:, 0], nc[:, 1], xyz, (word[:, 0] >> 36) & 0xF


def _ranks(node: np.ndarray) -> np.ndarray:
    """How many earlier rows of this array have the same node (0 for a node's first row)."""
    s = np.sort(node)
    if node.size < 2 or (s[1:] != s[:-1]).all():
        return np.zeros(node.size, dtype=np.int64)
    order = np.argsort(node, kind="stable")
    s = node[order]
    first = np.concatenate(([True], s[1:] != s[:-1]))
    start = np.maximum.accumulate(np.where(first, np.arange(s.size), 0))
    rank = np.empty(node.size, dtype=np.int64)
    rank[order] = np.arange(s.size) - start
    return rank


class _NodeState:
    """Per node, within one bus and one file: the last counter, the counts' average, whether seen."""

    def __init__(self) -> None:
        self.prev_node = 0
        self.counter = np.full(_NODES, -1, dtype=np.int64)
        self.ref16 = np.zeros((_NODES, 3), dtype=np.int64)
        self.seen = np.zeros(_NODES, dtype=bool)

    def walk(self, node: np.ndarray, xyz: np.ndarray, counter: np.ndarray):
        """Rows in order, in rounds (a node seen twice in one array: each row after its node's
        earlier one): yields ``(rows, nodes, predicted counts, expected counters)`` of a round; the
        caller then has ``xyz[rows]`` and ``counter[rows]`` filled (given when encoding, computed
        from the residuals when expanding), and the state takes them in."""
        rank = _ranks(node)
        for r in range(int(rank.max()) + 1 if rank.size else 0):
            i = np.flatnonzero(rank == r)
            nd = node[i]
            seen = self.seen[nd, None]
            yield i, nd, np.where(seen, (self.ref16[nd] + 8) >> 4, 0), (self.counter[nd] + 1) & 0xFFFF
            c16 = xyz[i] << 4
            self.ref16[nd] = np.where(seen, self.ref16[nd] + ((c16 - self.ref16[nd]) >> _SHIFT), c16)
            self.seen[nd] = True
            self.counter[nd] = counter[i]
        if node.size:
            self.prev_node = int(node[-1])


def _signed16(v: np.ndarray) -> np.ndarray:
    """``v`` modulo 2**16 as int16 values in [-32768, 32767]."""
    return ((v + 0x8000) & 0xFFFF) - 0x8000


def _zigzag(v: np.ndarray) -> np.ndarray:
    """Signed int64 to unsigned, small magnitudes small: 0, -1, 1, -2 -> 0, 1, 2, 3."""
    return (v << 1) ^ (v >> 63)


def _unzigzag(u: np.ndarray) -> np.ndarray:
    return (u >> 1) ^ -(u & 1)


def _planes(u: np.ndarray, width: int = 2) -> bytes:
    """Unsigned values of ``width`` bytes as all their lowest bytes, then all the next, ... (zstd
    codes each plane apart: the high bytes of small numbers are all alike)."""
    le = np.ascontiguousarray(u, dtype=f"<u{width}").ravel().view(np.uint8).reshape(-1, width)
    return le.T.tobytes()


def _unplanes(b: bytes, n: int, width: int = 2) -> np.ndarray:
    """`_planes` undone: ``n`` values (int64), or None when ``b`` is not ``n`` values of ``width`` bytes."""
    if len(b) != n * width:
        return None
    planes = np.frombuffer(b, dtype=np.uint8).reshape(width, n)
    return np.ascontiguousarray(planes.T).view(f"<u{width}").ravel().astype(np.int64)


def has_frame_span(data: bytes) -> bool:
    """Whether ``data`` holds a span ``<14 non-zero bytes> 0x00`` (the first at its start): the only
    place a SAMPLE frame can be (`SerialCompactor.spans` looks no further)."""
    a = np.frombuffer(data, dtype=np.uint8)
    zeros = np.flatnonzero(a == 0)
    if not zeros.size:
        return False
    if zeros[0] == _ENC:
        return True
    return bool((np.diff(zeros) == FRAME_SPAN).any())


class SerialCompactor:
    """One bus's serial chunks, in order, as ``capsheet.v2.RawSerialFrames`` messages (one file)."""

    def __init__(self) -> None:
        self._state = _NodeState()
        from host.record import schema as P
        self._cls = P.message_class(SCHEMA)

    def spans(self, data: bytes):
        """The SAMPLE frames of ``data`` that re-encode to themselves: their starts (int64 (n,), each
        the first of 15 bytes ending in the delimiter) and fields (node, counter, counts (n, 3), status)."""
        a = np.frombuffer(data, dtype=np.uint8)
        zeros = np.flatnonzero(a == 0)
        if not zeros.size:
            return zeros, _fields(np.zeros((0, _BODY), dtype=np.uint8))
        begin = np.concatenate(([0], zeros[:-1] + 1))
        start = begin[zeros - begin == _ENC]
        enc = a[start[:, None] + _OUT_POS]
        body, ok = _cobs_decode_rows(enc)
        ok &= (body[:, 0] == PROTOCOL_VERSION) & (body[:, 1] == int(MsgType.SAMPLE))
        if not ok.all():
            start, enc, body = start[ok], enc[ok], body[ok]
        fields = _fields(body)
        # the frame as it would be rebuilt from its fields: only a byte-for-byte match is compacted
        same = (_cobs_encode_rows(_bodies(*fields)) == enc).all(axis=1)
        if not same.all():
            return start[same], tuple(f[same] for f in fields)
        return start, fields

    def encode(self, data: bytes, *, bus: int, t: float, t_rx: float) -> bytes:
        """The serialized message of one chunk ``data`` of bus ``bus`` read at ``t_rx``, taken in at ``t``."""
        data = bytes(data)
        if not has_frame_span(data):
            # no 15-byte span at all (a packing gateway's SNAPSHOT frames, ~1 KB each): the message
            # holds the chunk as it came and the state is left as it was, what the general path
            # below makes of a chunk without SAMPLE frames; at ~0.1 ms a chunk less (five 64x64
            # gateways: ~0.5 ms per SYNC, in the receive path)
            return self._cls(bus=int(bus), t=float(t), t_rx=float(t_rx), raw=data).SerializeToString()
        start, (node, counter, xyz, status) = self.spans(data)
        n = node.size
        resid = np.zeros((n, 3), dtype=np.int64)
        dcounter = np.zeros(n, dtype=np.int64)
        prev_node = self._state.prev_node
        for i, _nd, pred, expect in self._state.walk(node, xyz, counter):
            resid[i] = xyz[i] - pred
            dcounter[i] = counter[i] - expect
        keep = np.ones(len(data), dtype=bool)
        if n:
            keep[start[:, None] + np.arange(FRAME_SPAN)] = False
        at = np.cumsum(keep)[start]  # raw bytes before each frame (a frame's first byte is not raw)
        msg = self._cls(bus=int(bus), t=float(t), t_rx=float(t_rx),
                        raw=np.frombuffer(data, np.uint8)[keep].tobytes())
        if n:
            msg.gap = _planes(at - np.concatenate(([0], at[:-1])), 4)
            msg.node = _planes((node - np.concatenate(([prev_node], node[:-1]))) & 0xFFFF)
            msg.counter = _planes(dcounter & 0xFFFF)
            msg.counts = _planes(_zigzag(resid))
            msg.status = status.astype(np.uint8).tobytes()
        return msg.SerializeToString()


class SerialExpander:
    """One bus's ``capsheet.v2.RawSerialFrames`` messages, in order, back to the chunks as read (one file)."""

    def __init__(self) -> None:
        self._state = _NodeState()

    def expand(self, msg) -> bytes:
        """The chunk of one parsed message. Raises `CompactError` (one line) when its columns do not fit."""
        raw = np.frombuffer(msg.raw, dtype=np.uint8)
        n = len(msg.status)
        if not n:
            if msg.gap or msg.node or msg.counter or msg.counts:
                raise CompactError("RawSerialFrames has columns but no status bytes")
            return raw.tobytes()
        gap, dnode, dcounter = (_unplanes(msg.gap, n, 4), _unplanes(msg.node, n), _unplanes(msg.counter, n))
        counts = _unplanes(msg.counts, 3 * n)
        if gap is None or dnode is None or dcounter is None or counts is None:
            raise CompactError(f"RawSerialFrames columns disagree: {n} frames' status but {len(msg.gap)} gap, "
                               f"{len(msg.node)} node, {len(msg.counter)} counter, {len(msg.counts)} counts bytes")
        at = np.cumsum(gap)
        if at[-1] > raw.size:
            raise CompactError(f"RawSerialFrames gaps reach byte {int(at[-1])} of {raw.size} raw bytes")
        node = (self._state.prev_node + np.cumsum(dnode)) & 0xFFFF
        resid = _unzigzag(counts).reshape(n, 3)
        status = np.frombuffer(msg.status, dtype=np.uint8).astype(np.int64)
        if (status > 0xF).any():
            raise CompactError("RawSerialFrames status over 4 bits")
        xyz = np.zeros((n, 3), dtype=np.int64)
        counter = np.zeros(n, dtype=np.int64)
        for i, _nd, pred, expect in self._state.walk(node, xyz, counter):
            xyz[i] = pred + resid[i]
            counter[i] = (expect + dcounter[i]) & 0xFFFF
        if ((xyz < -2048) | (xyz > 2047)).any():
            raise CompactError("RawSerialFrames count out of the 12-bit range")
        frames = np.zeros((n, FRAME_SPAN), dtype=np.uint8)
        frames[:, :_ENC] = _cobs_encode_rows(_bodies(node, counter, xyz, status))
        out = np.empty(raw.size + FRAME_SPAN * n, dtype=np.uint8)
        fstart = at + FRAME_SPAN * np.arange(n)
        is_frame = np.zeros(out.size, dtype=bool)
        idx = fstart[:, None] + np.arange(FRAME_SPAN)
        is_frame[idx] = True
        out[idx] = frames
        out[~is_frame] = raw
        return out.tobytes()


class CountsCoder:
    """A snapshot's counts ((n_links, 3) int16) against the same running average per link, in the
    order the snapshots are written (one file): ``counts_planes`` of ``capsheet.v2.Snapshot``.

    A link not valid in a snapshot is predicted 0 and leaves its average as it was (the aggregator
    records 0 there: the residual is then 0 too; any other value is still kept exactly). The same
    object encodes (`encode`) or decodes (`decode`); one per file, as `SerialCompactor`."""

    def __init__(self) -> None:
        self._ref16: np.ndarray | None = None
        self._seen: np.ndarray | None = None
        self._all_seen = False  # every link seen: the common case takes no masks

    # int32 throughout: 16 x an int16 count and the differences of two such fit, and a 64x64
    # snapshot's 24,192 counts are coded in the receive path 145 times a second
    def _prediction(self, n: int, valid: np.ndarray, every: bool) -> np.ndarray:
        if self._ref16 is None or self._ref16.shape[0] != n:  # the first snapshot (or another sheet)
            self._ref16 = np.zeros((n, 3), dtype=np.int32)
            self._seen = np.zeros(n, dtype=bool)
            self._all_seen = False
        pred = self._ref16 + 8
        pred >>= 4
        if not (every and self._all_seen):
            pred[~(self._seen & valid)] = 0
        return pred

    def _update(self, counts: np.ndarray, valid: np.ndarray, every: bool) -> None:
        c16 = counts << 4
        if every and self._all_seen:
            c16 -= self._ref16
            c16 >>= _SHIFT
            self._ref16 += c16
            return
        step = np.where(self._seen[:, None], self._ref16 + ((c16 - self._ref16) >> _SHIFT), c16)
        self._ref16 = np.where(valid[:, None], step, self._ref16)
        self._seen |= valid
        self._all_seen = bool(self._seen.all())

    def encode(self, counts, valid) -> bytes:
        """``counts`` (n_links, 3) int, ``valid`` (n_links,) bool -> the residuals' byte planes."""
        counts = np.asarray(counts).astype(np.int32)
        valid = np.asarray(valid, dtype=bool)
        every = bool(valid.all())
        resid = counts - self._prediction(counts.shape[0], valid, every)
        resid = _signed16(resid)  # int16 counts: modulo 2**16
        self._update(counts, valid, every)
        return _planes((resid << 1) ^ (resid >> 31))  # zigzag, as `_zigzag` for int32

    def decode(self, data: bytes, valid) -> np.ndarray:
        """The counts ((n_links, 3) int16) of `encode`'s bytes; `CompactError` when they do not fit."""
        valid = np.asarray(valid, dtype=bool)
        n = valid.shape[0]
        u = _unplanes(data, 3 * n)
        if u is None:
            raise CompactError(f"Snapshot counts_planes holds {len(data)} bytes, {n} links need {6 * n}")
        every = bool(valid.all())
        counts = _signed16(self._prediction(n, valid, every) + _unzigzag(u).reshape(n, 3).astype(np.int32))
        self._update(counts, valid, every)
        return counts.astype(np.int16)
