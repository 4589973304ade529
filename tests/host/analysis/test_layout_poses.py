"""The pose detector (host/analysis/layout/poses.py) on a simulated clock: readings fed at 50 Hz
from a scripted timeline of holds and moves, exact counts of the poses it takes and when."""

from __future__ import annotations

import numpy as np
import pytest

from host.analysis.layout import PoseDetector

G = 9.80665
RATE_HZ = 50.0


def directions(n: int, tilt_deg: float, seed: int) -> np.ndarray:
    """``n`` unit vectors ``tilt_deg`` from +z, random azimuths (seeded)."""
    g = np.random.Generator(np.random.MT19937(seed))
    az = g.uniform(0, 2 * np.pi, n)
    t = np.radians(tilt_deg)
    return np.stack([np.sin(t) * np.cos(az), np.sin(t) * np.sin(az), np.full(n, np.cos(t))], axis=1)


def run(timeline, n: int = 30, noise_pct_g: float = 1.0, seed: int = 1, babbler: bool = False, start=None, **kw):
    """Feed the detector the timeline [(kind, seconds, target (n, 3) unit)] and return the poses
    taken as (index, end_s, mean (n, 3)). ``move`` goes linearly from the last target to its own."""
    det = PoseDetector(**kw)
    g = np.random.Generator(np.random.MT19937(seed))
    uids = list(range(0x100, 0x100 + n))
    out = []
    t, k = 0.0, 0
    cur = timeline[0][2] if start is None else start
    for kind, dur, target in timeline:
        start, steps = cur, int(round(dur * RATE_HZ))
        for s in range(steps):
            now = k / RATE_HZ
            w = (s + 1) / steps if kind == "move" else 1.0
            v = start + (target - start) * w
            v = v / np.linalg.norm(v, axis=1, keepdims=True)
            r = G * v + g.normal(0, noise_pct_g / 100 * G, v.shape)
            if babbler:
                r[0] = g.normal(0, G, 3)
            det.add_many(uids, r, now)
            p = det.poll(now)
            if p is not None:
                out.append((p.index, round(p.end_s, 6), p.mean / np.linalg.norm(p.mean, axis=1, keepdims=True)))
            k += 1
        cur = target
    return det, out


FLAT = np.tile([0.0, 0.0, 1.0], (30, 1))
A = directions(30, 40, seed=2)
B = directions(30, 40, seed=3)


def test_each_hold_after_a_move_is_one_pose_taken_when_it_settles():
    tl = [("hold", 3.0, FLAT), ("move", 1.0, A), ("hold", 3.0, A), ("move", 1.0, B), ("hold", 3.0, B)]
    det, poses = run(tl)
    assert [p[0] for p in poses] == [0, 1, 2]
    # a hold that starts at T is taken once a whole settle window (1 s) lies in it: by T + 1.1 s
    for (_i, end, _m), start in zip(poses, (0.0, 4.0, 8.0)):
        assert start + 0.9 <= end <= start + 1.1 + 1e-9, (start, end)
    for (_i, _e, mean), truth in zip(poses, (FLAT, A, B)):
        assert np.degrees(np.arccos(np.clip((mean * truth).sum(axis=1), -1, 1))).max() < 1.0
    assert det.samples == 30 * 11 * 50 and det.bad_samples == 0


def test_a_pose_put_back_where_it_was_is_not_taken_twice():
    tl = [("hold", 3.0, FLAT), ("move", 1.0, A), ("hold", 3.0, A), ("move", 0.5, B), ("move", 0.5, A),
          ("hold", 3.0, A)]
    _det, poses = run(tl)
    assert [p[0] for p in poses] == [0, 1]


def test_a_move_back_to_an_earlier_pose_is_a_new_pose():
    tl = [("hold", 3.0, A), ("move", 1.0, B), ("hold", 3.0, B), ("move", 1.0, A), ("hold", 3.0, A)]
    _det, poses = run(tl)
    assert [p[0] for p in poses] == [0, 1, 2]


def test_a_sheet_that_never_stops_moving_gives_no_pose():
    tl = [("move", 2.0, A), ("move", 2.0, B), ("move", 2.0, FLAT), ("move", 2.0, A)]
    _det, poses = run(tl, start=FLAT)
    assert poses == []


def test_a_hold_shorter_than_the_settle_time_is_not_taken():
    tl = [("hold", 3.0, FLAT), ("move", 1.0, A), ("hold", 0.7, A), ("move", 1.0, B), ("hold", 3.0, B)]
    _det, poses = run(tl)
    assert [p[0] for p in poses] == [0, 1]
    assert poses[1][1] >= 5.7 + 0.9  # B's hold, not A's


def test_small_wobbles_under_the_settle_angle_still_settle():
    wob = A.copy()
    wob[:, 0] += np.radians(0.5)  # ~0.4 degrees off A
    tl = [("hold", 3.0, FLAT), ("move", 1.0, A), ("hold", 0.5, A), ("move", 0.2, wob), ("move", 0.2, A),
          ("hold", 3.0, A)]
    _det, poses = run(tl)
    assert [p[0] for p in poses] == [0, 1]


def test_one_babbling_chip_does_not_hold_the_procedure_up():
    tl = [("hold", 3.0, FLAT), ("move", 1.0, A), ("hold", 3.0, A)]
    _det, poses = run(tl, babbler=True, settle_fraction=0.95)
    assert [p[0] for p in poses] == [0, 1]
    _det, poses = run(tl, babbler=True, settle_fraction=1.0)  # everyone must be still: never
    assert poses == []


def test_bad_readings_are_counted_and_left_out():
    det = PoseDetector(chunk_s=0.1, settle_s=0.5)
    for k in range(60):
        t = k / 50
        det.add_many([1, 2], [[0, 0, G], [np.nan, 0, G]], t)
        det.add(3, (0.0, 0.0, 0.0), t)
        p = det.poll(t)
        if p is not None:
            assert p.uids.tolist() == [1]
    assert det.bad_samples == 120 and det.samples == 60 and det.poses_taken == 1


@pytest.mark.parametrize("kw, needle", [
    ({"chunk_s": 0}, "chunk_s"), ({"settle_s": 0.1}, "settle_s"), ({"settle_deg": -1}, "settle_deg"),
    ({"change_deg": 180}, "change_deg"), ({"change_fraction": 0}, "change_fraction"),
    ({"settle_fraction": 1.5}, "settle_fraction"),
])
def test_bad_parameters_are_named(kw, needle):
    with pytest.raises(ValueError, match=needle):
        PoseDetector(**kw)
