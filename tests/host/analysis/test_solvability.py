"""The two solvability criteria of `capsheet paper solvability` on the paper's Fig. 8 grid:
eq. (7)'s λ3/λ1 and the estimator's yaw standard deviation from its normal matrix."""

from __future__ import annotations

import numpy as np

from host.cli import paper


def test_yaw_std_flags_every_case_2_state_that_lambda_ratio_misses():
    res = paper.solvability_grid(8)
    n_case2 = 2 * 8 ** 3 + 8 ** 3 - 2 * 8 ** 2  # θc ∈ {0, π} or θf = π, on an 8^4 grid
    assert res["yaw_std"]["case2"] == n_case2  # all of them
    assert res["case2"] < n_case2 // 5  # λ3/λ1 < 0.1 finds few (squashed at a generic tilt: no)
    assert res["yaw_std"]["case1"] == res["case1"] > 0  # both find the horizontal unit


def test_yaw_std_gain_of_a_generic_unit_is_small_and_of_a_squashed_one_large():
    a, b, c = paper.unit_state(np.array([0.0, 1.0]), 0.0, 0.3, 0.4)
    gain = paper.yaw_std_gain(a, b, c)
    assert gain[0] > 100 and gain[1] < 5
