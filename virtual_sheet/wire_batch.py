"""SAMPLE frames for many chips at once, as bytes: the virtual sheet's chips encode a whole SYNC's
answers in one numpy pass (COBS, CRC and header of every row together) instead of a frame at a time.
`ChipArray` (virtual_sheet/chiparray.py) sends what these make; the tests hold them to the Python
encoder of protocol/framing.py byte for byte."""

from __future__ import annotations

import numpy as np

from protocol.crc import crc_position_tables
from protocol.messages import PROTOCOL_VERSION, MsgType

__all__ = ["cobs_encode_batch", "encode_samples_serial", "word_fields", "samples_rows", "samples_wire",
           "SampleCodec", "SampleEncoder", "sample_codec"]


def cobs_encode_batch(rows: np.ndarray) -> np.ndarray:
    """COBS (``cobs.cobs.encode``) of every row of ``rows`` (m, k) uint8, k < 254: (m, k + 1).

    >>> from cobs import cobs
    >>> rows = np.array([[0, 1, 0, 2], [3, 4, 5, 6]], np.uint8)
    >>> [bytes(r) for r in cobs_encode_batch(rows)] == [cobs.encode(bytes(r)) for r in rows]
    True
    """
    m, k = rows.shape
    if k >= 254:
        raise ValueError(f"Invalid row length {k} (COBS batch needs < 254)")
    zero = np.concatenate([rows == 0, np.ones((m, 1), dtype=bool)], axis=1)  # a virtual zero at k
    pos = np.where(zero, np.arange(k + 1), k + 1)
    nxt = np.minimum.accumulate(pos[:, ::-1], axis=1)[:, ::-1]  # index of the next zero at or after j
    out = np.empty((m, k + 1), dtype=np.uint8)
    out[:, 0] = nxt[:, 0] + 1
    after = nxt[:, 1:] - np.arange(k)  # for a zero at i: distance to the next zero after it
    out[:, 1:] = np.where(zero[:, :k], after, rows)
    return out


def _cobs_codes(zero: np.ndarray) -> np.ndarray:
    """COBS of rows whose zero bytes are where ``zero`` (m, k) bool is set: the code bytes at
    their places (and byte 0), 0 at the copied bytes, (m, k + 1) uint8 — so that
    ``COBS(row) = codes | (0, *row)``: the code bytes sit exactly where the row's zeros are."""
    enc = cobs_encode_batch(np.where(zero, 0, 1).astype(np.uint8))
    enc[:, 1:][~zero] = 0
    return enc


def _cobs_table(k: int) -> np.ndarray:
    """`_cobs_codes` of a ``k``-byte row, by where its zeros are (row ``z``: bit i set, byte i is 0)."""
    z = np.arange(1 << k, dtype=np.int64)
    return _cobs_codes(((z[:, None] >> np.arange(k)) & 1).astype(bool))


# `SampleCodec.table`: where the entries of each input start
_X, _Y, _Z, _S = 0, 4096, 8192, 12288
_FIELD_ENTRIES = 12288 + 16
_FIELD_OFF = np.array([[_X], [_Y], [_Z]], dtype=np.intp)
_FIELD_MASK = np.int64(0xFFF)


