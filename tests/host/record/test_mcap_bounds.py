"""host/record/mcap_read.py on chunks of each compression: a chunk is read when it decompresses to
exactly what it declares, refused (one line, nothing beyond the declared size produced) when it
holds more, and a file ending inside a record is a cut file, not an error."""

from __future__ import annotations

import pytest

from tests.host.record.crafted import base_recording, chunk, records, write_mcap


def _message(data: bytes) -> bytes:
    from mcap.data_stream import RecordBuilder
    from mcap.records import Message
    b = RecordBuilder()
    Message(channel_id=77, log_time=0, data=data, publish_time=0, sequence=0).write(b)
    return b.end()


@pytest.mark.parametrize("compression", ["zstd", "lz4", ""])
def test_a_chunk_is_read_at_its_declared_size_and_refused_beyond_it(tmp_path, compression):
    from mcap.records import Message

    from host.record.mcap_read import iter_records

    recs = records(base_recording(tmp_path / "base.mcap", n=2))
    inner = _message(b"\x01" * 5000)
    if compression == "lz4":
        import lz4.frame
        packed = lz4.frame.compress(inner)
    elif compression == "zstd":
        import zstandard
        packed = zstandard.ZstdCompressor().compress(inner)
    else:
        packed = inner
    ok = write_mcap(tmp_path / "ok.mcap", recs, chunk(b"", len(inner), compression, compressed=packed))
    with open(ok, "rb") as f:
        got = [r for r in iter_records(f, "ok") if isinstance(r, Message) and r.channel_id == 77]
    assert len(got) == 1 and got[0].data == b"\x01" * 5000
    bad = write_mcap(tmp_path / "bad.mcap", recs, chunk(b"", 100, compression, compressed=packed))
    with open(bad, "rb") as f, pytest.raises(ValueError, match="more than the 100 bytes it declares"):
        list(iter_records(f, "bad"))


def test_a_file_ending_inside_a_record_is_cut_not_refused(tmp_path):
    from host.record.mcap_read import iter_records

    data = base_recording(tmp_path / "base.mcap", n=3).read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) - 100])
    with open(tmp_path / "cut.mcap", "rb") as f:
        gen = iter_records(f, "cut")
        while True:
            try:
                next(gen)
            except StopIteration as stop:
                assert stop.value is True  # cut short
                break
