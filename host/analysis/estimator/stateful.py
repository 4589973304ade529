"""`ShapeEstimator`: the estimator of a stream of snapshots, holding its warm start itself."""

from __future__ import annotations

import time

import numpy as np

from .checks import (Options, check_int, check_link_length, check_noise_pct_g, check_options,
                     check_readings, rest_yaws)
from .pipeline import WarmStart, paper_snapshot, solve_snapshot
from .priors import DEFAULT_PRIOR
from .result import ShapeEstimate
from .structure import lattice_of, structure_of

__all__ = ["ShapeEstimator"]


class ShapeEstimator:
    """Shapes of one sheet from a stream of snapshots, each warm-started from the last.

    ``ShapeEstimator(rows, cols, link_length, **options)`` takes `estimate`'s options
    (``method``, ``rest``, ``model``, ``prior``, ``noise_pct_g``, ``bad_readings``,
    ``paper_options``), checks them once, and `update` estimates a snapshot. Between updates it
    holds what the next one starts from: the last yaws and joints, the structure of the last
    mask (sparsity pattern, ordering, Laplacian) and the last factorisation of the Gauss-Newton
    matrix, which the next snapshot's chord steps reuse while it still contracts well. A
    snapshot with a different mask of valid links (or bad readings masked out) gets that
    mask's structure and a new factorisation; its yaws still start from the last ones.

    The results are those of ``estimate(readings, ..., previous=last)`` in a loop (the same
    arithmetic, the same numbers); `estimate` stays for one-off calls, and its ``previous=``
    for code written before this class.

    Examples
    --------
    >>> import numpy as np
    >>> from host.analysis.estimator import ShapeEstimator
    >>> flat = np.tile([0.0, 0.0, 9.80665], (2 * 3 * 2, 1))  # a level 3x3 sheet
    >>> est = ShapeEstimator(3, 3, 0.01)
    >>> [round(float(v), 3) for v in est.update(flat).joints[2, 2]]
    [0.02, 0.02, 0.0]
    >>> est.updates
    1
    """

    def __init__(self, rows: int, cols: int, link_length: float, *, method: str = "global",
                 rest=None, model: str = "cells", prior: str = DEFAULT_PRIOR,
                 noise_pct_g: float = 1.0, bad_readings: str = "raise", paper_options=None):
        opts = check_options(method, model, prior, noise_pct_g, bad_readings, paper_options)
        self.rows = check_int("rows", rows, 2)
        self.cols = check_int("cols", cols, 2)
        self.link_length = check_link_length(link_length)
        self.options: Options = opts._replace(noise_pct_g=check_noise_pct_g(noise_pct_g))
        n = lattice_of(self.rows, self.cols).n_links
        self._rest = rest
        self._rest_yaw = None if rest is None else rest_yaws(rest, n, self.rows, self.cols)
        #: the last estimate (None before the first update or after `reset`)
        self.last: ShapeEstimate | None = None
        #: snapshots estimated since construction or the last `reset`
        self.updates = 0
        #: the caller's clock at the last update (``now``), seconds, or None
        self.last_update: float | None = None
        self._warm = WarmStart()
        self._held = None  # (mask key, structure) of the last update

    @property
    def structure(self):
        """The structure of the last update's mask (`structure.Structure`), or None."""
        return None if self._held is None else self._held[1]

    @property
    def factorisation(self):
        """The factorisation the next update's chord steps start from, or None."""
        sol = self._warm.solution
        return None if sol is None else sol.factorisation

    def reset(self) -> None:
        """Forget the warm start: the next update starts cold, from the rest shape."""
        self._warm = WarmStart()
        self.last = None
        self.updates = 0

    def update(self, readings: np.ndarray, valid: np.ndarray | None = None,
               now: float | None = None) -> ShapeEstimate:
        """Estimate one snapshot, warm-started from the last (see the class docstring).

        Parameters
        ----------
        readings : ndarray, shape (n_links, 3)
            As `estimate` takes them.
        valid : ndarray of bool, shape (n_links,), optional
            The links present (default: all).
        now : float, optional
            The caller's clock, seconds, kept as `last_update` (the estimator reads no clock
            for its decisions; `ShapeEstimate.timings` are wall times).

        Raises
        ------
        ValueError
            As `estimate`, for the readings and the mask; the warm start is kept.
        """
        t0 = time.perf_counter()
        opts = self.options
        snap = check_readings(readings, self.rows, self.cols, valid, opts.bad_readings)
        if opts.method == "paper":
            if snap.mask is not None:
                raise ValueError("method='paper' does not support missing links (the paper has "
                                 "none); use method='global'.")
            est = paper_snapshot(snap, self.rows, self.cols, self.link_length, opts, t0)
        else:
            st = self._held_structure(snap.mask)
            est = solve_snapshot(snap, st, self.link_length, opts, self._warm, self._rest,
                                 self._rest_yaw, t0)
            self._warm = WarmStart.of(est)
        self.last = est
        self.updates += 1
        self.last_update = now
        return est

    def _held_structure(self, mask):
        """The structure of ``mask``: the one held when the mask is unchanged, else (a change
        of the links present) the lattice's structure for the new mask."""
        key = None if mask is None else mask.tobytes()
        if self._held is None or self._held[0] != key:
            self._held = (key, structure_of(self.rows, self.cols, mask, self.options.model))
        return self._held[1]
