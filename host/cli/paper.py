"""``capsheet paper``: the paper's own experiments (Fig. 8, 9, 10), as the authors ran them.

* ``capsheet paper solvability`` — Fig. 8: one unit's (θc, θf, θr, θp) grid, 20 values each,
  where eq. (7) has ``λ3/λ1 < 0.1`` (the paper's criterion), and where capsheet's estimator
  (its Gauss-Newton normal matrix) finds a yaw standard deviation over `YAW_STD_RELATIVE_LIMIT`
  times a typical unit's; the flagged states split into the paper's cases, with a table.
* ``capsheet paper gaussian`` — Fig. 9: the 13x13-unit (14x14-joint) spring-mass sheet laid over
  a Gaussian (`TARGETS`), the model and both methods' estimates.
* ``capsheet paper noise`` — Fig. 10: mean and standard deviation of the joint error (% of the
  side after a least-squares overlay, 196 joints x ``--trials``) against noise 0-10 % g, the
  paper's method (`host.analysis.paper_method`) and capsheet's global estimator on the same
  draws, with the paper's 5 % failure line, for the Fig. 9 target and a second one.

The setup (paper section 3): the sheet is `virtual_sheet.drape.drape`'s spring-mass model, laid
flat over the target and relaxed until every link is L (to 1e-10); the sensor outputs follow
from the draped model (`virtual_sheet.geometry.ideal_readings`, sensor z the sheet's normal);
noise is added to each component, the level a percentage of g (``normal``: the level is the
standard deviation; ``uniform``: the half-width), drawn from MT19937 streams seeded by
``(seed, level)`` so every method and every run of a level sees the same draws; the error is the
distance of each joint after the least-squares rigid overlay, in % of the side ``13 L``.

Each writes a PNG, a markdown table and a JSON file under ``--out`` (default ``out/paper``) and
prints the table; progress goes to stderr (a bar on a terminal, a line every 10 s in a pipe or a
log, nothing with ``-q``).

The unit of Fig. 8 is built as follows (the paper's Fig. 7 is not in its text, so this is our
reading of it): joint A at the origin, link 3 (A->D) along +x, link 0 (A->B) at the corner angle
θc from it in the xy plane, C = B + D − A; the triangle A-C-D is folded about the diagonal AC by
θf (θf = π folds it onto A-B-C); the unit is then rolled by θr about x and pitched by θp about y.
Every link's sensor z is its triangle's normal (the unit's plane normal, carried by the fold);
θc, θf, θr in [0, π] and θp in [0, π/2], 20 evenly spaced values each (ends included).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from protocol.constants import G0


class _LazyEstimator:
    """``E.name`` -> ``host.analysis.estimator.name``, imported on first use: building the CLI's
    parser must not import scipy (it cost every ``capsheet`` command ~0.8 s)."""

    def __getattr__(self, name):
        from host.analysis import estimator
        return getattr(estimator, name)


E = _LazyEstimator()

__all__ = ["register", "unit_angles", "unit_state", "yaw_std_gain", "solvability_grid",
           "noise_study", "build_target", "TARGETS", "Target", "noise_draws", "paper_options"]

SIDE_JOINTS = 14  #: the paper's 13x13-unit sheet
LINK_LENGTH = 0.01  #: metres (the error is relative to the side, so L does not matter)
SIDE_M = (SIDE_JOINTS - 1) * LINK_LENGTH
NOISE_LEVELS = (0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0)  #: % g, as Fig. 10
QUICK_NOISE_LEVELS = (0.0, 1.0, 5.0)
#: "the estimation seems to fail discernibly when the estimation error goes beyond 5 % of the
#: side length" (section 3.3)
FAILURE_LINE_PCT = 5.0
NOISE_DISTS = ("normal", "uniform")
#: the methods compared, as `host.analysis.estimator.estimate` keyword arguments
METHODS = {"global": {}, "paper": {"method": "paper"}}
#: How the tables name the methods: "global" is capsheet's estimator with its defaults
LABELS = {"global": "capsheet default", "paper": "paper's method"}
#: `capsheet paper noise`'s targets unless ``--target`` is given: the paper's Fig. 9 drape, the
#: same sheet tilted (no level unit) and the compass-built net of the same Gaussian
NOISE_TARGETS = ("fig9", "fig9-tilted", "fig9-compass")
#: Fig. 9's Gaussian, ``A exp(−r²/2σ²)``: A = σ = S/4 (docs/estimator.md section 7 says why)
FIG9_AMPLITUDE_M = FIG9_SIGMA_M = SIDE_M / 4
#: the second target: Fig. 9's model on a plane tilted by this much, more than the bump's steepest
#: slope (31°), so that no unit is level anywhere
TILT_RAD = 0.8
PAPER_FIG9_TEXT = ("Paper, Fig. 9: \"Simulation result. The far and near plots are the model and "
                   "estimated shapes, respectively.\" Section 3.2: \"an example of general "
                   "situations using a Gaussian as a target shape\".")


# ---------------------------------------------------------------------------------------------
# Fig. 8: one unit's solvability over (θc, θf, θr, θp)
# ---------------------------------------------------------------------------------------------

def _rotate(v: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues: rotate vectors ``v`` (..., 3) about unit ``axis`` (..., 3) by ``angle`` (...)."""
    c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
    return v * c + np.cross(axis, v) * s + axis * np.sum(axis * v, -1, keepdims=True) * (1 - c)


