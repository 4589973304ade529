"""The serial stream decoder and the CAN mapping: round trips, chunking invariance, and damage that
loses only the frames it touches (never an exception)."""

import numpy as np
import pytest
from hypothesis import given, strategies as st
from cobs import cobs

from protocol import (DecodeError, ErrorReason, Sample, SampleBatch, Snapshot, StreamDecoder, decode_can,
                      decode_frame, encode, from_can, to_can)
from protocol.can import CAN_CLASSIC_MTU, FD_LENGTHS, MAX_FD_SNAPSHOT_SAMPLES, make_id, split_id
from protocol.framing import MAX_ENCODED_SIZE, encode_frame
from protocol.messages import MsgType, PROTOCOL_VERSION, Sync
from tests.strategies import messages

lists_of_messages = st.lists(messages(), min_size=1, max_size=12)


def feed_all(data: bytes, chunks=None, **kw):
    dec = StreamDecoder(**kw)
    if chunks is None:
        return dec.feed(data), dec
    out, pos = [], 0
    for n in chunks:
        out += dec.feed(data[pos:pos + n])
        pos += n
    out += dec.feed(data[pos:])
    return out, dec


# ------------------------------------------------------------------ round trips

@given(messages())
def test_every_message_round_trips_over_serial(msg):
    assert StreamDecoder().feed(encode(msg)) == [msg]


@given(messages(max_snapshot=MAX_FD_SNAPSHOT_SAMPLES))
def test_every_message_round_trips_over_can(msg):
    frame = to_can(msg)
    assert len(frame.data) <= (64 if frame.is_fd else CAN_CLASSIC_MTU)
    assert frame.is_fd == (len(msg.payload()) > CAN_CLASSIC_MTU)
    if frame.is_fd:
        assert len(frame.data) in FD_LENGTHS
    assert from_can(frame.arbitration_id, frame.data, is_fd=frame.is_fd) == msg
    prio, type_code, version, node = split_id(frame.arbitration_id)
    assert (prio, type_code, version, node) == (msg.PRIORITY, msg.TYPE, PROTOCOL_VERSION, msg.node)


@given(messages())
def test_serial_frame_layout_is_header_payload_crc(msg):
    body = cobs.decode(encode(msg)[:-1])
    assert body[:4] == bytes([PROTOCOL_VERSION, msg.TYPE]) + msg.node.to_bytes(2, "little")
    assert body[4:-2] == msg.payload()
    assert b"\x00" not in encode(msg)[:-1]


def test_classic_can_refuses_a_snapshot_and_fd_pads_it():
    snap = Snapshot.from_arrays(0, 1, 0, np.zeros((3, 3), int), np.zeros(3, int))
    with pytest.raises(ValueError, match="needs CAN FD"):
        to_can(snap, fd=False)
    f = to_can(snap)
    assert f.is_fd and len(f.data) == 20 and f.data[5 + 15:] == b""  # 5 + 3 * 5 = 20: no padding needed
    g = to_can(Snapshot.from_arrays(0, 1, 0, np.zeros((2, 3), int), np.zeros(2, int)))
    assert len(g.data) == 16 and g.data[15:] == b"\x00"  # 15 bytes -> FD length 16, padded with 0x00
    assert decode_can(g.arbitration_id, g.data[:-1] + b"\x01", is_fd=True).reason == ErrorReason.BAD_FIELD
    assert decode_can(g.arbitration_id, g.data + bytes(4), is_fd=True).reason == ErrorReason.BAD_LENGTH


def test_can_frames_of_another_version_are_reported_not_decoded():
    f = to_can(Sample(3, 1, 2, 3, 4, 0))
    other = make_id(MsgType.SAMPLE, 3, version=2)
    ev = decode_can(other, f.data)
    assert isinstance(ev, DecodeError) and ev.reason == ErrorReason.BAD_VERSION and ev.version == 2
    assert decode_can(f.arbitration_id & 0x7FF, f.data, is_extended_id=False).reason == ErrorReason.BAD_FIELD


