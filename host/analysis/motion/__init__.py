"""Shape while the sheet moves: the fused estimator (`MotionEstimator`: the lattice's
loops with gyroscopes, accelerometers and magnetometers) and the peers it is measured against.
docs/estimator.md §8."""

from .fused import FusedConfig, MotionEstimate, MotionEstimator, calibrated
from .peers import accel_only, per_link_filter

__all__ = ["FusedConfig", "MotionEstimate", "MotionEstimator", "calibrated", "accel_only",
           "per_link_filter"]