def unit_angles(tc, tf, tr, tp) -> tuple[np.ndarray, np.ndarray]:
    """Roll and pitch of the four links of a unit in state (θc, θf, θr, θp): `unit_state`'s
    first two."""
    alpha, beta, _ = unit_state(tc, tf, tr, tp)
    return alpha, beta


def unit_state(tc, tf, tr, tp) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Roll and pitch of the four links of a unit in state (θc, θf, θr, θp) (module docstring).

    Parameters
    ----------
    tc, tf, tr, tp : array_like, broadcastable
        Corner, fold, roll, pitch, radians.

    Returns
    -------
    alpha, beta, gamma : ndarray, shape (..., 4)
        Roll, pitch and yaw per link in the paper's numbering (`Lattice.units`), radians.
    """
    tc, tf, tr, tp = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (tc, tf, tr, tp)))
    sh = tc.shape
    zero = np.zeros(sh)
    A = np.zeros(sh + (3,))
    D = np.broadcast_to([1.0, 0.0, 0.0], sh + (3,))
    B = np.stack([np.cos(tc), np.sin(tc), zero], -1)
    C = B + D
    nz = np.broadcast_to([0.0, 0.0, 1.0], sh + (3,))
    axis = C - A
    na = np.linalg.norm(axis, axis=-1, keepdims=True)
    axis = np.where(na > 1e-9, axis / np.where(na > 1e-9, na, 1.0), [0.0, 1.0, 0.0])
    Df = _rotate(D, axis, tf)
    nf = _rotate(nz, axis, tf)
    links = [(B - A, nz), (C - B, nz), (C - Df, nf), (Df - A, nf)]  # paper numbering 0..3
    ex = np.broadcast_to([1.0, 0.0, 0.0], sh + (3,))
    ey = np.broadcast_to([0.0, 1.0, 0.0], sh + (3,))
    alpha, beta, gamma = [], [], []
    for v, n in links:
        x = _rotate(_rotate(v, ex, tr), ey, tp)
        z = _rotate(_rotate(n, ex, tr), ey, tp)
        x = x / np.linalg.norm(x, axis=-1, keepdims=True)
        z = z - np.sum(z * x, -1, keepdims=True) * x
        z = z / np.linalg.norm(z, axis=-1, keepdims=True)
        y = np.cross(z, x)
        reading = G0 * np.stack([x[..., 2], y[..., 2], z[..., 2]], -1)  # Rᵀ (0, 0, G0)
        a, b = E.roll_pitch(reading.reshape(-1, 3))
        alpha.append(a.reshape(sh))
        beta.append(b.reshape(sh))
        gamma.append(np.arctan2(x[..., 1], x[..., 0]))
    return np.stack(alpha, -1), np.stack(beta, -1), np.stack(gamma, -1)


#: The yaw criterion's threshold: a unit is poorly determined where its largest yaw standard
#: deviation (per unit residual noise, `yaw_std_gain`) exceeds this many times the grid's median
#: unit's — as λ3/λ1 < 0.1 flags a unit ten times worse conditioned than its best direction.
#: (An absolute 10, used before, sat inside the spread of well-determined units: their gains run
#: 2-30, median 6.1, the rank-deficient ones' 600-1000.)
YAW_STD_RELATIVE_LIMIT = 10.0


def _unit_residuals(alpha, beta, gamma, has_normal=None):
    """The estimator's residuals for one unit (``model="cells"``), shape (..., 6): loop closure
    (eq. 4, xy, real and imaginary) and every link's roll term ``w y_k · n`` with the cell's
    normal ``n = A × C / |A × C|`` — dropped (0) for a squashed cell, as the estimator drops it.
    ``has_normal`` (..., 1): which cells have a normal; default: ``|A × C| > 1e-6`` here (pass
    the unperturbed state's when differentiating, or a squashed cell's numerical normal of a
    perturbed state would count)."""
    ca, sa, cb, sb = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)
    cg, sg = np.cos(gamma), np.sin(gamma)
    d = np.stack([cb * cg, cb * sg, -sb], -1)
    y = np.stack([cg * sb * sa - sg * ca, sg * sb * sa + cg * ca, cb * sa], -1)
    loop = d[..., 0, :] + d[..., 1, :] - d[..., 2, :] - d[..., 3, :]
    m = np.cross(d[..., 1, :] + d[..., 3, :], d[..., 0, :] + d[..., 2, :])
    mm = np.linalg.norm(m, axis=-1, keepdims=True)
    if has_normal is None:
        has_normal = mm > 1e-6
    n = np.where(has_normal, m / np.where(mm > 0, mm, 1.0), 0.0)
    roll = E.ROLL_WEIGHT * np.sum(y * n[..., None, :], -1)
    return np.concatenate([loop[..., :2], roll], -1)


def _has_normal(beta, gamma) -> np.ndarray:
    cb, sb = np.cos(beta), np.sin(beta)
    d = np.stack([cb * np.cos(gamma), cb * np.sin(gamma), -sb], -1)
    m = np.cross(d[..., 1, :] + d[..., 3, :], d[..., 0, :] + d[..., 2, :])
    return np.linalg.norm(m, axis=-1, keepdims=True) > 1e-6


def yaw_std_gain(alpha, beta, gamma, eps: float = 1e-6) -> np.ndarray:
    """Per unit, the largest yaw standard deviation per unit residual noise, from the
    estimator's Gauss-Newton normal matrix ``JᵀJ + ε I`` (yaw 0 as gauge; J by central
    differences over yaws 1-3, a squashed cell's normal dropped as at the unperturbed state):
    ``sqrt(max diag((JᵀJ + ε)⁻¹))``. Rank-deficient units (Case 1, squashed) reach
    ``1/sqrt(ε)`` = 1000."""
    h = 1e-6
    has = _has_normal(beta, gamma)
    cols = []
    for k in (1, 2, 3):
        dg = np.zeros(gamma.shape)
        dg[..., k] = h
        cols.append((_unit_residuals(alpha, beta, gamma + dg, has)
                     - _unit_residuals(alpha, beta, gamma - dg, has)) / (2 * h))
    J = np.nan_to_num(np.stack(cols, -1), nan=0.0, posinf=0.0, neginf=0.0)  # (..., 6, 3)
    w, v = np.linalg.eigh(np.einsum("...ri,...rj->...ij", J, J))
    diag = np.sum(v * v / (np.maximum(w, 0.0) + eps)[..., None, :], -1)
    return np.sqrt(np.max(diag, -1))


#: The partition of the grid into the paper's cases, in precedence order (a state is counted in
#: the first group it belongs to), with the labels of the table and the figure's legend.
CASE_GROUPS = (
    ("case2", "Case 2: squashed (θc = 0 or π) or fully folded (θf = π)"),
    ("case1", "Case 1: horizontal (θf, θr ∈ {0, π}, θp = 0), not Case 2"),
    ("near_case2", "one grid step from Case 2"),
    ("near_case1", "one grid step from Case 1"),
    ("vertical", "links vertical (θp = π/2)"),
    ("other", "elsewhere"),
)


def _cases(pts: np.ndarray, steps: int) -> dict:
    """Masks of grid points ``(θc, θf, θr, θp)`` (N, 4): the `CASE_GROUPS` partition (each point
    in exactly one group) and, apart, ``case1_all``: every horizontal state (some are Case 2
    too)."""
    tol = 1e-9
    step = np.pi / (steps - 1)  # θc, θf, θr; θp's step is half of it
    on = lambda v, t: np.abs(v - t) < tol  # noqa: E731
    near = lambda v, t, s=step: np.abs(v - t) <= s + tol  # noqa: E731
    tc, tf, tr, tp = pts[:, 0], pts[:, 1], pts[:, 2], pts[:, 3]
    case1 = (on(tf, 0) | on(tf, np.pi)) & (on(tr, 0) | on(tr, np.pi)) & on(tp, 0)
    case2 = on(tc, 0) | on(tc, np.pi) | on(tf, np.pi)
    near2 = near(tc, 0) | near(tc, np.pi) | near(tf, np.pi)
    near1 = ((near(tf, 0) | near(tf, np.pi)) & (near(tr, 0) | near(tr, np.pi))
             & near(tp, 0, step / 2))
    vertical = on(tp, np.pi / 2)
    out, taken = {}, np.zeros(len(pts), bool)
    for key, mask in (("case2", case2), ("case1", case1), ("near_case2", near2),
                      ("near_case1", near1), ("vertical", vertical),
                      ("other", np.ones(len(pts), bool))):
        out[key] = mask & ~taken
        taken |= mask
    out["case1_all"] = case1
    return out


def _counts(pts: np.ndarray, steps: int) -> dict:
    c = _cases(pts, steps)
    return {"flagged": int(len(pts)), **{k: int(c[k].sum()) for k, _ in CASE_GROUPS},
            "case1_all": int(c["case1_all"].sum())}


def _grid(steps: int) -> np.ndarray:
    g = np.linspace(0.0, np.pi, steps)
    gp = np.linspace(0.0, np.pi / 2, steps)
    return np.stack(np.meshgrid(g, g, g, gp, indexing="ij"), -1)


def solvability_grid(steps: int = 20) -> dict:
    """Both criteria over the (θc, θf, θr, θp) grid: λ3/λ1 of eq. (7) (< 0.1: unsolvable in the
    paper's sense) and the estimator's yaw standard deviation gain (`yaw_std_gain` >
    `YAW_STD_RELATIVE_LIMIT` x its median over the grid), with the points each flags and how
    they split over `CASE_GROUPS`."""
    grid = _grid(steps)
    a, b, c = unit_state(*np.moveaxis(grid, -1, 0))
    ratio = E.solvability_units(a, b)
    gain = yaw_std_gain(a, b, c)
    median = float(np.median(gain))
    limit = YAW_STD_RELATIVE_LIMIT * median
    bad, bad_yaw = ratio < 0.1, gain > limit
    pts, pts_yaw = grid[bad], grid[bad_yaw]
    return {"steps": steps, "points": pts, "points_yaw": pts_yaw, "ratio": ratio, "gain": gain,
            "n_total": int(ratio.size), "eq7": _counts(pts, steps),
            "yaw_std": _counts(pts_yaw, steps), "yaw_gain_median": median,
            "yaw_gain_limit": limit, "both": int((bad & bad_yaw).sum()),
            "yaw_only": int((bad_yaw & ~bad).sum()), "eq7_only": int((bad & ~bad_yaw).sum())}


def _where(pts: np.ndarray, steps: int, key: str) -> str:
    """Where a criterion's states of one group lie: the share with θf ≥ 3π/4, and with θc
    within two grid steps of 0 or π (nearly squashed)."""
    sel = pts[_cases(pts, steps)[key]]
    if not len(sel):
        return "–"
    two = 2 * np.pi / (steps - 1) + 1e-9
    folded = np.mean(sel[:, 1] >= 0.75 * np.pi - 1e-9)
    squashed = np.mean((sel[:, 0] <= two) | (sel[:, 0] >= np.pi - two))
    return f"{100 * folded:.0f} % θf ≥ 3π/4, {100 * squashed:.0f} % θc within 2 steps of 0 or π"


def cmd_solvability(args) -> int:
    out = _outdir(args)
    steps = 8 if args.quick and args.steps is None else (args.steps or 20)
    t0 = time.perf_counter()
    res = solvability_grid(steps)
    dt = time.perf_counter() - t0
    e7, y = res["eq7"], res["yaw_std"]
    md = ["# Fig. 8 — unsolvable unit states, two criteria", "",
          f"Grid: θc, θf, θr ∈ [0, π], θp ∈ [0, π/2], {steps} values each, {res['n_total']:,} "
          f"states ({dt:.1f} s). The paper: all unsolvable states roughly in Case 1 or Case 2. "
          "Left: λ3/λ1 < 0.1 of eq. (7), the paper's criterion. Right: capsheet's estimator, "
          "the largest yaw standard deviation of the unit from its Gauss-Newton normal matrix "
          f"(cells model), per unit residual noise, > {YAW_STD_RELATIVE_LIMIT:g} × the grid's "
          f"median ({res['yaw_gain_median']:.2f}), i.e. > {res['yaw_gain_limit']:.1f}. Each "
          "state counted once, in the first group it belongs to:", "",
          "| group | λ3/λ1 < 0.1 | yaw std > limit |", "|---|---:|---:|"]
    md += [f"| {label} | {e7[k]:,} | {y[k]:,} |" for k, label in CASE_GROUPS]
    md += [f"| **flagged** | **{e7['flagged']:,}** | **{y['flagged']:,}** |", "",
           f"Case 1 holds {e7['case1_all']} horizontal states of the grid in all; those with θc "
           "∈ {0, π} or θf = π are counted under Case 2. Both criteria flag "
           f"{res['both']:,} states; only λ3/λ1: {res['eq7_only']:,}; only the yaw std: "
           f"{res['yaw_only']:,}.",
           f"Elsewhere (λ3/λ1): {_where(res['points'], steps, 'other')}; "
           f"(yaw std): {_where(res['points_yaw'], steps, 'other')}."]
    _emit(out / "solvability", "\n".join(md),
          {k: v for k, v in res.items() if k not in ("points", "points_yaw", "ratio", "gain")})
    from host.cli.figures import solvability_figure
    fig = solvability_figure(out / "solvability.png", res, CASE_GROUPS, _cases)
    import matplotlib.pyplot as plt
    plt.close(fig)
    print(f"wrote {out / 'solvability.png'}")
    return 0


# ---------------------------------------------------------------------------------------------
# Fig. 9 and 10: the paper's setup
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Target:
    """A model sheet and its noise-free sensor outputs.

    Attributes
    ----------
    name, description : str
    joints : ndarray, shape (14, 14, 3)
        Metres, world frame.
    readings : ndarray, shape (364, 3)
        Noise-free specific force, m/s², sensor frame.
    """

    name: str
    description: str
    joints: np.ndarray
    readings: np.ndarray


def _fig9_surface():
    from virtual_sheet.drape import HeightField
    a, s = FIG9_AMPLITUDE_M, FIG9_SIGMA_M
    return HeightField(lambda x, y: a * np.exp(-(x * x + y * y) / (2 * s * s)))


def _fig9_drape() -> np.ndarray:
    from virtual_sheet.drape import drape
    P, info = drape(_fig9_surface(), SIDE_JOINTS, SIDE_JOINTS, LINK_LENGTH, init="flat")
    if not info.converged:  # pragma: no cover - a fixed, tested construction
        raise RuntimeError(f"the Fig. 9 drape did not converge: {info}")
    return P


def _tilt(P: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return P @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]).T


_GAUSS = (f"Gaussian z = A exp(−r²/2σ²), A = σ = S/4 = {100 * FIG9_AMPLITUDE_M:.2f} cm "
          f"(S = 13 L = {100 * SIDE_M:g} cm)")
#: name -> description of the built-in targets (`build_target`); any `virtual_sheet.shapes`
#: name is a target too (its exact Chebyshev net by the compass construction).
TARGETS = {
    "fig9": f"{_GAUSS}; the 14x14 spring-mass sheet laid flat over it and relaxed "
            "(virtual_sheet.drape, init='flat'); sensor z: the sheet's normal",
    "fig9-tilted": f"the fig9 model on a plane tilted by {TILT_RAD:g} rad about x: the same "
                   "sheet, steeper than the bump anywhere: no unit is level (no Case 1)",
    "fig9-compass": f"{_GAUSS}; an exact Chebyshev net laid from the centre by the compass "
                    "construction (virtual_sheet.shapes 'gaussian') instead of the drape",
    "fig9-surface": "the fig9 drape, sensor z the Gaussian's surface normal under each link "
                    "(virtual_sheet.drape.surface_readings) instead of the sheet's",
}


@lru_cache(maxsize=None)
def build_target(name: str) -> Target:
    """The model sheet ``name`` (`TARGETS`, or a `virtual_sheet.shapes` name) and its readings."""
    from virtual_sheet.geometry import ideal_readings

    if name in ("fig9", "fig9-tilted", "fig9-surface"):
        P = _fig9_drape()
        if name == "fig9-tilted":
            P = _tilt(P, TILT_RAD)
        if name == "fig9-surface":
            from virtual_sheet.drape import surface_readings
            r = surface_readings(P, _fig9_surface())
        else:
            r = ideal_readings(P)
        return Target(name, TARGETS[name], P, r)
    from virtual_sheet.shapes import SHAPES, make_sheet
    shape = "gaussian" if name == "fig9-compass" else name
    if shape not in SHAPES or shape == "heightmap":
        raise ValueError(f"unknown target {name!r} (expected one of "
                         f"{', '.join(list(TARGETS) + [s for s in SHAPES if s != 'heightmap'])})")
    P = make_sheet(shape, SIDE_JOINTS, SIDE_JOINTS, LINK_LENGTH)
    desc = TARGETS.get(name, f"virtual_sheet shape {shape!r}: exact Chebyshev net (compass)")
    return Target(name, desc, P, ideal_readings(P))


def noise_draws(r0: np.ndarray, level: float, trials: int, seed: int,
                dist: str = "normal") -> list[np.ndarray]:
    """``trials`` noisy copies of the readings ``r0``: each component plus noise of ``level`` %
    g (``normal``: standard deviation; ``uniform``: half-width), from one MT19937 stream seeded
    by ``(seed, level)`` (the same draws for every method and every run of this level)."""
    if dist not in NOISE_DISTS:
        raise ValueError(f"Invalid noise distribution {dist!r} (expected one of {NOISE_DISTS})")
    rng = np.random.Generator(np.random.MT19937(np.random.SeedSequence(
        [int(seed), int(round(1000 * level))])))
    a = level / 100.0 * G0
    if dist == "normal":
        return [r0 + rng.normal(0.0, a, r0.shape) for _ in range(trials)]
    return [r0 + rng.uniform(-a, a, r0.shape) for _ in range(trials)]


def unit_solvability(target: Target) -> np.ndarray:
    """λ3/λ1 of eq. (7) of every unit of the noise-free target, shape (13, 13)."""
    a, b = E.roll_pitch(target.readings)
    return E.solvability(a, b, SIDE_JOINTS, SIDE_JOINTS)


def _stats(e: np.ndarray, times: list) -> dict:
    p05, p50, p95 = np.percentile(e, [5, 50, 95])
    return {"mean_pct": float(e.mean()), "std_pct": float(e.std()), "p05_pct": float(p05),
            "p50_pct": float(p50), "p95_pct": float(p95), "max_pct": float(e.max()),
            "time_ms": 1e3 * float(np.median(times)),
            "over_failure_line": bool(e.mean() > FAILURE_LINE_PCT)}


def noise_study(target: Target, levels, trials: int, seed: int, *, methods: dict | None = None,
                noise_dist: str = "normal", progress=None, on_level=None) -> list:
    """Fig. 10 data for one target: per noise level and method, the joint-error statistics over
    196 joints x ``trials`` (% of side: mean, std as the paper; percentiles, max) and the
    median time per snapshot.

    ``methods``: name -> `estimate` keyword arguments (default `METHODS`); every method sees the
    same draws (`noise_draws`). ``progress``: a `host.cli.progress.Progress` (one update per
    trial); ``on_level(row)`` is called after each level. Returns a list of dicts, one per level.
    """
    methods = METHODS if methods is None else methods
    n, rows = SIDE_JOINTS, []
    for level in levels:
        errs = {m: [] for m in methods}
        times = {m: [] for m in methods}
        for r in noise_draws(target.readings, level, trials, seed, noise_dist):
            for m, kw in methods.items():
                t0 = time.perf_counter()
                est = E.estimate(r, n, n, LINK_LENGTH, **kw)
                times[m].append(time.perf_counter() - t0)
                errs[m].append(E.error_percent_of_side(est.joints, target.joints,
                                                       LINK_LENGTH).ravel())
            if progress is not None:
                progress.update(1)
        row = {"noise_pct_g": float(level), "samples": n * n * trials,
               **{m: _stats(np.concatenate(errs[m]), times[m]) for m in methods}}
        rows.append(row)
        if on_level is not None:
            on_level(row)
    return rows


def works_up_to(rows: list, method: str) -> float | None:
    """The highest noise level (% g) up to which the method's mean error stays at or under the
    paper's failure line at every level (None: over it already at the first level)."""
    best = None
    for r in rows:
        if r[method]["over_failure_line"]:
            break
        best = r["noise_pct_g"]
    return best


def paper_options(items: list[str] | None):
    """``KEY=VALUE`` strings -> `host.analysis.paper_method.PaperOptions` (None if none given)."""
    if not items:
        return None
    from host.analysis.paper_method import PaperOptions

    fields = {f.name: f for f in dataclasses.fields(PaperOptions)}
    kw = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or key not in fields:
            raise ValueError(f"invalid --paper-option {item!r} (expected KEY=VALUE, KEY one of "
                             f"{', '.join(fields)})")
        kind = type(getattr(PaperOptions(), key))
        try:
            kw[key] = kind(value)
        except ValueError:
            what = {int: "an integer", float: "a number"}.get(kind, "a word")
            raise ValueError(f"invalid --paper-option {item!r} ({key} is {what})") from None
    return PaperOptions(**kw)


def _methods(args) -> dict:
    opts = paper_options(args.paper_option)
    if opts is None:
        return METHODS
    return {"global": {}, "paper": {"method": "paper", "paper_options": opts}}


def cmd_gaussian(args) -> int:
    out = _outdir(args)
    target = build_target(args.target)
    methods = _methods(args)
    r = noise_draws(target.readings, args.noise, 1, args.seed, args.noise_dist)[0]
    n = SIDE_JOINTS
    res, ests = {}, {}
    for m, kw in methods.items():
        t0 = time.perf_counter()
        est = E.estimate(r, n, n, LINK_LENGTH, **kw)
        dt = time.perf_counter() - t0
        err = E.error_percent_of_side(est.joints, target.joints, LINK_LENGTH)
        ests[m] = est
        res[m] = {"mean_pct": float(err.mean()), "std_pct": float(err.std()),
                  "max_pct": float(err.max()), "time_s": dt, "residual": est.residual}
    sv = unit_solvability(target)
    md = [f"# Fig. 9 — target {target.name}, {n}x{n} joints, noise {args.noise:g} % g "
          f"({args.noise_dist}), seed {args.seed}", "", f"Target: {target.description}.",
          f"Paper's method: {_options_text(methods)}.",
          f"Units with λ3/λ1 < 0.1 (noise-free): {int((sv < 0.1).sum())} of {sv.size}.", "",
          "| method | mean error % side | std | max | time per snapshot [ms] |",
          "|---|---:|---:|---:|---:|"]
    md += [f"| {m} | {v['mean_pct']:.3f} | {v['std_pct']:.3f} | {v['max_pct']:.3f} | "
           f"{1e3 * v['time_s']:.1f} |" for m, v in res.items()]
    _emit(out / "gaussian", "\n".join(md),
          {"target": target.name, "description": target.description, "noise_pct_g": args.noise,
           "noise_dist": args.noise_dist, "seed": args.seed, "methods": res,
           "paper_options": _options_dict(methods)})

    from host.cli.figures import gaussian_figure
    import matplotlib.pyplot as plt
    fig = gaussian_figure(out / "gaussian.png", target.joints, {m: ests[m].joints for m in methods},
                          {m: res[m]["mean_pct"] for m in methods}, shape=target.name,
                          noise_pct_g=args.noise, seed=args.seed, link_length=LINK_LENGTH,
                          caption=f"{PAPER_FIG9_TEXT}\nHere: {target.description}.")
    plt.close(fig)
    print(f"wrote {out / 'gaussian.png'}")
    return 0


def _options_dict(methods: dict) -> dict:
    from host.analysis.paper_method import PaperOptions
    opts = methods["paper"].get("paper_options") or PaperOptions()
    return dataclasses.asdict(opts)


def _options_text(methods: dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in _options_dict(methods).items())


def cmd_noise(args) -> int:
    from host.cli.progress import Progress

    out = _outdir(args)
    levels = QUICK_NOISE_LEVELS if args.quick else NOISE_LEVELS
    trials = args.trials if args.trials is not None else (2 if args.quick else 10)
    names = args.target or list(NOISE_TARGETS)
    methods = _methods(args)
    targets = [build_target(t) for t in names]
    results = {}
    md = [f"# Fig. 10 — {SIDE_JOINTS}x{SIDE_JOINTS} joints, {trials} trials per level, noise "
          f"{args.noise_dist} per component, seed {args.seed}", "",
          "Joint error after the least-squares overlay, % of the side (13 L): mean ± standard "
          f"deviation over {SIDE_JOINTS ** 2} joints x {trials} trials (the paper's statistic); "
          "median time per snapshot. The paper: the estimate \"fails discernibly\" beyond 5 % of "
          "the side and the sheet \"decently works with the noise level up to 5 %\" [g]. Both "
          "methods on the same draws. capsheet default: `estimate` with its defaults (global "
          "method, cells model, pitches closed by the noise-weighted height fit, prior "
          + _default_prior() + "); "
          "default / paper: the ratio of their means.", "",
          f"Paper's method: {_options_text(methods)}."]
    with Progress(len(targets) * len(levels) * trials, "noise study", "trial",
                  quiet=args.quiet) as bar:
        for target in targets:
            def on_level(row, name=target.name):
                bar.write(f"{name:12s} noise {row['noise_pct_g']:4.1f} % g: " + "  ".join(
                    f"{LABELS.get(m, m)} {row[m]['mean_pct']:6.3f} ± {row[m]['std_pct']:6.3f} % "
                    f"({row[m]['time_ms']:.1f} ms)" for m in methods)
                    + f"  default / paper {_ratio(row)}")
            rows = noise_study(target, levels, trials, args.seed, methods=methods,
                               noise_dist=args.noise_dist, progress=bar, on_level=on_level)
            for r in rows:
                p = r["paper"]["mean_pct"]
                r["default_over_paper"] = r["global"]["mean_pct"] / p if p > 0 else None
            sv = unit_solvability(target)
            solv = {"units": int(sv.size), "below_0_1": int((sv < 0.1).sum()),
                    "below_0_2": int((sv < 0.2).sum()), "median": float(np.median(sv)),
                    "min": float(sv.min()), "map": sv.round(4).tolist()}
            results[target.name] = {"description": target.description, "rows": rows,
                                    "solvability": solv,
                                    "works_up_to_pct_g": {m: works_up_to(rows, m) for m in methods}}
            md += ["", f"## {target.name}", "", f"{target.description}. Units with λ3/λ1 < 0.1 "
                   f"(noise-free): {solv['below_0_1']} of {solv['units']} (< 0.2: "
                   f"{solv['below_0_2']}; median {solv['median']:.2f}).", "",
                   "| noise % g | " + " | ".join(f"{LABELS.get(m, m)} mean ± std" for m in methods)
                   + " | default / paper | " + " | ".join(f"{LABELS.get(m, m)} ms" for m in methods)
                   + " |",
                   "|---:|" + "---:|" * (2 * len(methods) + 1)]
            md += [f"| {r['noise_pct_g']:.1f} | " + " | ".join(
                f"{r[m]['mean_pct']:.2f} ± {r[m]['std_pct']:.2f}"
                + (" ✗" if r[m]["over_failure_line"] else "") for m in methods)
                + f" | {_ratio(r)} | "
                + " | ".join(f"{r[m]['time_ms']:.1f}" for m in methods) + " |"
                for r in rows]
            md += ["", "Under the 5 % failure line at every level up to: " + "; ".join(
                f"{LABELS.get(m, m)} {_upto(results[target.name]['works_up_to_pct_g'][m])}"
                for m in methods)
                + " (✗: mean over the line)."]
    _emit(out / "noise", "\n".join(md),
          {"trials": trials, "seed": args.seed, "noise_dist": args.noise_dist,
           "failure_line_pct": FAILURE_LINE_PCT, "paper_options": _options_dict(methods),
           "targets": results})

    from host.cli.figures import noise_figure
    import matplotlib.pyplot as plt
    fig = noise_figure(out / "noise.png", results, list(methods), trials=trials, seed=args.seed,
                       side_joints=SIDE_JOINTS, noise_dist=args.noise_dist,
                       failure_line_pct=FAILURE_LINE_PCT)
    plt.close(fig)
    print(f"wrote {out / 'noise.png'}")
    return 0


def _ratio(row: dict) -> str:
    """The default's mean error over the paper's method's, as the table prints it."""
    g, p = row["global"]["mean_pct"], row["paper"]["mean_pct"]
    return f"{g / p:.2f}" if p > 0 else "–"


def _default_prior() -> str:
    from host.analysis.estimator.priors import DEFAULT_PRIOR
    return repr(DEFAULT_PRIOR)


def _upto(level) -> str:
    return "none (over at 0 % g)" if level is None else f"{level:g} % g"


# ---------------------------------------------------------------------------------------------
# plumbing
# ---------------------------------------------------------------------------------------------

def _outdir(args) -> Path:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    return out


def _emit(stem: Path, markdown: str, data: dict) -> None:
    print(markdown)
    stem.with_suffix(".md").write_text(markdown + "\n", encoding="utf-8")
    stem.with_suffix(".json").write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    print(f"wrote {stem.with_suffix('.md')} and {stem.with_suffix('.json')}")


def _bounded(kind, lo: float, hi: float | None = None, name: str = "value", need: str = ""):
    """An argparse type: ``kind(text)`` within [lo, hi], else one line naming what is allowed."""
    need = need or f"need an integer >= {lo}"

    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid {name} {text!r} ({need})") from None
        if not (np.isfinite(v) and v >= lo and (hi is None or v <= hi)):
            raise argparse.ArgumentTypeError(f"invalid {name} {text!r} ({need})")
        return v
    return parse


def _int_at_least(lo: int):
    return _bounded(int, lo)


_noise_arg = _bounded(float, 0.0, 100.0, "noise", "need a number of % g, 0..100")


def _target_arg(text: str) -> str:
    from virtual_sheet.shapes import SHAPES  # light: no scipy
    known = list(TARGETS) + [s for s in SHAPES if s != "heightmap"]
    if text not in known:
        raise argparse.ArgumentTypeError(f"unknown target {text!r} (expected one of "
                                         f"{', '.join(known)})")
    return text


def _paper_option_arg(text: str) -> str:
    try:
        paper_options([text])
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).replace("invalid --paper-option ", "")) from None
    return text


