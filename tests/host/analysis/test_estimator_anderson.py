"""The chord iteration's acceleration (`host.analysis.estimator.solver.anderson`): for a mode each step
overshoots (step = −ρ × the last), the accelerated move is the rest of the series, s / (1 + ρ);
any other pair of steps is left alone."""

from __future__ import annotations

import numpy as np

from host.analysis import estimator as E


def _series(rho: float, n: int = 50, seed: int = 2):
    """Steps of x -> x + s(x) for s(x) = -(1 + rho) (x - x*) along one direction: each step is
    -rho times the last, x converges to x* by overshooting."""
    g = np.random.Generator(np.random.MT19937(seed))
    e = g.normal(size=n)
    x_star = g.normal(size=n)
    x0 = x_star + 0.3 * e
    s = lambda x: -(1.0 + rho) * (x - x_star)  # noqa: E731
    x1 = x0 + s(x0)
    return x_star, x1, s(x0), s(x1)


def test_an_overshooting_mode_is_summed_to_its_fixed_point():
    for rho in (0.2, 0.5, 0.9):
        x_star, x1, s0, s1 = _series(rho)
        np.testing.assert_allclose(s1, -rho * s0)
        move = E.solver.anderson(s1, (s0, s0))
        np.testing.assert_allclose(x1 + move, x_star, atol=1e-12)
        # the plain step would land -rho times as far on the other side
        assert np.max(np.abs(x1 + s1 - x_star)) > 0.1 * rho * np.max(np.abs(x1 - x_star))


def test_steps_that_do_not_reverse_are_left_alone():
    g = np.random.Generator(np.random.MT19937(5))
    a, b = g.normal(size=40), g.normal(size=40)
    for s_prev, s in ((a, 0.5 * a), (a, b), (a, -0.5 * a + 2.0 * b)):  # contracting, unrelated, weak
        assert E.solver.anderson(s, (s_prev, s_prev)) is s
    assert E.solver.anderson(a, None) is a
    assert E.solver.anderson(np.zeros(40), (a, a)).tolist() == [0.0] * 40
