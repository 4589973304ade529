"""`protocol.messages`: the messages' fields and their checks, the sample words and the SNAPSHOT
unpacking (their encodings on the wire: test_framing.py, test_can.py, test_vectors.py)."""

import numpy as np
import pytest
from hypothesis import given, strategies as st

from protocol.messages import Sample, Snapshot, Sync


def test_sync_is_broadcast_only_and_validates_fields():
    with pytest.raises(ValueError, match="node"):
        Sync(node=3, counter=1)
    with pytest.raises(ValueError, match="Invalid counter: 65536"):
        Sync(counter=65536)
    with pytest.raises(ValueError, match="Invalid x: 2048"):
        Sample(1, 0, 2048, 0, 0, 0)


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


def test_a_sample_word_is_the_documented_40_bits_little_endian():
    # docs/protocol.md §4.3: x, y, z 12-bit two's complement at bits 0, 12, 24, status at 36.
    # (1, -1, 0) with status 0b0101: 0x001 | 0xFFF << 12 | 0x000 << 24 | 0x5 << 36 = 0x50_00FF_F001
    from protocol.messages import pack_sample_words, unpack_sample_words
    word = pack_sample_words(np.array([[1, -1, 0]]), np.array([5]))
    assert word == bytes([0x01, 0xF0, 0xFF, 0x00, 0x50])
    counts, status = unpack_sample_words(word)
    assert counts.tolist() == [[1, -1, 0]] and status.tolist() == [5]
    with pytest.raises(ValueError, match="multiple of 5 bytes, got 6"):
        unpack_sample_words(word + b"\x00")


def test_a_payload_that_does_not_decode_says_why():
    from protocol.messages import PayloadError, decode_payload
    with pytest.raises(PayloadError) as e:
        decode_payload(0x7E, 1, b"")
    assert e.value.reason == "UNKNOWN_TYPE"
    with pytest.raises(PayloadError) as e:
        decode_payload(int(Sample.TYPE), 1, bytes(6))  # a SAMPLE is 7 bytes
    assert e.value.reason == "BAD_LENGTH"


def test_a_sample_batch_is_its_samples():
    from protocol.messages import SampleBatch
    b = SampleBatch(np.array([3, 4], np.uint16), np.array([9, 9], np.uint16),
                    np.array([[1, 2, 3], [-4, 5, -6]], np.int16), np.array([0, 2], np.uint8))
    assert len(b) == 2
    assert b.messages() == [Sample(3, 9, 1, 2, 3, 0), Sample(4, 9, -4, 5, -6, 2)]


def _record_by_hand(rec: bytes):
    """One IMU record (docs §16.1) read with int.from_bytes and struct, nothing of protocol.messages:
    the independent reference for the numpy decoders."""
    import struct
    word = int.from_bytes(rec[:5], "little")
    axes = [(word >> s) & 0xFFF for s in (0, 12, 24)]
    counts = [a - 4096 if a & 0x800 else a for a in axes]
    rest = struct.unpack("<" + "h" * ((len(rec) - 5) // 2), rec[5:])
    return counts, word >> 36, rest[0], list(rest[1:4]), list(rest[4:7]) or None


@given(st.sampled_from([1, 2]),
       st.lists(st.tuples(st.integers(0, 0xFFFF), st.integers(0, 0xFF00), st.integers(1, 77), st.binary(min_size=19 * 77,
                                                                                                  max_size=19 * 77)),
                min_size=1, max_size=5))
def test_unpack_snapshots_imu_is_each_snapshots_arrays_and_the_records_read_by_hand(fmt, parts):
    """Any bytes are a valid record, so the records are random bytes: the batch decoder equals, bit for
    bit, `SnapshotImu.arrays` on each frame (the per-frame path) and a by-hand reading of each record."""
    from protocol.messages import IMU_RECORD_SIZE, SnapshotImu, unpack_snapshots_imu
    size = IMU_RECORD_SIZE[fmt]
    snaps = [SnapshotImu(0x7FFF, counter, first, fmt, raw[:size * min(n, 53 if fmt == 2 else 77)])
             for counter, first, n, raw in parts]
    counter, link, counts, status, t_us, gyro, mag = unpack_snapshots_imu(snaps)
    slow = [np.concatenate(a) for a in zip(*(s.arrays()[:4] for s in snaps))]
    for got, want in zip((counts, status, t_us, gyro), slow):
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
    if fmt == 1:
        assert mag is None and all(s.arrays()[4] is None for s in snaps)
    else:
        assert mag.tobytes() == np.concatenate([s.arrays()[4] for s in snaps]).tobytes()
    hand = [_record_by_hand(s.records[i:i + size]) for s in snaps for i in range(0, len(s.records), size)]
    assert counter.tolist() == [s.counter for s in snaps for _ in range(s.count)]
    assert link.tolist() == [s.first_link + k for s in snaps for k in range(s.count)]
    assert counts.tolist() == [h[0] for h in hand] and status.tolist() == [h[1] for h in hand]
    assert t_us.tolist() == [h[2] for h in hand] and gyro.tolist() == [h[3] for h in hand]
    if fmt == 2:
        assert mag.tolist() == [h[4] for h in hand]


def test_unpack_snapshots_imu_refuses_a_mix_of_formats_and_unpacks_nothing_to_empties():
    from protocol.messages import SnapshotImu, unpack_snapshots_imu
    six = SnapshotImu(1, 0, 0, 1, bytes(13))
    nine = SnapshotImu(1, 0, 1, 2, bytes(19))
    with pytest.raises(ValueError, match=r"formats \[1, 2\] in one batch"):
        unpack_snapshots_imu([six, nine])
    out = unpack_snapshots_imu([])
    assert [a.shape for a in out[:6]] == [(0,), (0,), (0, 3), (0,), (0,), (0, 3)] and out[6] is None


def test_unpack_snapshots_imu_gives_the_golden_vectors_fields():
    """The SNAPSHOT_IMU golden vectors (tests/vectors/serial.json: wire bytes beside their fields, written
    from docs/protocol.md §16.5's examples) through the stream decoder and the batch unpacker."""
    import json
    from pathlib import Path

    from protocol.framing import StreamDecoder
    from protocol.messages import unpack_snapshots_imu
    doc = json.loads((Path(__file__).resolve().parents[1] / "vectors" / "serial.json").read_text())
    vecs = [v for v in doc["vectors"] if v["type"] == "SNAPSHOT_IMU" and "fields" in v]
    assert {v["name"] for v in vecs} >= {"snapshot_imu_6_axis", "snapshot_imu_9_axis"}
    for v in vecs:
        [msg] = StreamDecoder().feed(bytes.fromhex(v["hex"]))
        counter, link, counts, status, t_us, gyro, mag = unpack_snapshots_imu([msg])
        f = v["fields"]
        n = len(f["counts"])
        assert counter.tolist() == [f["counter"]] * n and link.tolist() == [f["first_link"] + k for k in range(n)]
        assert counts.tolist() == f["counts"] and status.tolist() == f["status"]
        assert t_us.tolist() == f["time_us"] and gyro.tolist() == f["gyro"]
        assert (mag is None and "mag" not in f) or mag.tolist() == f["mag"]
