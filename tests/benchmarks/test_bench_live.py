"""benchmarks/bench_live.py's completeness over a window of SYNCs: numerator and denominator over
the same counters (it once reported 100.83 % complete)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "bench_live", Path(__file__).resolve().parents[2] / "benchmarks" / "bench_live.py")
bench_live = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_live)
window_completeness = bench_live.window_completeness


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


def _sweep(rates, limit):
    ran = []

    def held_at(r):
        ran.append(r)
        return r <= limit
    return bench_live.sweep_order(rates, held_at), ran


def test_sweep_goes_up_from_145_while_rates_hold():
    done, ran = _sweep([30, 60, 145, 300, 640], limit=400)
    assert done == ran == [145, 300, 640]


def test_sweep_goes_down_from_145_until_a_rate_holds():
    done, ran = _sweep([30, 60, 145, 300, 640], limit=50)
    assert done == ran == [145, 60, 30]
    done, ran = _sweep([30, 60, 145, 300, 640], limit=10)  # none holds: every lower rate tried
    assert ran == [145, 60, 30]


def test_a_rate_is_held_only_if_complete_sent_and_every_chip_started():
    ok = {"rate_hz": 145.0, "complete_pct": 99.3, "achieved_sync_hz": 144.0, "started": 364}
    assert bench_live.held(ok, 364)
    # what the CAN row reported as held: complete, but the host sent 68.8 of 145 SYNC/s
    assert not bench_live.held(dict(ok, achieved_sync_hz=68.8), 364)
    # a bring-up that found 5 chips of 1,984 completes its 5 links every time
    assert not bench_live.held(dict(ok, started=5), 364)
    assert not bench_live.held(dict(ok, complete_pct=98.9), 364)
    assert not bench_live.held({"rate_hz": 145.0, "error": "CapacityError"}, 364)
