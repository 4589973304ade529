"""What every capsheet process sets up for itself, whichever room starts it (a command, the
estimator's process): BLAS on one thread (`one_blas_thread`). ``host.cli.main`` calls it for every
command; a process the host starts calls it again, for the libraries it loads itself."""

from __future__ import annotations

import os
import sys

__all__ = ["BLAS_THREAD_VARS", "one_blas_thread"]

#: environment variables through which a user chooses the BLAS / OpenMP thread count themselves
BLAS_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def one_blas_thread() -> bool:
    """Run BLAS single-threaded unless the user chose a thread count (any of `BLAS_THREAD_VARS`).

    capsheet's matrices are small (a few hundred rows): a BLAS thread pool only adds hand-offs, and
    OpenBLAS's idle workers spin on the other cores, which the live path's I/O threads, the virtual
    sheet and ``capsheet estimate --jobs`` need (offline 14x14 estimation ran at ~400 snapshots per
    CPU-second with two OpenBLAS threads per worker, ~1,050 with one). Parallel work is done by
    processes. Libraries already loaded are limited through threadpoolctl; the environment variables
    are set for those loaded later (scipy's own OpenBLAS) and for child processes. Returns whether
    it limited anything."""
    if any(v in os.environ for v in BLAS_THREAD_VARS):
        return False
    for v in BLAS_THREAD_VARS:
        os.environ[v] = "1"
    if not {"numpy", "scipy"} & sys.modules.keys():
        return True  # no BLAS loaded yet (a command's start): the variables limit it when it loads
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - a declared dependency; the variables still apply
        return True
    threadpool_limits(limits=1, user_api="blas")
    return True
