"""Crafted files that a capsheet reader must refuse (tests/host/record/test_untrusted_files.py, and the
fuzzers): recordings, layouts, calibrations, robot configs and CAN logs, each small, each made here
from a real recording or from the formats' documented layouts. ``corpus(folder)`` writes them and
returns ``{name: (path, kind)}``; kind says which command reads it."""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path

import numpy as np

MAGIC = b"\x89MCAP0\r\n"


def base_recording(path: Path, *, rows: int = 3, cols: int = 4, n: int = 12, valid: bool = True) -> Path:
    """A real capsheet recording (host.record.recording.Recorder): ``n`` snapshots of a flat sheet,
    raw input included, zstd chunks."""
    from host.record.recording import Recorder
    from host.snapshots.aggregator import LatticeSnapshot
    from protocol.lattice import Lattice

    lat = Lattice(rows, cols)
    r = np.zeros((lat.n_links, 3))
    r[:, 2] = 9.80665
    with Recorder(path, lat, 0.01, flush_interval_s=0.0) as rec:
        for c in range(n):
            rec.raw(0, "serial", bytes([c % 251, 0]), port="/dev/null", t=float(c))
            v = np.full(lat.n_links, valid)
            rec.snapshot(LatticeSnapshot(c, 1.0 + c, 1.7e9 + c, np.where(v[:, None], r, np.nan), v,
                                         np.zeros(lat.n_links, np.uint8), bool(v.all()), 0.001))
    return path


def records(path: Path) -> list:
    """Every data record of an MCAP file (no header, data end or footer), chunks opened (the bounded
    reader's own parse)."""
    from mcap.records import DataEnd, Footer, Header

    from host.record.mcap_read import iter_records
    with open(path, "rb") as f:
        return [r for r in iter_records(f, str(path)) if not isinstance(r, (Header, DataEnd, Footer))]


def write_mcap(path: Path, recs: list, extra: bytes = b"") -> Path:
    """An MCAP file of ``recs`` at top level (no chunks), then ``extra`` (raw record bytes, e.g. a
    crafted chunk), data end, footer and closing magic."""
    from mcap.data_stream import RecordBuilder
    from mcap.records import DataEnd, Footer, Header

    b = RecordBuilder()
    Header(profile="", library="crafted").write(b)
    for r in recs:
        r.write(b)
    body = b.end()
    tail = RecordBuilder()
    DataEnd(data_section_crc=0).write(tail)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(tail)
    path.write_bytes(MAGIC + body + extra + tail.end() + MAGIC)
    return path


def chunk(data: bytes, declared: int, compression: str = "zstd", compressed: bytes | None = None) -> bytes:
    """A chunk record's bytes: ``compressed`` (default ``data`` zstd-compressed) declaring ``declared``
    bytes once decompressed."""
    from mcap.data_stream import RecordBuilder
    from mcap.records import Chunk

    if compressed is None:
        import zstandard
        compressed = zstandard.ZstdCompressor(level=3).compress(data) if compression == "zstd" else data
    b = RecordBuilder()
    Chunk(compression=compression, data=compressed, message_end_time=0, message_start_time=0,
          uncompressed_crc=0, uncompressed_size=declared).write(b)
    return b.end()


def _with_session(recs: list, **change) -> list:
    from mcap.records import Metadata
    out = []
    for r in recs:
        if isinstance(r, Metadata) and r.name == "capsheet.session":
            meta = dict(r.metadata)
            meta.update({k: v if isinstance(v, str) else json.dumps(v) for k, v in change.items()})
            r = Metadata(name=r.name, metadata=meta)
        out.append(r)
    return out


def _message_bytes(channel_id: int, data: bytes) -> bytes:
    from mcap.data_stream import RecordBuilder
    from mcap.records import Message
    b = RecordBuilder()
    Message(channel_id=channel_id, log_time=0, data=data, publish_time=0, sequence=0).write(b)
    return b.end()


