"""The paper's method, every choice it leaves open side by side, on the paper's own experiment.
Prints JSON (and with ``--markdown`` the docs/estimator.md tables on stderr).

Setup: `host.cli.paper` (`capsheet paper noise`'s): the 14x14 spring-mass drape over the Fig. 9
Gaussian and the other targets (``--target``), noise per component from MT19937 streams seeded by
``(seed, level)`` — every row on the same draws — and the paper's error: mean (and standard
deviation) of the 196 joints' distances after the least-squares overlay, % of the side, over
``--trials`` trials per level.

Also, per target, the units themselves ("units"): how many end in a wrong minimum (relative yaws
more than 0.5 rad off the truth's) with the default selection and with ``select=min``, and how
many of min's wrong units have a smaller eq. (8) than the truth — the reason the smallest eq. (8)
is not the shape.

Rows: the paper's method with its defaults (`host.analysis.paper_method.PaperOptions`) and with
one choice changed at a time; capsheet's global estimator (default, and ``prior="off"``); and the
same with uniform instead of normal noise. Columns: noise 0, 1, 3, 5, 10 % g, and the highest
level up to which the mean stays under the paper's 5 % failure line.

    .venv/bin/python benchmarks/bench_paper.py [--trials 10] [--quick] [--markdown] > run.json
    .venv/bin/python benchmarks/bench_paper.py --markdown-from run.json   # the tables again
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from host.analysis.paper_method import PaperOptions  # noqa: E402
from host.cli import paper  # noqa: E402
from host.cli.progress import Progress  # noqa: E402

LEVELS = (0.0, 1.0, 3.0, 5.0, 10.0)
TARGETS = ("fig9", "fig9-tilted", "fig9-compass", "fig9-surface")
D = PaperOptions()
#: row name -> what changes from the defaults (PaperOptions fields); "global*" rows are
#: capsheet's estimator
VARIANTS = {
    "paper (defaults)": {},
    "select=min (smallest eq. 8 of all starts)": {"select": "min"},
    "accept=0.01": {"accept": 0.01},
    "accept=0.03": {"accept": 0.03},
    "accept=0.3": {"accept": 0.3},
    "n_starts=1 (the square cell only)": {"n_starts": 1},
    "n_starts=12": {"n_starts": 12},
    "starts=random, n_starts=12, select=min": {"starts": "random", "n_starts": 12,
                                                "select": "min"},
    "combine=tree": {"combine": "tree"},
    "combine=chain": {"combine": "chain"},
    "combine=chain, select=min": {"combine": "chain", "select": "min"},
    "joints=walk": {"joints": "walk"},
    "max_iter=30": {"max_iter": 30},
    "max_iter=3000": {"max_iter": 3000},
}
GLOBALS = {"global (capsheet default)": {}, "global, prior off": {"prior": "off"}}


def methods() -> dict:
    m = {name: {"method": "paper", "paper_options": dataclasses.replace(D, **kw)}
         for name, kw in VARIANTS.items()}
    m.update(GLOBALS)
    return m


def unit_minima(target, levels, trials: int, seed: int, dist: str) -> dict:
    """Per level: share of units in a wrong minimum (default selection, select=min), and of
    min's wrong units the share whose eq. (8) is below the truth's."""
    import numpy as np

    from host.analysis import paper_method as pm
    from host.analysis.estimator import roll_pitch
    from protocol.lattice import Lattice
    from virtual_sheet.geometry import link_angles

    n = paper.SIDE_JOINTS
    units = Lattice(n, n).units
    gamma = link_angles(target.joints)[2]
    true = pm._wrap(gamma[units] - gamma[units][..., :1])
    out = {}
    for level in levels:
        wrong = {"default": [], "min": []}
        lower = []
        for r in paper.noise_draws(target.readings, level, trials, seed, dist):
            a, b = roll_pitch(r)
            cd, cn = pm._coefficients(a, b, units.reshape(-1, 4))
            z = np.exp(1j * true.reshape(-1, 4))
            p_true = np.abs((cd * z).sum(-1)) ** 2 + np.abs((cn * z).sum(-1)) ** 2
            for name, opts in (("default", D), ("min", dataclasses.replace(D, select="min"))):
                delta, P, _ = pm.unit_yaws(a, b, n, n, opts)
                w = (np.abs(pm._wrap(delta - true)).max(-1) > 0.5).ravel()
                wrong[name].append(w.mean())
                if name == "min" and w.any():
                    lower.append(np.mean(P.ravel()[w] < p_true[w]))
        out[f"{level:g}"] = {"wrong_default_pct": round(100 * float(np.mean(wrong["default"])), 2),
                             "wrong_min_pct": round(100 * float(np.mean(wrong["min"])), 2),
                             "min_wrong_below_truth_pct": (round(100 * float(np.mean(lower)), 1)
                                                           if lower else None)}
    return out


def summarise(rows: list, names) -> dict:
    return {name: {"mean_pct": {f"{r['noise_pct_g']:g}": round(r[name]["mean_pct"], 3)
                                for r in rows},
                   "std_pct": {f"{r['noise_pct_g']:g}": round(r[name]["std_pct"], 3)
                               for r in rows},
                   "time_ms": round(sum(r[name]["time_ms"] for r in rows) / len(rows), 1),
                   "works_up_to_pct_g": paper.works_up_to(rows, name)}
            for name in names}


#: the readings the summary table compares across targets
SUMMARY = ("paper (defaults)", "n_starts=1 (the square cell only)",
           "select=min (smallest eq. 8 of all starts)", "combine=chain",
           "global (capsheet default)", "global, prior off")


def summary(out: dict) -> list[str]:
    """One row per target: the mean error at 5 and 10 % g of the readings in `SUMMARY`."""
    levels = [lv for lv in ("5", "10") if lv in out["targets"][next(iter(out["targets"]))]
              ["rows"]["paper (defaults)"]["mean_pct"]]
    lines = ["| target | " + " | ".join(SUMMARY) + " |", "|---|" + "---:|" * len(SUMMARY)]
    for tname, t in out["targets"].items():
        lines.append(f"| {tname} | " + " | ".join(
            " / ".join(f"{t['rows'][name]['mean_pct'][lv]:.2f}" for lv in levels)
            for name in SUMMARY) + " |")
    return [f"Mean % of side at {' / '.join(levels)} % g:", ""] + lines + [""]


def markdown(out: dict) -> str:
    lines = summary(out)
    for tname, t in out["targets"].items():
        levels = list(next(iter(t["rows"].values()))["mean_pct"])
        lines += [f"**{tname}** ({out['noise_dist']} noise) — mean ± std, % of side:", "",
                  "| reading | " + " | ".join(f"{lv} % g" for lv in levels)
                  + " | under 5 % up to | ms |", "|---|" + "---:|" * (len(levels) + 2)]
        for name, r in t["rows"].items():
            up = r["works_up_to_pct_g"]
            lines.append(f"| {name} | " + " | ".join(
                f"{r['mean_pct'][lv]:.2f} ± {r['std_pct'][lv]:.2f}" for lv in levels)
                + f" | {'–' if up is None else f'{up:g} % g'} | {r['time_ms']:.0f} |")
        u = t["units"]
        lines += ["", "| units in a wrong minimum | " + " | ".join(f"{lv} % g" for lv in levels)
                  + " |", "|---|" + "---:|" * len(levels),
                  "| default selection | " + " | ".join(f"{u[lv]['wrong_default_pct']:.1f} %"
                                                     for lv in levels) + " |",
                  "| select=min | " + " | ".join(f"{u[lv]['wrong_min_pct']:.1f} %"
                                              for lv in levels) + " |",
                  "| … of which eq. (8) below the truth's | " + " | ".join(
                      "–" if u[lv]["min_wrong_below_truth_pct"] is None
                      else f"{u[lv]['min_wrong_below_truth_pct']:.0f} %" for lv in levels) + " |"]
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=10, help="trials per level (default 10)")
    ap.add_argument("--seed", type=int, default=2008, help="MT19937 seed (default 2008)")
    ap.add_argument("--target", action="append", default=None,
                    help=f"targets (default {', '.join(TARGETS)})")
    ap.add_argument("--noise-dist", choices=paper.NOISE_DISTS, default="normal")
    ap.add_argument("--quick", action="store_true", help="2 trials, levels 0 and 5, fig9 only")
    ap.add_argument("--markdown", action="store_true", help="also print the tables on stderr")
    ap.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    ap.add_argument("--markdown-from", metavar="JSON", default=None,
                    help="print the tables of a saved run's JSON (stdout) and stop")
    args = ap.parse_args(argv)
    if args.markdown_from:
        print(markdown(json.loads(Path(args.markdown_from).read_text())))
        return 0
    if args.trials < 1:
        ap.error("--trials must be >= 1")
    trials, levels = (2, (0.0, 5.0)) if args.quick else (args.trials, LEVELS)
    names = args.target or (["fig9"] if args.quick else list(TARGETS))
    m = methods()
    t0 = time.perf_counter()
    out = {"benchmark": "paper_method", "lattice": "14x14", "trials": trials, "seed": args.seed,
           "noise_dist": args.noise_dist, "levels_pct_g": list(levels),
           "defaults": dataclasses.asdict(D), "targets": {}}
    with Progress(len(names) * len(levels) * trials, "bench_paper", "trial",
                  quiet=args.quiet) as bar:
        for name in names:
            target = paper.build_target(name)
            rows = paper.noise_study(target, levels, trials, args.seed, methods=m,
                                     noise_dist=args.noise_dist, progress=bar)
            out["targets"][name] = {"description": target.description,
                                    "rows": summarise(rows, m),
                                    "units": unit_minima(target, levels, trials, args.seed,
                                                         args.noise_dist)}
    out["seconds"] = round(time.perf_counter() - t0, 1)
    if args.markdown:
        print(markdown(out), file=sys.stderr)
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
