"""The two solvability criteria of `capsheet paper solvability` on the paper's Fig. 8 grid:
eq. (7)'s λ3/λ1 and the estimator's yaw standard deviation from its normal matrix."""

from __future__ import annotations

import numpy as np
import pytest

from host.cli import paper


def test_the_yaw_criterion_flags_rank_deficient_units_not_generic_ones():
    res = paper.solvability_grid(8)
    y = res["yaw_std"]
    n_case2 = 2 * 8 ** 3 + 8 ** 3 - 2 * 8 ** 2  # θc ∈ {0, π} or θf = π, on an 8^4 grid
    assert y["case2"] == n_case2 and res["eq7"]["case2"] < n_case2 // 5
    assert y["case1"] == res["eq7"]["case1"] > 0  # both find the horizontal unit
    assert y["other"] < 0.01 * res["n_total"]  # not a share of the generic units
    gain = res["gain"]
    assert np.median(gain) < 10 and res["yaw_gain_limit"] == pytest.approx(10 * np.median(gain))


def test_yaw_std_gain_of_a_generic_unit_is_small_and_of_a_squashed_one_large():
    a, b, c = paper.unit_state(np.array([0.0, 1.0]), 0.0, 0.3, 0.4)
    gain = paper.yaw_std_gain(a, b, c)
    assert gain[0] > 100 and gain[1] < 5
