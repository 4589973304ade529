"""bench_soak's memory figures: a rise of a few seconds that went back is not growth, a step that
stayed is (`_steady_growth`, computed from the 5-s samples the benchmark takes)."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import bench_soak  # noqa: E402


def _series(step_at=None, spikes=()):
    return [(float(t), 96.0 + (1.5 if step_at is not None and t >= step_at else 0.0) + (8.0 if t in spikes else 0.0))
            for t in range(0, 965, 5)]


def test_a_rise_that_went_back_is_not_steady_growth_but_a_step_that_stayed_is():
    spiky = _series(spikes=(700, 955))  # the last sample inside a rise: single samples say +8
    assert bench_soak._steady_growth(spiky, 120.0, 960.0) == 0.0
    assert bench_soak._steady_growth(_series(step_at=500), 120.0, 960.0) == 1.5
    assert bench_soak._steady_growth(_series(step_at=930), 120.0, 960.0) == 1.5  # half the last minute
    assert bench_soak._steady_growth(_series(), 120.0, 200.0) is None  # too short for two windows
