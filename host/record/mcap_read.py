"""Reading an MCAP file someone else wrote, with bounds (`host.record.recording.read` and
`iter_snapshots` read through it).

MCAP (https://mcap.dev/spec) frames every record as ``opcode u8, length u64, body``; a chunk record
holds other records, compressed, and states its ``uncompressed_size``. The ``mcap`` package's
stream reader trusts those numbers: it decompresses a chunk to the size the chunk declares (a 33 KB
file declaring gigabytes took ``capsheet replay`` to 2.1 GB) and reads a field's declared length
from the file as it stands. Here:

* a record longer than what is left of the file means the file was cut short (a killed writer):
  reading stops there, as before, and the caller is told (``truncated``);
* a record's body is read whole (bounded by the file's size) and parsed from memory, so a field's
  declared length cannot make a read larger than the record;
* a chunk declaring more than `MAX_CHUNK_BYTES` decompressed, or a file whose chunks together
  declare more than `MAX_EXPANSION` times its own size (at least `EXPANSION_FLOOR_BYTES`), is refused
  before anything is decompressed, and decompression never produces more than the chunk declared;
* a record that does not parse in the middle of a file, a chunk that does not decompress to its
  declared size, an unknown compression: ValueError naming the byte offset.

The records capsheet reads (header, schema, channel, message, chunk, metadata, attachment, data
end, footer) are parsed with the ``mcap`` package's record classes; the index and summary records
are skipped.
"""

from __future__ import annotations

import io
import os
import struct

__all__ = ["iter_records", "MAX_CHUNK_BYTES", "MAX_EXPANSION", "EXPANSION_FLOOR_BYTES", "MAGIC"]

MAGIC = b"\x89MCAP0\r\n"
#: a chunk's decompressed size, at most (capsheet writes ~1 MB chunks, `Recorder`'s ``chunk_size``)
MAX_CHUNK_BYTES = 64 << 20
#: decompressed bytes per byte of file, at most (capsheet's recordings: about 4.5)
MAX_EXPANSION = 100
#: ... but a small file may always decompress to this much
EXPANSION_FLOOR_BYTES = 64 << 20
_HEAD = struct.Struct("<BQ")


def _parsers():
    from mcap.opcode import Opcode
    from mcap.records import Attachment, Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema
    return {Opcode.HEADER: Header.read, Opcode.FOOTER: Footer.read, Opcode.SCHEMA: Schema.read,
            Opcode.CHANNEL: Channel.read, Opcode.MESSAGE: None, Opcode.CHUNK: Chunk.read,
            Opcode.METADATA: Metadata.read, Opcode.ATTACHMENT: Attachment.read, Opcode.DATA_END: DataEnd.read}, \
        Opcode, Message


def _parse(opcode: int, body: bytes, where: str):
    """The record of ``opcode`` in ``body``, or None (a record capsheet does not read)."""
    from mcap.data_stream import ReadDataStream
    from mcap.exceptions import EndOfFile

    parsers, Opcode, Message = _parsers()
    if opcode not in parsers:
        return None
    stream = ReadDataStream(io.BytesIO(body))
    try:
        if opcode == Opcode.MESSAGE:
            if len(body) < 22:
                raise ValueError("shorter than a message header")
            return Message.read(stream, len(body))
        rec = parsers[opcode](stream)
    except (EndOfFile, struct.error, UnicodeDecodeError, ValueError, KeyError) as exc:
        raise ValueError(f"{where}: a corrupt record (opcode 0x{opcode:02x}: {str(exc) or type(exc).__name__})") \
            from None
    if stream.count > len(body):
        raise ValueError(f"{where}: a corrupt record (opcode 0x{opcode:02x} longer than its length)")
    return rec


