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
