"""The fused estimator's per-link steps in C (host/analysis/motion/_kernel/link_filter.c) give the
numpy code's numbers (host/analysis/motion/fused.py `_np_*`), on random states of many links."""

from __future__ import annotations

import numpy as np
import pytest

from host.analysis.motion import fused

pytestmark = pytest.mark.skipif(fused._klib is None, reason="the motion kernel is not built "
                                "(no C compiler at install, or CAPSHEET_NO_KERNEL set)")


def _state(n, seed):
    g = np.random.Generator(np.random.MT19937(seed))
    R = fused.rotation_matrices(g.normal(0, 1.5, (n, 3)))
    A = g.normal(0, 1e-3, (n, 6, 6))
    P = A @ A.transpose(0, 2, 1) + 1e-6 * np.eye(6)
    return g, R, P


def _both(name, n, args_of):
    """Run step ``name`` through the kernel and through numpy on copies of the same arrays."""
    out = []
    for use in (fused._kernel_step, lambda nm, *a: fused.NUMPY_STEPS[nm](*a)):
        args = args_of()
        use(name, *args)
        out.append(args)
    return out


@pytest.mark.parametrize("name", ["propagate", "accel", "yaw", "apply"])
def test_each_per_link_step_is_the_same_in_c_and_numpy(name):
    n = 57

    def args_of():
        g, R, P = _state(n, 11)
        if name == "propagate":
            return (R, P, g.normal(0, 3, (n, 3)), g.normal(0, 3, (n, 3)),
                    g.uniform(0.005, 0.01, n), g.uniform(0, 1e-6, n), g.uniform(0, 1e-9, n))
        if name == "accel":
            valid = g.random(n) > 0.2
            return (R, P, g.normal(0, 10, (n, 3)), g.normal(0, 10, (n, 3)),
                    g.uniform(1e-3, 1e-2, n), 25.0, valid, np.zeros((n, 6)), np.zeros(n))
        if name == "yaw":
            return (P, g.normal(0, 1e-3, n), g.uniform(1e6, 1e7, n), np.zeros((n, 6)))
        return (R, g.normal(0, 1e-3, (n, 3)), P, g.normal(0, 1e-3, (n, 6)))

    c, p = _both(name, n, args_of)
    for a, b in zip(c, p):
        if isinstance(a, np.ndarray) and a.dtype == np.float64:
            assert np.array_equal(np.isnan(a), np.isnan(b)), name  # NaN in the same places
            a, b = np.nan_to_num(a), np.nan_to_num(b)
            scale = max(np.abs(b).max(), 1e-300)
            assert np.abs(a - b).max() <= 1e-12 * scale, (name, np.abs(a - b).max(), scale)
    # the check can fail: a different rate in the kernel's propagation shows
    if name == "propagate":
        args = args_of()
        args[3][0, 0] += 1e-6
        fused._kernel_step(name, *args)
        assert np.abs(args[0] - p[0]).max() > 1e-12


def test_a_mask_handed_to_the_kernel_stays_alive_until_the_call():
    """A boolean mask goes to the kernel as a uint8 copy; the arguments must keep that copy alive.
    A cast pointer to it did not: the copy was freed before the call, numpy's allocator gave its
    bytes to the next array of that size (here 64 arrays of zeros; live, another thread's while
    cffi had released the interpreter lock) and the kernel read the links' valid flags as 0 — a
    6-axis recording replayed 0.004 % of side apart from its live estimates."""
    valid = np.ones(12, dtype=bool)
    args = fused._kernel_args("accel", (np.zeros((12, 3, 3)), valid))
    junk = [np.zeros(12, dtype=np.uint8) for _ in range(64)]
    assert [args[1][k] for k in range(12)] == [1] * 12
    assert len(junk) == 64
