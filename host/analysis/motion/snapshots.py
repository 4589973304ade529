"""A recorded or live snapshot into the fused estimator: what ``capsheet demo``, ``capsheet
host --live`` and ``capsheet estimate`` feed `MotionEstimator` alike, one snapshot at a time, in order.

A snapshot is anything with the attributes of `host.snapshots.snapshot.LatticeSnapshot`: ``timestamp`` (s),
``valid`` (n_links,), ``readings`` (n_links, 3) m/s², ``gyro`` (n_links, 3) rad/s or None, ``mag``
(n_links, 3) T or None, ``sample_time_s`` (n_links,) s after the SYNC (NaN: unknown).
"""

from __future__ import annotations

import numpy as np

__all__ = ["FusedShape", "fused_update", "RESTART_S"]

#: every valid link's sample time this far behind the estimator's: a new time base (a SYNC counter
#: restarted, another session), and the fused estimator starts again; less, or on some links only,
#: those links' records are not newer than the ones it has (a conversion repeated for two SYNCs
#: close together, a record out of order) and are left out of this snapshot
RESTART_S = 0.5


class FusedShape:
    """The fused estimator's shape as the recorder and the live view take an estimate: ``joints``,
    ``valid`` (the links of the snapshot that had an IMU record), ``method``; ``motion`` the
    `host.analysis.motion.MotionEstimate` itself."""

    method = "fused"

    def __init__(self, motion, valid: np.ndarray) -> None:
        self.motion, self.joints, self.valid = motion, motion.joints, valid


def fused_update(fused, snap):
    """One snapshot into the fused estimator: each link at its own sample time (the SYNC's
    host time plus the chip's ``time_us``), links without an IMU record masked, and links whose
    record is not newer than the one the estimator has (a conversion repeated for two SYNCs close
    together) left out of this snapshot. None for a snapshot without IMU records (the chips did not
    take CONFIG_IMU) or without a newer one; every link `RESTART_S` behind is a new time base: the
    estimator starts again (`MotionEstimator.sample_times_s` is then None)."""
    if snap.gyro is None:
        return None
    valid = snap.valid & np.isfinite(snap.gyro[:, 0])
    if not valid.any():
        return None
    t = snap.timestamp + np.where(np.isfinite(snap.sample_time_s), snap.sample_time_s, 0.0)
    last = fused.sample_times_s
    if last is not None:
        stale = valid & (t <= last)
        if stale.any():
            valid = valid & ~stale
            if not valid.any():  # no link's record is newer than what the estimator has
                if np.all(t[stale] < last[stale] - RESTART_S):
                    fused.reset()  # a new time base (a SYNC counter restarted): start again
                return None
    gyro = np.where(valid[:, None], snap.gyro, 0.0)
    accel = np.where(valid[:, None], snap.readings, 0.0)
    mag = None if snap.mag is None else np.where(valid[:, None], snap.mag, 0.0)
    try:
        return FusedShape(fused.update(t, accel, gyro, mag, valid=valid), valid)
    except ValueError:  # e.g. a sample time that went back (a SYNC counter restarted): start again
        fused.reset()
        return None
