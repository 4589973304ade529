"""Serial input and snapshot counts stored by their information (host/record/compact.py): every
chunk comes back byte for byte, whatever it holds and wherever it was cut, and a recording written
that way replays to the snapshots the host made, as one written as the wire bytes does."""

from __future__ import annotations

import numpy as np
import pytest
import zstandard
from mcap.records import Schema
from mcap.stream_reader import StreamReader
from cobs import cobs
from hypothesis import given, settings, strategies as st

from host.record import compact as C
from host.record import schema as P
from host.record.recording import Recorder, read
from protocol.framing import decode_frame, encode, encode_frame
from protocol.lattice import Lattice
from protocol.messages import MsgType, Sample, Sync

Frames = P.message_class("RawSerialFrames")


def _rng(seed: int) -> np.random.Generator:
    return np.random.Generator(np.random.MT19937(seed))


def _round_trip(chunks: list[bytes]) -> tuple[list[bytes], list]:
    """Chunks through a compactor, serialized and parsed, and an expander."""
    comp, exp = C.SerialCompactor(), C.SerialExpander()
    msgs = [Frames.FromString(comp.encode(c, bus=0, t=1.0, t_rx=0.5)) for c in chunks]
    return [exp.expand(m) for m in msgs], msgs


def _sheet_wire(noise: float, n_syncs: int, lattice: str = "4x4") -> list[bytes]:
    """Each SYNC's bytes from a commissioned per-chip virtual sheet (the chips' own encoders)."""
    from virtual_sheet.gateway import Gateway
    from virtual_sheet.sheet import VirtualSheet

    gw = Gateway(VirtualSheet("gaussian", lattice, seed=4, noise=noise), packed=False)
    gw.power_on(0.0)
    gw.commission(0.0)
    gw.pop_output(1.0)
    out, t = [], 0.01
    for k in range(n_syncs):
        t += 1 / 145
        gw.feed(encode(Sync(counter=(65530 + k) & 0xFFFF)), t)  # the counter wraps on the way
        gw.poll(t)
        out.append(gw.pop_wire(t)[0])
    return out


def _cut(data: bytes, n: int, rng) -> list[bytes]:
    cuts = np.sort(rng.integers(0, len(data) + 1, n))
    return [data[a:b] for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(data)])]


def _whole_samples(chunk: bytes) -> int:
    """SAMPLE frames lying whole in ``chunk`` (between its start or a delimiter and a delimiter),
    counted with the protocol's own frame decoder, not the compactor's."""
    parts = chunk.split(b"\x00")[:-1]  # the last part has no delimiter in this chunk
    return sum(isinstance(decode_frame(p), Sample) for p in parts)


@pytest.mark.parametrize("noise", [0.0, 1.0])
def test_a_virtual_sheets_stream_cut_anywhere_comes_back_byte_for_byte(noise):
    wire = b"".join(_sheet_wire(noise, 30))
    assert len(wire) == 30 * 24 * 15  # 24 links, one SAMPLE each per SYNC
    chunks = _cut(wire, 97, _rng(7))
    back, msgs = _round_trip(chunks)
    assert back == chunks
    # every SAMPLE lying whole in a chunk became columns; the bytes kept raw are the cut ones
    assert [len(m.status) for m in msgs] == [_whole_samples(c) for c in chunks]
    assert sum(len(m.status) for m in msgs) > 0.8 * 30 * 24
    assert sum(len(m.raw) for m in msgs) == len(wire) - 15 * sum(len(m.status) for m in msgs)


