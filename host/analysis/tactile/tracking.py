"""Stable contact ids over snapshots (Hungarian matching within a gate)."""

from __future__ import annotations

from dataclasses import replace
from typing import Sequence

import numpy as np

from .contacts import Contact

__all__ = ["ContactTracker"]


class ContactTracker:
    """Stable ids for contacts over snapshots.

    Association: minimum total distance between the previous snapshot's tracks and the new
    contacts (Hungarian, `scipy.optimize.linear_sum_assignment`), pairs farther than
    ``gate_m`` not matched; unmatched contacts start new tracks (ids count up from 0, never
    reused); a track not matched for more than ``max_missed`` snapshots ends.

    Parameters
    ----------
    gate_m : float
        Largest distance a contact moves between snapshots and keeps its id, metres.
    max_missed : int
        Snapshots a track may go unmatched (a contact blinking below threshold keeps its id).
    force_window : int
        Every tracked contact's ``force_n_held`` is the mean of its force over its last
        ``force_window`` snapshots (default 4: the reading noise of a single snapshot's force
        halves); the history restarts when a snapshot's force leaves the mean by more than
        ``force_jump`` (default 0.3, relative: a press or a release is followed at once).
    """

    def __init__(self, gate_m: float, max_missed: int = 2, force_window: int = 4,
                 force_jump: float = 0.3):
        if not (gate_m > 0):
            raise ValueError(f"Invalid gate_m: {gate_m!r} (need > 0)")
        if not (int(force_window) >= 1 and force_jump > 0):
            raise ValueError(f"Invalid force_window/force_jump: {force_window!r}, {force_jump!r} "
                             "(need an integer >= 1 and a fraction > 0)")
        self.gate_m = float(gate_m)
        self.max_missed = int(max_missed)
        self.force_window = int(force_window)
        self.force_jump = float(force_jump)
        self._tracks: dict[int, tuple[np.ndarray, int]] = {}  # id -> (position, missed)
        self._forces: dict[int, list[float]] = {}             # id -> recent forces
        self._next = 0

    def update(self, contacts: Sequence[Contact]) -> list[Contact]:
        """The contacts with their track ids, same order."""
        from scipy.optimize import linear_sum_assignment

        ids = list(self._tracks)
        assigned = [-1] * len(contacts)
        if ids and contacts:
            A = np.array([self._tracks[t][0] for t in ids])
            B = np.array([c.position for c in contacts])
            D = np.linalg.norm(A[:, None, :] - B[None, :, :], axis=2)
            cost = np.where(D <= self.gate_m, D, 1e6 * self.gate_m)
            r, c = linear_sum_assignment(cost)
            for a, b in zip(r, c):
                if D[a, b] <= self.gate_m:
                    assigned[b] = ids[a]
        matched = set(x for x in assigned if x >= 0)
        for t in ids:
            if t not in matched:
                pos, missed = self._tracks[t]
                if missed + 1 > self.max_missed:
                    del self._tracks[t]
                    self._forces.pop(t, None)
                else:
                    self._tracks[t] = (pos, missed + 1)
        out = []
        for c, t in zip(contacts, assigned):
            if t < 0:
                t = self._next
                self._next += 1
            self._tracks[t] = (np.asarray(c.position, float), 0)
            hist = self._forces.setdefault(t, [])
            if hist and abs(c.force_n - np.mean(hist)) > self.force_jump * abs(np.mean(hist)):
                hist.clear()
            hist.append(float(c.force_n))
            del hist[:-self.force_window]
            out.append(replace(c, id=t, force_n_held=float(np.mean(hist))))
        return out
