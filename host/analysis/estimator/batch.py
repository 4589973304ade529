"""`estimate_batch`: a sequence of snapshots, many solved together (what an offline run wants)."""

from __future__ import annotations

import time

import numpy as np

from .angles import G0
from .checks import (READING_NORM_RANGE, check_int, check_noise_pct_g, check_options,
                     check_previous)
from .joints import joints_and_mask
import host.analysis.estimator.pipeline as pipeline  # CLOSE_PITCHES, read at call time
from .pipeline import (WarmStart, closed_pitches, estimate, link_angles, link_solvability,
                       noise_and_priors)
from .priors import DEFAULT_PRIOR
from .result import ShapeEstimate, Solution
from .solver import solve_global_batch
from .structure import lattice_of, structure_of

__all__ = ["estimate_batch", "GROUPED"]

#: The priors whose weights `estimate_batch` computes for a whole group at once (the others'
#: snapshots go to `estimate` one at a time).
GROUPED = ("level", "adaptive", "off")

def estimate_batch(readings: np.ndarray, rows: int, cols: int, link_length: float,
                   valid: np.ndarray | None = None, previous: ShapeEstimate | None = None, *,
                   noise_pct_g: float = 1.0, bad_readings: str = "raise",
                   batch: int = 32, prior: str = DEFAULT_PRIOR) -> list[ShapeEstimate]:
    """Estimate a sequence of snapshots, many at a time: what an offline run wants.

    The result is what ``estimate(readings[k], ..., previous=result[k - 1])`` in a loop gives
    (``method="global"``, ``model="cells"``, the same ``prior``), to the solver's tolerance:
    the same cost is minimised with the same stopping rule, but ``batch`` consecutive snapshots
    are solved together — every snapshot of a group starts from the estimate before the group
    (without ``previous``, the first snapshot is estimated alone and the rest start there),
    their chord steps share one factorisation and their arithmetic runs as one numpy pass (one
    multi-right-hand-side solve per step, one joint solve per group), so the per-call overhead
    that dominates a 14x14 snapshot is paid once per group. A snapshot the group cannot finish
    (its mask differs from the group's, its readings need checking, its step fails to descend or
    it needs more than `BATCH_MAX_ITER` steps) is estimated by `estimate` on its own, in order.

    Parameters
    ----------
    readings : ndarray, shape (S, n_links, 3)
        Specific force per snapshot, m/s², as `estimate` takes one.
    valid : ndarray of bool, shape (S, n_links) or (n_links,), optional
        Per snapshot (or for all) the links present. Default: all.
    previous : ShapeEstimate, optional
        The estimate before the first snapshot (warm start), as in `estimate`.
    noise_pct_g, bad_readings, prior
        As in `estimate` (default prior `DEFAULT_PRIOR`). The priors "fixed" and "local" are
        estimated one snapshot at a time (by `estimate`), the others in groups.
    batch : int
        Snapshots solved together (>= 1).

    Returns
    -------
    list of ShapeEstimate, one per snapshot. ``iterations`` counts the snapshot's own steps,
    ``factorisations`` is 1 on the snapshot whose group paid a factorisation, and ``timings``
    holds its share of the group's time (``"batched"``: 1.0 when it was solved in a group).

    Raises
    ------
    ValueError
        As `estimate`, prefixed with the snapshot's index; wrong shapes or dtypes of the inputs.
    """
    rows = check_int("rows", rows, 2)
    cols = check_int("cols", cols, 2)
    batch = check_int("batch", batch, 1)
    check_options(prior=prior, bad_readings=bad_readings)
    # the group's estimates carry it without `estimate` seeing it: checked here, once
    noise_pct_g = check_noise_pct_g(noise_pct_g)
    lat = lattice_of(rows, cols)
    n = lat.n_links
    R = np.asarray(readings)
    if R.dtype.kind not in "iuf":
        raise ValueError(f"Invalid readings: dtype {R.dtype} (need real numbers, m/s²)")
    if R.ndim != 3 or R.shape[1:] != (n, 3):
        raise ValueError(f"Expected `readings` to have shape (S, {n}, 3) for a {rows}x{cols} "
                         f"lattice, got {R.shape}.")
    S = R.shape[0]
    if valid is None:
        V = np.ones((S, n), bool)
    else:
        V = np.asarray(valid)
        if V.dtype != bool:
            raise ValueError(f"Invalid valid: dtype {V.dtype} (need a boolean mask, True = "
                             "link present)")
        if V.shape == (n,):
            V = np.broadcast_to(V, (S, n))
        if V.shape != (S, n):
            raise ValueError(f"Expected `valid` to have shape ({S}, {n}) or ({n},), got "
                             f"{V.shape}.")
    kw = dict(noise_pct_g=noise_pct_g, bad_readings=bad_readings, prior=prior)
    # the checks `estimate` makes (it raises what is wrong; its messages name the links)
    if previous is not None:
        check_previous(previous, n, rows, cols)
    L = float(link_length) if isinstance(link_length, (int, float, np.number)) \
        and not isinstance(link_length, (bool, np.bool_)) else link_length
    if S == 0:
        return []
    out: list[ShapeEstimate | None] = [None] * S

    def _one(k, r_k, v_k, before):
        try:
            return estimate(r_k, rows, cols, link_length, valid=v_k, previous=before, **kw)
        except ValueError as exc:
            raise ValueError(f"snapshot {k}: {exc}") from exc

    prev = previous
    lo, hi = READING_NORM_RANGE
    for s0 in range(0, S, batch):
        t0 = time.perf_counter()
        r = R[s0:s0 + batch].astype(float, copy=False)
        v = V[s0:s0 + batch]
        m = r.shape[0]
        norm = np.sqrt(np.einsum("bij,bij->bi", r, r)) / G0
        clean = np.all(np.isfinite(r), axis=2) & (norm >= lo) & (norm <= hi)
        mask0 = v[0]
        fast = np.all(v == mask0, axis=1) & np.all(clean | ~mask0, axis=1) & mask0.any()
        if not (isinstance(L, float) and np.isfinite(L) and L > 0) or prior not in GROUPED:
            fast[:] = False  # `estimate` says what is wrong with it
        if prev is None and fast[0]:  # a cold start is one snapshot's job; the rest start there
            out[s0] = prev = _one(s0, r[0], v[0], None)
            fast[0] = False
        idx = np.flatnonzero(fast)
        if idx.size:
            mask = None if mask0.all() else mask0
            st = structure_of(rows, cols, mask, "cells")
            # the stages `estimate` runs (host.analysis.estimator.pipeline), on the group at once
            rr, alpha, beta, _ = link_angles(r[idx], mask0, mask)
            if pipeline.CLOSE_PITCHES:
                beta, _ = closed_pitches(st, alpha, beta)
            _, prior_w, bend_w, tol = noise_and_priors(prior, st, rr, norm[idx], mask0, False)
            target = st.rest_yaw
            chain = WarmStart.of(prev)
            warm = chain.covering(mask0)
            start, lu = warm.start(st, target)
            gamma, iters, failed, n_fact, lu, prob_of = solve_global_batch(
                st, alpha, beta, start, target, prior_w, bend_w, lu, tol)
            ok = ~failed
            rows_ok = np.flatnonzero(ok)
            t1 = time.perf_counter()
            if rows_ok.size:
                P, d, nrm, g_out, a_out, b_out, residual = joints_and_mask(
                    st, L, alpha[ok], beta[ok], gamma[ok], target, warm.joint_prior(st, L))
                solv = link_solvability(a_out, b_out, None, rows, cols)
            dt = (time.perf_counter() - t0) / max(idx.size, 1)
            kept = None  # the chain's fallback (`WarmStart.next_fallback`) when not each one's own
            for j, kk in enumerate(idx[ok]):
                sol_j = Solution(st, lu, prob_of(int(rows_ok[j])), g_out[j])
                own = WarmStart(g_out[j], P[j].reshape(rows, cols, 3), sol_j, mask0)
                if j == 0:  # the rest have the first one's links: each its own, or the same kept one
                    first = chain.next_fallback(mask0, own)
                    kept = None if first is own else first
                fallback = own if kept is None else kept
                out[s0 + kk] = ShapeEstimate(
                    joints=P[j].reshape(rows, cols, 3), directions=d[j], residual=float(residual[j]),
                    solvability=solv[j], normals=nrm[j], yaws=g_out[j], alpha=a_out[j],
                    beta=b_out[j], valid=mask0.copy(), link_length=L, method="global",
                    iterations=int(iters[rows_ok[j]]), factorisations=n_fact if j == 0 else 0,
                    timings={"angles": 0.0, "yaw": (t1 - t0) / max(idx.size, 1),
                             "joints": 0.0, "total": dt, "batched": 1.0},
                    noise_pct_g=float(noise_pct_g),
                    solution=sol_j, warm_fallback=fallback)
            fast[idx[failed]] = False
        # the rest, one at a time and in order (what `estimate` says about them is the answer)
        for kk in range(m):
            if out[s0 + kk] is not None:
                continue
            before = next((out[q] for q in range(s0 + kk - 1, -1, -1) if out[q] is not None),
                          previous)
            out[s0 + kk] = _one(s0 + kk, r[kk], v[kk], before)
        prev = out[s0 + m - 1]
    return out  # type: ignore[return-value]