class SampleCodec:
    """SAMPLE frames as two little-endian 64-bit lanes per frame, from one table gather.

    One SAMPLE on the wire, as a 16-byte row (the last byte is padding)::

        0 COBS code | 1 version | 2 type | 3-4 node | 5-6 counter | 7-11 word | 12-13 CRC | 14 0x00

    The word's bytes are x (12 bits), y, z, status (4 bits) back to back. Every table entry is
    such a row, 16 bytes, holding what one input adds to the frame before COBS: its bits at their
    place, its term of the CRC (linear over GF(2), `protocol.crc.crc_position_tables`) at the CRC's place
    (lane 1 bits 32-47, high byte first), and zero flags at lane 1 bits 48-58 (`_zero_bits`). The
    inputs touch distinct bits except the CRC's, so the frame before COBS is the XOR of one entry
    per input: the 12-bit x, y and z (4096 entries each), the status (16), the node with the fixed
    header (`node_entries`, kept per chip) and the counter (`counter_entry`, per SYNC). The CRC's
    two bytes add their zero flags by one lookup of the 16-bit CRC (`crc_zero`, bits 11-12), and
    the 13-bit zero pattern then looks up every code byte of the frame at once (`cobs`); a `cobs`
    entry also carries the flags of lane 1 bits 48-58, so XORing it clears them and sets the code
    bytes (which sit exactly where the zeros are, and at byte 0). `SampleEncoder` runs it.

    A word byte made of two fields (x's high and y's low nibble; z's high nibble and the status)
    is 0 only if both parts are: each part flags "not 0" on its own bit, and the COBS table reads
    the byte as 0 when neither bit is set. int64 throughout (bit 63 wraps as in uint64).
    """

    #: the zero pattern's bits: body byte (before COBS) -> bit, or the two bits of a split byte
    #: (set when that part is *not* 0); version (0) and type (1) are constants, not in the pattern
    _zero_bits = {2: 0, 3: 1, 4: 2, 5: 3, 6: 4, 7: (5, 6), 8: 7, 9: 8, 10: (9, 10), 11: 11, 12: 12}

    def __init__(self) -> None:
        t, c0 = crc_position_tables(11)  # body bytes 0-10: version, type, node, counter, word
        t = self._t = t.astype(np.int64)

        def crc_at(crc):
            return ((crc >> 8) << 32) | ((crc & 0xFF) << 40)

        def flag(bit, cond):
            return np.asarray(cond).astype(np.int64) << (48 + bit)
        self._crc_at, self._flag = crc_at, flag
        zb = self._zero_bits
        tab = np.zeros((_FIELD_ENTRIES, 2), dtype=np.int64)
        v = np.arange(4096, dtype=np.int64)
        lo, hi = v & 0xFF, v >> 8  # x: word byte 0, low nibble of byte 1
        tab[_X:_X + 4096, 0] = lo << 56
        tab[_X:_X + 4096, 1] = hi | crc_at(t[6][lo] ^ t[7][hi]) | flag(zb[6], lo == 0) | flag(zb[7][0], hi != 0)
        lo, hi = v & 0xF, v >> 4  # y: high nibble of word byte 1, byte 2
        tab[_Y:_Y + 4096, 1] = ((lo << 4) | (hi << 8) | crc_at(t[7][lo << 4] ^ t[8][hi]) | flag(zb[7][1], lo != 0)
                                | flag(zb[8], hi == 0))
        lo, hi = v & 0xFF, v >> 8  # z: word byte 3, low nibble of byte 4
        tab[_Z:_Z + 4096, 1] = ((lo << 16) | (hi << 24) | crc_at(t[9][lo] ^ t[10][hi]) | flag(zb[9], lo == 0)
                                | flag(zb[10][0], hi != 0))
        s = np.arange(16, dtype=np.int64)  # status: high nibble of word byte 4
        tab[_S:_S + 16, 1] = (s << 28) | crc_at(t[10][s << 4]) | flag(zb[10][1], s != 0)
        self.fields = tab
        hdr = (PROTOCOL_VERSION, int(MsgType.SAMPLE))
        self._hdr = hdr
        self._const = int(c0 ^ t[0][hdr[0]] ^ t[1][hdr[1]])  # CRC init and the fixed header's terms
        # the counter's two bytes (body 4-5, frame 5-6), Python ints: one entry per SYNC
        b = range(256)
        self._ctr_lo = [int(crc_at(t[4][i])) | (i == 0) << (48 + zb[4]) for i in b]
        self._ctr_hi = [int(crc_at(t[5][i])) | (i == 0) << (48 + zb[5]) for i in b]
        v = np.arange(1 << 16)  # the CRC as lane-1 bits 32-47 read as uint16: high byte, low byte
        self.crc_zero = ((((v & 0xFF) == 0).astype(np.uint16) << zb[11])
                         | (((v >> 8) == 0).astype(np.uint16) << zb[12]))
        # the COBS code bytes by zero pattern: the body's zero bytes from the pattern's bits
        z = np.arange(1 << 13, dtype=np.int64)
        bit = (z[:, None] >> np.arange(13)) & 1
        zero = np.zeros((1 << 13, 13), dtype=bool)
        zero[:, 0], zero[:, 1] = hdr[0] == 0, hdr[1] == 0
        for pos, k in zb.items():
            zero[:, pos] = (bit[:, k] == 1) if isinstance(k, int) else ((bit[:, k[0]] | bit[:, k[1]]) == 0)
        cobs16 = np.zeros((1 << 13, 16), dtype=np.uint8)
        cobs16[:, :14] = _cobs_codes(zero)
        cobs16.view("<i8")[:, 1] |= (z & 0x7FF) << 48  # XOR clears the flags
        self.cobs = np.ascontiguousarray(cobs16.view("V16")[:, 0])  # (8192,) 16-byte rows, gathered whole

    def node_entries(self, node: np.ndarray) -> np.ndarray:
        """(m, 2) int64: what the node (with the fixed header and the CRC's init) adds, per node."""
        nd = np.asarray(node).astype(np.int64)
        lo, hi = nd & 0xFF, nd >> 8
        e = np.empty((nd.size, 2), dtype=np.int64)
        e[:, 0] = self._hdr[0] << 8 | self._hdr[1] << 16 | (nd << 24)
        e[:, 1] = (self._crc_at(self._const ^ self._t[2][lo] ^ self._t[3][hi]) | self._flag(self._zero_bits[2], lo == 0)
                   | self._flag(self._zero_bits[3], hi == 0))
        return e

    def counter_entry(self, counter: int) -> tuple[int, int]:
        """What the counter adds: ``(lane 0, lane 1)``."""
        c = counter & 0xFFFF
        return c << 40, self._ctr_lo[c & 0xFF] ^ self._ctr_hi[c >> 8]


