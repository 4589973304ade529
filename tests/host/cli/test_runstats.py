"""`host.cli.runstats`: run statistics in bounded memory. `Samples` against the standard
library's statistics; `CompletenessWindow` against `host.snapshots.snapshot.window_completeness` over the
whole list, on seeded emission sequences with wraps, repeats, late and pre-window counters."""

from __future__ import annotations

import math
import statistics

import numpy as np
import pytest

from host.snapshots.snapshot import window_completeness
from host.cli.runstats import CompletenessWindow, Samples


def test_samples_are_exact_below_capacity():
    vals = [3.0, -1.5, 7.25, 0.0, 2.0, 2.0, 11.0]
    s = Samples(capacity=16, recent_capacity=4)
    for v in vals:
        s.add(v)
    assert s.count == len(s) == 7 and s.cut == 0
    assert s.mean == pytest.approx(sum(vals) / 7)
    assert (s.min, s.max) == (-1.5, 11.0)
    assert s.median() == statistics.median(vals) == 2.0
    assert s.recent(3) == [2.0, 2.0, 11.0] and s.recent(10) == [0.0, 2.0, 2.0, 11.0]
    assert s.last == 11.0
    assert Samples().median() is None and Samples().mean is None and not Samples()


def test_samples_beyond_capacity_keep_exact_moments_and_a_uniform_sample():
    rng = np.random.Generator(np.random.PCG64(5))
    vals = rng.exponential(1.0, 200_000)  # skewed: a biased sample would move the median
    s = Samples(capacity=4096, seed=1)
    for v in vals:
        s.add(v)
    assert s.count == 200_000 and s.cut == 200_000 - 4096
    assert s.mean == pytest.approx(math.fsum(vals) / len(vals), rel=1e-12)
    assert (s.min, s.max) == (float(vals.min()), float(vals.max()))
    # the exponential's median is ln 2; a uniform sample of 4096 lands within a few 0.01 of it
    assert abs(s.median() - math.log(2)) < 0.05
    # a sample of the first values only (no replacement) would give the same median as those
    assert s.median() != statistics.median(vals[:4096].tolist())
    again = Samples(capacity=4096, seed=1)
    for v in vals:
        again.add(v)
    assert again.median() == s.median()  # seeded


def _emissions(rng, n_syncs: int, first: int, lost: float = 0.02, repeat: float = 0.01,
               late: int = 6, before: int = 5):
    """(counter, complete) in an emission order: SYNCs from ``first - before``, some lost, some
    emitted late (up to ``late`` places out of order), some twice (incomplete, then complete)."""
    out = []
    for k in range(-before, n_syncs + 3):
        if rng.random() < lost:
            continue
        c = (first + k) & 0xFFFF
        if rng.random() < repeat:
            out.append((c, False))
            out.append((c, True))
        else:
            out.append((c, bool(rng.random() < 0.97)))
    # late ones: swap within a small distance
    for i in range(0, len(out) - late, 17):
        j = i + int(rng.integers(1, late))
        out[i], out[j] = out[j], out[i]
    return out


@pytest.mark.parametrize("first, n_syncs, keep, seed", [
    (100, 3000, 64, 1),
    (65500, 5000, 128, 2),       # the counter wraps inside the window
    (0, 140_000, 512, 3),        # longer than 2^16: needs syncs_sent
    (40000, 2000, 100_000, 4),   # nothing folded
])
def test_completeness_window_equals_the_whole_list(first, n_syncs, keep, seed):
    rng = np.random.Generator(np.random.PCG64(seed))
    seq = _emissions(rng, n_syncs, first)
    w = CompletenessWindow(first, keep=keep)
    for i, (c, ok) in enumerate(seq):
        w.add(c, ok)
        assert w.held <= 2 * keep
        if i % 997 == 0 and n_syncs < 65536:  # mid-run, as the live line asks
            end = (c + 1) & 0xFFFF
            assert w.result(end) == window_completeness(seq[:i + 1], first, end)
    end = (first + n_syncs) & 0xFFFF
    assert w.last_counter == seq[-1][0]
    assert w.result(end, n_syncs) == window_completeness(seq, first, end, n_syncs)
    if n_syncs < 65536:
        assert w.result(end) == window_completeness(seq, first, end)


def test_bad_capacities_are_refused():
    with pytest.raises(ValueError, match="capacity"):
        Samples(capacity=0)
    with pytest.raises(ValueError, match="keep"):
        CompletenessWindow(0, keep=0)
