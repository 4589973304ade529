"""Tactile benchmark: contacts, forces and footprints on every virtual foam body, fingers, close
pairs, presses in time and the speed of the whole step (docs/tactile.md).

Setup: a 14x14-joint sheet, L = 1 cm, on a foam block, a cylinder (R = 8 cm) and a sphere
(R = 10 cm), foam h = 20 mm, E = 20 kPa, ν = 0.25 (`virtual_sheet.foam.FoamLayer`'s defaults;
on the curved bodies the layer is softer, `FoamBody.contact_layer`), white reading noise of the
given % g per axis. The rest shape is learned from 32 untouched snapshots at the same noise
(`TactileSensor.learn_rest`); every snapshot is then estimated with the rest shape as the prior and
its contacts found, one `TactileSensor` per placement (it tracks over the placement's snapshots).

Sections (``--section``, repeatable; default all):

* ``static`` — indenters of one kind (sphere R = 15 mm, flat punch a = 7.5 mm, 2 N each; a
  capsule "finger" R = 10 mm, half-length 20 mm, 3 N), one, or two ``separation_l`` link
  lengths apart (round ones in a random direction; fingers side by side, parallel), at a random
  angle about a random point within L/2 of the sheet's middle (``layouts`` placements,
  ``snapshots`` noisy snapshots of each). One JSON row per (body, indenter, separation, noise);
  1000 untouched snapshots per body and noise.
* ``sweep`` — pairs of spheres and of fingers at 1-4 L (1 % g): where the lattice's sampling
  stops separating two contacts.
* ``presses`` — a finger pressed, held and released within a second (50 ms ramps, 0.5 s held),
  and one sliding at 10 cm/s while held, at 145 snapshots/s (1 % g): one track from onset to
  release, the onset and release times against the truth, the force-time curve.
* ``speed`` — the whole tactile step (estimate, deformation, contacts, fit, tracking) for a
  14x14 sheet with three contacts held (a sphere, a punch and a finger), one process on one
  core (CPU time), beside the estimator alone measured in the same run (its 14x14 rate on a
  quiet machine is in docs/estimator.md: the ratio says how loaded this one is).

Row fields (static, sweep):

* ``count_exact_pct``; ``silent_wrong_count_pct``: wrong count and no contact flagged
  ``ambiguous`` (misses included); ``ambiguous_pct``: snapshots with a contact flagged;
  ``resolved_pct`` (pairs): snapshots with two contacts, each within 0.5 L of a true one and
  its force within 20 %;
* ``position_err_l_mean`` / ``_p95``: matched centres, link lengths (Hungarian, gate 2 L);
* ``force_err_mean_pct`` / ``_p95_pct`` / ``force_bias_pct``: (F_est − F_true) / F_true per matched
  contact and snapshot (an ambiguous contact holding two true ones is compared with their sum);
  ``force_z_p95``: the 95th percentile of |F_est − F_true| / force_std_n (1.96 if the stated
  uncertainty were exact and Gaussian);
* ``false_positives_per_1000``: detected contacts matched to no true one per 1000 snapshots;
* ``force_held_err_p95_pct`` / ``force_held_bias_pct``: `Contact.force_n_held` (the track's mean
  over its last 4 snapshots);
* ``axes_err_pct_mean`` / ``axes_err_pct_p95`` (major, minor): the half-depth footprint against
  the true dent's (`FoamScene.footprints`, same definition), signed mean and p95 of |err|;
  ``angle_err_deg_mean`` / ``_p95`` where the truth is elongated (fingers);
  ``contact_axes_err_pct_mean`` / ``_p95``: the pressure patch against the true pressure's.

``--force-model sum`` gives the sampled Winkler integral for comparison; ``--quick`` a smoke
run; ``--json`` prints only JSON; ``--body`` and ``--noise`` select rows; ``--figure PNG`` draws
estimated against true footprints and forces for every body and indenter
(`host.analysis.tactile.plot.footprint_figure`). Progress goes to stderr.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
             "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"  # one core (the speed section's premise), before numpy is imported

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from host.analysis.estimator import estimate  # noqa: E402
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
SECTIONS = ("static", "sweep", "presses", "speed")
RATE_HZ = 145.0


def rng_of(*seed: int) -> np.random.Generator:
    return np.random.Generator(np.random.MT19937(list(seed)))


def indenter(kind: str, angle: float):
    if kind == "sphere":
        return SphereIndenter(0.015)
    if kind == "punch":
        return FlatPunch(0.0075)
    return CapsuleIndenter(0.01, 0.02, angle_rad=angle)


def layout(rng: np.random.Generator, kind: str, sep: float | None
           ) -> list[tuple[tuple[float, float], float]]:
    """Centres ``(u, v)`` (metres) and angles: a random point within ±L/2 of the sheet's middle
    and, for ``sep``, two points ``sep`` L apart about it — along a random direction for round
    indenters, across the common random direction of two fingers (side by side)."""
    mid = np.array([-0.5 * L, -0.5 * L]) + rng.uniform(-0.5, 0.5, 2) * L
    a = float(rng.uniform(-np.pi / 2, np.pi / 2))
    if sep is None:
        return [(tuple(mid), a)]
    e = np.array([np.cos(a), np.sin(a)])
    if kind == "capsule":
        e = np.array([-e[1], e[0]])
    d = 0.5 * sep * L * e
    return [(tuple(mid - d), a), (tuple(mid + d), a)]


def match(det, truth_idx, gate=2.0):
    """Hungarian matching of detected contact indices to true ones; pairs within ``gate`` L."""
    from scipy.optimize import linear_sum_assignment
    if not det or not truth_idx:
        return []
    D = np.linalg.norm(np.array([c.index for c in det])[:, None, :]
                       - np.array(truth_idx)[None, :, :], axis=2)
    r, c = linear_sum_assignment(D)
    return [(a, b, D[a, b]) for a, b in zip(r, c) if D[a, b] <= gate]


def _angle_diff(a: float, b: float) -> float:
    return float(abs((a - b + np.pi / 2) % np.pi - np.pi / 2))


def _p95(x) -> float | None:
    x = np.asarray(x, float)
    return float(np.percentile(np.abs(x), 95)) if x.size else None


def _mean(x) -> float | None:
    x = np.asarray(x, float)
    return float(np.mean(x)) if x.size else None


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
            rng = rng_of(self.seed, 2, k, 0 if sep is None else int(sep * 10),
                         {"sphere": 0, "punch": 1, "capsule": 2}[kind])
            presses = [Press(indenter(kind, a), c, FORCE_N[kind]) for c, a in layout(rng, kind, sep)]
            sc = FoamScene(BODIES[body], presses, ROWS, COLS, L)
            truth = sc.contacts(0.0)
            idx = [lattice_index(sc.rest_joints, t.position) for t in truth]
            self._scenes[key] = (ideal_readings(sc.joints(0.0)), truth, idx, sc.footprints(0.0))
        return self._scenes[key]

    def run(self, body: str, kind: str, sep: float | None, noise: float, layouts: int,
            snapshots: int, keep=None) -> dict:
        rest = self.rest(body, noise)
        rng = rng_of(self.seed, 3, int(noise * 100), 0 if sep is None else int(sep * 10))
        n_snap = exact = silent = extra = ambiguous = resolved = 0
        pos_err, f_err, fh_err, fz, axes_err, ang_err, cax_err = ([] for _ in range(7))
        for k in range(layouts):
            r, truth, idx, fps = self.scene(body, kind, sep, k)
            sensor = TactileSensor(rest, self.foam, settings=self.settings)
            for s in range(snapshots):
                fr = sensor.process(noisy_readings(r, noise, rng), t_s=s / RATE_HZ)
                n_snap += 1
                cs = fr.contacts
                if keep is not None and s == snapshots - 1:
                    keep.append((body, kind, sep, k, fr, truth, idx, fps))
                exact += len(cs) == len(truth)
                flagged = any(c.ambiguous for c in cs)
                ambiguous += flagged
                silent += len(cs) != len(truth) and not flagged
                pairs = match(cs, idx)
                extra += len(cs) - len(pairs)
                ok = 0
                for a, b, dist in pairs:
                    c = cs[a]
                    pos_err.append(dist)
                    f_true = truth[b].force_n
                    if c.ambiguous and len(cs) < len(truth):
                        f_true = sum(t.force_n for t in truth)  # one contact holding both
                    e = (c.force_n - f_true) / f_true
                    ok += abs(e) <= 0.2 and dist <= 0.5
                    f_err.append(e * 100)
                    fz.append(abs(c.force_n - f_true) / max(c.force_std_n, 1e-12))
                    fh_err.append((c.force_n_held - f_true) / f_true * 100)
                    if len(cs) == len(truth):
                        fp = fps[b]
                        axes_err.append((c.axes_m / np.array(fp.dent_axes_m) - 1) * 100)
                        cax_err.append((c.contact_axes_m / np.array(fp.pressure_axes_m) - 1) * 100)
                        if kind == "capsule":  # lattice i runs along surface u on every body
                            ang_err.append(np.degrees(_angle_diff(c.angle_rad, fp.dent_angle_rad)))
                resolved += len(truth) == 2 and len(cs) == 2 and ok == 2
        f = np.array(f_err)
        row = {"body": body, "indenter": kind, "separation_l": sep, "noise_pct_g": noise,
               "force_n": FORCE_N[kind], "snapshots": n_snap,
               "count_exact_pct": 100 * exact / n_snap,
               "silent_wrong_count_pct": 100 * silent / n_snap,
               "ambiguous_pct": 100 * ambiguous / n_snap,
               "resolved_pct": 100 * resolved / n_snap if sep is not None else None,
               "position_err_l_mean": _mean(pos_err), "position_err_l_p95": _p95(pos_err),
               "force_err_mean_pct": _mean(np.abs(f)), "force_err_p95_pct": _p95(f),
               "force_bias_pct": _mean(f), "force_z_p95": _p95(fz),
               "false_positives_per_1000": 1000 * extra / n_snap,
               "force_held_err_p95_pct": _p95(fh_err), "force_held_bias_pct": _mean(fh_err)}
        if axes_err:
            a, ca = np.array(axes_err), np.array(cax_err)
            row["axes_err_pct_mean"] = [float(x) for x in a.mean(axis=0)]
            row["axes_err_pct_p95"] = [float(x) for x in np.percentile(np.abs(a), 95, axis=0)]
            row["contact_axes_err_pct_mean"] = [float(x) for x in ca.mean(axis=0)]
            row["contact_axes_err_pct_p95"] = [float(x) for x in
                                               np.percentile(np.abs(ca), 95, axis=0)]
        if ang_err:
            row["angle_err_deg_mean"] = float(np.mean(ang_err))
            row["angle_err_deg_p95"] = float(np.percentile(ang_err, 95))
        return row

    def untouched(self, body: str, noise: float, snapshots: int) -> dict:
        rest = self.rest(body, noise)
        rng = rng_of(self.seed, 4, int(noise * 100))
        sensor = TactileSensor(rest, self.foam, settings=self.settings)
        hits = contacts = 0
        for s in range(snapshots):
            fr = sensor.process(noisy_readings(self.r0(body), noise, rng), t_s=s / RATE_HZ)
            hits += bool(fr.contacts)
            contacts += len(fr.contacts)
        return {"body": body, "indenter": "none", "separation_l": None, "noise_pct_g": noise,
                "force_n": 0.0, "snapshots": snapshots,
                "count_exact_pct": 100 * (snapshots - hits) / snapshots,
                "silent_wrong_count_pct": 100 * hits / snapshots, "ambiguous_pct": 0.0,
                "resolved_pct": None, "position_err_l_mean": None, "position_err_l_p95": None,
                "force_err_mean_pct": None, "force_err_p95_pct": None, "force_bias_pct": None,
                "force_z_p95": None, "false_positives_per_1000": 1000 * contacts / snapshots,
                "force_held_err_p95_pct": None, "force_held_bias_pct": None}

    def press(self, body: str, slide: bool, noise: float = 1.0) -> dict:
        """A finger pressed at 0.1 s over 50 ms to 3 N, held, released from 0.65 s over 50 ms
        (force 0 again at 0.7 s), 145 snapshots/s from 0 to 1 s; ``slide``: moving at 10 cm/s
        along its own axis from the onset."""
        rest = self.rest(body, noise)
        rng = rng_of(self.seed, 5, int(slide))
        ang = 0.4
        v = (0.1 * np.cos(ang), 0.1 * np.sin(ang)) if slide else (0.0, 0.0)
        start = (-0.025 * np.cos(ang) - 0.005, -0.025 * np.sin(ang) - 0.005) if slide \
            else (-0.005, -0.005)
        t_on, t_off, ramp = 0.1, 0.65, 0.05
        p = Press(CapsuleIndenter(0.01, 0.02, angle_rad=ang), start, 3.0, t_on_s=t_on,
                  t_off_s=t_off, ramp_s=ramp, velocity_mps=v)
        sc = FoamScene(BODIES[body], [p], ROWS, COLS, L)
        sensor = TactileSensor(rest, self.foam, settings=self.settings)
        n = int(RATE_HZ) + 1
        ids, events, curve = set(), [], []
        for s in range(n):
            t = s / RATE_HZ
            fr = sensor.process(noisy_readings(ideal_readings(sc.joints(t)), noise, rng), t_s=t)
            events += fr.events
            ids |= {c.id for c in fr.contacts}
            f_true = p.force_at(t)
            f_est = sum(c.force_n for c in fr.contacts)
            curve.append((t, f_true, f_est, len(fr.contacts)))
        for s in range(4):   # the release event comes max_missed snapshots after the release
            t = (n + s) / RATE_HZ
            events += sensor.process(noisy_readings(ideal_readings(sc.joints(t)), noise, rng),
                                     t_s=t).events
        onsets = [e for e in events if e.kind == "onset"]
        releases = [e for e in events if e.kind == "release"]
        T = 1.0 / RATE_HZ
        c = np.array(curve)
        hold = (c[:, 0] >= t_on + ramp) & (c[:, 0] <= t_off)
        press = c[:, 1] > 0
        return {"body": body, "case": "slide" if slide else "press", "noise_pct_g": noise,
                "rate_hz": RATE_HZ, "force_n": 3.0, "ramp_s": ramp, "hold_s": t_off - t_on - ramp,
                "tracks": len(ids), "onsets": len(onsets), "releases": len(releases),
                "onset_err_snapshots": (onsets[0].t_s - t_on) / T if onsets else None,
                "release_err_snapshots": (releases[0].t_s - (t_off + ramp)) / T
                if releases else None,
                "snapshots_counted_wrong_while_pressed": int(np.sum(c[press, 3] != 1)),
                "snapshots_with_contact_while_untouched": int(np.sum(c[~press, 3] != 0)),
                "hold_force_err_p95_pct": _p95((c[hold, 2] - c[hold, 1]) / c[hold, 1] * 100),
                "hold_force_bias_pct": _mean((c[hold, 2] - c[hold, 1]) / c[hold, 1] * 100),
                "curve_err_p95_pct_of_peak": _p95((c[press, 2] - c[press, 1]) / 3.0 * 100)}

    def speed(self, repeats: int = 3, snapshots: int = 60) -> dict:
        """CPU time per tactile step (three contacts held) and per estimate alone, interleaved."""
        rest = self.rest("block", 1.0)
        presses = [Press(SphereIndenter(0.015), (-0.03, -0.03), 2.0),
                   Press(FlatPunch(0.0075), (0.03, -0.025), 2.0),
                   Press(CapsuleIndenter(0.01, 0.02, 0.5), (0.0, 0.03), 3.0)]
        sc = FoamScene(BODIES["block"], presses, ROWS, COLS, L)
        r = ideal_readings(sc.joints(0.0))
        rng = rng_of(self.seed, 6)
        rs = [noisy_readings(r, 1.0, rng) for _ in range(snapshots)]
        sensor = TactileSensor(rest, self.foam, settings=self.settings)
        t = 0.0
        first = time.process_time()
        fr = sensor.process(rs[0], t_s=t)
        first = time.process_time() - first
        counts = []
        tac, est = [], []
        for rep in range(repeats):
            prev = None
            t0 = time.process_time()
            for x in rs:
                prev = estimate(x, ROWS, COLS, L, rest=rest.yaws, previous=prev)
            est.append(snapshots / (time.process_time() - t0))
            t0 = time.process_time()
            for x in rs:
                t += 1.0 / RATE_HZ
                fr = sensor.process(x, t_s=t)
                counts.append(len(fr.contacts))
            tac.append(snapshots / (time.process_time() - t0))
        load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
        return {"lattice": f"{ROWS}x{COLS}", "contacts": 3, "snapshots": snapshots,
                "repeats": repeats, "tactile_steps_per_s": tac, "estimates_per_s": est,
                "tactile_over_estimate": [e / s for e, s in zip(est, tac)],
                "first_snapshot_ms": first * 1e3, "contacts_seen": sorted(set(counts)),
                "load_average": [float(x) for x in load],
                "kernel": __import__("host.analysis.tactile.response",
                                     fromlist=["USE_KERNEL"]).USE_KERNEL}


def plan(quick: bool, bodies) -> list[tuple]:
    """(section, body, indenter, separation, noise) of every static row."""
    rows = []
    for body in bodies:
        for kind in ("sphere", "punch", "capsule"):
            for sep in (None, 2.0, 3.0, 4.0):
                rows.append(("static", body, kind, sep, 1.0))
            for noise in (0.3, 2.0, 5.0):
                rows.append(("static", body, kind, None, noise))
        for noise in NOISES:
            rows.append(("untouched", body, "none", None, noise))
    return rows


def _fmt(x, spec=".1f"):
    return "—" if x is None or (isinstance(x, float) and np.isnan(x)) else format(x, spec)


def table(rows: list[dict]) -> str:
    out = ["| body | indenter | separation | noise (% g) | count exact | silent wrong | ambiguous | "
           "resolved | position (L) mean / p95 | force (%) mean / p95 | bias (%) | z p95 | "
           "false / 1000 | held p95 (%) |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        sep = "single" if r["separation_l"] is None else f"{r['separation_l']:g} L"
        if r["indenter"] == "none":
            sep = "untouched"
        out.append(f"| {r['body']} | {r['indenter']} | {sep} | {r['noise_pct_g']:g} | "
                   f"{r['count_exact_pct']:.1f} % | {r['silent_wrong_count_pct']:.1f} % | "
                   f"{r['ambiguous_pct']:.1f} % | {_fmt(r['resolved_pct'])} | "
                   f"{_fmt(r['position_err_l_mean'], '.2f')} / {_fmt(r['position_err_l_p95'], '.2f')} | "
                   f"{_fmt(r['force_err_mean_pct'])} / {_fmt(r['force_err_p95_pct'])} | "
                   f"{_fmt(r['force_bias_pct'], '+.1f')} | {_fmt(r['force_z_p95'])} | "
                   f"{r['false_positives_per_1000']:.1f} | {_fmt(r['force_held_err_p95_pct'])} |")
    fp = [r for r in rows if "axes_err_pct_mean" in r]
    if fp:
        out += ["", "| body | indenter | separation | noise (% g) | half-depth footprint: major / "
                    "minor error (%) mean, p95 | angle error (°) mean / p95 | contact patch: "
                    "major / minor error (%) mean, p95 |", "|---|---|---|---|---|---|---|"]
        for r in fp:
            sep = "single" if r["separation_l"] is None else f"{r['separation_l']:g} L"
            m, p = r["axes_err_pct_mean"], r["axes_err_pct_p95"]
            cm, cp = r["contact_axes_err_pct_mean"], r["contact_axes_err_pct_p95"]
            ang = (f"{r['angle_err_deg_mean']:.1f} / {r['angle_err_deg_p95']:.1f}"
                   if "angle_err_deg_mean" in r else "—")
            out.append(f"| {r['body']} | {r['indenter']} | {sep} | {r['noise_pct_g']:g} | "
                       f"{m[0]:+.1f} / {m[1]:+.1f}, {p[0]:.1f} / {p[1]:.1f} | {ang} | "
                       f"{cm[0]:+.1f} / {cm[1]:+.1f}, {cp[0]:.1f} / {cp[1]:.1f} |")
    return "\n".join(out)


def press_table(rows: list[dict]) -> str:
    out = ["| body | case | tracks | onset / release error (snapshots) | wrong count while "
           "pressed | contact while untouched | hold force p95 / bias (%) | curve p95 (% of "
           "peak) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['body']} | {r['case']} | {r['tracks']} | "
                   f"{_fmt(r['onset_err_snapshots'], '+.1f')} / "
                   f"{_fmt(r['release_err_snapshots'], '+.1f')} | "
                   f"{r['snapshots_counted_wrong_while_pressed']} | "
                   f"{r['snapshots_with_contact_while_untouched']} | "
                   f"{_fmt(r['hold_force_err_p95_pct'])} / {_fmt(r['hold_force_bias_pct'], '+.1f')}"
                   f" | {_fmt(r['curve_err_p95_pct_of_peak'])} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="few snapshots (smoke run)")
    ap.add_argument("--json", action="store_true", help="print only JSON")
    ap.add_argument("--section", action="append", choices=SECTIONS,
                    help="sections to run (repeatable; default all)")
    ap.add_argument("--body", action="append", choices=sorted(BODIES),
                    help="bodies to run (repeatable; default all)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--force-model", choices=("fit", "sum"), default="fit",
                    help="DetectorSettings.force_model (default fit; sum: the sampled Winkler "
                         "integral)")
    ap.add_argument("--noise", type=float, action="append",
                    help="only the static rows at these noise levels, %% g (repeatable)")
    ap.add_argument("--figure", metavar="PNG",
                    help="also draw estimated against true footprints and forces, every body "
                         "and indenter (one placement each, 1 %% g) to this PNG")
    args = ap.parse_args(argv)
    layouts, snaps, fp_n = (2, 4, 100) if args.quick else (5, 8, 1000)
    bodies = args.body or list(BODIES)
    sections = args.section or list(SECTIONS)
    b = Bench(seed=args.seed, force_model=args.force_model)
    t0 = time.perf_counter()
    todo = []
    if "static" in sections:
        todo += [t for t in plan(args.quick, bodies) if not args.noise or t[4] in args.noise]
    if "sweep" in sections:
        todo += [("sweep", body, kind, sep, 1.0) for body in bodies
                 for kind in ("sphere", "capsule") for sep in (1.0, 1.5, 2.0, 2.5, 3.0)]
    if "presses" in sections:
        todo += [("presses", body, "capsule", slide, 1.0) for body in bodies
                 for slide in (False, True)]
    if "speed" in sections:
        todo.append(("speed", "block", None, None, 1.0))
    res = {"config": {"rows": ROWS, "cols": COLS, "link_length_m": L,
                      "foam": {"thickness_m": LAYER.thickness_m,
                               "youngs_modulus_pa": LAYER.youngs_modulus_pa,
                               "poisson": LAYER.poisson},
                      "bodies": {"block": "top face", "cylinder": "R 0.08 m", "sphere": "R 0.1 m"},
                      "layouts": layouts, "snapshots_per_layout": snaps,
                      "untouched_snapshots": fp_n, "force_model": args.force_model,
                      "settings": {k: getattr(b.settings, k) for k in
                                   b.settings.__dataclass_fields__}},
           "rows": [], "sweep": [], "presses": [], "speed": None}
    keep = [] if args.figure else None
    for n, (what, body, kind, sep, noise) in enumerate(todo):
        if what == "static":
            draw = noise == 1.0 and (sep is None or (sep == 2.0 and kind == "capsule"))
            res["rows"].append(b.run(body, kind, sep, noise, layouts, snaps,
                                     keep if draw else None))
        elif what == "untouched":
            res["rows"].append(b.untouched(body, noise, fp_n))
        elif what == "sweep":
            res["sweep"].append(b.run(body, kind, sep, noise, layouts, snaps))
        elif what == "presses":
            res["presses"].append(b.press(body, bool(sep)))
        else:
            res["speed"] = b.speed(repeats=1 if args.quick else 3)
        el = time.perf_counter() - t0
        print(f"bench_tactile: {n + 1}/{len(todo)} rows, {el:.0f} s, ETA "
              f"{el / (n + 1) * (len(todo) - n - 1):.0f} s", file=sys.stderr)
    if args.figure:
        from host.analysis.tactile.plot import footprint_figure
        footprint_figure(keep, args.figure, L)
        print(f"bench_tactile: figure written to {args.figure}", file=sys.stderr)
    res["wall_s"] = time.perf_counter() - t0
    print(json.dumps(res))
    if not args.json:
        for title, rows in (("", res["rows"]), ("sweep", res["sweep"])):
            if rows:
                print(f"\n{title}\n" + table(rows))
        if res["presses"]:
            print("\n" + press_table(res["presses"]))
        if res["speed"]:
            s = res["speed"]
            print(f"\nspeed: {s['lattice']}, {s['contacts']} contacts: tactile step "
                  f"{', '.join(f'{x:.0f}' for x in s['tactile_steps_per_s'])} /s; estimator "
                  f"alone {', '.join(f'{x:.0f}' for x in s['estimates_per_s'])} /s; load "
                  f"{', '.join(f'{x:.2f}' for x in s['load_average'])}")
        print(f"\n({res['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