@given(st.integers(0, (1 << 29) - 1), st.binary(max_size=64), st.booleans())
def test_any_can_frame_decodes_or_reports(arb, data, fd):
    out = decode_can(arb, data, is_fd=fd)
    assert isinstance(out, DecodeError) or to_can(out, fd=fd).data[:len(data)] == data


def test_sync_is_broadcast_only_and_validates_fields():
    with pytest.raises(ValueError, match="node"):
        Sync(node=3, counter=1)
    with pytest.raises(ValueError, match="Invalid counter: 65536"):
        Sync(counter=65536)
    with pytest.raises(ValueError, match="Invalid x: 2048"):
        Sample(1, 0, 2048, 0, 0, 0)


# ------------------------------------------------------------------ chunking invariance

@given(lists_of_messages, st.lists(st.integers(0, 40), max_size=60))
def test_whole_byte_by_byte_and_chunks_give_identical_events(msgs, chunks):
    wire = b"".join(encode(m) for m in msgs)
    whole, _ = feed_all(wire)
    assert whole == msgs
    bytewise, _ = feed_all(wire, [1] * len(wire))
    chunked, _ = feed_all(wire, chunks)
    assert bytewise == whole == chunked


@given(st.binary(max_size=3000), st.lists(st.integers(1, 300), max_size=30))
def test_garbage_chunking_invariance_including_errors(data, chunks):
    whole, d1 = feed_all(data)
    chunked, d2 = feed_all(data, chunks)
    assert whole == chunked
    assert d1.stats.errors == d2.stats.errors


# ------------------------------------------------------------------ damage

@given(st.binary(max_size=4000))
def test_any_bytes_never_raise_and_every_event_is_accounted(data):
    events, dec = feed_all(data)
    errors = [e for e in events if isinstance(e, DecodeError)]
    assert dec.stats.error_count == len(errors)
    assert dec.stats.frames == len(events) - len(errors)
    segments = [s for s in data.split(b"\x00")[:-1] if s]  # complete, non-empty
    assert len(events) <= len(segments) + 1  # +1: a pending oversize run is reported before its delimiter


@given(lists_of_messages, st.data())
def test_garbage_between_frames_loses_only_the_frames_it_touches(msgs, data):
    wire, expected, garbage_segments = b"", [], 0
    for m in msgs:
        junk = data.draw(st.binary(max_size=40))
        if junk and data.draw(st.booleans()):
            junk += b"\x00"  # delimited garbage: the next frame survives
        wire += junk
        touched = bool(junk) and not junk.endswith(b"\x00")
        if not touched:
            expected.append(m)
        garbage_segments += len([s for s in junk.split(b"\x00")[:-1] if s]) if junk.endswith(b"\x00") else 0
        wire += encode(m)
    events, dec = feed_all(wire)
    got = [e for e in events if not isinstance(e, DecodeError)]
    it = iter(got)
    assert all(any(g == m for g in it) for m in expected)  # expected is a subsequence of got, in order
    assert len(got) >= len(expected)


@given(lists_of_messages, st.data())
def test_one_bit_flip_loses_at_most_the_frames_around_it(msgs, data):
    frames = [encode(m) for m in msgs]
    wire = bytearray(b"".join(frames))
    pos = data.draw(st.integers(0, len(wire) - 1))
    wire[pos] ^= 1 << data.draw(st.integers(0, 7))
    # frame k holds byte pos; flipping its delimiter also merges frame k+1 into it
    starts = np.cumsum([0] + [len(f) for f in frames])
    k = int(np.searchsorted(starts, pos, side="right") - 1)
    touched = {k, k + 1} if pos == starts[k + 1] - 1 else {k}
    events, _ = feed_all(bytes(wire))
    got = [e for e in events if not isinstance(e, DecodeError)]
    assert got == [m for i, m in enumerate(msgs) if i not in touched]