_CODEC: SampleCodec | None = None


def sample_codec() -> SampleCodec:
    global _CODEC
    if _CODEC is None:
        _CODEC = SampleCodec()
    return _CODEC


class SampleEncoder:
    """The SAMPLE frames of chips with the nodes ``node`` (n,): `SampleCodec` on one table of the
    field entries, one entry per chip and a slot for the counter; the gather indices and buffers
    of an all-chip SYNC are kept (the array builds a new encoder when a node changes). Per SYNC,
    every chip: the counts into the indices (a copy, a mask, an offset), one gather, one XOR
    reduction, two lookups (CRC zeros, COBS), one XOR — a dozen numpy calls whatever n is. Not
    reentrant (one caller at a time, as the array it belongs to)."""

    def __init__(self, node: np.ndarray, codec: SampleCodec | None = None) -> None:
        tb = self.codec = codec or sample_codec()
        node = np.asarray(node)
        n = self.n = node.size
        self.slot = _FIELD_ENTRIES + n  # the counter's entry, written per SYNC
        rows = np.concatenate([tb.fields, tb.node_entries(node), np.zeros((1, 2), dtype=np.int64)])
        self.lanes = rows  # (entries, 2) int64 ...
        self.table = rows.view("V16")[:, 0]  # ... and the same memory as 16-byte rows
        self.idx = self._indices(np.arange(n))
        self.buffers = self._buffers(n)

    def _indices(self, chips: np.ndarray) -> np.ndarray:
        """(6, m) gather indices: rows 0-2 x, y, z (per SYNC), 3 the chip's own entry, 4 the
        counter's slot, 5 the status (per SYNC, when some status is not 0)."""
        idx = np.empty((6, chips.size), dtype=np.intp)
        idx[3] = _FIELD_ENTRIES + chips
        idx[4] = self.slot
        return idx

    @staticmethod
    def _buffers(m: int):
        return (np.empty((6, m), dtype="V16"), np.empty(2 * m, dtype=np.int64), np.empty(m, dtype=np.uint16),
                np.empty(m, dtype="V16"))

    def encode(self, counter: int, counts: np.ndarray, status: np.ndarray | None,
               chips: np.ndarray | None = None) -> np.ndarray:
        """(m, 2) int64 lanes of the frames of every chip (``chips`` None: a buffer, valid until the
        next call) or of chips ``chips`` (indices into ``node``).

        ``counts`` (m, 3) ints, their low 12 bits sent; ``status`` (m,) SampleStatus bits (the low
        4 sent), or None when every one is 0."""
        tb = self.codec
        m = counts.shape[0]
        if chips is None:
            idx, (g, r, z, code) = self.idx, self.buffers
        else:
            idx, (g, r, z, code) = self._indices(np.asarray(chips)), self._buffers(m)
        self.lanes[self.slot] = tb.counter_entry(counter)
        f = idx[:3]
        np.copyto(f, counts.T, casting="unsafe")  # a contiguous copy first: the mask on it is cheaper
        np.bitwise_and(f, _FIELD_MASK, out=f)
        np.add(f, _FIELD_OFF, out=f)
        rows = 5
        if status is not None:
            np.bitwise_and(status, 0xF, out=idx[5], casting="unsafe")
            idx[5] += _S
            rows = 6
        # mode "clip": an unbuffered gather (the indices are in range)
        tb_rows = g[:rows]
        self.table.take(idx[:rows], out=tb_rows, mode="clip")
        np.bitwise_xor.reduce(tb_rows.view("<i8").reshape(rows, 2 * m), axis=0, out=r)  # the frames before COBS
        r16 = r.view(np.uint16).reshape(m, 8)  # 6: the CRC, 7: the zero flags
        np.bitwise_or(r16[:, 7], tb.crc_zero.take(r16[:, 6], mode="clip"), out=z)
        tb.cobs.take(z, out=code, mode="clip")
        np.bitwise_xor(r, code.view("<i8"), out=r)
        return r.reshape(m, 2)

    def wire(self, counter: int, counts: np.ndarray, status: np.ndarray | None,
             chips: np.ndarray | None = None) -> bytes:
        """The frames of `encode`, back to back, as the wire has them."""
        return samples_wire(self.encode(counter, counts, status, chips))


