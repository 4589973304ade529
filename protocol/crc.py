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

__all__ = ["crc16_ccitt_false", "CRC_INIT", "CRC_POLY", "CRC_CHECK", "crc16_rows"]

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


_TABLE = _table().astype(np.int64)


def crc16_rows(rows: np.ndarray) -> np.ndarray:
    """CRC-16/CCITT-FALSE of every row of a ``(n, m)`` uint8 array, vectorised over rows.

    Used by the batch fast path of the stream decoder; agrees with `crc16_ccitt_false` row by row.
    """
    crc = np.full(rows.shape[0], CRC_INIT, dtype=np.int64)
    r = rows.astype(np.int64)
    for k in range(rows.shape[1]):
        crc = ((crc << 8) & 0xFFFF) ^ _TABLE[((crc >> 8) ^ r[:, k]) & 0xFF]
    return crc
