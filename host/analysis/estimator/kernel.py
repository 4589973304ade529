"""The estimator's compiled kernel (host/analysis/_kernel/, cffi, built at install): its ``ffi`` and
``lib``, or None when it is not built, and the switch every stage reads at call time.

Set ``host.analysis.estimator.kernel.USE_KERNEL = False`` to run the numpy code instead (same
numbers to rounding; tests/host/analysis/test_estimator_kernel.py compares them).
"""

from __future__ import annotations

import os

try:  # the compiled cost-and-gradient kernel (host/analysis/_kernel/); optional
    if os.environ.get("CAPSHEET_NO_KERNEL"):
        raise ImportError("CAPSHEET_NO_KERNEL is set")
    from .._yaw_kernel import ffi, lib
except ImportError:  # not built (no C compiler at install): the numpy code, same numbers
    ffi = lib = None

#: Evaluate a single snapshot's yaw cost and gradient (model "cells", the chord steps) with the
#: compiled kernel when it is built; False: the numpy code (same numbers to ~1e-15 relative;
#: tests/host/analysis/test_estimator_kernel.py). `estimate_batch` always uses numpy.
USE_KERNEL = lib is not None

__all__ = ["USE_KERNEL", "ffi", "lib"]
