"""Serial framing (docs/protocol.md §6): header + payload + CRC, COBS-encoded, 0x00-delimited.

Sans-I/O: `encode` turns a message into wire bytes, `StreamDecoder.feed` turns wire bytes into
events. Wire input never raises: damage becomes a `DecodeError` event, counted in
`StreamDecoder.stats`, and every valid frame around it is still delivered.

Frame before COBS (little-endian fields, CRC big-endian so that the CRC over the whole is 0)::

    offset  size  field
    0       1     version   (PROTOCOL_VERSION = 1)
    1       1     type      (MsgType)
    2       2     node      (u16 LE)
    4       n     payload   (docs §4)
    4+n     2     CRC-16/CCITT-FALSE over bytes 0 .. 3+n, most significant byte first
"""

from __future__ import annotations

import struct
from collections import Counter
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
from cobs import cobs

from .crc import crc16_ccitt_false, crc16_rows
from .messages import (IMU_RECORD_SIZE, TIME_UNKNOWN, ImuBatch, ImuSample, SampleFormat, unpack_imu_records)
from .messages import (PROTOCOL_VERSION, MsgType, Message, PayloadError, Sample, SampleBatch, SAMPLE_WORD_SIZE,
                       STATUS_STATES, Snapshot, SnapshotFrames, Status, StatusBatch, decode_payload)

__all__ = ["HEADER", "HEADER_SIZE", "CRC_SIZE", "MAX_FRAME_SIZE", "MAX_PAYLOAD_SIZE", "MAX_ENCODED_SIZE",
           "SAMPLE_WIRE_SIZE", "ErrorReason", "DecodeError", "SampleBatch", "ImuBatch", "StatusBatch", "SnapshotFrames",
           "DecoderStats", "NATIVE_SCAN",
           "encode", "encode_frame", "decode_frame", "StreamDecoder", "cobs_encoded_size"]

HEADER = struct.Struct("<BBH")
assert HEADER.size == 4
HEADER_SIZE = HEADER.size
CRC_SIZE = 2
MAX_FRAME_SIZE = 1024  #: header + payload + CRC, before COBS (docs §6.3)
MAX_PAYLOAD_SIZE = MAX_FRAME_SIZE - HEADER_SIZE - CRC_SIZE  #: 1018


def cobs_encoded_size(n: int) -> int:
    """Size of ``n`` bytes after COBS, without the delimiter: ``n + 1 + n // 254``."""
    return n + 1 + n // 254


MAX_ENCODED_SIZE = cobs_encoded_size(MAX_FRAME_SIZE)  #: 1029: longer runs without 0x00 are OVERSIZE
#: A SAMPLE on the wire: COBS(4 + 7 + 2 = 13 bytes) = 14 bytes, plus the 0x00 delimiter.
SAMPLE_WIRE_SIZE = cobs_encoded_size(HEADER_SIZE + Sample.SIZE + CRC_SIZE) + 1
assert SAMPLE_WIRE_SIZE == 15


class ErrorReason(Enum):
    """Why a frame was dropped (docs §6.4). Every one is counted in `DecoderStats.errors`."""

    BAD_COBS = "bad_cobs"  #: the bytes between two delimiters are not valid COBS
    SHORT = "short"  #: shorter than header + CRC (6 bytes)
    BAD_CRC = "bad_crc"  #: CRC mismatch
    OVERSIZE = "oversize"  #: over MAX_ENCODED_SIZE bytes without a delimiter, or over MAX_FRAME_SIZE decoded
    BAD_VERSION = "bad_version"  #: version byte is not PROTOCOL_VERSION (an incompatible peer)
    UNKNOWN_TYPE = "unknown_type"  #: type code not defined
    BAD_LENGTH = "bad_length"  #: payload length does not match the type
    BAD_FIELD = "bad_field"  #: a field value out of range


@dataclass(frozen=True, slots=True)
class DecodeError:
    """A dropped frame. ``excerpt`` is up to the first 16 bytes of what was dropped (as received);
    ``version`` is the peer's version byte for BAD_VERSION."""

    reason: ErrorReason
    detail: str
    excerpt: bytes = b""
    version: int | None = None


@dataclass
class DecoderStats:
    """Counters of a `StreamDecoder`: bytes in, frames out, errors by reason."""

    bytes_in: int = 0
    frames: int = 0
    errors: Counter = field(default_factory=Counter)

    @property
    def error_count(self) -> int:
        return sum(self.errors.values())