def test_damaged_bytes_other_types_and_cut_frames_are_kept_as_they_came():
    rng = _rng(11)
    good = [encode(Sample(node=n, counter=9, x=-2048, y=2047, z=n, status=n % 16)) for n in range(1, 9)]
    body = bytearray(cobs.decode(encode(Sample(node=3, counter=9, x=1, y=2, z=3))[:-1]))
    body[-1] ^= 0x01  # the CRC's low byte: COBS-encoded afresh, the frame's CRC no longer holds
    bad_crc = cobs.encode(bytes(body)) + b"\x00"
    assert decode_frame(bad_crc[:-1]).__class__.__name__ == "DecodeError"
    version2 = encode_frame(MsgType.SAMPLE, 4, Sample(node=4, counter=9).payload(), version=2)
    status_frame = encode_frame(MsgType.STATUS, 5, bytes(7))  # 7-byte payload: a SAMPLE's length, not its type
    noise_bytes = bytes(rng.integers(0, 256, 40, dtype=np.uint8))
    stream = b"".join([good[0], bad_crc, good[1], version2, good[2], status_frame, noise_bytes, good[3],
                       b"\x00\x00", good[4] + good[5], good[0][:-1], b"\x07\x00", good[6][:7]]) + good[6][7:] + good[7]
    chunks = [stream[:len(stream) // 2], stream[len(stream) // 2:]]
    back, msgs = _round_trip(chunks)
    assert back == chunks
    raw = b"".join(m.raw for m in msgs)
    for kept in (bad_crc, version2, status_frame, noise_bytes, good[0][:-1] + b"\x07\x00"):
        assert kept in raw  # not a valid SAMPLE: as it came
    assert sum(len(m.status) for m in msgs) == sum(_whole_samples(c) for c in chunks)


def test_a_frame_the_compactor_would_not_rebuild_exactly_is_kept_raw(monkeypatch):
    """Exactness never depends on the chips encoding as the compactor does: a frame whose rebuilt
    bytes differ from the original stays raw. Here the rebuilding is broken for node 5 (as a chip
    with another encoding would look): node 5's frames are kept raw and every chunk still comes back."""
    real = C._cobs_encode_rows

    def off_for_node_5(body):
        out = real(body)
        out[(body[:, 2] == 5) & (body[:, 3] == 0), 5] ^= 0x40
        return out

    wire = b"".join(_sheet_wire(1.0, 6))
    chunks = _cut(wire, 11, _rng(3))
    comp = C.SerialCompactor()
    monkeypatch.setattr(C, "_cobs_encode_rows", off_for_node_5)
    msgs = [Frames.FromString(comp.encode(c, bus=0, t=0.0, t_rx=0.0)) for c in chunks]
    monkeypatch.setattr(C, "_cobs_encode_rows", real)
    exp = C.SerialExpander()
    assert [exp.expand(m) for m in msgs] == chunks
    node5 = [f for f in wire.split(b"\x00")[:-1] if getattr(decode_frame(f), "node", None) == 5]
    assert len(node5) == 6
    raw = b"".join(m.raw for m in msgs)
    assert sum(f + b"\x00" in raw for f in node5) >= 5  # each one not cut by a chunk edge
    assert sum(len(m.status) for m in msgs) == sum(_whole_samples(c) for c in chunks) - sum(
        f + b"\x00" in raw for f in node5)


def test_an_expander_refuses_columns_that_do_not_fit_in_one_line():
    [c] = _sheet_wire(0.0, 1)
    m = Frames.FromString(C.SerialCompactor().encode(c, bus=0, t=0.0, t_rx=0.0))
    assert len(m.status) == 24
    short = Frames.FromString(m.SerializeToString())
    short.counts = short.counts[:-1]
    with pytest.raises(C.CompactError, match="columns disagree"):
        C.SerialExpander().expand(short)
    far = Frames.FromString(m.SerializeToString())
    far.gap = C._planes(np.array([0] * 23 + [10_000]), 4)
    with pytest.raises(C.CompactError, match="gaps reach byte"):
        C.SerialExpander().expand(far)
    huge = Frames.FromString(m.SerializeToString())
    huge.counts = b"\xff" * len(m.counts)
    with pytest.raises(C.CompactError, match="12-bit range"):
        C.SerialExpander().expand(huge)


_samples = st.builds(lambda n, c, x, y, z, s: encode(Sample(node=n, counter=c, x=x, y=y, z=z, status=s)),
                     st.integers(0, 0xFFFE), st.integers(0, 0xFFFF), *(st.integers(-2048, 2047),) * 3,
                     st.integers(0, 15))


@settings(max_examples=300, deadline=None)
@given(parts=st.lists(st.one_of(st.binary(max_size=40), _samples, _samples.map(lambda f: f[:-1]),  # its delimiter lost
                                st.just(b"\x00")), max_size=30),
       cuts=st.lists(st.integers(0, 2000), max_size=12))
def test_any_bytes_cut_anyhow_come_back_exactly(parts, cuts):
    data = b"".join(parts)
    edges = sorted({min(c, len(data)) for c in cuts})
    chunks = [data[a:b] for a, b in zip([0] + edges, edges + [len(data)])]
    back, msgs = _round_trip(chunks)
    assert back == chunks
    assert sum(len(m.status) for m in msgs) == sum(_whole_samples(c) for c in chunks)


@settings(max_examples=300, deadline=None)
@given(data=st.lists(st.one_of(st.binary(max_size=30), _samples, st.just(b"\x00"), st.just(b"\x01" * 14)),
                     max_size=12).map(b"".join))
def test_a_frame_span_is_found_exactly_where_a_split_at_the_delimiters_finds_one(data):
    """`has_frame_span` against the rule written apart: a piece between delimiters (or before the
    first) of exactly 14 bytes, with its delimiter."""
    assert C.has_frame_span(data) == any(len(p) == C.FRAME_SPAN - 1 for p in data.split(b"\x00")[:-1])


def _packed_wire(n_syncs: int) -> list[bytes]:
    """Each SYNC's bytes from a packing gateway (SNAPSHOT frames of many links, STATUS passed on)."""
    from virtual_sheet.gateway import Gateway
    from virtual_sheet.sheet import VirtualSheet

    gw = Gateway(VirtualSheet("gaussian", "8x8", seed=5, noise=1.0), packed=True)
    gw.power_on(0.0)
    gw.commission(0.0)
    gw.pop_output(1.0)
    out, t = [], 0.01
    for k in range(n_syncs):
        t += 1 / 145
        gw.feed(encode(Sync(counter=k)), t)
        gw.poll(t)
        out.append(gw.pop_wire(t)[0])
    return out


def test_chunks_without_a_frame_span_encode_as_the_general_path_does(monkeypatch):
    """A chunk with no 15-byte span (a packing gateway's) skips the column work: the same message
    bytes, and the same state carried to the next chunk, as the general path (forced here by a
    `has_frame_span` that always says yes) makes, over packed chunks interleaved with per-chip ones."""
    packed = _packed_wire(6)
    assert packed and not any(C.has_frame_span(c) for c in packed)
    per_chip = _sheet_wire(1.0, 6)
    assert all(C.has_frame_span(c) for c in per_chip)
    chunks = [c for pair in zip(packed, per_chip) for c in pair] + [b"", b"\x05\x00"]

    def encoded() -> list[bytes]:
        comp = C.SerialCompactor()
        return [comp.encode(c, bus=2, t=3.5 + k, t_rx=3.0 + k) for k, c in enumerate(chunks)]
    fast = encoded()
    monkeypatch.setattr(C, "has_frame_span", lambda data: True)
    assert fast == encoded()
    back, _ = _round_trip(chunks)
    assert back == chunks


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 40), rounds=st.integers(1, 12))
def test_snapshot_counts_come_back_exactly_whatever_their_range_and_validity(seed, n, rounds):
    rng = _rng(seed)
    enc, dec = C.CountsCoder(), C.CountsCoder()
    for _ in range(rounds):
        counts = rng.integers(-32768, 32768, (n, 3)).astype(np.int16)  # 16-bit IMU counts too
        valid = rng.random(n) < 0.8
        counts[~valid] = np.where(rng.random(((~valid).sum(), 3)) < 0.5, 0, counts[~valid])
        np.testing.assert_array_equal(dec.decode(enc.encode(counts, valid), valid), counts)


