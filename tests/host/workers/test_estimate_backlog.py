"""``--estimate-process``: snapshots due an estimate wait in order while the estimator process is
busy, `ESTIMATE_BACKLOG_S` of them (by their own times) at most; the older ones are given up and
counted. A real estimator process, stopped with SIGSTOP while the snapshots come, so that exactly
the ones the pipe takes are in flight and the rest wait."""

from __future__ import annotations

import argparse
import os
import signal
import time

import numpy as np
import pytest

from host.snapshots.snapshot import LatticeSnapshot
from host.cli import record_args as RA
from host.record.recording import read_recording
from protocol.lattice import Lattice
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.shapes import make_sheet

pytestmark = pytest.mark.skipif(not hasattr(signal, "SIGSTOP"), reason="needs SIGSTOP (POSIX)")

RATE = 64.0  # snapshots per second: their times k / 64 are exact in binary


def _session(tmp_path):
    args = argparse.Namespace(record=str(tmp_path / "run.mcap"), live=None, live_rate=1e9,
                              estimate_process=True)
    # not a live host session: the file gets every estimate (a host session's gets 5 a second)
    return RA.SessionOutputs(args, Lattice(5, 6), 0.01, mode="test")


def _wait(cond, what: str, limit_s: float = 120.0) -> None:
    end = time.monotonic() + limit_s
    while not cond():
        assert time.monotonic() < end, what
        time.sleep(0.01)


def test_snapshots_wait_in_order_while_the_estimator_is_busy_and_the_oldest_are_given_up(tmp_path):
    out = _session(tmp_path)
    w = out.worker
    assert w is not None
    r = ideal_readings(make_sheet("cylinder", 5, 6, 0.01))
    ok = np.ones(r.shape[0], bool)
    n = 200
    try:
        _wait(lambda: (w.results(0.05) or True) and w.warm, "the estimator's warm-up")
        os.kill(w.pid, signal.SIGSTOP)
        for k in range(n):
            out.snapshot(LatticeSnapshot(k, k / RATE, float(k), r, ok, np.zeros(r.shape[0], np.uint8),
                                         True, 0.0))
        in_flight = w.max_in_flight
        assert len(out._sent) == in_flight  # the pipe took these; the others wait
        # the newest snapshot's time is 199/64 s; those within 2 s of it wait (k >= 71), the ones
        # before them were given up
        held = 129
        assert RA.ESTIMATE_BACKLOG_S == 2.0
        assert list(s.counter for s in out._waiting) == list(range(n - held, n))
        assert out.estimates_not_made == n - in_flight - held
    finally:
        os.kill(w.pid, signal.SIGCONT)
    _wait(lambda: (out.poll(0.05) or True) and not out._sent and not out._waiting, "the estimates")
    assert out.estimates_made == in_flight + held
    out.close()
    rec = read_recording(tmp_path / "run.mcap")
    assert len(rec) == n  # every snapshot recorded
    expect = list(range(in_flight)) + list(range(n - held, n))
    assert [int(c) for c in rec.estimates["counter"]] == expect  # in order


def test_a_backlog_is_bounded_by_count_too(tmp_path, monkeypatch):
    monkeypatch.setattr(RA, "ESTIMATE_BACKLOG_MAX", 5)
    out = _session(tmp_path)
    w = out.worker
    r = ideal_readings(make_sheet("cylinder", 5, 6, 0.01))
    ok = np.ones(r.shape[0], bool)
    try:
        _wait(lambda: (w.results(0.05) or True) and w.warm, "the estimator's warm-up")
        os.kill(w.pid, signal.SIGSTOP)
        for k in range(40):
            out.snapshot(LatticeSnapshot(k, k / RATE / 100, float(k), r, ok,  # all within 2 s
                                         np.zeros(r.shape[0], np.uint8), True, 0.0))
        assert [s.counter for s in out._waiting] == list(range(35, 40))
        assert out.estimates_not_made == 40 - w.max_in_flight - 5
    finally:
        os.kill(w.pid, signal.SIGCONT)
    out.close()
    # closing gives up what still waits, counted
    assert out.estimates_made + out.estimates_not_made == 40