def encode_frame(type_code: int, node: int, payload: bytes, version: int = PROTOCOL_VERSION) -> bytes:
    """Low level: one frame on the wire (COBS + trailing 0x00) from its parts, unvalidated
    except for size. Tests use it to build frames a conforming sender never would."""
    body = HEADER.pack(version, type_code, node) + payload
    if len(body) + CRC_SIZE > MAX_FRAME_SIZE:
        raise ValueError(f"Frame of {len(body) + CRC_SIZE} bytes exceeds MAX_FRAME_SIZE {MAX_FRAME_SIZE}")
    body += crc16_ccitt_false(body).to_bytes(2, "big")
    return cobs.encode(body) + b"\x00"


def encode(msg: Message) -> bytes:
    """A message as serial wire bytes: COBS(header + payload + CRC) + b'\\x00'."""
    return encode_frame(msg.TYPE, msg.node, msg.payload())


def decode_frame(encoded: bytes) -> Message | DecodeError:
    """Decode the bytes between two delimiters (without the 0x00). Never raises.

    The checks, in the order of docs/protocol.md §8.1: OVERSIZE (run), BAD_COBS, OVERSIZE (decoded
    frame over 1024 bytes), SHORT, BAD_CRC, BAD_VERSION, then the payload's (UNKNOWN_TYPE, BAD_FIELD
    for node 0xFFFF, BAD_LENGTH, BAD_FIELD)."""
    excerpt = bytes(encoded[:16])
    if len(encoded) > MAX_ENCODED_SIZE:
        return DecodeError(ErrorReason.OVERSIZE, f"frame exceeds {MAX_ENCODED_SIZE} bytes without a delimiter", excerpt)
    try:
        body = cobs.decode(encoded)
    except cobs.DecodeError as exc:
        return DecodeError(ErrorReason.BAD_COBS, str(exc), excerpt)
    if len(body) > MAX_FRAME_SIZE:  # COBS of a frame with zeros is shorter than the worst case
        return DecodeError(ErrorReason.OVERSIZE, f"frame of {len(body)} bytes exceeds {MAX_FRAME_SIZE}", excerpt)
    if len(body) < HEADER_SIZE + CRC_SIZE:
        return DecodeError(ErrorReason.SHORT, f"{len(body)} bytes, need at least {HEADER_SIZE + CRC_SIZE}", excerpt)
    if crc16_ccitt_false(body) != 0:
        return DecodeError(ErrorReason.BAD_CRC, f"CRC mismatch over {len(body)} bytes", excerpt)
    version, type_code, node = HEADER.unpack_from(body)
    if version != PROTOCOL_VERSION:
        return DecodeError(ErrorReason.BAD_VERSION,
                           f"peer speaks protocol version {version}, this is version {PROTOCOL_VERSION}",
                           excerpt, version)
    try:
        return decode_payload(type_code, node, body[HEADER_SIZE:-CRC_SIZE])
    except PayloadError as exc:
        return DecodeError(ErrorReason[exc.reason], exc.detail, excerpt)


_SAMPLE_ENC = SAMPLE_WIRE_SIZE - 1  # 14 encoded bytes between delimiters
_SAMPLE_DEC = _SAMPLE_ENC - 1  # 13 decoded bytes


#: the fast path's frames by encoded length between delimiters: SAMPLE (14), IMU_SAMPLE format 1
#: (22) and format 2 (28) (docs §6.3, §16.3)
_FAST_KINDS = {_SAMPLE_ENC: (1, MsgType.SAMPLE)}
for _f, _size in IMU_RECORD_SIZE.items():
    _FAST_KINDS[HEADER_SIZE + 2 + _size + CRC_SIZE + 1] = (1 + int(_f), MsgType.IMU_SAMPLE)
_STATUS_KIND = 4
#: STATUS (15 encoded bytes), on the fast path only with ``batch_status`` (`StatusBatch` events)
_STATUS_ENC = HEADER_SIZE + Status.SIZE + CRC_SIZE + 1
assert _STATUS_ENC not in _FAST_KINDS
_FAST_KINDS_STATUS = {**_FAST_KINDS, _STATUS_ENC: (_STATUS_KIND, MsgType.STATUS)}
assert sorted(k for k, _ in _FAST_KINDS_STATUS.values()) == [1, 2, 3, _STATUS_KIND]
#: a fast kind's decoded frame length (its encoded length less COBS's one overhead byte)
_FAST_DEC_LEN = {k: enc - 1 for enc, (k, _) in _FAST_KINDS_STATUS.items()}