def register(subparsers) -> None:
    """Add ``capsheet paper {solvability,gaussian,noise}``."""
    p = subparsers.add_parser("paper", help="the paper's Fig. 8-10, as the authors ran them "
                                            "(PNG + tables)",
                              description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="paper_command", metavar="FIGURE")

    def common(sp, seed=True):
        sp.add_argument("--out", default="out/paper", help="output directory (default out/paper)")
        sp.add_argument("--quick", action="store_true", help="small run, for tests")
        if seed:
            sp.add_argument("--seed", type=_int_at_least(0), default=2008,
                            help="MT19937 seed (default 2008)")
            sp.add_argument("--noise-dist", choices=NOISE_DISTS, default="normal",
                            help="noise per component: normal (the level is its standard "
                                 "deviation, default) or uniform (its half-width)")
            sp.add_argument("--paper-option", action="append", type=_paper_option_arg,
                            metavar="KEY=VALUE",
                            help="a choice the paper leaves open (host.analysis.paper_method."
                                 "PaperOptions: combine, starts, n_starts, select, accept, "
                                 "max_iter, joints, seed); repeat for several")

    s = sub.add_parser("solvability", help="Fig. 8: unsolvable unit states (λ3/λ1 < 0.1, and "
                                           "the estimator's yaw standard deviation)")
    common(s, seed=False)
    s.add_argument("--steps", type=_int_at_least(2), default=None,
                   help="grid values per angle (default 20; 8 with --quick)")
    s.set_defaults(func=cmd_solvability)

    g = sub.add_parser("gaussian", help="Fig. 9: the draped Gaussian sheet, model and estimates")
    common(g)
    g.add_argument("--noise", type=_noise_arg, default=0.0, help="noise, %% g (default 0)")
    g.add_argument("--target", type=_target_arg, default="fig9",
                   help=f"model sheet (default fig9; {', '.join(TARGETS)}, or a shape)")
    g.set_defaults(func=cmd_gaussian)

    nz = sub.add_parser("noise", help="Fig. 10: joint error vs noise 0-10 %% g, both methods")
    common(nz)
    nz.add_argument("--trials", type=_int_at_least(1), default=None,
                    help="trials per noise level (default 10; 2 with --quick)")
    nz.add_argument("--target", type=_target_arg, action="append", default=None,
                    help="model sheet, repeat for several (default: "
                         + ", ".join(NOISE_TARGETS) + ")")
    nz.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    nz.set_defaults(func=cmd_noise)

    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


if __name__ == "__main__":  # pragma: no cover
    from host.cli import main
    sys.exit(main(["paper"] + sys.argv[1:]))