def _decompress(chunk, where: str) -> bytes:
    """A chunk's records, decompressed to at most its declared ``uncompressed_size``."""
    size = int(chunk.uncompressed_size)
    if chunk.compression == "":
        data = bytes(chunk.data)
    elif chunk.compression == "zstd":
        try:
            import zstandard
        except ImportError:
            raise ValueError(f"{where}: a zstd chunk, and the zstandard package is not installed") from None
        try:
            reader = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(chunk.data))
            out = bytearray()
            while len(out) <= size:
                piece = reader.read(min(1 << 20, size + 1 - len(out)))
                if not piece:
                    break
                out += piece
            data = bytes(out)
        except zstandard.ZstdError as exc:
            raise ValueError(f"{where}: a chunk that does not decompress (zstd: {exc})") from None
    elif chunk.compression == "lz4":
        try:
            import lz4.frame
        except ImportError:
            raise ValueError(f"{where}: an lz4 chunk, and the lz4 package is not installed") from None
        try:
            data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size + 1)
        except RuntimeError as exc:
            raise ValueError(f"{where}: a chunk that does not decompress (lz4: {exc})") from None
    else:
        raise ValueError(f"{where}: a chunk compressed with {chunk.compression!r} (capsheet reads zstd, lz4 or none)")
    if len(data) > size:
        raise ValueError(f"{where}: a chunk that decompresses to more than the {size:,} bytes it declares")
    if len(data) < size:
        raise ValueError(f"{where}: a chunk that decompresses to {len(data):,} bytes, not the {size:,} it declares")
    return data


def _chunk_records(data: bytes, where: str):
    from mcap.opcode import Opcode
    at = 0
    while at < len(data):
        if len(data) - at < _HEAD.size:
            raise ValueError(f"{where}: a chunk whose last record is cut")
        opcode, length = _HEAD.unpack_from(data, at)
        at += _HEAD.size
        if length > len(data) - at:
            raise ValueError(f"{where}: a record of {length} bytes in a chunk of {len(data)}")
        if opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
            rec = _parse(opcode, data[at:at + length], where)
            if rec is not None:
                yield rec
        at += length


def iter_records(f, name: str = "?"):
    """The records of the MCAP file ``f`` (opened binary, at its start) in order, chunks opened
    (module docstring). Returns (as ``StopIteration.value``) True when the file was cut short:
    it ended inside a record, or before its footer. ValueError for a file that is not MCAP, a
    corrupt record, or a chunk beyond the bounds."""
    size = os.fstat(f.fileno()).st_size
    budget = max(EXPANSION_FLOOR_BYTES, MAX_EXPANSION * size)
    if f.read(len(MAGIC)) != MAGIC:
        raise ValueError(f"{name!r} is not an MCAP file (magic bytes missing)")
    _, Opcode, _ = _parsers()
    while True:
        at = f.tell()
        head = f.read(_HEAD.size)
        if len(head) < _HEAD.size:
            return True  # ended between records, before the footer
        opcode, length = _HEAD.unpack(head)
        if length > size - f.tell():
            return True  # a record cut in the middle: a killed writer
        body = f.read(length)
        if len(body) < length:
            return True
        where = f"{name}: byte {at}"
        rec = _parse(opcode, body, where)
        if opcode == Opcode.CHUNK and rec is not None:
            declared = int(rec.uncompressed_size)
            if declared > MAX_CHUNK_BYTES:
                raise ValueError(f"{where}: a chunk declaring {declared:,} bytes decompressed, more than a "
                                 f"recording's chunks hold ({MAX_CHUNK_BYTES:,})")
            budget -= declared
            if budget < 0:
                raise ValueError(f"{name}: its chunks decompress to more than {MAX_EXPANSION} times the file's "
                                 f"{size:,} bytes (a recording compresses about 5 times): refused")
            yield from _chunk_records(_decompress(rec, where), where)
        elif rec is not None:
            yield rec
            if opcode == Opcode.FOOTER:  # then the closing magic: without it the file was cut
                return f.read(len(MAGIC)) != MAGIC


# -- what a capsheet recording's records may say ----------------------------------------------------

#: errors a malformed record raises while it is decoded (wrapped into one ValueError by `malformed`)
def malformed_errors() -> tuple:
    from google.protobuf.message import DecodeError
    return (KeyError, TypeError, IndexError, AttributeError, OverflowError, RecursionError, DecodeError,
            struct.error, UnicodeDecodeError)


