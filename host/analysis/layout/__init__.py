"""Learning which chip sits on which link from the sheet itself (docs/host.md, "Learning the layout").

Pure computation on what a host sees on the wire (chip ids and their readings) and the time it is
given: `poses.PoseDetector` tells each held pose from the readings (changed, then settled);
`learn.learn_layout` decides the chip of every link from the poses of `learn.PROCEDURE`, and
`learn.check_layout` holds an existing layout to the same evidence; both judge the result by the
lattice's loop closure (`learn.unit_residuals`, the estimator's residual per unit).
"""

from .learn import (LOOP_RESIDUAL_LIMIT, PROCEDURE, CheckResult, LayoutLearnError, LearnResult, check_layout, judge_pose,
                    learn_layout, unit_residuals)
from .poses import Pose, PoseDetector

__all__ = ["LOOP_RESIDUAL_LIMIT", "PROCEDURE", "Pose", "PoseDetector", "LearnResult", "CheckResult", "LayoutLearnError",
           "learn_layout", "check_layout", "judge_pose", "unit_residuals"]
