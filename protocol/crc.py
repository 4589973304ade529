"""CRC-16/CCITT-FALSE, the serial frame check (docs/protocol.md §6.2).

Catalogue parameters (Greg Cook's CRC RevEng catalogue, "CRC-16/IBM-3740", alias CCITT-FALSE):
width 16, poly 0x1021, init 0xFFFF, refin false, refout false, xorout 0x0000, check 0x29B1,
residue 0x0000. The CRC is sent most significant byte first, so the CRC over a whole frame
including its CRC is 0 — which is how receivers check it.

>>> hex(crc16_ccitt_false(b"123456789"))
'0x29b1'
>>> crc16_ccitt_false(b"123456789" + bytes([0x29, 0xB1]))
0
"""

from __future__ import annotations

import binascii

import numpy as np

__all__ = ["crc16_ccitt_false", "CRC_INIT", "CRC_POLY", "CRC_CHECK", "CRC_TABLE", "crc16_rows"]

CRC_POLY = 0x1021
CRC_INIT = 0xFFFF
CRC_CHECK = 0x29B1  #: CRC of b"123456789"


def crc16_ccitt_false(data: bytes, crc: int = CRC_INIT) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (``binascii.crc_hqx`` computes this polynomial in C)."""
    return binascii.crc_hqx(data, crc)


def _table() -> np.ndarray:
    t = np.zeros(256, dtype=np.uint16)
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ CRC_POLY) if c & 0x8000 else (c << 1)
        t[i] = c & 0xFFFF
    return t


#: The byte-wise table: ``CRC_TABLE[b]`` is the register (init 0) after byte ``b``, uint16 (256,).
#: The one table of the project (the stream decoder's batch path, the simulated chips' encoders).
CRC_TABLE = _table()
CRC_TABLE.setflags(write=False)


def crc16_rows(rows: np.ndarray) -> np.ndarray:
    """CRC-16/CCITT-FALSE of every row of a ``(n, m)`` array of bytes, vectorised over rows: uint16 (n,).

    Used by the batch fast path of the stream decoder and the simulated chips' batch encoders;
    agrees with `crc16_ccitt_false` row by row. Rows up to `_POSITION_MAX` bytes (every SAMPLE and
    IMU_SAMPLE body) take one gather from per-position tables (`_position_tables`) instead of a
    numpy step per byte.

    >>> rows = np.frombuffer(b"123456789" * 2, np.uint8).reshape(2, 9)
    >>> [hex(int(c)) for c in crc16_rows(rows)]
    ['0x29b1', '0x29b1']
    """
    rows = np.asarray(rows)
    if rows.dtype != np.uint8:
        rows = rows.astype(np.uint8)  # byte values in a wider integer type
    n, m = rows.shape
    if 0 < m <= _POSITION_MAX:
        flat, c0, offsets = _position_tables(m)
        terms = flat[rows + offsets]  # (n, m): each byte's term at its place
        return np.bitwise_xor.reduce(terms, axis=1) ^ np.uint16(c0)
    crc = np.full(n, CRC_INIT, dtype=np.uint16)
    for k in range(m):
        crc = (crc << np.uint16(8)) ^ CRC_TABLE[(crc >> np.uint16(8)) ^ rows[:, k]]
    return crc


#: the longest row `crc16_rows` takes by position tables (m × 256 entries each, kept per length)
_POSITION_MAX = 64
_POSITION_TABLES: dict[int, tuple[np.ndarray, int, np.ndarray]] = {}


def crc_position_tables(m: int) -> tuple[np.ndarray, int]:
    """The CRC of an ``m``-byte message term by term: ``(t (m, 256) uint16, c0)`` with
    ``crc(b) = c0 ^ t[0][b[0]] ^ ... ^ t[m-1][b[m-1]]`` (see `_position_tables`; read-only, kept per
    length). For encoders that fold the CRC into their own tables (the virtual chip array's)."""
    flat, c0, _ = _position_tables(m)
    return flat.reshape(m, 256), c0


def _position_tables(m: int) -> tuple[np.ndarray, int, np.ndarray]:
    """CRC-16/CCITT-FALSE of an ``m``-byte message as a sum of per-byte terms: the register update
    is linear over GF(2), so ``crc(b) = c0 ^ t[0][b[0]] ^ ... ^ t[m-1][b[m-1]]`` with ``t[j][v]``
    the CRC (init 0) of byte ``v`` at place ``j`` and zeros after it, and ``c0`` the CRC (init
    0xFFFF) of ``m`` zero bytes. Returns ``(t flattened (m·256,) uint16, c0, offsets 256·j (m,))``."""
    e = _POSITION_TABLES.get(m)
    if e is None:
        t = np.zeros((m, 256), dtype=np.uint16)
        for j in range(m):
            c = CRC_TABLE.copy()  # byte v at place j, init 0: the register after it is TABLE[v]
            for _ in range(m - 1 - j):  # then the zero bytes after it
                c = (c << np.uint16(8)) ^ CRC_TABLE[c >> np.uint16(8)]
            t[j] = c
        t.setflags(write=False)
        offsets = (np.arange(m, dtype=np.intp) * 256)
        e = _POSITION_TABLES[m] = (t.reshape(-1), crc16_ccitt_false(bytes(m)), offsets)
    return e