def word_fields(word: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """40-bit sample words (m,) as ``(counts (m, 3) 12-bit fields, status (m,))``."""
    w = np.asarray(word).astype(np.int64)
    return (w[:, None] >> np.array([0, 12, 24])) & 0xFFF, (w >> 36) & 0xF


def encode_samples_serial(node: np.ndarray, counter: int, word: np.ndarray) -> np.ndarray:
    """Every SAMPLE frame (version, SAMPLE, node, counter, 5-byte word, CRC, COBS, 0x00) as rows
    of a (m, 15) uint8 array: the bytes `protocol.framing.encode` gives for each.

    ``node`` (m,) ints < 65536, ``word`` (m,) 40-bit sample words (int64 or uint64)."""
    counts, status = word_fields(word)
    return samples_rows(SampleEncoder(node).encode(counter, counts, status))


def samples_rows(lanes: np.ndarray) -> np.ndarray:
    """The (m, 2) lanes of `SampleEncoder.encode` as (m, 15) uint8 frames (a view)."""
    return lanes.astype("<i8", copy=False).view(np.uint8).reshape(-1, 16)[:, :15]


def samples_wire(lanes: np.ndarray) -> bytes:
    """The (m, 2) lanes of `SampleEncoder.encode`: the m frames back to back, as the wire has them."""
    lanes = np.ascontiguousarray(lanes, dtype="<i8")
    # one 15-byte item per 16-byte row: a single copy loop (a (m, 15) uint8 slice copies row by row)
    return np.ndarray((lanes.shape[0],), dtype="V15", buffer=lanes, strides=(16,)).tobytes()
