"""`protocol.can`: the CAN mapping (identifiers, classic and FD frames, round trips, another version
reported) and `protocol.can.CanDecoder`, the sans-I/O CAN receiver, without python-can: frames are plain objects
with python-can's attribute names, and `FrameBlock` arrays. Whole input, one frame per call and any
grouping give the same messages (h11's three-way test); `FrameBlock` rows decode as the same frames
one by one; every message is what `decode_can` makes of its frame alone (an independent rule); any
frames never raise; what is dropped without an event is counted."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol import DecodeError, ErrorReason, SampleBatch, from_can, to_can
from protocol.can import (CAN_CLASSIC_MTU, FD_LENGTHS, MAX_FD_SNAPSHOT_SAMPLES, CanDecoder, EchoFilter, FrameBlock,
                          decode_can, make_id, split_id)
from protocol.messages import PROTOCOL_VERSION, Ack, MsgType, Sample, Snapshot, Status, Sync
from tests.strategies import messages


def frame(aid, data, *, ext=True, fd=False, err=False, rtr=False):
    return SimpleNamespace(arbitration_id=aid, data=bytes(data), is_extended_id=ext, is_fd=fd,
                           is_error_frame=err, is_remote_frame=rtr)


def of(msg, **kw):
    f = to_can(msg)
    return frame(f.arbitration_id, f.data, fd=f.is_fd, **kw)


def flat(events) -> list:
    return [m for ev in events for m in (ev.messages() if isinstance(ev, SampleBatch) else [ev])]


def mix(seed: int, n: int = 400) -> list:
    rng = np.random.Generator(np.random.MT19937(seed))
    out = []
    for k in range(n):
        u = int(rng.integers(0, 10))
        node = int(rng.integers(1, 300))
        if u < 6:
            x, y, z = (int(v) for v in rng.integers(-2048, 2048, 3))
            out.append(of(Sample(node, k & 0xFFFF, x, y, z, int(rng.integers(0, 16)))))
        elif u == 6:
            out.append(of(Ack(node, MsgType.START, 0)))
        elif u == 7:
            out.append(of(Status(node, 3, 0, 0, 0, k)))
        elif u == 8:
            f = to_can(Sample(node, k, 1, 2, 3, 0))
            out.append(frame(f.arbitration_id, f.data[:5]))  # a SAMPLE cut short
        else:
            out.append(frame(0, b"", err=True))
    return out


def test_whole_one_by_one_and_chunked_give_the_same_messages():
    frames = mix(1)
    whole = CanDecoder().feed(frames)
    one = CanDecoder()
    single = [ev for f in frames for ev in one.feed([f])]
    chunked_dec = CanDecoder()
    rng = np.random.Generator(np.random.MT19937(2))
    cuts = np.sort(rng.choice(np.arange(1, len(frames)), 30, replace=False)).tolist()
    chunked = [ev for a, b in zip([0, *cuts], [*cuts, len(frames)]) for ev in chunked_dec.feed(frames[a:b])]
    assert flat(whole) == flat(single) == flat(chunked)
    kept = [f for f in frames if not f.is_error_frame]
    assert flat(whole) == [decode_can(f.arbitration_id, f.data) for f in kept]
    assert sum(isinstance(e, SampleBatch) for e in whole) < sum(isinstance(e, SampleBatch) for e in single)
    dec = CanDecoder()
    dec.feed(frames)
    errs = [e for e in flat(whole) if isinstance(e, DecodeError)]
    assert dec.stats.error_frames == sum(f.is_error_frame for f in frames) > 0
    assert sum(dec.stats.errors.values()) == len(errs) > 0
    assert dec.stats.frames == len(flat(whole)) - len(errs)
    assert dec.stats.bytes_in == sum(len(f.data) for f in kept)


def test_a_frame_block_decodes_as_its_frames_one_by_one():
    msgs = [Sample(k + 1, 9, k, -k, 1024, k % 16) for k in range(50)]
    ids = np.array([to_can(m).arbitration_id for m in msgs], dtype=np.uint32)
    ids[7] = make_id(MsgType.SAMPLE, 0xFFFF & 0x7FFF, version=2)  # not this version: the slow path says why
    rows = np.frombuffer(b"".join(to_can(m).data for m in msgs), dtype=np.uint8).reshape(50, 7)
    block = CanDecoder().feed([of(Sync(counter=9)), FrameBlock(ids, rows), of(Ack(3, MsgType.STOP, 0))])
    one = CanDecoder().feed([of(Sync(counter=9))] + [frame(int(i), r.tobytes()) for i, r in zip(ids, rows)]
                            + [of(Ack(3, MsgType.STOP, 0))])
    assert flat(block) == flat(one)
    assert isinstance(flat(block)[8], DecodeError) and flat(block)[8].reason.name == "BAD_VERSION"


def test_echoes_fd_on_classic_and_remote_frames_are_dropped_and_counted():
    echo = EchoFilter()
    sync = to_can(Sync(counter=4))
    echo.sent(sync.arbitration_id, sync.data)
    dec = CanDecoder(echo=echo)
    fd_sample = to_can(Sample(5, 4, 1, 2, 3, 0), fd=True)
    echoes: list = []
    got = dec.feed([frame(sync.arbitration_id, sync.data), frame(fd_sample.arbitration_id, fd_sample.data, fd=True),
                    frame(make_id(MsgType.SAMPLE, 5), b"", rtr=True), of(Sample(6, 4, 0, 0, 1024, 0))], echoes)
    assert flat(got) == [Sample(6, 4, 0, 0, 1024, 0)]
    assert echoes == [(sync.arbitration_id, sync.data)] and echo.echoes == 1
    assert (dec.stats.fd_on_classic, dec.stats.remote_frames) == (1, 1)
    assert flat(CanDecoder(fd=True).feed([frame(fd_sample.arbitration_id, fd_sample.data, fd=True)])) == \
        [Sample(5, 4, 1, 2, 3, 0)]


@given(st.lists(st.tuples(st.integers(0, (1 << 30) - 1), st.binary(max_size=12), st.booleans(), st.booleans(),
                          st.booleans(), st.booleans()), max_size=40))
def test_any_frames_never_raise_and_each_is_accounted_for(raw):
    frames = [frame(a, d, ext=e, fd=fd, err=err, rtr=r) for a, d, e, fd, err, r in raw]
    dec = CanDecoder(fd=True)
    events = dec.feed(frames)
    st_ = dec.stats
    n_events = len(flat(events))
    dropped = st_.error_frames + st_.remote_frames
    assert n_events + dropped == len(frames)
    assert all(not isinstance(e, DecodeError) or e.reason in st_.errors for e in flat(events))


@given(st.lists(st.tuples(st.sampled_from([make_id(MsgType.SAMPLE, 1) & ~0xFFFF, 0]), st.integers(0, 0xFFFF),
                          st.integers(0, 1 << 30), st.sampled_from([5, 6, 7, 8, 12]), st.booleans(), st.booleans()),
                min_size=1, max_size=30), st.integers(0, 2 ** 32 - 1))
def test_every_sample_decode_can_accepts_takes_the_batch_path(raw, seed):
    # the receiver batches SAMPLEs by a test of the identifier and length before decode_can; what
    # decode_can would make a Sample of must pass that test (the path after it has no SAMPLE branch):
    # every Sample comes out inside a SampleBatch, in order, and nothing else does
    rng = np.random.Generator(np.random.MT19937(seed))
    frames = []
    for base, node, other, n, ext, fd in raw:
        aid = (base | node) if base else other
        frames.append(frame(aid, rng.integers(0, 256, n).astype(np.uint8).tobytes(), ext=ext, fd=fd))
    events = CanDecoder(fd=True).feed(frames)
    samples = [ev for f in frames if isinstance(ev := decode_can(f.arbitration_id, f.data, is_extended_id=f.is_extended_id,
                                                                   is_fd=f.is_fd), Sample)]
    assert [m for ev in events if isinstance(ev, SampleBatch) for m in ev.messages()] == samples
    assert not any(isinstance(ev, Sample) for ev in events)


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
