"""`host.snapshots.snapshot.window_completeness`: numerator and denominator over the same SYNCs (bench_live
once reported 100.83 % complete, `capsheet demo` 100.1 %)."""

from __future__ import annotations

import pytest

from host.snapshots.snapshot import window_completeness


def test_snapshots_of_syncs_sent_before_the_window_are_not_counted():
    # counters 0..9 sent before the window, 10..19 in it; 5..9 complete inside it (late), 10..19 complete
    snaps = [(c, True) for c in range(5, 20)]
    got = window_completeness(snaps, 10, 20)
    assert got == {"syncs_sent": 10, "snapshots": 10, "complete": 10, "complete_pct": 100.0}


def test_after_the_window_and_missing_ones():
    snaps = [(10, True), (11, False), (13, True), (20, True), (21, True)]  # 12 never came, 14..19 neither
    got = window_completeness(snaps, 10, 20)
    assert got == {"syncs_sent": 10, "snapshots": 3, "complete": 2, "complete_pct": 20.0}


def test_a_counter_seen_twice_counts_once():
    got = window_completeness([(3, True), (3, True), (4, False)], 3, 5)
    assert got == {"syncs_sent": 2, "snapshots": 2, "complete": 1, "complete_pct": 50.0}


@pytest.mark.parametrize("first", [65530, 65535])
def test_the_window_wraps_at_2_16(first):
    end = (first + 10) & 0xFFFF
    snaps = [((first + i) & 0xFFFF, i != 3) for i in range(-2, 12)]
    got = window_completeness(snaps, first, end)
    assert got == {"syncs_sent": 10, "snapshots": 10, "complete": 9, "complete_pct": 90.0}


def test_never_above_100_percent():
    snaps = [(c, True) for c in range(0, 200)]
    for first in range(0, 150, 7):
        assert window_completeness(snaps, first, first + 37)["complete_pct"] == 100.0


def test_a_window_longer_than_2_16_syncs_needs_and_uses_the_hosts_count():
    n = 70_000  # 8 min at 145 Hz: end - first is 4,464 mod 2^16
    first = 65_000
    snaps = [((first + i) & 0xFFFF, i % 10 != 0) for i in range(-5, n + 5)]
    got = window_completeness(snaps, first, (first + n) & 0xFFFF, syncs_sent=n + 1)  # read one late
    assert got == {"syncs_sent": n, "snapshots": n, "complete": n - n // 10, "complete_pct": 90.0}
    # without the count only the last 2^16 residue is seen: the bug this argument is for
    short = window_completeness(snaps, first, (first + n) & 0xFFFF)
    assert short["syncs_sent"] == n - 65_536


def test_snapshots_out_of_order_are_unwrapped_one_after_the_other():
    first = 65_534
    order = [0, 1, 3, 2, 5, 4, 6, 7]  # a late one after its successor, across the wrap
    snaps = [((first + i) & 0xFFFF, True) for i in order]
    got = window_completeness(snaps, first, (first + 8) & 0xFFFF, syncs_sent=8)
    assert got == {"syncs_sent": 8, "snapshots": 8, "complete": 8, "complete_pct": 100.0}
