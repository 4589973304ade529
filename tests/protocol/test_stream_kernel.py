"""The stream decoder's compiled scan (protocol/_kernel/stream.c) against its numpy and per-frame
Python code: the same events, in the same order, from valid, damaged and random input, in any
chunking; and SNAPSHOT runs (`SnapshotFrames`) that are exactly the frames `decode_frame` gives."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from protocol.framing import (NATIVE_SCAN, DecodeError, ErrorReason, StreamDecoder, decode_frame, encode,
                              encode_frame)
from protocol.messages import (ChipState, ImuBatch, ImuSample, MsgType, SampleBatch, Snapshot, SnapshotFrames,
                               Status, StatusBatch)
from tests.strategies import messages, snapshots

pytestmark = pytest.mark.skipif(not NATIVE_SCAN, reason="protocol/_kernel/stream.c is not built (no C compiler "
                                                        "at install, or CAPSHEET_NO_KERNEL set)")

_BATCHES = (SampleBatch, StatusBatch, ImuBatch, SnapshotFrames)
_FIELDS = {SampleBatch: ("node", "counter", "counts", "status"),
           StatusBatch: ("node", "state", "flags", "rx_errors", "missed_syncs", "uptime_s"),
           ImuBatch: ("node", "counter", "counts", "status", "time_us", "gyro", "mag"),
           SnapshotFrames: ("node", "frame_counter", "first_link", "sizes", "counter", "link", "counts", "status")}


def norm(ev):
    """An event as comparable plain data: a batch's arrays with their dtypes."""
    if isinstance(ev, _BATCHES):
        out = [type(ev).__name__]
        for f in _FIELDS[type(ev)]:
            a = getattr(ev, f)
            out.append(None if a is None else (f, str(a.dtype), a.shape, a.tolist()))
        return tuple(out)
    return ev


def expand(events):
    """Batches as the messages they hold (what a decoder without batching gives)."""
    out = []
    for ev in events:
        out.extend(ev.messages() if isinstance(ev, _BATCHES) else [ev])
    return out


def run(data: bytes, chunks, **kw):
    dec = StreamDecoder(**kw)
    out, pos = [], 0
    for n in chunks:
        out += dec.feed(data[pos:pos + n])
        pos += n
    out += dec.feed(data[pos:])
    return out, dec.stats


def imu_samples():
    i16 = st.integers(-32768, 32767)
    acc = st.integers(-2048, 2047)
    return st.one_of(
        st.builds(ImuSample, st.integers(0, 0xFFFE), st.integers(0, 0xFFFF), acc, acc, acc, st.integers(0, 15),
                  st.integers(-32768, 32767), i16, i16, i16),
        st.builds(ImuSample, st.integers(0, 0xFFFE), st.integers(0, 0xFFFF), acc, acc, acc, st.integers(0, 15),
                  st.integers(-32768, 32767), i16, i16, i16, i16, i16, i16))