def _recorded(path, lat, chunks, *, compact, split_size=None, chunk_size=1 << 20):
    with Recorder(path, lat, 0.01, compact=compact, split_size=split_size, chunk_size=chunk_size,
                  flush_interval_s=0.0 if split_size else 1.0) as rec:
        for k, c in enumerate(chunks):
            rec.raw(0, "serial", c, "p", t=float(k))
        return list(rec.paths)


def test_each_file_of_a_split_set_expands_alone(tmp_path):
    lat = Lattice(4, 4)
    chunks = _cut(b"".join(_sheet_wire(1.0, 40)), 60, _rng(5))
    paths = _recorded(tmp_path / "run.mcap", lat, chunks, compact=True, split_size=8000, chunk_size=4096)
    assert len(paths) >= 3
    alone = [[p for _, _, p in read(f).raw[0]] for f in paths]
    assert all(alone) and sum(alone, []) == chunks
    assert [p for _, _, p in read(tmp_path / "run.mcap").raw[0]] == chunks  # the set by its name


def test_a_compact_recording_is_smaller_and_holds_the_same_input(tmp_path):
    lat = Lattice(8, 8)  # 112 links: a SYNC's answers are 1,680 bytes, about two reads
    chunks = _cut(b"".join(_sheet_wire(1.0, 100, "8x8")), 200, _rng(6))
    [plain] = _recorded(tmp_path / "plain.mcap", lat, chunks, compact=False)
    [small] = _recorded(tmp_path / "small.mcap", lat, chunks, compact=True)
    assert [p for _, _, p in read(plain).raw[0]] == [p for _, _, p in read(small).raw[0]] == chunks
    # the raw channel's messages, compressed as the file compresses them (zstd 9): a SAMPLE's 15
    # bytes are its noise-bound counts' ~2 bytes
    sizes = [len(zstandard.ZstdCompressor(level=9).compress(b"".join(_messages(f, "/capsheet/raw/bus0"))))
             for f in (plain, small)]
    assert sizes[1] < 0.4 * sizes[0], sizes


def _messages(path, topic: str) -> list[bytes]:
    from mcap.records import Channel, Message
    topics, out = {}, []
    with open(path, "rb") as f:
        for r in StreamReader(f).records:
            if isinstance(r, Channel):
                topics[r.id] = r.topic
            elif isinstance(r, Message) and topics[r.channel_id] == topic:
                out.append(bytes(r.data))
    return out


