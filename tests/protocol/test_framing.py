"""The serial framing and stream decoder: round trips, chunking invariance, and damage that loses
only the frames it touches (never an exception). The CAN mapping: test_can.py."""

import numpy as np
from hypothesis import given, strategies as st
from cobs import cobs

from protocol import DecodeError, ErrorReason, Sample, SampleBatch, StreamDecoder, decode_frame, encode
from protocol.framing import MAX_ENCODED_SIZE, encode_frame
from protocol.messages import ChipState, MsgType, PROTOCOL_VERSION, Status, StatusBatch
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


@given(messages())
def test_serial_frame_layout_is_header_payload_crc(msg):
    body = cobs.decode(encode(msg)[:-1])
    assert body[:4] == bytes([PROTOCOL_VERSION, msg.TYPE]) + msg.node.to_bytes(2, "little")
    assert body[4:-2] == msg.payload()
    assert b"\x00" not in encode(msg)[:-1]


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




@given(lists_of_messages, st.integers(0, 2**32 - 1), st.lists(st.integers(1, 60), max_size=40))
def test_status_batches_give_the_same_heartbeats_as_the_exact_path_in_any_chunking(msgs, seed, chunks):
    """``batch_status``: runs of STATUS come out as `StatusBatch`es whose rows are exactly the `Status`
    messages the exact path decodes; a STATUS the exact path refuses (a state no chip has, a bad
    CRC) is refused alike, with the same reason, and nothing around it is lost."""
    rng = np.random.Generator(np.random.MT19937(seed))
    states = [int(s) for s in ChipState]
    beats = [Status(int(rng.integers(1, 0xFFFE)), states[int(rng.integers(len(states)))], int(rng.integers(0, 16)),
                    int(rng.integers(0, 256)), int(rng.integers(0, 256)), int(rng.integers(0, 2**32)))
             for _ in range(24)]
    bad_state = encode_frame(MsgType.STATUS, 7, bytes([9, 0, 0, 0, 1, 0, 0, 0]))  # state 9: no such state
    raw = bytearray(cobs.decode(encode(beats[0])[:-1]))
    raw[-1] ^= 0x01  # one bit of the CRC: refused
    bad_crc = cobs.encode(bytes(raw)) + b"\x00"
    wire = (b"".join(encode(m) for m in beats[:8]) + bad_state + b"".join(encode(m) for m in msgs)
            + bytes(bad_crc) + b"".join(encode(m) for m in beats[8:]))
    exact, _ = feed_all(wire, chunks or None, batch_samples=True)
    batched, dec = feed_all(wire, chunks or None, batch_samples=True, batch_status=True)
    flat = []
    for e in batched:
        flat += e.messages() if isinstance(e, (StatusBatch, SampleBatch)) else [e]
    want = []
    for e in exact:
        want += e.messages() if isinstance(e, SampleBatch) else [e]
    assert [(type(e), getattr(e, "reason", None)) for e in flat] == [(type(e), getattr(e, "reason", None)) for e in want]
    assert [e for e in flat if not isinstance(e, DecodeError)] == [e for e in want if not isinstance(e, DecodeError)]
    assert sum(len(e) for e in batched if isinstance(e, StatusBatch)) >= 16  # the runs did take the fast path
    assert not any(isinstance(e, Status) and e in beats for e in batched)  # none of the good ones went slow
    assert sum(isinstance(e, DecodeError) for e in flat) == 2 and dec.stats.errors[ErrorReason.BAD_CRC] == 1