@given(lists_of_messages, st.data())
def test_truncation_delivers_every_complete_frame(msgs, data):
    wire = b"".join(encode(m) for m in msgs)
    cut = data.draw(st.integers(0, len(wire)))
    complete = wire[:cut].count(b"\x00")
    events, dec = feed_all(wire[:cut])
    assert events == msgs[:complete]
    # the rest arrives later: nothing lost
    assert dec.feed(wire[cut:]) == msgs[complete:]


def test_oversize_run_is_reported_once_and_the_next_frame_survives():
    good = encode(Sample(1, 2, 3, 4, 5, 0))
    wire = b"\x01" * (MAX_ENCODED_SIZE + 500) + b"\x00" + good
    for chunks in (None, [1] * len(wire), [700, 700, 700]):
        events, dec = feed_all(wire, chunks)
        assert [type(e) for e in events] == [DecodeError, Sample]
        assert events[0].reason == ErrorReason.OVERSIZE and dec.stats.errors[ErrorReason.OVERSIZE] == 1


def test_unknown_type_bad_version_and_short_frames_are_counted_by_reason():
    wire = (encode_frame(0x3E, 1, b"") + encode_frame(MsgType.SAMPLE, 1, bytes(7), version=9)
            + cobs.encode(b"\x01\x02") + b"\x00" + encode(Sample(1, 0, 0, 0, 0, 0)))
    events, dec = feed_all(wire)
    assert [getattr(e, "reason", None) for e in events] == [ErrorReason.UNKNOWN_TYPE, ErrorReason.BAD_VERSION,
                                                           ErrorReason.SHORT, None]
    assert events[1].version == 9
    assert sum(dec.stats.errors.values()) == 3 and dec.stats.frames == 1


# ------------------------------------------------------------------ the batch fast path

@given(lists_of_messages, st.integers(0, 2**32 - 1))
def test_batch_mode_gives_the_same_samples_as_the_exact_path(msgs, seed):
    rng = np.random.Generator(np.random.MT19937(seed))
    samples = [Sample(int(rng.integers(1, 0xFFFE)), int(rng.integers(0, 65536)), *map(int, rng.integers(-2048, 2048, 3)),
                      int(rng.integers(0, 16))) for _ in range(30)]
    mixed = samples[:10] + msgs + samples[10:]
    wire = b"".join(encode(m) for m in mixed)
    events, _ = feed_all(wire, batch_samples=True)
    flat = []
    for e in events:
        flat += e.messages() if isinstance(e, SampleBatch) else [e]
    assert flat == mixed
    # and the exact per-frame path (decode_frame) agrees frame by frame
    assert [decode_frame(seg) for seg in wire.split(b"\x00")[:-1]] == mixed
    assert all(isinstance(e, SampleBatch) or not isinstance(e, Sample) for e in events)


@given(st.lists(st.integers(0, 2**32 - 1), min_size=1, max_size=6))
def test_unpack_snapshots_equals_unpacking_each(seeds):
    from protocol.messages import unpack_snapshots
    snaps = []
    for seed in seeds:
        rng = np.random.Generator(np.random.MT19937(seed))
        n = int(rng.integers(1, 40))
        snaps.append(Snapshot.from_arrays(0, int(rng.integers(0, 65536)), int(rng.integers(0, 1000)),
                                          rng.integers(-2048, 2048, (n, 3)), rng.integers(0, 16, n)))
    counter, link, counts, status = unpack_snapshots(snaps)
    assert counter.tolist() == [s.counter for s in snaps for _ in range(s.count)]
    assert link.tolist() == [s.first_link + k for s in snaps for k in range(s.count)]
    assert counts.tolist() == [row for s in snaps for row in s.counts.tolist()]
    assert status.tolist() == [v for s in snaps for v in s.status.tolist()]