def crafted():
    """Frames a conforming sender never sends: each must be left to the exact decoder."""
    u16 = st.integers(0, 0xFFFF)

    @st.composite
    def bad_snapshot(draw):
        count = draw(st.integers(0, 12))
        first = draw(st.sampled_from([0, 0xFFFF - count, 0x10000 - count, 0xFFFF, draw(u16)]))
        words = bytes(draw(st.binary(min_size=5 * count, max_size=5 * count)))
        extra = draw(st.sampled_from([b"", b"\x01", b"\x01\x02\x03\x04"]))
        declared = draw(st.sampled_from([count, (count + 1) & 0xFF, 0]))
        payload = (draw(u16).to_bytes(2, "little") + (first & 0xFFFF).to_bytes(2, "little") + bytes([declared])
                   + words + extra)[:draw(st.integers(0, 1018))]
        node = draw(st.sampled_from([1, 0xFFFF, draw(st.integers(0, 0xFFFF))]))
        version = draw(st.sampled_from([1, 1, 1, 2]))
        return encode_frame(MsgType.SNAPSHOT, node, payload, version=version)

    @st.composite
    def bad_status(draw):  # a STATUS-sized frame whose state is not a ChipState, or node 0xFFFF
        payload = bytes([draw(st.integers(0, 255))]) + draw(st.binary(min_size=7, max_size=7))
        return encode_frame(MsgType.STATUS, draw(st.sampled_from([3, 0xFFFF])), payload)

    @st.composite
    def wrong_type_same_size(draw):  # a SAMPLE's size and another type, or a SAMPLE of the wrong size
        t = draw(st.sampled_from([MsgType.SAMPLE, MsgType.ACK, MsgType.STATUS, MsgType.IMU_SAMPLE, 0x3E]))
        return encode_frame(t, draw(st.integers(0, 0xFFFF)), draw(st.binary(min_size=0, max_size=30)))

    return st.one_of(bad_snapshot(), bad_status(), wrong_type_same_size())


@st.composite
def streams(draw):
    """Wire bytes: valid frames of every kind, crafted and damaged frames, junk and idle fill."""
    pieces = draw(st.lists(st.one_of(
        messages().map(encode), imu_samples().map(encode), snapshots(202).map(encode),
        st.builds(Status, st.integers(0, 0xFFFE), st.sampled_from(list(ChipState)), st.integers(0, 255),
                  st.integers(0, 255), st.integers(0, 255), st.integers(0, 2**32 - 1)).map(encode),
        crafted(), st.binary(max_size=40), st.just(b"\x00\x00")), min_size=1, max_size=25))
    wire = bytearray(b"".join(pieces))
    for _ in range(draw(st.integers(0, 3))):  # bit flips anywhere
        if wire:
            pos = draw(st.integers(0, len(wire) - 1))
            wire[pos] ^= 1 << draw(st.integers(0, 7))
    return bytes(wire)


flags = st.fixed_dictionaries({"batch_samples": st.booleans(), "batch_status": st.booleans(),
                               "batch_snapshots": st.booleans()})


@settings(max_examples=300, deadline=None)
@given(streams(), st.lists(st.integers(1, 400), max_size=12), flags)
def test_compiled_and_python_scans_give_the_same_events_and_counts(wire, chunks, kw):
    native, st_n = run(wire, chunks, native=True, **kw)
    python, st_p = run(wire, chunks, native=False, **kw)
    assert [norm(e) for e in native] == [norm(e) for e in python]
    assert (st_n.bytes_in, st_n.frames, st_n.errors) == (st_p.bytes_in, st_p.frames, st_p.errors)


@settings(max_examples=200, deadline=None)
@given(streams(), st.lists(st.integers(1, 400), max_size=12))
def test_every_batch_holds_exactly_the_frames_decode_frame_gives(wire, chunks):
    """Against the reference: each frame alone through `decode_frame`, no batching, no fast path."""
    batched, _ = run(wire, chunks, native=True, batch_samples=True, batch_status=True, batch_snapshots=True)
    frames = [f for f in wire[:wire.rfind(b"\x00") + 1].split(b"\x00")[:-1] if f] if b"\x00" in wire else []
    reference = [decode_frame(f) for f in frames]
    assert expand(batched) == reference


def test_snapshot_runs_are_one_event_per_run_between_other_frames():
    rng = np.random.default_rng(5)
    snaps = [Snapshot.from_arrays(9, c, 202 * k, rng.integers(-2048, 2048, (202, 3)), rng.integers(0, 16, 202))
             for c in (7, 8) for k in range(3)]
    status = Status(4, ChipState.STREAMING, 0, 0, 0, 12)
    wire = b"".join(encode(s) for s in snaps[:3]) + encode(status) + b"".join(encode(s) for s in snaps[3:])
    for native in (True, False):
        ev, stats = run(wire, [], native=native, batch_samples=True, batch_status=True, batch_snapshots=True)
        assert [type(e) for e in ev] == [SnapshotFrames, StatusBatch, SnapshotFrames]
        assert ev[0].messages() == snaps[:3] and ev[2].messages() == snaps[3:]
        assert ev[0].sizes.tolist() == [202, 202, 202] and ev[0].link.tolist() == list(range(606))
        assert ev[0].frame_counter.tolist() == [7, 7, 7] and ev[0].counter.tolist() == [7] * 606
        assert stats.frames == 7 and not stats.errors