_SNAPSHOT_KIND = 5  #: SNAPSHOT frames, on the fast path only with ``batch_snapshots`` (`SnapshotFrames`)


def _load_scan():
    """The compiled scan (protocol/_kernel/stream.c), or None: not built, or ``CAPSHEET_NO_KERNEL``
    set (then the numpy and per-frame Python code below decode alike)."""
    import os
    if os.environ.get("CAPSHEET_NO_KERNEL"):
        return None
    try:
        from ._stream_kernel import ffi, lib
    except ImportError:
        return None
    return ffi, lib


_SCAN = _load_scan()
#: True when `StreamDecoder` scans with the compiled kernel (protocol/_kernel/stream.c)
NATIVE_SCAN = _SCAN is not None
#: the scan's row of a fast kind: every decoded SAMPLE, STATUS and IMU_SAMPLE fits
_ROW_STRIDE = 32


def _scan_tables():
    """The scan's fast-kind tables (kind k at index k - 1): decoded lengths, and the types by
    ``batch_status`` (STATUS only with it, which a host sets; -1 matches no frame)."""
    if _SCAN is None:
        return None, {}
    lens, types = [0] * 4, {False: [0] * 4, True: [0] * 4}
    for k, m in _FAST_DEC_LEN.items():
        lens[k - 1] = m
    for k, ty in _FAST_KINDS_STATUS.values():
        types[True][k - 1] = int(ty)
        types[False][k - 1] = int(ty) if k != _STATUS_KIND else -1
    new = _SCAN[0].new
    return new("int32_t[4]", lens), {b: new("int32_t[4]", t) for b, t in types.items()}


_SCAN_LENS, _SCAN_TYPES = _scan_tables()


class _Scratch:
    """The compiled scan's output arrays, grown to the largest chunk seen (one set per decoder)."""

    def __init__(self) -> None:
        self.cap = 0

    def ensure(self, n: int) -> None:
        if n <= self.cap:
            return
        cap = max(n, 2 * self.cap, 1 << 12)
        nf, nsnap, nsamp = cap // 2 + 1, cap // 16 + 1, cap // SAMPLE_WORD_SIZE + 1
        self.start = np.empty(nf, np.int64)
        self.length = np.empty(nf, np.int64)
        self.kind = np.empty(nf, np.int8)
        self.rows = np.empty((nf, _ROW_STRIDE), np.uint8)
        self.snap_node = np.empty(nsnap, np.uint16)
        self.snap_counter = np.empty(nsnap, np.uint16)
        self.snap_first = np.empty(nsnap, np.uint16)
        self.snap_count = np.empty(nsnap, np.int64)
        self.s_counter = np.empty(nsamp, np.uint16)
        self.s_link = np.empty(nsamp, np.int64)
        self.s_counts = np.empty((nsamp, 3), np.int16)
        self.s_status = np.empty(nsamp, np.uint8)
        ffi = _SCAN[0]
        o = self.out = ffi.new("capsheet_scan_t *")
        p = lambda a, t: ffi.cast(t, a.ctypes.data)  # noqa: E731 - the arrays are kept on self
        o.start, o.length, o.kind = p(self.start, "int64_t *"), p(self.length, "int64_t *"), p(self.kind, "int8_t *")
        o.rows, o.row_stride = p(self.rows, "uint8_t *"), _ROW_STRIDE
        o.snap_node, o.snap_counter = p(self.snap_node, "uint16_t *"), p(self.snap_counter, "uint16_t *")
        o.snap_first, o.snap_count = p(self.snap_first, "uint16_t *"), p(self.snap_count, "int64_t *")
        o.s_counter, o.s_link = p(self.s_counter, "uint16_t *"), p(self.s_link, "int64_t *")
        o.s_counts, o.s_status = p(self.s_counts, "int16_t *"), p(self.s_status, "uint8_t *")
        self.cap = cap