def corpus(folder: Path) -> dict[str, tuple[Path, str]]:
    """The crafted files (module docstring). Kinds: ``recording``, ``layout``, ``calibration``,
    ``robot``, ``canlog``."""
    from mcap.records import Channel, Message

    from host.record.recording import TOPIC_SNAPSHOT

    folder.mkdir(parents=True, exist_ok=True)
    good = base_recording(folder / "good.mcap")
    recs = records(good)
    snap_ch = next(r.id for r in recs if isinstance(r, Channel) and r.topic == TOPIC_SNAPSHOT)
    out: dict[str, tuple[Path, str]] = {}

    def rec(name: str, path: Path) -> None:
        out[name] = (path, "recording")

    # a chunk declaring 2 GiB decompressed (refused before decompressing)
    rec("chunk_declares_2gib", write_mcap(folder / "bomb_declared.mcap", recs,
                                          chunk(bytes(1 << 20), 2 << 30)))
    # forty chunks of 48 MiB of one message each (~80 KB of file): more than the file may expand
    import zstandard
    big = _message_bytes(999, bytes(48 << 20))
    z = zstandard.ZstdCompressor(level=3).compress(big)
    rec("forty_chunks_of_48_mib", write_mcap(folder / "bomb_many.mcap", recs,
                                             b"".join(chunk(b"", len(big), compressed=z) for _ in range(40))))
    # a chunk that holds more than it declares
    rec("chunk_holds_more", write_mcap(folder / "chunk_lies.mcap", recs, chunk(big, 1024, compressed=z)))
    rec("chunk_unknown_compression", write_mcap(folder / "chunk_brotli.mcap", recs,
                                                chunk(b"", 10, "brotli", compressed=b"x" * 10)))
    # the session declaring a lattice of 1e8 links, and one whose link count is not its lattice's
    rec("lattice_1e8_links", write_mcap(folder / "huge_lattice.mcap",
                                        _with_session(recs, rows=10000, cols=5000, n_links=99_985_000)))
    rec("n_links_1e8", write_mcap(folder / "n_links.mcap", _with_session(recs, n_links=100_000_000)))
    rec("link_length_nan", write_mcap(folder / "nan_link.mcap", _with_session(recs, link_length_m="NaN")))
    rec("link_length_1e300", write_mcap(folder / "big_link.mcap", _with_session(recs, link_length_m=1e300)))
    rec("session_nested_json", write_mcap(folder / "nested.mcap",
                                          _with_session(recs, rows="[" * 5000 + "]" * 5000)))
    # a snapshot message declaring 32767 links with 17's arrays
    from host.record import schema as P
    m = P.message_class("capsheet.v2.Snapshot")()
    m.n_links = 32767
    m.status = bytes(17)
    lies = [r if not (isinstance(r, Message) and r.channel_id == snap_ch) else
            Message(channel_id=r.channel_id, log_time=r.log_time, publish_time=r.publish_time, sequence=r.sequence,
                    data=m.SerializeToString()) for r in recs]
    rec("snapshot_declares_32767_links", write_mcap(folder / "snap_lies.mcap", lies))
    junk = [r if not (isinstance(r, Message) and r.channel_id == snap_ch) else
            Message(channel_id=r.channel_id, log_time=r.log_time, publish_time=r.publish_time, sequence=r.sequence,
                    data=b"\xff" * 40) for r in recs]
    rec("snapshot_not_protobuf", write_mcap(folder / "snap_junk.mcap", junk))
    # a corrupt record in the middle: a channel whose topic string claims 1 GB inside a record of 30
    data = bytearray(write_mcap(folder / "tmp.mcap", recs).read_bytes())
    k = data.index(TOPIC_SNAPSHOT.encode()) - 4
    data[k:k + 4] = struct.pack("<I", 1 << 30)
    (folder / "corrupt_channel.mcap").write_bytes(bytes(data))
    rec("channel_topic_claims_1gb", folder / "corrupt_channel.mcap")
    data = bytearray(good.read_bytes())
    data[len(data) // 2: len(data) // 2 + 64] = b"\xa5" * 64
    (folder / "flipped.mcap").write_bytes(bytes(data))
    rec("bytes_flipped_mid_file", folder / "flipped.mcap")
    (folder / "not_mcap.mcap").write_bytes(b"PK\x03\x04" + bytes(60))
    rec("not_mcap", folder / "not_mcap.mcap")
    # every snapshot without a valid link: nothing can be estimated
    rec("no_valid_link", base_recording(folder / "all_invalid.mcap", valid=False))
    # not regular files behind a recording's name
    (folder / "zero.mcap").symlink_to("/dev/zero")
    rec("dev_zero", folder / "zero.mcap")
    os.mkfifo(folder / "fifo.mcap")
    rec("fifo", folder / "fifo.mcap")

    # layouts (``capsheet host --layout``)
    def put(name: str, kind: str, text, suffix: str) -> None:
        p = folder / f"{name}{suffix}"
        p.write_bytes(text if isinstance(text, bytes) else text.encode())
        out[name] = (p, kind)

    put("layout_5000x5000", "layout", '{"rows":5000,"cols":5000,"chips":[{"uid":"0x1","link":0}]}', ".json")
    put("layout_link_1e30", "layout", "uid,link\n0x1," + "1" * 31 + "\n", ".csv")
    put("layout_40000_chips", "layout", "".join(f"0x{k + 1:x},{k}\n" for k in range(40000)), ".csv")
    put("layout_nested", "layout", '{"chips": ' + "[" * 20000 + "]" * 20000 + "}", ".json")
    (folder / "layout_zero.json").symlink_to("/dev/zero")
    out["layout_dev_zero"] = (folder / "layout_zero.json", "layout")
    os.mkfifo(folder / "layout_fifo.csv")
    out["layout_fifo"] = (folder / "layout_fifo.csv", "layout")

    # calibrations (``capsheet demo --calibration``), of the demo's 14x14 sheet
    from host.analysis.calibration import Calibration
    cal = Calibration.identity(14, 14).to_dict()

    def cal_with(**chip0) -> str:
        d = json.loads(json.dumps(cal))
        d["chips"][0].update(chip0)
        return json.dumps(d)
    put("cal_misalignment_1e308", "calibration", cal_with(misalignment=[1e308, 0, 0]), ".json")
    put("cal_bias_nan", "calibration", cal_with(bias=[float("nan"), 0, 0]), ".json")
    put("cal_scale_inf", "calibration", cal_with(scale=["Infinity", 1, 1]).replace('"Infinity"', "Infinity"), ".json")
    put("cal_5000x5000", "calibration", json.dumps({**cal, "rows": 5000, "cols": 5000}), ".json")
    put("cal_nested", "calibration", '{"format": "capsheet-calibration", "version": 1, "x": '
        + "[" * 20000 + "]" * 20000 + "}", ".json")
    with open(folder / "cal_sparse_1gb.json", "wb") as f:  # a sparse file: its size is refused unread
        f.truncate(1 << 30)
    out["cal_sparse_1gb"] = (folder / "cal_sparse_1gb.json", "calibration")
    (folder / "cal_zero.json").symlink_to("/dev/zero")
    out["cal_dev_zero"] = (folder / "cal_zero.json", "calibration")

    # robot configs (``capsheet view --config``)
    sheet = '[[sheet]]\nname = "a"\nrpy_deg = [0, 0, 0]\n'
    put("robot_nested", "robot", "x = " + "[" * 5000 + "]" * 5000 + "\n", ".toml")
    put("robot_translation_nan", "robot", sheet + "translation = [nan, 0, 0]\n", ".toml")
    put("robot_translation_1e300", "robot", sheet + "translation = [1e300, 0, 0]\n", ".toml")
    put("robot_1000_sheets", "robot", "".join(f'[[sheet]]\nname = "s{k}"\ntranslation = [0, 0, 0]\n'
                                              f'rpy_deg = [0, 0, 0]\n' for k in range(1000)), ".toml")
    put("robot_dotted_40_deep", "robot", "[" + ".".join(["a"] * 40) + "]\nb = 1\n", ".toml")
    (folder / "robot_zero.toml").symlink_to("/dev/zero")
    out["robot_dev_zero"] = (folder / "robot_zero.toml", "robot")

    # CAN logs (``capsheet replay FILE --lattice``)
    put("canlog_junk_blf", "canlog", b"LOGG" + bytes(range(256)) * 8, ".blf")
    put("canlog_junk_asc", "canlog", "date Mon Jan 1\nbase hex\n" + "1.0 1 7FF Rx d 9 " + "ff " * 9 + "\n", ".asc")
    # a BLF log (python-can's writer) with a zlib container of 40 MiB of zeros (~40 KB in the file)
    import can
    import zlib
    from can.io.blf import BLFWriter
    w = BLFWriter(str(folder / "tmp.blf"))
    w.on_message_received(can.Message(arbitration_id=0x1001, data=b"\x01\x02", is_extended_id=True, channel=0))
    w.stop()
    blf = (folder / "tmp.blf").read_bytes()
    body = struct.pack("<H6xL4x", 2, 128 << 10) + zlib.compress(bytes(40 << 20), 9)
    obj = struct.pack("<4sHHLL", b"LOBJ", 16, 1, 16 + len(body), 10) + body + bytes((16 + len(body)) % 4)
    hs = struct.unpack_from("<4sL", blf)[1]
    put("canlog_blf_zlib_bomb", "canlog", blf[:hs] + obj + blf[hs:], ".blf")
    (folder / "can_zero.log").symlink_to("/dev/zero")
    out["canlog_dev_zero"] = (folder / "can_zero.log", "canlog")
    return out


def argv(path: Path, kind: str, out_dir: Path) -> list[list[str]]:
    """The command lines that read ``path`` (one per command that takes such a file)."""
    p = str(path)
    if kind == "recording":
        # --allow-truncated: the crafted files have no summary; read them through, to what they hold
        return [["estimate", p, "--out", str(out_dir / f"{path.stem}.npz"), "--overwrite", "-q", "--jobs", "1",
                 "--allow-truncated"], ["replay", p, "-q", "--no-estimate", "--allow-truncated"]]
    if kind == "layout":
        return [["host", "--port", "loop://", "--lattice", "4x4", "--layout", p, "--duration", "0.1", "-q"]]
    if kind == "calibration":
        return [["demo", "--calibration", p, "--duration", "0.1"]]
    if kind == "robot":
        return [["view", "--config", p, "--duration", "0.1"]]
    if kind == "canlog":
        return [["replay", p, "--lattice", "4x4", "-q", "--no-estimate"]]
    raise ValueError(kind)
