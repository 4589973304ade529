"""The streaming sensor: readings in, tracked contacts out (`TactileSensor.process`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..estimator import ShapeEstimate, estimate
from .contacts import Contact, DetectorSettings, dilate, find_contacts
from .foam import Foam
from .response import footprint_table
from .rest import RestShape, deformation
from .tracking import ContactTracker

__all__ = ["TactileFrame", "TactileSensor", "ONSET_LOOKBACK", "ONSET_K"]

#: Snapshots kept to read a new contact's force back to its onset (`TactileSensor`).
ONSET_LOOKBACK = 4
#: A snapshot before a contact's detection belongs to it when the contact's fitted model reads
#: a force above this many of its standard deviations there.
ONSET_K = 3.0


@dataclass(frozen=True, eq=False)
class TactileFrame:
    """What one snapshot tells.

    Attributes
    ----------
    t_s : float or None
        Snapshot time, seconds.
    estimate : ShapeEstimate
    displacement : ndarray, shape (rows, cols)
        Normal displacement into the foam, metres.
    contacts : list of Contact
        With track ids.
    total_force_n : float
        Sum of the contacts' forces, N.
    events : list of TrackEvent
        Onsets and releases of contacts that this snapshot revealed (`ContactTracker`).
    """

    t_s: float | None
    estimate: ShapeEstimate
    displacement: np.ndarray
    contacts: list[Contact]
    total_force_n: float
    events: list = field(default_factory=list)


class TactileSensor:
    """Readings in, tracked contacts out (module docstring).

    Parameters
    ----------
    rest : RestShape
        Known (`RestShape.from_joints`) or learned (`TactileSensor.learn_rest`).
    foam : Foam
    settings : DetectorSettings, optional
    gate : float, optional
        Tracking gate, link lengths (default 2).
    max_missed : int, optional
        Snapshots a track may go unmatched (default 2).
    baseline_tau_s : float or None, optional
        Time constant of the baseline, seconds (default 60; None: no baseline). While nothing
        touches, the rest surface follows slow change (foam creep, settling, temperature, a
        chip's drifting bias): every joint's baseline ``b_i`` moves towards its displacement by
        ``1 − exp(−Δt / τ)`` per snapshot, ``Δt`` from the snapshots' ``t_s``; displacements are
        measured from ``rest − b n``. The rate of change is tracked too (an α-β tracker), so a
        steady creep is followed without lag and extrapolated while frozen. Snapshots without
        ``t_s`` leave it alone.
    baseline_hold_s : float, optional
        The baseline is frozen while any contact is present and this long after the last one
        (default 2 s: a contact fading below the threshold, the foam recovering), seconds.
    """

    def __init__(self, rest: RestShape, foam: Foam, settings: DetectorSettings | None = None,
                 gate: float = 2.0, max_missed: int = 2, baseline_tau_s: float | None = 60.0,
                 baseline_hold_s: float = 2.0):
        self.rest = rest
        self.foam = foam
        self.settings = settings or DetectorSettings()
        self.tracker = ContactTracker(gate * rest.link_length, max_missed)
        if baseline_tau_s is not None and not (baseline_tau_s > 0):
            raise ValueError(f"Invalid baseline_tau_s: {baseline_tau_s!r} s (need > 0, or None)")
        if not (baseline_hold_s >= 0):
            raise ValueError(f"Invalid baseline_hold_s: {baseline_hold_s!r} s (need >= 0)")
        self.baseline_tau_s = baseline_tau_s
        self.baseline_hold_s = float(baseline_hold_s)
        #: The rest surface's drift along its normals, metres, positive into the foam.
        self.baseline_m = np.zeros((rest.rows, rest.cols))
        #: Its rate of change, m/s (the baseline extrapolates along it while frozen).
        self.baseline_rate_mps = np.zeros((rest.rows, rest.cols))
        self._t_prev: float | None = None       # time of the last baseline update
        self._t_contact: float | None = None
        self._estimate: ShapeEstimate | None = None   # the estimator's warm start
        self._contacts: list[Contact] = []            # the contact fit's warm start
        self._moved: np.ndarray | None = None         # the joints the last overlay left out
        footprint_table()   # built once here, not in the first touched snapshot
        #: The last `ONSET_LOOKBACK` snapshots' times and displacements (the onset's look-back).
        self._history: list[tuple[float, np.ndarray]] = []

    def _baseline_at(self, t_s: float | None) -> np.ndarray:
        """The baseline at ``t_s``: its level plus its rate times the time since the last update
        (the drift goes on under a contact; the extrapolation is capped at ``baseline_tau_s``)."""
        if t_s is None or self._t_prev is None:
            return self.baseline_m
        dt = min(max(float(t_s) - self._t_prev, 0.0), self.baseline_tau_s)
        return self.baseline_m + self.baseline_rate_mps * dt

    def _follow(self, d: np.ndarray, touched: bool, t_s: float | None) -> None:
        """The baseline step (class docstring): an α-β tracker of every joint's level and rate,
        ``α = 1 − exp(−Δt / τ)``, ``β = α² / (2 − α)`` (critically damped: a steady creep is
        followed without lag); frozen (level and rate) while touched and ``hold`` after."""
        if self.baseline_tau_s is None or t_s is None:
            return
        t = float(t_s)
        if touched:
            self._t_contact = t
        free = not touched and (self._t_contact is None
                                or t - self._t_contact >= self.baseline_hold_s)
        if self._t_prev is None:
            self._t_prev = t
            return
        if free and t > self._t_prev:
            dt = t - self._t_prev
            a = 1.0 - np.exp(-dt / self.baseline_tau_s)
            b = a * a / (2.0 - a)
            pred = self._baseline_at(t)   # d was measured from it: d is the innovation
            self.baseline_m = pred + a * d
            self.baseline_rate_mps = self.baseline_rate_mps + b * d / dt
            self._t_prev = t

    @staticmethod
    def learn_rest(readings: Sequence[np.ndarray], rows: int, cols: int, link_length: float,
                   valid: np.ndarray | None = None, prior: RestShape | None = None
                   ) -> RestShape:
        """Learn the rest shape from snapshots of an untouched sheet, shape ``(n_links, 3)``
        each, m/s² (the estimator with ``prior`` or its own rest layout as prior)."""
        rest = None if prior is None else prior.yaws
        ests = [estimate(r, rows, cols, link_length, valid=valid, rest=rest)
                for r in readings]
        return RestShape.learn(ests)

    def process(self, readings: np.ndarray, valid: np.ndarray | None = None,
                t_s: float | None = None) -> TactileFrame:
        """One snapshot: readings ``(n_links, 3)`` m/s², sensor frames, docs/design.md link
        order; ``t_s`` its time, seconds (the baseline and the tracker's prediction need it).

        The estimator starts from the previous snapshot's yaws (``previous=``: a warm start,
        its prior is still the rest shape); the rigid overlay leaves out the joints the previous
        snapshot's contacts moved, and is redone only when a contact appears outside them; the
        contact fit starts from the previous snapshot's contacts (`find_contacts`'s
        ``previous``)."""
        est = estimate(readings, self.rest.rows, self.rest.cols, self.rest.link_length,
                       valid=valid, rest=self.rest.yaws, previous=self._estimate)
        self._estimate = est
        base = self._baseline_at(t_s) if self.baseline_tau_s is not None else None
        d, aligned = deformation(est.joints, self.rest, exclude=self._moved, baseline_m=base)
        found = find_contacts(d, self.rest, self.foam, self.settings, aligned=aligned,
                              previous=self._contacts)
        moved = None
        if found:
            core = np.zeros(d.shape, bool)
            for c in found:
                core |= c.region
            moved = dilate(core)
            if self._moved is None or np.any(core & ~self._moved):
                # a dent the overlay did not leave out: fit it again without the dents' tails
                d, aligned = deformation(est.joints, self.rest, exclude=moved, baseline_m=base)
                found = find_contacts(d, self.rest, self.foam, self.settings, aligned=aligned,
                                      previous=found)
        self._moved = moved
        self._follow(d, bool(found), t_s)
        contacts = self.tracker.update(found, now=t_s)
        events = self.tracker.pop_events()
        if t_s is not None and any(e.kind == "onset" for e in events):
            contacts, events = self._refine_onsets(contacts, events)
        if t_s is not None:
            self._history = (self._history + [(float(t_s), d)])[-ONSET_LOOKBACK:]
        self._contacts = contacts
        return TactileFrame(t_s=t_s, estimate=est, displacement=d, contacts=contacts,
                            total_force_n=float(sum(c.force_n for c in contacts)),
                            events=events)

    def _refine_onsets(self, contacts: list[Contact], events: list) -> tuple[list, list]:
        """A new contact is detected once its deepest joint passes ``k_detect σ``; by then a
        ramping press has been on for a snapshot or more. Its fitted model (geometry held,
        force and offset free: a linear fit, its response at the rest joints) is read back
        through the last `ONSET_LOOKBACK` snapshots: the onset is the earliest of the
        consecutive snapshots before it whose force exceeds `ONSET_K` times the contact's
        standard deviation (a matched filter: several times more sensitive than one joint)."""
        from dataclasses import replace as dc_replace

        from .response import line_response

        rest, lam = self.rest, self.foam.shear_length_m
        kmap = rest.k_map(self.foam)
        out_c, out_e = list(contacts), []
        for e in events:
            if e.kind != "onset":
                out_e.append(e)
                continue
            n, c = next(((n, c) for n, c in enumerate(out_c) if c.id == e.id), (None, None))
            if c is None or c.model is None or not self._history:
                out_e.append(e)
                continue
            m = c.model
            sup = c.region.copy()
            for _ in range(self.settings.skirt):
                sup = dilate(sup)
            X = rest.joints[sup] - m.centre
            t1 = m.direction
            t2 = np.cross(c.normal, t1)
            xy = np.stack([X @ t1, X @ t2], axis=1)
            k = float(kmap[c.peak])
            T = line_response(xy, np.zeros(2), m.half_width_m, m.half_length_m, 0.0, lam, k)
            B = np.stack([T, np.ones_like(T)], axis=1)
            P = np.linalg.pinv(B)[0]            # the force as a linear read of the joints
            onset = e.t_s
            for t_prev, d_prev in reversed(self._history):
                if float(P @ d_prev[sup]) > ONSET_K * max(c.force_std_n, 1e-9):
                    onset = t_prev
                else:
                    break
            if onset != e.t_s:
                self.tracker.set_onset(e.id, onset)
                e = dc_replace(e, t_s=onset)
                out_c[n] = dc_replace(c, onset_s=onset)
            out_e.append(e)
        return out_c, out_e
