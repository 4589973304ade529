"""``capsheet paper``: reproduce the paper's figures 8, 9 and 10, and compare both estimators.

* ``capsheet paper solvability`` — Fig. 8: the (θc, θf, θr, θp) grid, 20 steps each, where a
  single unit's eq. (7) has ``λ3/λ1 < 0.1``, and where the estimator's yaw standard deviation
  (its Gauss-Newton normal matrix) exceeds `YAW_STD_GAIN_LIMIT` times the noise; how many of
  each fall in the paper's Case 1 (horizontal) and Case 2 (squashed / fully folded), points
  coloured by case.
* ``capsheet paper gaussian`` — Fig. 9: a 13x13-unit (14x14-joint) sheet on the Gaussian, model and
  estimate (both methods) side by side in 3D.
* ``capsheet paper noise`` — Fig. 10: mean and standard deviation of the joint error (% of the side
  length after a least-squares overlay) against noise 0-10 % g, 196 joints x ``--trials``, both
  methods on the same data, and the run time per snapshot of each.

Each writes a PNG, a markdown table and a JSON file under ``--out`` (default ``out/paper``) and
prints the table. The unit of Fig. 8 is built as follows (the paper's Fig. 7 is not in its text, so
this is our reading of it): joint A at the origin, link 3 (A->D) along +x, link 0 (A->B) at the
corner angle θc from it in the xy plane, C = B + D − A; the triangle A-C-D is folded about the
diagonal AC by θf (θf = π folds it onto A-B-C); the unit is then rolled by θr about x and pitched by
θp about y. Every link's sensor z is its triangle's normal (the unit's plane normal, carried by the
fold); θc, θf, θr in [0, π] and θp in [0, π/2], 20 evenly spaced values each (ends included).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
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
           "noise_study"]

SIDE_JOINTS = 14  #: the paper's 13x13-unit sheet
LINK_LENGTH = 0.01  #: metres (the error is relative to the side, so L does not matter)
NOISE_LEVELS = (0.0, 0.3, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0)  #: % g
QUICK_NOISE_LEVELS = (0.0, 1.0, 5.0)


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


#: The yaw criterion's threshold: a unit is poorly determined where a yaw's standard deviation
#: exceeds this many times the residuals' noise.
YAW_STD_GAIN_LIMIT = 10.0


def _unit_residuals(alpha, beta, gamma):
    """The estimator's residuals for one unit (``model="cells"``), shape (..., 6): loop closure
    (eq. 4, xy, real and imaginary) and every link's roll term ``w y_k · n`` with the cell's
    normal ``n = A × C / |A × C|`` (0 for a squashed cell)."""
    ca, sa, cb, sb = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)
    cg, sg = np.cos(gamma), np.sin(gamma)
    d = np.stack([cb * cg, cb * sg, -sb], -1)
    y = np.stack([cg * sb * sa - sg * ca, sg * sb * sa + cg * ca, cb * sa], -1)
    loop = d[..., 0, :] + d[..., 1, :] - d[..., 2, :] - d[..., 3, :]
    m = np.cross(d[..., 1, :] + d[..., 3, :], d[..., 0, :] + d[..., 2, :])
    mm = np.linalg.norm(m, axis=-1, keepdims=True)
    n = np.where(mm > 1e-6, m / np.where(mm > 1e-6, mm, 1.0), 0.0)
    roll = E.ROLL_WEIGHT * np.sum(y * n[..., None, :], -1)
    return np.concatenate([loop[..., :2], roll], -1)


def yaw_std_gain(alpha, beta, gamma, eps: float = 1e-6) -> np.ndarray:
    """Per unit, the largest yaw standard deviation per unit residual noise, from the
    estimator's Gauss-Newton normal matrix ``JᵀJ + ε I`` (yaw 0 as gauge; J by central
    differences over yaws 1-3): ``sqrt(max diag((JᵀJ + ε)⁻¹))``. Rank-deficient units (Case 1,
    squashed) reach ``1/sqrt(ε)`` = 1000."""
    h = 1e-6
    cols = []
    for k in (1, 2, 3):
        dg = np.zeros(gamma.shape)
        dg[..., k] = h
        cols.append((_unit_residuals(alpha, beta, gamma + dg)
                     - _unit_residuals(alpha, beta, gamma - dg)) / (2 * h))
    J = np.nan_to_num(np.stack(cols, -1), nan=0.0, posinf=0.0, neginf=0.0)  # (..., 6, 3)
    w, v = np.linalg.eigh(np.einsum("...ri,...rj->...ij", J, J))
    diag = np.sum(v * v / (np.maximum(w, 0.0) + eps)[..., None, :], -1)
    return np.sqrt(np.max(diag, -1))


def _cases(pts: np.ndarray, steps: int) -> dict:
    """Case masks of grid points ``(θc, θf, θr, θp)`` (N, 4): exactly on Case 1 / Case 2, within
    one grid step of Case 1, links vertical (θp = π/2)."""
    tol = 1e-9
    on = lambda v, t: np.abs(v - t) < tol  # noqa: E731
    near = lambda v, t: np.abs(v - t) <= (np.pi / (steps - 1)) + tol  # noqa: E731
    case1 = ((on(pts[:, 1], 0) | on(pts[:, 1], np.pi)) & (on(pts[:, 2], 0) | on(pts[:, 2], np.pi))
             & on(pts[:, 3], 0))
    case2 = on(pts[:, 0], 0) | on(pts[:, 0], np.pi) | on(pts[:, 1], np.pi)
    case1_near = ((near(pts[:, 1], 0) | near(pts[:, 1], np.pi))
                  & (near(pts[:, 2], 0) | near(pts[:, 2], np.pi)) & near(pts[:, 3], 0))
    vertical = on(pts[:, 3], np.pi / 2)
    return {"case1": case1, "case2": case2, "case1_near": case1_near & ~case2,
            "vertical": vertical & ~case1_near & ~case2,
            "other": ~case1_near & ~case2 & ~vertical}


def _counts(pts: np.ndarray, steps: int) -> dict:
    c = _cases(pts, steps)
    return {"n_unsolvable": int(len(pts)), "case1": int(c["case1"].sum()),
            "case2": int(c["case2"].sum()), "case1_or_2": int((c["case1"] | c["case2"]).sum()),
            "case1_within_one_step": int(c["case1_near"].sum()),
            "vertical_theta_p": int(c["vertical"].sum()), "other": int(c["other"].sum())}


def solvability_grid(steps: int = 20) -> dict:
    """Both criteria over the (θc, θf, θr, θp) grid: λ3/λ1 of eq. (7) (< 0.1: unsolvable in the
    paper's sense) and the estimator's yaw standard deviation gain (`yaw_std_gain` >
    `YAW_STD_GAIN_LIMIT`), with the points each flags and how they split over the cases."""
    g = np.linspace(0.0, np.pi, steps)
    gp = np.linspace(0.0, np.pi / 2, steps)
    tc, tf, tr, tp = np.meshgrid(g, g, g, gp, indexing="ij")
    a, b, c = unit_state(tc, tf, tr, tp)
    ratio = E.solvability_units(a, b)
    gain = yaw_std_gain(a, b, c)
    grid = np.stack([tc, tf, tr, tp], -1)
    bad = ratio < 0.1
    bad_yaw = gain > YAW_STD_GAIN_LIMIT
    pts, pts_yaw = grid[bad], grid[bad_yaw]
    res = {"steps": steps, "points": pts, "points_yaw": pts_yaw, "ratio": ratio, "gain": gain,
           "n_total": int(ratio.size), **_counts(pts, steps),
           "yaw_std": _counts(pts_yaw, steps),
           "yaw_only": int((bad_yaw & ~bad).sum()), "eq7_only": int((bad & ~bad_yaw).sum())}
    return res


def cmd_solvability(args) -> int:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = _outdir(args)
    steps = 8 if args.quick else args.steps
    if steps < 2:
        print(f"capsheet paper solvability: error: --steps must be >= 2, got {steps}",
              file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    res = solvability_grid(steps)
    dt = time.perf_counter() - t0
    y = res["yaw_std"]
    rows = [("grid points", res["n_total"], res["n_total"]),
            ("flagged", res["n_unsolvable"], y["n_unsolvable"]),
            ("… in Case 1 (horizontal: θf, θr ∈ {0, π}, θp = 0)", res["case1"], y["case1"]),
            ("… in Case 2 (squashed θc ∈ {0, π}, or folded θf = π)", res["case2"], y["case2"]),
            ("… in Case 1 or 2", res["case1_or_2"], y["case1_or_2"]),
            ("… not Case 2, within one grid step of Case 1", res["case1_within_one_step"],
             y["case1_within_one_step"]),
            ("… not Case 1/2, links vertical (θp = π/2)", res["vertical_theta_p"],
             y["vertical_theta_p"]),
            ("… elsewhere", res["other"], y["other"])]
    md = ["# Fig. 8 — unsolvable unit states, two criteria", "",
          f"Grid: θc, θf, θr ∈ [0, π], θp ∈ [0, π/2], {steps} values each ({dt:.1f} s). "
          "Paper: all unsolvable states roughly in Case 1 or Case 2. λ3/λ1 < 0.1 of eq. (7) "
          "against the estimator's yaw standard deviation (Gauss-Newton normal matrix of the "
          f"cells model, per unit residual noise) > {YAW_STD_GAIN_LIMIT:g}.", "",
          "| | λ3/λ1 < 0.1 | yaw std > limit |", "|---|---:|---:|"]
    md += [f"| {k} | {v} | {w} |" for k, v, w in rows]
    md += ["", f"Flagged by the yaw std only: {res['yaw_only']}; by λ3/λ1 only: "
           f"{res['eq7_only']}."]
    _emit(out / "solvability", "\n".join(md),
          {k: v for k, v in res.items() if k not in ("points", "points_yaw", "ratio", "gain")})

    fig = plt.figure(figsize=(12, 5.5))
    colours = (("case1", "Case 1", "C0"), ("case1_near", "near Case 1", "C9"),
               ("case2", "Case 2", "C3"), ("vertical", "θp = π/2", "C2"),
               ("other", "elsewhere", "C1"))
    for k, (pts, title) in enumerate(((res["points"], "λ3/λ1 < 0.1 (eq. 7, Fig. 8)"),
                                      (res["points_yaw"], f"yaw std > {YAW_STD_GAIN_LIMIT:g}×"
                                       " noise (normal matrix)"))):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        cases = _cases(pts, steps) if len(pts) else {}
        for key, label, colour in colours:
            sel = cases.get(key, np.zeros(0, bool))
            if key == "case2":
                sel = cases.get("case2", sel)
            elif key == "case1":
                sel = cases.get("case1", sel) & ~cases.get("case2", sel)
            if np.any(sel):
                ax.scatter(pts[sel, 1], pts[sel, 2], pts[sel, 3], s=6, color=colour,
                           label=f"{label} ({int(sel.sum())})")
        ax.set_xlabel("θf [rad]")
        ax.set_ylabel("θr [rad]")
        ax.set_zlabel("θp [rad]")
        ax.set_title(title)
        ax.legend(loc="upper left", fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "solvability.png", dpi=110)
    plt.close(fig)
    print(f"wrote {out / 'solvability.png'}")
    return 0


# ---------------------------------------------------------------------------------------------
# Fig. 9 and 10: the Gaussian sheet
# ---------------------------------------------------------------------------------------------

def _truth(shape: str = "gaussian"):
    from virtual_sheet.geometry import ideal_readings
    from virtual_sheet.shapes import make_sheet
    P = make_sheet(shape, SIDE_JOINTS, SIDE_JOINTS, LINK_LENGTH)
    return P, ideal_readings(P)


def cmd_gaussian(args) -> int:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from virtual_sheet.sensor import noisy_readings

    out = _outdir(args)
    P, r0 = _truth(args.shape)
    rng = np.random.Generator(np.random.MT19937(args.seed))
    r = noisy_readings(r0, args.noise, rng)
    n = SIDE_JOINTS
    res, ests = {}, {}
    for m in E.METHODS:
        t0 = time.perf_counter()
        est = E.estimate(r, n, n, LINK_LENGTH, method=m)
        dt = time.perf_counter() - t0
        err = E.error_percent_of_side(est.joints, P, LINK_LENGTH)
        ests[m] = est
        res[m] = {"mean_pct": float(err.mean()), "std_pct": float(err.std()),
                  "max_pct": float(err.max()), "time_s": dt, "residual": est.residual}
    md = [f"# Fig. 9 — {args.shape}, {n}x{n} joints, noise {args.noise} % g, seed {args.seed}", "",
          "| method | mean error % side | std | max | time per snapshot [ms] |",
          "|---|---:|---:|---:|---:|"]
    md += [f"| {m} | {v['mean_pct']:.3f} | {v['std_pct']:.3f} | {v['max_pct']:.3f} | "
           f"{1e3 * v['time_s']:.1f} |" for m, v in res.items()]
    _emit(out / "gaussian", "\n".join(md), {"shape": args.shape, "noise_pct_g": args.noise,
                                            "seed": args.seed, "methods": res})

    from host.cli.figures import gaussian_figure
    fig = gaussian_figure(out / "gaussian.png", P, {m: ests[m].joints for m in E.METHODS},
                          {m: res[m]["mean_pct"] for m in E.METHODS}, shape=args.shape, noise_pct_g=args.noise,
                          seed=args.seed, link_length=LINK_LENGTH)
    plt.close(fig)
    print(f"wrote {out / 'gaussian.png'}")
    return 0


def noise_study(levels, trials: int, seed: int, shape: str = "gaussian", progress=None) -> list:
    """Fig. 10 data: per noise level and method, joint-error mean/std (% side) and time/snapshot.

    Both methods see the same noisy readings; every trial draws fresh noise from one seeded
    MT19937 stream. Returns a list of dicts, one per level.
    """
    from virtual_sheet.sensor import noisy_readings

    P, r0 = _truth(shape)
    n = SIDE_JOINTS
    rng = np.random.Generator(np.random.MT19937(seed))
    rows = []
    from tqdm import tqdm
    bar = tqdm(total=len(levels) * trials, unit="trial", desc="noise study", file=sys.stderr,
               disable=False, dynamic_ncols=True)
    for level in levels:
        errs = {m: [] for m in E.METHODS}
        times = {m: [] for m in E.METHODS}
        for _ in range(trials):
            r = noisy_readings(r0, level, rng)
            for m in E.METHODS:
                t0 = time.perf_counter()
                est = E.estimate(r, n, n, LINK_LENGTH, method=m)
                times[m].append(time.perf_counter() - t0)
                errs[m].append(E.error_percent_of_side(est.joints, P, LINK_LENGTH).ravel())
            bar.update(1)
        row = {"noise_pct_g": level, "samples": n * n * trials}
        for m in E.METHODS:
            e = np.concatenate(errs[m])
            p05, p50, p95 = np.percentile(e, [5, 50, 95])
            row[m] = {"mean_pct": float(e.mean()), "std_pct": float(e.std()), "p05_pct": float(p05),
                      "p50_pct": float(p50), "p95_pct": float(p95),
                      "time_ms": 1e3 * float(np.median(times[m]))}
        rows.append(row)
        if progress:
            progress(row)
    bar.close()
    return rows


def cmd_noise(args) -> int:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = _outdir(args)
    levels = QUICK_NOISE_LEVELS if args.quick else NOISE_LEVELS
    trials = 2 if args.quick and args.trials is None else (args.trials or 10)

    def progress(row):
        print(f"noise {row['noise_pct_g']:4.1f} % g: " + "  ".join(
            f"{m} {row[m]['mean_pct']:6.3f} ± {row[m]['std_pct']:6.3f} % ({row[m]['time_ms']:.1f} ms)"
            for m in E.METHODS), flush=True)

    rows = noise_study(levels, trials, args.seed, args.shape, progress)
    md = [f"# Fig. 10 — {args.shape}, {SIDE_JOINTS}x{SIDE_JOINTS} joints, {trials} trials, "
          f"seed {args.seed}", "",
          "Joint error after least-squares overlay, % of side length ((cols−1)·L); mean ± std over "
          f"{SIDE_JOINTS ** 2} joints x {trials} trials; median time per snapshot. The paper: the "
          "estimate \"fails discernibly\" beyond 5 % of the side and works up to 5 % g noise.", "",
          "| noise % g | global mean | global std | paper mean | paper std | global ms | paper ms |",
          "|---:|---:|---:|---:|---:|---:|---:|"]
    md += [f"| {r['noise_pct_g']:.1f} | {r['global']['mean_pct']:.3f} | {r['global']['std_pct']:.3f} "
           f"| {r['paper']['mean_pct']:.3f} | {r['paper']['std_pct']:.3f} | "
           f"{r['global']['time_ms']:.2f} | {r['paper']['time_ms']:.1f} |" for r in rows]
    _emit(out / "noise", "\n".join(md), {"shape": args.shape, "trials": trials, "seed": args.seed,
                                         "rows": rows})

    from host.cli.figures import noise_figure
    fig = noise_figure(out / "noise.png", rows, E.METHODS, shape=args.shape, side_joints=SIDE_JOINTS,
                       trials=trials, seed=args.seed)
    plt.close(fig)
    print(f"wrote {out / 'noise.png'}")
    return 0


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


def register(subparsers) -> None:
    """Add ``capsheet paper {solvability,gaussian,noise}``."""
    p = subparsers.add_parser("paper", help="reproduce the paper's Fig. 8-10 (PNG + tables)",
                              description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="paper_command", metavar="FIGURE")

    def common(sp, seed=True):
        sp.add_argument("--out", default="out/paper", help="output directory (default out/paper)")
        sp.add_argument("--quick", action="store_true", help="small run, for tests")
        if seed:
            sp.add_argument("--seed", type=int, default=2008, help="MT19937 seed")

    s = sub.add_parser("solvability", help="Fig. 8: unsolvable unit states (λ3/λ1 < 0.1, and "
                                           "the estimator's yaw standard deviation)")
    common(s, seed=False)
    s.add_argument("--steps", type=int, default=20, help="grid values per angle (default 20)")
    s.set_defaults(func=cmd_solvability)

    g = sub.add_parser("gaussian", help="Fig. 9: Gaussian sheet, model and estimates in 3D")
    common(g)
    g.add_argument("--noise", type=float, default=0.0, help="noise, %% g (default 0)")
    g.add_argument("--shape", default="gaussian", help="virtual_sheet shape (default gaussian)")
    g.set_defaults(func=cmd_gaussian)

    nz = sub.add_parser("noise", help="Fig. 10: joint error vs noise, both methods, and timing")
    common(nz)
    nz.add_argument("--trials", type=int, default=None, help="trials per level (default 10)")
    nz.add_argument("--shape", default="gaussian", help="virtual_sheet shape (default gaussian)")
    nz.set_defaults(func=cmd_noise)

    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


if __name__ == "__main__":  # pragma: no cover
    from host.cli import main
    sys.exit(main(["paper"] + sys.argv[1:]))
