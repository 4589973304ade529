"""Tactile benchmark: contacts and forces on every virtual foam body (docs/tactile.md).

Setup: a 14x14-joint sheet, L = 1 cm, on a foam block, a cylinder (R = 8 cm) and a sphere
(R = 10 cm), foam h = 20 mm, E = 20 kPa, ν = 0.25 (`virtual_sheet.foam.FoamLayer`'s defaults;
on the curved bodies the layer is softer, `FoamBody.contact_layer`), white reading noise of the
given % g per axis. The rest shape is learned from 32 untouched snapshots at the same noise
(`TactileSensor.learn_rest`); every snapshot is then estimated with the rest shape as the prior and
its contacts found.

Indenters of one kind (sphere R = 15 mm, flat punch a = 7.5 mm, 2 N each; a capsule "finger"
R = 10 mm, half-length 20 mm, 3 N, at a random angle), one, or two ``separation_l`` link lengths
apart in a random direction about a random point within L/2 of the sheet's middle (``layouts``
placements, ``snapshots`` noisy snapshots of each). One JSON row per (body, indenter, separation,
noise):

* ``count_exact_pct``: snapshots whose contact count is right; ``silent_wrong_count_pct``: wrong
  count and no contact flagged ``merged`` (the issue's "never a wrong count without saying so");
* ``position_err_l_mean`` / ``_p95``: matched detected vs true centres, link lengths (lattice
  indices; Hungarian, gate 2 L);
* ``force_err_mean_pct`` / ``force_err_p95_pct``: |F_est − F_true| / F_true per matched contact and
  snapshot; ``force_bias_pct``: mean of (F_est − F_true) / F_true. A merged contact is compared with
  the sum of the true contacts it holds;
* ``false_positives_per_1000``: detected contacts matched to no true one, per 1000 snapshots; on
  untouched rows (indenter ``none``, 1000 snapshots) every contact is one;
* ``force_held_err_p95_pct`` / ``force_held_bias_pct``: the same for ``Contact.force_n_held``,
  the tracked contact's mean over its last 4 snapshots (the first snapshots of a layout have
  fewer);
* capsule rows: ``axes_err_pct`` (major, minor) against the true dent's half-depth footprint
  (from the virtual deflection, same moment definition) and ``angle_err_deg_mean`` / ``_p95``.

Forces are read with the fitted dent template (`DetectorSettings.force_model` ``"fit"``);
``--force-model sum`` gives the sampled Winkler integral for comparison. ``--quick`` for a smoke
run; ``--json`` prints only JSON; ``--body`` and ``--noise`` select rows. Progress goes to stderr.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from host.analysis.tactile import DetectorSettings, Foam, TactileSensor, lattice_index  # noqa: E402
from virtual_sheet.foam import (CapsuleIndenter, FlatPunch, FoamBlock, FoamCylinder,  # noqa: E402
                                FoamLayer, FoamScene, FoamSphere, Press, SphereIndenter)
from virtual_sheet.geometry import ideal_readings  # noqa: E402
from virtual_sheet.sensor import noisy_readings  # noqa: E402

ROWS = COLS = 14
L = 0.01
LAYER = FoamLayer()
BODIES = {"block": FoamBlock(LAYER), "cylinder": FoamCylinder(0.08, LAYER),
          "sphere": FoamSphere(0.1, LAYER)}
FORCE_N = {"sphere": 2.0, "punch": 2.0, "capsule": 3.0}
NOISES = (0.3, 1.0, 2.0, 5.0)


def rng_of(*seed: int) -> np.random.Generator:
    return np.random.Generator(np.random.MT19937(list(seed)))


def indenter(kind: str, rng: np.random.Generator):
    if kind == "sphere":
        return SphereIndenter(0.015)
    if kind == "punch":
        return FlatPunch(0.0075)
    return CapsuleIndenter(0.01, 0.02, angle_rad=float(rng.uniform(-np.pi / 2, np.pi / 2)))


def layout(rng: np.random.Generator, sep: float | None) -> list[tuple[float, float]]:
    """Centres ``(u, v)``, metres: a random point within ±L/2 of the sheet's middle and, for
    ``sep``, two points ``sep`` L apart in a random direction about it."""
    mid = np.array([-0.5 * L, -0.5 * L]) + rng.uniform(-0.5, 0.5, 2) * L
    if sep is None:
        return [tuple(mid)]
    a = rng.uniform(0, np.pi)
    d = 0.5 * sep * L * np.array([np.cos(a), np.sin(a)])
    return [tuple(mid - d), tuple(mid + d)]


def match(det, truth_idx, gate=2.0):
    """Hungarian matching of detected contact indices to true ones; pairs within ``gate`` L."""
    from scipy.optimize import linear_sum_assignment
    if not det or not truth_idx:
        return []
    D = np.linalg.norm(np.array([c.index for c in det])[:, None, :]
                       - np.array(truth_idx)[None, :, :], axis=2)
    r, c = linear_sum_assignment(D)
    return [(a, b, D[a, b]) for a, b in zip(r, c) if D[a, b] <= gate]


def true_footprint(scene: FoamScene, centre) -> tuple[np.ndarray, float]:
    """Half-axes (major, minor), metres, and the major axis's angle from +u of the true dent's
    half-depth footprint (the virtual deflection on its fine grid, uniform weights)."""
    d = scene.deflection(0.0)
    U, V = np.meshgrid(d.u, d.v, indexing="ij")
    near = np.hypot(U - centre[0], V - centre[1]) < 0.05
    m = near & (d.w >= 0.5 * d.w[near].max())
    xy = np.stack([U[m], V[m]], axis=1)
    C = np.cov(xy.T, bias=True)
    ev, evec = np.linalg.eigh(C)
    return 2.0 * np.sqrt(ev[::-1]), float(np.arctan2(evec[1, 1], evec[0, 1]))


def _angle_diff(a: float, b: float) -> float:
    return float(abs((a - b + np.pi / 2) % np.pi - np.pi / 2))


class Bench:
    """Caches learned rest shapes (per body and noise) and scenes (noise-independent)."""

    def __init__(self, seed: int = 7, force_model: str = "fit"):
        self.seed = seed
        self.settings = DetectorSettings(force_model=force_model)
        self.foam = Foam(LAYER.thickness_m, LAYER.youngs_modulus_pa, LAYER.poisson)
        self._rest: dict = {}
        self._r0: dict = {}
        self._scenes: dict = {}

    def r0(self, body: str) -> np.ndarray:
        if body not in self._r0:
            self._r0[body] = ideal_readings(FoamScene(BODIES[body], [], ROWS, COLS, L).rest_joints)
        return self._r0[body]

    def rest(self, body: str, noise: float):
        key = (body, noise)
        if key not in self._rest:
            rng = rng_of(self.seed, 1, int(noise * 100))
            snaps = [noisy_readings(self.r0(body), noise, rng) for _ in range(32)]
            self._rest[key] = TactileSensor.learn_rest(snaps, ROWS, COLS, L)
        return self._rest[key]

    def scene(self, body: str, kind: str, sep: float | None, k: int):
        key = (body, kind, sep, k)
        if key not in self._scenes:
            rng = rng_of(self.seed, 2, k, 0 if sep is None else int(sep * 10))
            ind = indenter(kind, rng)
            presses = [Press(ind, p, FORCE_N[kind]) for p in layout(rng, sep)]
            sc = FoamScene(BODIES[body], presses, ROWS, COLS, L)
            truth = sc.contacts(0.0)
            idx = [lattice_index(sc.rest_joints, t.position) for t in truth]
            shape = true_footprint(sc, truth[0].position_uv) if kind == "capsule" else None
            self._scenes[key] = (ideal_readings(sc.joints(0.0)), truth, idx, shape)
        return self._scenes[key]

    def run(self, body: str, kind: str, sep: float | None, noise: float, layouts: int,
            snapshots: int) -> dict:
        rest = self.rest(body, noise)
        rng = rng_of(self.seed, 3, int(noise * 100), 0 if sep is None else int(sep * 10))
        n_snap = exact = silent = extra = 0
        pos_err, f_err, fh_err, axes_err, ang_err = [], [], [], [], []
        for k in range(layouts):
            r, truth, idx, shape = self.scene(body, kind, sep, k)
            sensor = TactileSensor(rest, self.foam, settings=self.settings)
            for _ in range(snapshots):
                fr = sensor.process(noisy_readings(r, noise, rng))
                n_snap += 1
                cs = fr.contacts
                exact += len(cs) == len(truth)
                silent += len(cs) != len(truth) and not any(c.merged for c in cs)
                pairs = match(cs, idx)
                extra += len(cs) - len(pairs)
                for a, b, dist in pairs:
                    c = cs[a]
                    pos_err.append(dist)
                    f_true = truth[b].force_n
                    if c.merged and len(cs) < len(truth):
                        f_true = sum(t.force_n for t in truth)  # one contact holding both
                    f_err.append((c.force_n - f_true) / f_true * 100)
                    fh_err.append((c.force_n_held - f_true) / f_true * 100)
                    if shape is not None:
                        axes_err.append((c.axes_m / shape[0] - 1) * 100)
                        ang_err.append(np.degrees(_angle_diff(c.angle_rad, shape[1])))
        f = np.array(f_err) if f_err else np.array([np.nan])
        p = np.array(pos_err) if pos_err else np.array([np.nan])
        row = {"body": body, "indenter": kind, "separation_l": sep, "noise_pct_g": noise,
               "force_n": FORCE_N[kind], "snapshots": n_snap,
               "count_exact_pct": 100 * exact / n_snap,
               "silent_wrong_count_pct": 100 * silent / n_snap,
               "position_err_l_mean": float(np.mean(p)),
               "position_err_l_p95": float(np.percentile(p, 95)),
               "force_err_mean_pct": float(np.mean(np.abs(f))),
               "force_err_p95_pct": float(np.percentile(np.abs(f), 95)),
               "force_bias_pct": float(np.mean(f)),
               "false_positives_per_1000": 1000 * extra / n_snap,
               "force_held_err_p95_pct": float(np.percentile(np.abs(fh_err), 95))
               if fh_err else None,
               "force_held_bias_pct": float(np.mean(fh_err)) if fh_err else None}
        if axes_err:
            a = np.array(axes_err)
            row["axes_err_pct"] = [float(x) for x in np.mean(a, axis=0)]
            row["angle_err_deg_mean"] = float(np.mean(ang_err))
            row["angle_err_deg_p95"] = float(np.percentile(ang_err, 95))
        return row

    def untouched(self, body: str, noise: float, snapshots: int) -> dict:
        rest = self.rest(body, noise)
        rng = rng_of(self.seed, 4, int(noise * 100))
        sensor = TactileSensor(rest, self.foam, settings=self.settings)
        hits = contacts = 0
        for _ in range(snapshots):
            fr = sensor.process(noisy_readings(self.r0(body), noise, rng))
            hits += bool(fr.contacts)
            contacts += len(fr.contacts)
        return {"body": body, "indenter": "none", "separation_l": None, "noise_pct_g": noise,
                "force_n": 0.0, "snapshots": snapshots,
                "count_exact_pct": 100 * (snapshots - hits) / snapshots,
                "silent_wrong_count_pct": 100 * hits / snapshots,
                "position_err_l_mean": None, "position_err_l_p95": None,
                "force_err_mean_pct": None, "force_err_p95_pct": None, "force_bias_pct": None,
                "false_positives_per_1000": 1000 * contacts / snapshots,
                "force_held_err_p95_pct": None, "force_held_bias_pct": None}


def plan(quick: bool, bodies) -> list[tuple]:
    """(what, body, indenter, separation, noise) of every row."""
    rows = []
    for body in bodies:
        for kind in ("sphere", "punch"):
            for sep in (None, 2.0, 3.0, 4.0):
                rows.append(("run", body, kind, sep, 1.0))
            for noise in (0.3, 2.0, 5.0):
                rows.append(("run", body, kind, None, noise))
        rows.append(("run", body, "capsule", None, 1.0))
        for noise in NOISES:
            rows.append(("untouched", body, "none", None, noise))
    return rows


def _fmt(x, spec=".1f"):
    return "—" if x is None or (isinstance(x, float) and np.isnan(x)) else format(x, spec)


def table(rows: list[dict]) -> str:
    out = ["| body | indenter | separation | noise (% g) | count exact | silent wrong count | "
           "position error (L) mean / p95 | force error (%) mean / p95 | force bias (%) | "
           "false contacts / 1000 | held force (4 snapshots) p95 (%) |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        sep = "single" if r["separation_l"] is None else f"{r['separation_l']:g} L"
        if r["indenter"] == "none":
            sep = "untouched"
        out.append(f"| {r['body']} | {r['indenter']} | {sep} | {r['noise_pct_g']:g} | "
                   f"{r['count_exact_pct']:.1f} % | {r['silent_wrong_count_pct']:.1f} % | "
                   f"{_fmt(r['position_err_l_mean'], '.2f')} / {_fmt(r['position_err_l_p95'], '.2f')} | "
                   f"{_fmt(r['force_err_mean_pct'])} / {_fmt(r['force_err_p95_pct'])} | "
                   f"{_fmt(r['force_bias_pct'], '+.1f')} | {r['false_positives_per_1000']:.1f} | "
                   f"{_fmt(r['force_held_err_p95_pct'])} |")
    caps = [r for r in rows if "axes_err_pct" in r]
    if caps:
        out += ["", "| body | capsule (finger) at 1 % g | major / minor half-axis error (%) | "
                    "angle error (°) mean / p95 |", "|---|---|---|---|"]
        for r in caps:
            out.append(f"| {r['body']} | {r['snapshots']} snapshots | {r['axes_err_pct'][0]:+.0f} / "
                       f"{r['axes_err_pct'][1]:+.0f} | {r['angle_err_deg_mean']:.1f} / "
                       f"{r['angle_err_deg_p95']:.1f} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="few snapshots (smoke run)")
    ap.add_argument("--json", action="store_true", help="print only JSON")
    ap.add_argument("--body", action="append", choices=sorted(BODIES),
                    help="bodies to run (repeatable; default all)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--force-model", choices=("fit", "sum"), default="fit",
                    help="DetectorSettings.force_model (default fit; sum: the sampled Winkler "
                         "integral, the model before issue 17's per-snapshot work)")
    ap.add_argument("--noise", type=float, action="append",
                    help="only the rows at these noise levels, %% g (repeatable; default all)")
    args = ap.parse_args(argv)
    layouts, snaps, fp_n = (2, 4, 100) if args.quick else (5, 8, 1000)
    bodies = args.body or list(BODIES)
    b = Bench(seed=args.seed, force_model=args.force_model)
    t0 = time.perf_counter()
    todo = plan(args.quick, bodies)
    if args.noise:
        todo = [t for t in todo if t[4] in args.noise]
    rows = []
    for n, (what, body, kind, sep, noise) in enumerate(todo):
        if what == "run":
            rows.append(b.run(body, kind, sep, noise, layouts, snaps))
        else:
            rows.append(b.untouched(body, noise, fp_n))
        el = time.perf_counter() - t0
        print(f"bench_tactile: {n + 1}/{len(todo)} rows, {el:.0f} s, ETA "
              f"{el / (n + 1) * (len(todo) - n - 1):.0f} s", file=sys.stderr)
    res = {"config": {"rows": ROWS, "cols": COLS, "link_length_m": L,
                      "foam": {"thickness_m": LAYER.thickness_m,
                               "youngs_modulus_pa": LAYER.youngs_modulus_pa,
                               "poisson": LAYER.poisson},
                      "bodies": {"block": "top face", "cylinder": "R 0.08 m", "sphere": "R 0.1 m"},
                      "layouts": layouts, "snapshots_per_layout": snaps,
                      "untouched_snapshots": fp_n, "force_model": args.force_model},
           "rows": rows, "wall_s": time.perf_counter() - t0}
    print(json.dumps(res))
    if not args.json:
        print()
        print(table(rows))
        print(f"\n({res['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
