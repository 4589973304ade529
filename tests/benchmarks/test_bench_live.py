"""benchmarks/bench_live.py: the order of its rate sweep and its rule for a rate held (the
completeness over a window of SYNCs it uses is tested in tests/host/snapshots/test_window_completeness.py)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "bench_live", Path(__file__).resolve().parents[2] / "benchmarks" / "bench_live.py")
bench_live = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_live)


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


def test_the_6_axis_rows_run_on_the_gateways_their_records_need():
    """Per chip, 364 6-axis IMU_SAMPLEs (23 B on the wire) at 145 Hz are 101 % of one 12 Mbaud UART:
    the row runs over two gateways; packed in SNAPSHOT_IMU (13 B a record) they fit one."""
    per = bench_live.imu_capacity(bench_live.CONFIGS["14x14-6axis-per-chip-2gw"])
    assert per["gateways"] == per["gateways_needed"] == 2 and per["load_pct_per_gateway"] <= 100
    # by hand: 182 chips x 23 B x 10 bits x 145 Hz / 12e6
    assert per["load_pct_per_gateway"] == pytest.approx(100 * 182 * 23 * 10 * 145 / 12e6, abs=0.1)
    packed = bench_live.imu_capacity(bench_live.CONFIGS["14x14-6axis-packed"])
    assert packed["gateways"] == packed["gateways_needed"] == 1 and packed["framing"] == "SNAPSHOT_IMU"
    assert 50 < packed["load_pct_per_gateway"] < 60  # 364 x 13 B + 5 frames' overhead, x 10 bits x 145 Hz
