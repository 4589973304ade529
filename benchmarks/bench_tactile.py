"""Tactile benchmark: contacts and forces on the virtual foam block (docs/tactile.md).

Setup: a 14x14-joint sheet, L = 1 cm, on a foam block (h = 20 mm, E = 20 kPa, ν = 0.25; the
defaults of `virtual_sheet.foam.FoamLayer`), white reading noise of the given % g per axis. The
rest shape is learned from 32 untouched snapshots at the same noise (`TactileSensor.learn_rest`);
every snapshot is then estimated with the rest shape as the prior and its contacts found.

Two indenters of the same kind (sphere R = 15 mm, or flat punch a = 7.5 mm), 2 N each, their
centres ``sep`` link lengths apart in a random direction about a random point near the sheet's
centre (``layouts`` placements, ``snapshots`` noisy snapshots of each). Metrics:

* count: fraction of snapshots whose contact count is exactly right;
* position error: distance, in link lengths, between matched detected and true centres, both in
  lattice indices (Hungarian matching, gate 2 L);
* force error: |F_est − F_true| / F_true of matched contacts, %;
* false positives: fraction of untouched snapshots reporting any contact.

Prints JSON (``--json`` only JSON) and markdown tables. ``--quick`` for a smoke run.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from host.analysis.tactile import Foam, TactileSensor, lattice_index  # noqa: E402
from virtual_sheet.foam import (FlatPunch, FoamBlock, FoamLayer, FoamScene, Press,  # noqa: E402
                                SphereIndenter)
from virtual_sheet.geometry import ideal_readings  # noqa: E402
from virtual_sheet.sensor import noisy_readings  # noqa: E402

ROWS = COLS = 14
L = 0.01
FORCE_N = 2.0
INDENTERS = {"sphere": SphereIndenter(0.015), "punch": FlatPunch(0.0075)}


def rng_of(seed: int) -> np.random.Generator:
    return np.random.Generator(np.random.MT19937(seed))


def host_foam(layer: FoamLayer) -> Foam:
    return Foam(layer.thickness_m, layer.youngs_modulus_pa, layer.poisson)


def layout(rng: np.random.Generator, sep: float | None, n: int = 2) -> list[tuple[float, float]]:
    """Centres (x, y) in metres: a random point within ±L/2 of the sheet's middle and, for
    ``sep``, two points ``sep`` L apart in a random direction about it."""
    mid = np.array([-0.5 * L, -0.5 * L]) + rng.uniform(-0.5, 0.5, 2) * L
    if sep is None or n == 1:
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


class Bench:
    """Caches scenes (noise-independent) and learned rest shapes (per noise level)."""

    def __init__(self, layer: FoamLayer = FoamLayer(), seed: int = 7):
        self.layer = layer
        self.foam = host_foam(layer)
        self.seed = seed
        self.rest_scene = FoamScene(FoamBlock(layer), [], ROWS, COLS, L)
        self.r0 = ideal_readings(self.rest_scene.rest_joints)
        self._rest: dict[float, object] = {}
        self._scenes: dict[tuple, tuple] = {}

    def rest(self, noise: float):
        if noise not in self._rest:
            rng = rng_of(self.seed * 1000 + int(noise * 100))
            snaps = [noisy_readings(self.r0, noise, rng) for _ in range(32)]
            self._rest[noise] = TactileSensor.learn_rest(snaps, ROWS, COLS, L)
        return self._rest[noise]

    def scene(self, kind: str, sep: float | None, k: int, n: int = 2):
        key = (kind, sep, k, n)
        if key not in self._scenes:
            rng = rng_of(self.seed * 7919 + k)
            pos = layout(rng, sep, n)
            sc = FoamScene(FoamBlock(self.layer), [Press(INDENTERS[kind], p, FORCE_N) for p in pos],
                           ROWS, COLS, L)
            truth = sc.contacts(0.0)
            P = sc.joints(0.0)
            idx = [lattice_index(sc.rest_joints, t.position) for t in truth]
            self._scenes[key] = (ideal_readings(P), truth, idx)
        return self._scenes[key]

    def run(self, kind: str, sep: float | None, noise: float, layouts: int, snapshots: int,
            n: int = 2) -> dict:
        rest = self.rest(noise)
        rng = rng_of(self.seed * 31 + int(noise * 100) + (0 if sep is None else int(sep * 10)))
        counts, pos_err, force_err, depth_err = [], [], [], []
        for k in range(layouts):
            r, truth, idx = self.scene(kind, sep, k, n)
            sensor = TactileSensor(rest, self.foam)
            for _ in range(snapshots):
                fr = sensor.process(noisy_readings(r, noise, rng))
                counts.append(len(fr.contacts) == len(truth))
                for a, b, dist in match(fr.contacts, idx):
                    pos_err.append(dist)
                    force_err.append(abs(fr.contacts[a].force_n - truth[b].force_n)
                                     / truth[b].force_n * 100)
                    depth_err.append(abs(fr.contacts[a].depth_m - truth[b].max_deflection_m)
                                     / truth[b].max_deflection_m * 100)
        f = np.array(force_err) if force_err else np.array([np.nan])
        p = np.array(pos_err) if pos_err else np.array([np.nan])
        return {"kind": kind, "sep_L": sep, "noise_pct_g": noise, "contacts": n,
                "snapshots": len(counts), "count_exact": float(np.mean(counts)),
                "pos_err_L_mean": float(np.mean(p)), "pos_err_L_p95": float(np.percentile(p, 95)),
                "force_err_pct_mean": float(np.mean(f)),
                "force_err_pct_p95": float(np.percentile(f, 95)),
                "depth_err_pct_mean": float(np.mean(depth_err)) if depth_err else float("nan")}

    def false_positives(self, noise: float, snapshots: int) -> dict:
        rest = self.rest(noise)
        rng = rng_of(self.seed * 17 + int(noise * 100))
        sensor = TactileSensor(rest, self.foam)
        hits = contacts = 0
        for _ in range(snapshots):
            fr = sensor.process(noisy_readings(self.r0, noise, rng))
            hits += bool(fr.contacts)
            contacts += len(fr.contacts)
        return {"noise_pct_g": noise, "snapshots": snapshots,
                "fp_rate": hits / snapshots, "fp_contacts": contacts}


def _row(r: dict) -> str:
    sep = "single" if r["sep_L"] is None else f"{r['sep_L']:g} L"
    return (f"| {r['kind']} | {sep} | {r['noise_pct_g']:g} | {r['snapshots']} | "
            f"{100 * r['count_exact']:.1f} % | {r['pos_err_L_mean']:.2f} / {r['pos_err_L_p95']:.2f} | "
            f"{r['force_err_pct_mean']:.1f} / {r['force_err_pct_p95']:.1f} | "
            f"{r['depth_err_pct_mean']:.1f} |")


HEADER = ("| indenter | separation | noise (% g) | snapshots | count exact | "
          "position error (L) mean / p95 | force error (%) mean / p95 | depth error (%) |\n"
          "|---|---|---|---|---|---|---|---|")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="few snapshots (smoke run)")
    ap.add_argument("--json", action="store_true", help="print only JSON")
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args(argv)
    layouts, snaps, fp_n = (2, 4, 100) if args.quick else (6, 10, 1000)
    b = Bench(seed=args.seed)
    t0 = time.perf_counter()
    res = {"config": {"rows": ROWS, "cols": COLS, "link_length_m": L, "force_n": FORCE_N,
                      "foam": {"thickness_m": b.layer.thickness_m,
                               "youngs_modulus_pa": b.layer.youngs_modulus_pa,
                               "poisson": b.layer.poisson},
                      "layouts": layouts, "snapshots_per_layout": snaps}}
    res["main"] = [b.run(kind, sep, 1.0, layouts, snaps) for kind in INDENTERS
                   for sep in (None, 3, 4, 6)]
    for r in res["main"]:
        if r["sep_L"] is None:
            r["contacts"] = 1
    res["noise"] = [b.run(kind, 4, noise, layouts, snaps) for kind in INDENTERS
                    for noise in (0.3, 1.0, 2.0, 5.0)]
    res["separation"] = [b.run(kind, sep, 1.0, layouts, snaps) for kind in INDENTERS
                         for sep in (2, 3, 4, 6)]
    res["false_positives"] = [b.false_positives(noise, fp_n) for noise in (0.3, 1.0, 2.0, 5.0)]
    res["wall_s"] = time.perf_counter() - t0
    if args.json:
        print(json.dumps(res, indent=1))
        return 0
    print(json.dumps(res))
    print()
    print(f"Virtual foam block 14x14, L = 1 cm, 2 N per indenter (sphere R 15 mm, punch a 7.5 mm), "
          f"foam h 20 mm, E 20 kPa, nu 0.25; {layouts} layouts x {snaps} snapshots per row.\n")
    print("**At 1 % g** (single contact; two contacts >= 3 L apart)\n")
    print(HEADER)
    for r in res["main"]:
        print(_row(r))
    print("\n**Noise** (two contacts 4 L apart)\n")
    print(HEADER)
    for r in res["noise"]:
        print(_row(r))
    print("\n**Separation** (1 % g)\n")
    print(HEADER)
    for r in res["separation"]:
        print(_row(r))
    print("\n**False positives** (untouched sheet)\n")
    print("| noise (% g) | snapshots | snapshots with a contact |\n|---|---|---|")
    for r in res["false_positives"]:
        print(f"| {r['noise_pct_g']:g} | {r['snapshots']} | {100 * r['fp_rate']:.2f} % |")
    print(f"\n({res['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
