"""`host.analysis.motion.snapshots.fused_update`: a snapshot into the fused estimator, as ``capsheet
host``, ``demo``, ``replay`` and ``estimate`` feed it — including links whose record is not newer
than the one before (a conversion repeated for two SYNCs close together)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from host.analysis.motion import MotionEstimator
from host.analysis.motion.snapshots import RESTART_S, fused_update
from protocol.constants import G0

N = 12  # 3x3 joints


def _snap(t: float, sample_time_s=None):
    readings = np.tile([0.0, 0.0, G0], (N, 1))
    return SimpleNamespace(timestamp=t, valid=np.ones(N, dtype=bool), readings=readings, gyro=np.zeros((N, 3)),
                           mag=None, sample_time_s=np.zeros(N) if sample_time_s is None else sample_time_s)


def test_a_link_whose_record_is_not_newer_is_left_out_not_a_restart():
    fused = MotionEstimator(3, 3, 0.01)
    assert fused_update(fused, _snap(10.0)) is not None
    # the next SYNC came 3 ms later and link 4's chip answered it with the same conversion (its
    # time, SYNC + time_us, is the one it had): left out of this snapshot, the others go on
    st = np.zeros(N)
    st[4] = -0.003
    out = fused_update(fused, _snap(10.003, st))
    assert out is not None and out.valid.sum() == N - 1 and not out.valid[4]
    assert fused.snapshots == 2
    # every link's record repeated: nothing new, and the estimator keeps its state
    assert fused_update(fused, _snap(10.003)) is None
    assert fused.snapshots == 2 and fused.sample_times_s is not None
    assert fused_update(fused, _snap(10.013)) is not None and fused.snapshots == 3


def test_every_link_far_behind_is_a_new_time_base_and_the_estimator_starts_again():
    fused = MotionEstimator(3, 3, 0.01)
    fused_update(fused, _snap(100.0))
    assert fused_update(fused, _snap(100.0 - RESTART_S / 2)) is None and fused.sample_times_s is not None  # kept
    assert fused_update(fused, _snap(100.0 - 2 * RESTART_S)) is None and fused.sample_times_s is None  # started again
    assert fused_update(fused, _snap(50.0)) is not None and fused.snapshots == 1
