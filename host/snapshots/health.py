"""Chip health, continuously, from the snapshots a sheet streams (docs/calibration.md, "Health").

Sans-I/O: `HealthChecker.update` takes one snapshot's readings, its validity mask and ``now``, and
returns the events it found; `host.session.core.Host` feeds it every snapshot it hands out (``host.snapshots.health
= HealthChecker(...)``) and reports the events as host events.

Two checks, both on *static* stretches only (the sheet still: `StaticDetector`, a variance
threshold), when Assumption 1 holds and every chip must read gravity alone:

* **Magnitude.** Every ``window`` still snapshots, each chip's mean reading ``m_k``: a calibrated
  chip reads ``|m_k| = g`` to within its residual (about 1 mg); ``|m_k| − g`` is the chip's
  deviation (`HealthChecker.deviation`). Beyond ``magnitude_threshold_mps2`` (default 20 mg) the
  chip is flagged (event ``"health_magnitude"``), and cleared when it comes back
  (``"health_magnitude_ok"``). Uncalibrated realistic chips deviate by up to ~50 mg: the check is
  meant for a calibrated sheet.
* **Bias shift.** Between two still windows each chip's mean changes by ``Δ_k``; a sheet that moved
  or bent changes neighbouring chips alike, so ``Δ_k`` is compared with the component-wise median of
  ``Δ`` over the chip's neighbours of the same kind (i-links (i±1, j), (i, j±1); j-links likewise;
  their frames are nearly parallel). A chip whose ``|Δ_k − median|`` exceeds
  ``shift_threshold_mps2`` (default 10 mg) and ``shift_factor`` (default 5) times the median of that
  quantity over the sheet jumped against its neighbours: event ``"health_bias_shift"``.

>>> import numpy as np
>>> hc = HealthChecker(3, 3, window=3)
>>> flat = np.tile([0.0, 0.0, 9.80665], (12, 1))
>>> [len(hc.update(flat, None, t)) for t in range(6)]
[0, 0, 0, 0, 0, 0]
>>> flat[1, 2] += 0.5   # chip 1 reads 51 mg too much
>>> [e.kind for t in range(6, 12) for e in hc.update(flat, None, t)]
['health_magnitude', 'health_bias_shift']
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from host.analysis.calibration import G0, StaticDetector
from protocol.lattice import Lattice

__all__ = ["HealthChecker", "HealthEvent"]

_MG = G0 / 1000.0


@dataclass(frozen=True, slots=True)
class HealthEvent:
    """One finding: ``kind`` in {"health_magnitude", "health_magnitude_ok", "health_bias_shift"},
    the ``link``, ``value`` (m/s²: the deviation or the jump), ``t`` (the ``now`` it was found)."""

    t: float
    kind: str
    link: int
    value: float
    detail: str


def _neighbours(lat: Lattice) -> list[np.ndarray]:
    """Same-kind neighbour links of every link (lattice order)."""
    out: list[np.ndarray] = []
    for k in range(lat.n_links):
        ln = lat.link(k)
        rows = lat.rows - 1 if ln.axis == 0 else lat.rows
        cols = lat.cols if ln.axis == 0 else lat.cols - 1
        nb = [lat.index_of(ln.axis, i, j) for i, j in ((ln.i - 1, ln.j), (ln.i + 1, ln.j), (ln.i, ln.j - 1),
                                                        (ln.i, ln.j + 1)) if 0 <= i < rows and 0 <= j < cols]
        out.append(np.array(nb, dtype=int))
    return out


class HealthChecker:
    """Per-chip |reading| ≈ g and bias-shift checks on still snapshots (module docstring).

    Parameters
    ----------
    rows, cols : int
        Joints of the lattice.
    window : int
        Still snapshots per averaged window (default 25); also the stillness window.
    still_threshold_mps2 : float
        `StaticDetector` threshold, m/s² (default 1 % g).
    magnitude_threshold_mps2 : float
        Flag a chip whose ``| |m_k| − g |`` exceeds this (default 20 mg = 0.196 m/s²).
    shift_threshold_mps2, shift_factor : float
        Bias-shift thresholds (default 10 mg and 5).
    """

    def __init__(self, rows: int, cols: int, *, window: int = 25, still_threshold_mps2: float = 0.098,
                 magnitude_threshold_mps2: float = 20 * _MG, shift_threshold_mps2: float = 10 * _MG,
                 shift_factor: float = 5.0) -> None:
        self.lattice = Lattice(int(rows), int(cols))
        for name, v in (("magnitude_threshold_mps2", magnitude_threshold_mps2),
                        ("shift_threshold_mps2", shift_threshold_mps2), ("shift_factor", shift_factor)):
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"Invalid {name}: {v!r} (need a finite value > 0)")
        n = self.lattice.n_links
        self.detector = StaticDetector(n, window=window, threshold_mps2=still_threshold_mps2)
        self.window = int(window)
        self.magnitude_threshold_mps2 = float(magnitude_threshold_mps2)
        self.shift_threshold_mps2 = float(shift_threshold_mps2)
        self.shift_factor = float(shift_factor)
        self._nb = _neighbours(self.lattice)
        self._acc: list[np.ndarray] = []
        self._previous: np.ndarray | None = None  # last still window's means
        self.deviation = np.full(n, np.nan)  #: latest ``|m_k| − g`` per chip, m/s² (NaN: not seen still)
        self.flagged = np.zeros(n, dtype=bool)  #: chips currently beyond the magnitude threshold
        self.windows = 0  #: still windows evaluated
        self.shifts = 0  #: bias shifts reported

    def update(self, readings: np.ndarray, valid: np.ndarray | None, now: float) -> list[HealthEvent]:
        """One snapshot: readings (n_links, 3) m/s² (NaN where invalid), ``valid`` (n_links,) or
        None, ``now`` seconds (stamped on the events). Returns the events found (often none)."""
        n = self.lattice.n_links
        r = np.asarray(readings, dtype=float)
        if r.shape != (n, 3):
            raise ValueError(f"Expected `readings` to have shape ({n}, 3), got {r.shape}.")
        ok = np.isfinite(r).all(axis=1)
        if valid is not None:
            ok &= np.asarray(valid, dtype=bool)
        r = np.where(ok[:, None], r, np.nan)
        if not self.detector.update(r):
            self._acc = []
            return []
        self._acc.append(r)
        if len(self._acc) < self.window:
            return []
        stack = np.array(self._acc)  # (window, n, 3)
        count = np.isfinite(stack).all(axis=2).sum(axis=0)
        mean = np.nansum(stack, axis=0) / np.maximum(count, 1)[:, None]
        spread = np.sqrt(np.nansum((stack - mean) ** 2, axis=(0, 2)) / np.maximum(count, 1) / 3)
        # a chip judged needs half the window, and to have been still itself
        use = (count >= max(2, self.window // 2)) & (spread < self.detector.threshold_mps2)
        mean = np.where(use[:, None], mean, np.nan)
        self._acc = []
        self.windows += 1
        return self._magnitude(mean, now) + self._shift(mean, now)

    def _magnitude(self, mean: np.ndarray, now: float) -> list[HealthEvent]:
        dev = np.linalg.norm(mean, axis=1) - G0
        seen = np.isfinite(dev)
        self.deviation = np.where(seen, dev, self.deviation)
        bad = seen & (np.abs(dev) > self.magnitude_threshold_mps2)
        good = seen & ~bad
        events = []
        for k in np.flatnonzero(bad & ~self.flagged).tolist():
            events.append(HealthEvent(now, "health_magnitude", k, float(dev[k]),
                                      f"link {k} reads |f| = {G0 + dev[k]:.4f} m/s² on a still sheet: "
                                      f"{dev[k] / _MG:+.1f} mg from g (threshold "
                                      f"{self.magnitude_threshold_mps2 / _MG:.0f} mg)"))
        for k in np.flatnonzero(good & self.flagged).tolist():
            events.append(HealthEvent(now, "health_magnitude_ok", k, float(dev[k]),
                                      f"link {k} reads g again ({dev[k] / _MG:+.1f} mg)"))
        self.flagged = (self.flagged | bad) & ~good
        return events

    def _shift(self, mean: np.ndarray, now: float) -> list[HealthEvent]:
        prev = self._previous
        self._previous = mean if prev is None else np.where(np.isfinite(mean), mean, prev)
        if prev is None:
            return []
        d = mean - prev  # (n, 3); NaN where a chip was missing in either window
        known = np.isfinite(d).all(axis=1)

        def jumps(excluded: np.ndarray) -> np.ndarray:
            e = np.full(len(d), np.nan)
            for k, nb in enumerate(self._nb):
                nb = nb[known[nb] & ~excluded[nb]]
                if len(nb) >= 2 and known[k]:
                    e[k] = np.linalg.norm(d[k] - np.median(d[nb], axis=0))
            return e

        excluded = np.zeros(len(d), dtype=bool)
        e = jumps(excluded)
        if not np.isfinite(e).any():
            return []
        limit = max(self.shift_threshold_mps2, self.shift_factor * float(np.nanmedian(e)))
        events = []
        # the worst chip first, then again without it (a jumping chip drags its neighbours' medians)
        while excluded.sum() < max(1, len(d) // 10):
            cand = np.where(excluded | ~np.isfinite(e), -np.inf, e)
            k = int(np.argmax(cand))
            if not cand[k] > limit:
                break
            excluded[k] = True
            self.shifts += 1
            events.append(HealthEvent(now, "health_bias_shift", k, float(e[k]),
                                      f"link {k} jumped {e[k] / _MG:.1f} mg against its neighbours between "
                                      f"two still windows (threshold {limit / _MG:.1f} mg): a bias shift?"))
            e = jumps(excluded)
        return events