def _fast_samples(rows: np.ndarray, msg_type: int = MsgType.SAMPLE) -> tuple[np.ndarray, np.ndarray]:
    """COBS-decode and check ``(n, L)`` candidate frames of one type and length at once (SAMPLE:
    L = 14; IMU_SAMPLE: 22 or 28).

    Returns ``(ok mask (n,), decoded (n, L - 1))``. Rows not ok go to the exact slow path, which
    reports the precise reason; rows ok are exactly those `decode_frame` would accept.
    """
    n, enc = rows.shape
    r = rows.astype(np.int64)
    dec = np.empty((n, enc - 1), dtype=np.int64)
    nxt = r[:, 0].copy()  # position of the next code byte
    for p in range(1, enc):
        is_code = nxt == p
        dec[:, p - 1] = np.where(is_code, 0, r[:, p])
        nxt = np.where(is_code, p + r[:, p], nxt)
    ok = nxt == enc
    ok &= crc16_rows(dec) == 0
    ok &= dec[:, 0] == PROTOCOL_VERSION
    ok &= dec[:, 1] == msg_type
    ok &= (dec[:, 3] << 8 | dec[:, 2]) != 0xFFFF
    return ok, dec


class StreamDecoder:
    """Feed serial bytes, get messages and `DecodeError` events, in wire order.

    Parameters
    ----------
    batch_samples : bool
        If true, runs of SAMPLE frames come out as one `SampleBatch` each instead of `Sample`
        messages (the host's fast path: millions of samples per second).
    batch_status : bool
        If true, runs of STATUS frames come out as one `StatusBatch` each instead of `Status`
        messages (a host's heartbeats: one per chip per second, 8,064 a second from a 64x64 sheet,
        more frames than its packed samples). The same frames are accepted either way.
    batch_snapshots : bool
        If true, runs of SNAPSHOT frames come out as one `SnapshotFrames` each instead of
        `Snapshot` messages (a host's packing gateways). The same frames are accepted either way.
    native : bool or None
        Scan with the compiled kernel (protocol/_kernel/stream.c): one pass over a read in C
        instead of numpy per frame kind and Python per SNAPSHOT. None (default): when it is built
        (`NATIVE_SCAN`). The events are the same either way (tests/protocol/test_stream_kernel.py).

    The decoder holds at most ``MAX_ENCODED_SIZE`` bytes of an incomplete frame: a longer run
    without a delimiter is reported once as OVERSIZE and skipped up to the next 0x00.
    Whole input, byte by byte, or any chunking give the same events.
    """

    def __init__(self, *, batch_samples: bool = False, batch_status: bool = False, batch_snapshots: bool = False,
                 native: bool | None = None) -> None:
        self.batch_samples = batch_samples
        self.batch_status = batch_status
        self.batch_snapshots = batch_snapshots
        if native and not NATIVE_SCAN:
            raise ValueError("The compiled stream scan is not available (protocol/_kernel/stream.c not built, "
                             "or CAPSHEET_NO_KERNEL set)")
        self.native = NATIVE_SCAN if native is None else bool(native)
        self._scratch = _Scratch() if self.native else None
        self.stats = DecoderStats()
        self._partial = bytearray()
        self._discarding = False

    @property
    def pending_bytes(self) -> int:
        """Bytes of an incomplete frame held, waiting for their 0x00 delimiter."""
        return len(self._partial)

    def reset(self) -> None:
        """Forget any partial frame (e.g. after the port was reopened)."""
        self._partial.clear()
        self._discarding = False

    def feed(self, data: bytes) -> list:
        """Consume ``data``; return the events of every frame it completes."""
        self.stats.bytes_in += len(data)
        events: list = []
        last = data.rfind(b"\x00")
        if last < 0:
            self._grow(data, events)
            return events
        if self._discarding:
            first = data.find(b"\x00")
            self._discarding = False
            self._partial.clear()
            chunk = bytes(data[first + 1:last + 1])
        elif self._partial:  # the held frame's end and the frames after it: one chunk, one pass
            chunk = bytes(self._partial) + bytes(data[:last + 1])
            self._partial.clear()
        else:
            chunk = bytes(data[:last + 1])
        self._decode_chunk(chunk, events)
        self._grow(data[last + 1:], events)
        return events

    def _grow(self, tail: bytes, events: list) -> None:
        if self._discarding or not tail:
            return
        self._partial += tail
        if len(self._partial) > MAX_ENCODED_SIZE:
            events.append(self._error(DecodeError(
                ErrorReason.OVERSIZE, f"frame exceeds {MAX_ENCODED_SIZE} bytes without a delimiter",
                bytes(self._partial[:16]))))
            self._partial.clear()
            self._discarding = True

    def _error(self, err: DecodeError) -> DecodeError:
        self.stats.errors[err.reason] += 1
        return err

    def _slow(self, seg: bytes, events: list) -> None:
        ev = decode_frame(seg)
        if isinstance(ev, DecodeError):
            events.append(self._error(ev))
        else:
            self.stats.frames += 1
            events.append(ev)

    def _decode_chunk(self, chunk: bytes, events: list) -> None:
        """Decode ``chunk``, which ends with 0x00, frame by frame in order."""
        if not chunk:
            return
        if self.native:
            self._scan_chunk(chunk, events)
            return
        if not self.batch_snapshots:
            self._numpy_chunk(chunk, events)
            return
        mine: list = []
        self._numpy_chunk(chunk, mine)
        run: list = []  # runs of SNAPSHOT frames, one SnapshotFrames each (as the compiled scan gives them)
        for ev in mine:
            if type(ev) is Snapshot:
                run.append(ev)
                continue
            if run:
                events.append(SnapshotFrames.from_frames(run))
                run = []
            events.append(ev)
        if run:
            events.append(SnapshotFrames.from_frames(run))

    def _scan_chunk(self, chunk: bytes, events: list) -> None:
        """`_decode_chunk` with the compiled scan: kinds, decoded rows and SNAPSHOT samples in one C
        pass; the frames it does not take go to `decode_frame`, as in `_numpy_chunk`."""
        ffi, lib = _SCAN
        sc = self._scratch
        sc.ensure(len(chunk))
        nf = lib.capsheet_scan_chunk(ffi.from_buffer(chunk), len(chunk), PROTOCOL_VERSION, MAX_FRAME_SIZE, 4,
                                     _SCAN_TYPES[bool(self.batch_status)], _SCAN_LENS,
                                     MsgType.SNAPSHOT if self.batch_snapshots else -1, sc.out)
        if nf == 0:
            return
        kind = sc.kind[:nf]
        if self.batch_status:  # what Status._validate refuses goes the exact slow way
            st = np.flatnonzero(kind == _STATUS_KIND)
            if st.size:
                bad = ~np.isin(sc.rows[st, HEADER_SIZE], STATUS_STATES)
                kind[st[bad]] = 0
        if not kind.any():
            for s, n in zip(sc.start[:nf].tolist(), sc.length[:nf].tolist()):
                self._slow(chunk[s:s + n], events)
            return
        edges = np.flatnonzero(kind[1:] != kind[:-1]) + 1
        bounds = [0, *edges.tolist(), nf]
        kinds = kind[bounds[:-1]].tolist()
        snap_i = 0
        samp_i = 0
        for a, b, k in zip(bounds[:-1], bounds[1:], kinds):
            if k == _SNAPSHOT_KIND:
                j = snap_i + (b - a)
                sizes = sc.snap_count[snap_i:j].copy()
                m = samp_i + int(sizes.sum())
                self.stats.frames += b - a
                events.append(SnapshotFrames(sc.snap_node[snap_i:j].copy(), sc.snap_counter[snap_i:j].copy(),
                                             sc.snap_first[snap_i:j].copy(), sizes, sc.s_counter[samp_i:m].copy(),
                                             sc.s_link[samp_i:m].copy(), sc.s_counts[samp_i:m].copy(),
                                             sc.s_status[samp_i:m].copy()))
                snap_i, samp_i = j, m
            elif k == 0:
                for s, n in zip(sc.start[a:b].tolist(), sc.length[a:b].tolist()):
                    self._slow(chunk[s:s + n], events)
            else:
                d = sc.rows[a:b, :_FAST_DEC_LEN[k]].astype(np.int64)
                if k == 1:
                    self._emit_samples(d, events)
                elif k == _STATUS_KIND:
                    self._emit_status(d, events)
                else:
                    self._emit_imu(d, SampleFormat(k - 1), events)

    def _numpy_chunk(self, chunk: bytes, events: list) -> None:
        """`_decode_chunk` without the compiled scan: numpy per fast frame kind, `decode_frame` per
        other frame."""
        buf = np.frombuffer(chunk, dtype=np.uint8)
        ends = np.flatnonzero(buf == 0)
        starts = np.empty_like(ends)
        starts[0] = 0
        starts[1:] = ends[:-1] + 1
        lengths = ends - starts
        keep = lengths > 0  # empty frames (repeated delimiters) are idle fill, not errors
        starts, lengths = starts[keep], lengths[keep]
        if starts.size == 0:
            return
        kind = np.zeros(starts.size, dtype=np.int8)  # 0 slow, 1 SAMPLE, 2/3 IMU_SAMPLE format 1/2
        decs: dict[int, np.ndarray] = {}
        row_of = np.zeros(starts.size, dtype=np.int64)
        fast = _FAST_KINDS_STATUS if self.batch_status else _FAST_KINDS
        for enc, (k, t) in fast.items():
            cand = np.flatnonzero(lengths == enc)
            if cand.size:
                rows = buf[starts[cand, None] + np.arange(enc)]
                ok, dec = _fast_samples(rows, t)
                if k == _STATUS_KIND:  # what Status._validate refuses goes the exact slow way
                    ok &= np.isin(dec[:, HEADER_SIZE], STATUS_STATES)
                kind[cand[ok]] = k
                decs[k] = dec[ok]
                row_of[cand[ok]] = np.arange(int(ok.sum()))
        if not kind.any():
            for s, n in zip(starts.tolist(), lengths.tolist()):
                self._slow(chunk[s:s + n], events)
            return
        edges = np.flatnonzero(np.diff(kind)) + 1
        bounds = np.concatenate([[0], edges, [starts.size]])
        for a, b in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
            k = int(kind[a])
            if k == 1:
                self._emit_samples(decs[1][row_of[a]:row_of[b - 1] + 1], events)
            elif k == _STATUS_KIND:
                self._emit_status(decs[k][row_of[a]:row_of[b - 1] + 1], events)
            elif k:
                self._emit_imu(decs[k][row_of[a]:row_of[b - 1] + 1], SampleFormat(k - 1), events)
            else:
                for s, n in zip(starts[a:b].tolist(), lengths[a:b].tolist()):
                    self._slow(chunk[s:s + n], events)

    def _emit_imu(self, d: np.ndarray, fmt: SampleFormat, events: list) -> None:
        self.stats.frames += d.shape[0]
        node = (d[:, 2] | (d[:, 3] << 8)).astype(np.uint16)
        counter = (d[:, 4] | (d[:, 5] << 8)).astype(np.uint16)
        size = IMU_RECORD_SIZE[fmt]
        counts, status, t_us, gyro, mag = unpack_imu_records(d[:, 6:6 + size].astype(np.uint8).reshape(-1), fmt)
        batch = ImuBatch(node, counter, counts, status, t_us, gyro, mag)
        if self.batch_samples:
            events.append(batch)
        else:
            events.extend(batch.messages())

    def _emit_status(self, d: np.ndarray, events: list) -> None:
        self.stats.frames += d.shape[0]
        p = HEADER_SIZE
        events.append(StatusBatch(
            (d[:, 2] | (d[:, 3] << 8)).astype(np.uint16), d[:, p].astype(np.uint8), d[:, p + 1].astype(np.uint8),
            d[:, p + 2].astype(np.uint8), d[:, p + 3].astype(np.uint8),
            (d[:, p + 4] | (d[:, p + 5] << 8) | (d[:, p + 6] << 16) | (d[:, p + 7] << 24)).astype(np.uint32)))

    def _emit_samples(self, d: np.ndarray, events: list) -> None:
        self.stats.frames += d.shape[0]
        node = (d[:, 2] | (d[:, 3] << 8)).astype(np.uint16)
        counter = (d[:, 4] | (d[:, 5] << 8)).astype(np.uint16)
        w = d[:, 6] | (d[:, 7] << 8) | (d[:, 8] << 16) | (d[:, 9] << 24) | (d[:, 10] << 32)
        axes = np.stack([(w >> s) & 0xFFF for s in (0, 12, 24)], axis=1)
        counts = (axes - ((axes & 0x800) << 1)).astype(np.int16)
        status = ((w >> 36) & 0xF).astype(np.uint8)
        if self.batch_samples:
            events.append(SampleBatch(node, counter, counts, status))
        else:
            events.extend(SampleBatch(node, counter, counts, status).messages())


assert SAMPLE_WORD_SIZE == 5