@pytest.mark.parametrize("compact", [True, False])
def test_a_session_rerecorded_either_way_replays_to_the_hosts_snapshots(pty_recording, tmp_path, compact):
    """The host's own recording (compact), replayed into a new recording written compact or as the
    wire bytes: both replay to the snapshots the host made, bit for bit."""
    from host.record.replay import Replay

    rec = read(pty_recording)
    att = rec.attachments
    again = tmp_path / "again.mcap"
    rp = Replay(pty_recording)
    with Recorder(again, rp.lattice, rp.link_length, compact=compact,
                  session={k: rec.session[k] for k in ("rate_hz", "sync", "deadline_s", "transports")
                           if k in rec.session},
                  layout=att.get("layout.json"), calibration=att.get("calibration.json")) as out:
        for snap in rp.snapshots(recorder=out):
            out.snapshot(snap)
    back = read(again)
    with open(again, "rb") as f:
        schemas = {r.name for r in StreamReader(f).records if isinstance(r, Schema)}
    assert ("capsheet.v2.RawSerialFrames" in schemas) == compact and ("capsheet.v2.RawSerial" in schemas) != compact
    assert [c[2] for c in back.raw[0]] == [c[2] for c in rec.raw[0]]
    snaps = list(Replay(again).snapshots())
    assert len(snaps) == len(rec) >= 10
    for k, s in enumerate(snaps):
        assert s.counter == rec.counter[k] and s.timestamp == rec.timestamp[k]
        np.testing.assert_array_equal(s.readings.astype(np.float32), rec.readings[k])
        np.testing.assert_array_equal(s.valid, rec.valid[k])
        np.testing.assert_array_equal(s.status, rec.status[k])
    np.testing.assert_array_equal(back.readings, rec.readings)  # the snapshots it recorded, read back


def test_snapshot_counts_planes_follow_the_documented_rule_byte_for_byte():
    """docs/recording.md's rule, worked by hand for two links over three snapshots, so that a reader
    written from the page reads what the recorder writes (the round trip above holds for any rule
    shared by both directions; this pins the one the page states): per link and axis a state r in
    sixteenths, prediction (r + 8) >> 4 once seen (0 before, and 0 where the link is not valid),
    residual modulo 2**16 as int16, zigzag, little-endian u16 as all low bytes then all high bytes;
    a valid count c sets r = 16 c the first time, else r += (16 c - r) >> 3."""
    coder = C.CountsCoder()
    a_valid, b_out = np.array([True, True]), np.array([True, False])
    s1 = np.array([[100, 0, -1], [2000, -2048, 7]], dtype=np.int16)
    s2 = np.array([[108, 0, -1], [0, 0, 0]], dtype=np.int16)  # link 1 not valid: 0 recorded, predicted 0
    s3 = np.array([[-5, 0, -1], [2010, 32767, 7]], dtype=np.int16)
    # s1: nothing seen: residual = count -> zigzag 200, 0, 1, 4000 (0x0FA0), 4095 (0x0FFF), 14
    assert coder.encode(s1, a_valid) == bytes([200, 0, 1, 0xA0, 0xFF, 14, 0, 0, 0, 0x0F, 0x0F, 0])
    # s2: link 0 x: r 1600 -> prediction 1608 >> 4 = 100, residual 8 -> 16; z: r -16 -> -8 >> 4 = -1,
    # residual 0; link 1 invalid: 0 - 0
    assert coder.encode(s2, b_out) == bytes([16, 0, 0, 0, 0, 0] + [0] * 6)
    # s3: link 0 x: r 1600 + (1728 - 1600) >> 3 = 1616 -> 1624 >> 4 = 101, residual -106 -> 211;
    # link 1 (its state untouched by s2): x r 32000 -> 2000, residual 10 -> 20; y r -32768 -> -2048,
    # residual 32767 + 2048 = 34815 = -30721 modulo 2**16 -> 61441 (0xF001); z r 112 -> 7, residual 0
    assert coder.encode(s3, a_valid) == bytes([211, 0, 0, 20, 0x01, 0] + [0, 0, 0, 0, 0xF0, 0])
    # s4 = s3 again, every link seen and valid: link 0 x: r 1616 + (-80 - 1616) >> 3 = 1404 -> 1412 >> 4
    # = 88, residual -93 -> 185; link 1 x: r 32000 + (32160 - 32000) >> 3 = 32020 -> 2001, residual 9
    # -> 18; y: r -32768 + (524272 + 32768) >> 3 = 36862 -> 2304, residual 30463 -> 60926 (0xEDFE)
    assert coder.encode(s3, a_valid) == bytes([185, 0, 0, 18, 0xFE, 0] + [0, 0, 0, 0, 0xED, 0])
