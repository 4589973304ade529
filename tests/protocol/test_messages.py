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