def malformed(path, exc) -> ValueError:
    """The one-line ValueError for a record that did not decode (``exc``)."""
    what = str(exc).splitlines()[0][:120] if str(exc) else ""
    return ValueError(f"{path}: a record capsheet cannot read ({type(exc).__name__}{': ' + what if what else ''})")


def _int(session: dict, key: str, name) -> int:
    v = session.get(key)
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"{name}: capsheet.session {key} {v!r} is not an integer")
    return v


def check_session(session: dict, name) -> tuple[int, int, int]:
    """``(rows, cols, n_links)`` of a recording's ``capsheet.session`` metadata, checked before
    anything is sized by them: a lattice of at least 2x2 joints and at most a sheet's
    `protocol.files.MAX_LINKS` links, ``n_links`` its links, a link length of 0.1 mm .. 10 m and a
    rate of at most 4 kHz when given. ValueError naming the field otherwise."""
    from protocol.files import MAX_LINKS

    rows, cols, n = (_int(session, k, name) for k in ("rows", "cols", "n_links"))
    if rows < 2 or cols < 2:
        raise ValueError(f"{name}: capsheet.session declares a {rows}x{cols} lattice (a sheet has at least 2x2 joints)")
    links = rows * (cols - 1) + cols * (rows - 1)
    if links > MAX_LINKS:
        raise ValueError(f"{name}: capsheet.session declares a {rows}x{cols} lattice of {links:,} links, more than a "
                         f"sheet's {MAX_LINKS:,}")
    if n != links:
        raise ValueError(f"{name}: capsheet.session n_links {n:,} is not the {rows}x{cols} lattice's {links}")
    for key, lo, hi in (("link_length_m", 1e-4, 10.0), ("rate_hz", 1e-6, 4000.0)):
        if key in session:
            v = session[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v <= hi:  # NaN fails too
                raise ValueError(f"{name}: capsheet.session {key} {v!r} is outside [{lo:g}, {hi:g}]")
    return rows, cols, n


def check_snapshot(m, name) -> int:
    """A protobuf ``capsheet.v2.Snapshot``'s link count, its arrays checked against it (before
    any is unpacked by it)."""
    from protocol.files import MAX_LINKS

    n = int(m.n_links)
    if not 0 < n <= MAX_LINKS:
        raise ValueError(f"{name}: a snapshot message of {n:,} links (a sheet has 1..{MAX_LINKS:,})")
    for field, lengths in (("counts", (0, 3 * n)), ("readings", (0, 3 * n)), ("valid", ((n + 7) // 8,)),
                           ("status", (n,)), ("gyro", (0, 3 * n)), ("mag", (0, 3 * n)), ("sample_time_s", (0, n))):
        have = len(getattr(m, field))
        if have not in lengths:
            raise ValueError(f"{name}: a snapshot message of {n} links with {have} {field} values")
    return n


def check_chip_calibration(cal, n_links: int, name, *, need_node: bool = False) -> None:
    """A recorded ``calibration.json`` (the chips' offsets and sensitivities, their nodes): every
    link within the lattice, node ids 16-bit, values finite, sensitivities > 0."""
    import math

    links = cal.get("links", []) if isinstance(cal, dict) else None
    if not isinstance(links, list):
        raise ValueError(f"{name}: calibration.json: 'links' is not a list")
    for i, c in enumerate(links):
        where = f"{name}: calibration.json links[{i}]"
        if not isinstance(c, dict):
            raise ValueError(f"{where}: not an object")
        k, node = c.get("link"), c.get("node", None if need_node else 0)
        if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k < n_links:
            raise ValueError(f"{where}: link {k!r} is not one of the lattice's 0..{n_links - 1}")
        if isinstance(node, bool) or not isinstance(node, int) or not 0 <= node < 1 << 16:
            raise ValueError(f"{where}: node {node!r} is not a 16-bit node id")
        for key in ("offset", "sensitivity"):
            v = c.get(key)
            if (not isinstance(v, list) or len(v) != 3 or not all(
                    isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
                    or (key == "sensitivity" and min(v) <= 0)):
                raise ValueError(f"{where}: {key} {v!r} is not 3 finite numbers" + (" > 0" if key == "sensitivity" else ""))
