"""`host.snapshots.deadline.DeadlinePolicy` alone: fed latencies (the simulated clock's SYNC -> last frame,
seconds), the deadline it answers and how often it moved, as exact numbers worked out by hand from
the rule (1.5 x the largest of the last 256 + 2 ms, every 32 measurements, within the bounds; up at
once, down by at most 5 % per update; a late frame raises it at once)."""

from __future__ import annotations

import pytest

from host.snapshots.deadline import DeadlinePolicy


def adaptive(start=0.01, lo=0.005, hi=0.2):
    return DeadlinePolicy(start, min_deadline_s=lo, max_deadline_s=hi)


def test_a_fixed_deadline_ignores_every_measurement():
    p = DeadlinePolicy(0.03)
    assert not p.adaptive and p.min_deadline_s == p.max_deadline_s == 0.03
    for _ in range(100):
        p.measure(0.5)
    p.measure(1.0, late=True)
    assert p.deadline_s == 0.03 and p.changes == 0 and p.late_raises == 0


def test_the_starting_value_is_clipped_to_the_bounds():
    assert adaptive(start=0.5).deadline_s == 0.2
    assert adaptive(start=0.001).deadline_s == 0.005


def test_nothing_moves_before_32_measurements_then_the_first_update_replaces_the_guess():
    p = adaptive(start=0.1)
    for _ in range(31):
        p.measure(0.004)
    assert p.deadline_s == 0.1 and p.changes == 0
    p.measure(0.004)  # the 32nd: target 1.5 * 4 ms + 2 ms = 8 ms, set outright (not by 5 % steps)
    assert p.deadline_s == pytest.approx(0.008) and p.changes == 1


def test_a_lower_target_is_approached_by_at_most_5_percent_per_update():
    p = adaptive(start=0.1)
    for _ in range(32):
        p.measure(0.06)  # 1.5 * 60 ms + 2 ms = 92 ms
    assert p.deadline_s == pytest.approx(0.092)
    # the window still holds the 60 ms measurements for 256 of them: the target stays 92 ms
    for _ in range(224):
        p.measure(0.004)
    assert p.deadline_s == pytest.approx(0.092) and p.changes == 1
    # now the window holds only 4 ms: target 8 ms, but each update goes down by 5 % at most
    for k in range(3):
        for _ in range(32):
            p.measure(0.004)
        assert p.deadline_s == pytest.approx(0.092 * 0.95 ** (k + 1))
    assert p.changes == 4


def test_a_higher_target_is_taken_at_once_within_the_upper_bound():
    p = adaptive(start=0.01)
    for _ in range(32):
        p.measure(0.004)
    assert p.deadline_s == pytest.approx(0.008)
    for _ in range(31):
        p.measure(0.004)
    p.measure(0.05)  # the largest in the window: 1.5 * 50 ms + 2 ms = 77 ms, at the update
    assert p.deadline_s == pytest.approx(0.077) and p.changes == 2
    for _ in range(32):
        p.measure(1.0)  # 1.502 s: bounded to 0.2 s
    assert p.deadline_s == 0.2 and p.changes == 3


def test_a_late_frame_raises_the_deadline_at_once_and_only_upwards():
    p = adaptive(start=0.01)
    p.measure(0.03, late=True)  # 1.5 * 30 ms + 2 ms = 47 ms, without waiting for an update
    assert p.deadline_s == pytest.approx(0.047) and p.changes == 1 and p.late_raises == 1
    p.measure(0.005, late=True)  # asks for 9.5 ms: lower, so nothing moves
    assert p.deadline_s == pytest.approx(0.047) and p.changes == 1 and p.late_raises == 1


def test_switching_adaptation_off_keeps_the_deadline_where_it_is():
    p = adaptive(start=0.01)
    p.measure(0.03, late=True)
    p.adaptive = False
    for _ in range(64):
        p.measure(0.001)
    assert p.deadline_s == pytest.approx(0.047) and p.changes == 1


@pytest.mark.parametrize("kw, match", [
    (dict(deadline_s=float("nan")), "deadline_s"),
    (dict(deadline_s=0.0), "deadline_s"),
    (dict(min_deadline_s=0.2, max_deadline_s=0.1), "min_deadline_s"),
    (dict(min_deadline_s=0.0, max_deadline_s=0.1), "min_deadline_s"),
    (dict(min_deadline_s=0.01, max_deadline_s=float("inf")), "max_deadline_s"),
])
def test_invalid_settings_are_refused_by_name(kw, match):
    with pytest.raises(ValueError, match=match):
        DeadlinePolicy(**kw)