@pytest.mark.parametrize("native", [True, False])
def test_snapshot_edges_are_decided_as_the_spec_says(native):
    """§4.8: first_link + count may reach 65,536, not pass it; count 1..255 and 5 bytes a word."""
    w = bytes(range(1, 11))  # two words
    ok = encode_frame(MsgType.SNAPSHOT, 2, (5).to_bytes(2, "little") + (0xFFFE).to_bytes(2, "little") + b"\x02" + w)
    past = encode_frame(MsgType.SNAPSHOT, 2, (5).to_bytes(2, "little") + (0xFFFF).to_bytes(2, "little") + b"\x02" + w)
    zero = encode_frame(MsgType.SNAPSHOT, 2, (5).to_bytes(2, "little") + (0).to_bytes(2, "little") + b"\x00")
    short = encode_frame(MsgType.SNAPSHOT, 2, (5).to_bytes(2, "little") + (0).to_bytes(2, "little") + b"\x02" + w[:9])
    reserved = encode_frame(MsgType.SNAPSHOT, 0xFFFF, (5).to_bytes(2, "little") + (0).to_bytes(2, "little") + b"\x02" + w)
    ev, stats = run(ok + past + zero + short + reserved, [], native=native, batch_samples=True,
                    batch_snapshots=True)
    assert type(ev[0]) is SnapshotFrames and ev[0].link.tolist() == [0xFFFE, 0xFFFF]
    assert [e.reason for e in ev[1:]] == [ErrorReason.BAD_FIELD, ErrorReason.BAD_LENGTH, ErrorReason.BAD_LENGTH,
                                          ErrorReason.BAD_FIELD]
    assert stats.frames == 1 and sum(stats.errors.values()) == 4


def test_the_scan_reuses_its_arrays_without_sharing_them_with_events():
    """Events keep their values after the decoder scans the next read into the same scratch."""
    rng = np.random.default_rng(6)
    a = Snapshot.from_arrays(1, 1, 0, rng.integers(-2048, 2048, (50, 3)), rng.integers(0, 16, 50))
    b = Snapshot.from_arrays(1, 2, 0, rng.integers(-2048, 2048, (50, 3)), rng.integers(0, 16, 50))
    dec = StreamDecoder(batch_samples=True, batch_snapshots=True, native=True)
    first = dec.feed(encode(a))
    dec.feed(encode(b))
    assert first[0].messages() == [a]


def test_a_damaged_snapshot_is_reported_and_its_neighbours_kept():
    rng = np.random.default_rng(7)
    snaps = [Snapshot.from_arrays(3, 1, 100 * k, rng.integers(-2048, 2048, (100, 3)), rng.integers(0, 16, 100))
             for k in range(3)]
    wire = bytearray(b"".join(encode(s) for s in snaps))
    wire[len(encode(snaps[0])) + 40] ^= 0x10  # inside the second frame's words
    ev, stats = run(bytes(wire), [], native=True, batch_samples=True, batch_snapshots=True)
    assert [type(e) for e in ev] == [SnapshotFrames, DecodeError, SnapshotFrames]
    assert ev[1].reason == ErrorReason.BAD_CRC
    assert ev[0].messages() + ev[2].messages() == [snaps[0], snaps[2]]
    assert stats.frames == 2 and stats.errors[ErrorReason.BAD_CRC] == 1
