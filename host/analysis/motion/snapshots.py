"""A recorded or live snapshot into the fused estimator (issue 30): what ``capsheet demo``, ``capsheet
host --live`` and ``capsheet estimate`` feed `MotionEstimator` alike, one snapshot at a time, in order.

A snapshot is anything with the attributes of `host.aggregator.LatticeSnapshot`: ``timestamp`` (s),
``valid`` (n_links,), ``readings`` (n_links, 3) m/s², ``gyro`` (n_links, 3) rad/s or None, ``mag``
(n_links, 3) T or None, ``sample_time_s`` (n_links,) s after the SYNC (NaN: unknown).
"""

from __future__ import annotations

import numpy as np

__all__ = ["FusedShape", "fused_update"]


class FusedShape:
    """The fused estimator's shape as the recorder and the live view take an estimate: ``joints``,
    ``valid`` (the links of the snapshot that had an IMU record), ``method``; ``motion`` the
    `host.analysis.motion.MotionEstimate` itself."""

    method = "fused"

    def __init__(self, motion, valid: np.ndarray) -> None:
        self.motion, self.joints, self.valid = motion, motion.joints, valid


def fused_update(fused, snap):
    """One snapshot into the fused estimator (issue 30): each link at its own sample time (the SYNC's
    host time plus the chip's ``time_us``), links without an IMU record masked. None for a snapshot
    without IMU records (the chips did not take CONFIG_IMU)."""
    if snap.gyro is None:
        return None
    valid = snap.valid & np.isfinite(snap.gyro[:, 0])
    if not valid.any():
        return None
    t = snap.timestamp + np.where(np.isfinite(snap.sample_time_s), snap.sample_time_s, 0.0)
    gyro = np.where(valid[:, None], snap.gyro, 0.0)
    accel = np.where(valid[:, None], snap.readings, 0.0)
    mag = None if snap.mag is None else np.where(valid[:, None], snap.mag, 0.0)
    try:
        return FusedShape(fused.update(t, accel, gyro, mag, valid=valid), valid)
    except ValueError:  # e.g. a sample time that went back (a SYNC counter restarted): start again
        fused.reset()
        return None
