"""A Vector BLF file checked before python-can reads it (`host.record.replay.load_can_log`).

python-can's BLF reader trusts the file's sizes: it reads the header's declared size, each object's
declared size, and inflates each zlib log container whole (``zlib.decompressobj().decompress``
without a limit: a 1 MB container of zeros is a gigabyte). Here, before python-can opens it, the
file is walked once with bounds: the header and every object must fit in the file, a container
may inflate to at most `MAX_CONTAINER_BYTES` (python-can writes 128 KiB ones) and all of them
together to at most `MAX_EXPANSION` times the file's size (at least `EXPANSION_FLOOR_BYTES`).
Inflating is streamed: never more than the bound is held. The layout is python-can's
(``can.io.blf``: ``LOGG`` file header, ``LOBJ`` objects, log container type 10, zlib method 2).
"""

from __future__ import annotations

import os
import struct
import zlib

__all__ = ["check_blf", "MAX_CONTAINER_BYTES", "MAX_EXPANSION", "EXPANSION_FLOOR_BYTES"]

FILE_HEADER = struct.Struct("<4sLBBBBBBBBQQLL8H8H")
assert FILE_HEADER.size == 72
OBJ_HEADER = struct.Struct("<4sHHLL")
assert OBJ_HEADER.size == 16
CONTAINER = struct.Struct("<H6xL4x")
assert CONTAINER.size == 16
LOG_CONTAINER, NO_COMPRESSION, ZLIB_DEFLATE = 10, 0, 2
#: one log container's inflated size, at most
MAX_CONTAINER_BYTES = 16 << 20
#: inflated bytes per byte of file, at most (zlib can reach about 1000)
MAX_EXPANSION = 100
EXPANSION_FLOOR_BYTES = 64 << 20


def check_blf(f, name: str) -> None:
    """Walk the BLF file ``f`` (binary, at its start) with bounds (module docstring); ValueError
    naming the byte offset for one that python-can should not be given."""
    size = os.fstat(f.fileno()).st_size
    budget = max(EXPANSION_FLOOR_BYTES, MAX_EXPANSION * size)
    head = f.read(FILE_HEADER.size)
    if len(head) < FILE_HEADER.size or head[:4] != b"LOGG":
        raise ValueError(f"{name}: not a BLF file (no LOGG header)")
    header_size = FILE_HEADER.unpack(head)[1]
    if not FILE_HEADER.size <= header_size <= size:
        raise ValueError(f"{name}: a BLF header of {header_size} bytes in a file of {size}")
    f.seek(header_size)
    while True:
        at = f.tell()
        raw = f.read(OBJ_HEADER.size)
        if len(raw) < OBJ_HEADER.size:
            return  # the end (python-can stops at a short object header too)
        sig, _, _, obj_size, obj_type = OBJ_HEADER.unpack(raw)
        if sig != b"LOBJ":
            raise ValueError(f"{name}: byte {at}: not a BLF object (no LOBJ)")
        body_len = obj_size - OBJ_HEADER.size
        if body_len < 0 or body_len > size - f.tell():
            raise ValueError(f"{name}: byte {at}: a BLF object of {obj_size} bytes, longer than the rest of the file")
        if obj_type != LOG_CONTAINER:
            f.seek(body_len + obj_size % 4, os.SEEK_CUR)
            continue
        body = f.read(body_len)
        f.seek(obj_size % 4, os.SEEK_CUR)
        if len(body) < CONTAINER.size:
            raise ValueError(f"{name}: byte {at}: a log container shorter than its header")
        method, _declared = CONTAINER.unpack_from(body)
        if method == ZLIB_DEFLATE:
            d = zlib.decompressobj()
            try:
                out = d.decompress(body[CONTAINER.size:], MAX_CONTAINER_BYTES + 1)
            except zlib.error as exc:
                raise ValueError(f"{name}: byte {at}: a log container that does not inflate ({exc})") from None
            inflated = len(out)
            del out
        else:
            inflated = len(body) - CONTAINER.size
        if inflated > MAX_CONTAINER_BYTES:
            raise ValueError(f"{name}: byte {at}: a log container inflating to more than {MAX_CONTAINER_BYTES:,} "
                             f"bytes (python-can writes 128 KiB ones)")
        budget -= inflated
        if budget < 0:
            raise ValueError(f"{name}: its log containers inflate to more than {MAX_EXPANSION} times the file's "
                             f"{size:,} bytes: refused")
