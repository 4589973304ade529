"""Stable contact ids over snapshots, onsets and releases (sans-I/O: the time is passed in)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from .contacts import Contact

__all__ = ["ContactTracker", "TrackEvent"]


@dataclass(frozen=True)
class TrackEvent:
    """A contact arriving or leaving.

    Attributes
    ----------
    kind : {"onset", "release"}
    id : int
        The track.
    t_s : float or None
        Onset: the time of the first snapshot the contact was seen in. Release: the time of the
        first snapshot it was no longer seen in (the event itself comes ``max_missed``
        snapshots later, once the track has ended). None where the snapshots carry no time.
    peak_force_n : float
        The largest force of the track so far, N.
    """

    kind: str
    id: int
    t_s: float | None
    peak_force_n: float


@dataclass
class _Track:
    position: np.ndarray
    velocity: np.ndarray
    t_s: float | None          # time of the last match
    missed: int
    onset_s: float | None
    forces: list
    peak: float
    t_first_missed: float | None = None


class ContactTracker:
    """Stable ids for contacts over snapshots, with their onsets and releases.

    Association: every track's position is predicted to the snapshot's time ``now`` from its
    velocity (the difference of its last two positions over their time; zero without times);
    contacts and predictions are paired by minimum total distance (Hungarian,
    `scipy.optimize.linear_sum_assignment`), pairs farther than ``gate_m`` not matched.
    Unmatched contacts start new tracks (ids count up from 0, never reused, an ``"onset"``
    event); a track not matched for more than ``max_missed`` snapshots ends (a ``"release"``
    event). The tracker reads no clock: ``now`` is the snapshot's time (h11-style, sans-I/O).

    Parameters
    ----------
    gate_m : float
        Largest distance between a track's predicted position and a contact that keeps the
        track's id, metres.
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
        if not (int(max_missed) >= 0):
            raise ValueError(f"Invalid max_missed: {max_missed!r} (need an integer >= 0)")
        self.gate_m = float(gate_m)
        self.max_missed = int(max_missed)
        self.force_window = int(force_window)
        self.force_jump = float(force_jump)
        self._tracks: dict[int, _Track] = {}
        self._events: list[TrackEvent] = []
        self._next = 0
        self._now: float | None = None

    @property
    def active_ids(self) -> list[int]:
        """Ids of the tracks alive (matched or within ``max_missed``)."""
        return list(self._tracks)

    def pop_events(self) -> list[TrackEvent]:
        """The onsets and releases since the last call, in order."""
        out, self._events = self._events, []
        return out

    def set_onset(self, track_id: int, t_s: float) -> None:
        """Move a live track's onset earlier (`TactileSensor` reads a new contact back through
        the snapshots before its detection); later contacts of the track carry it."""
        tr = self._tracks.get(track_id)
        if tr is not None and (tr.onset_s is None or t_s < tr.onset_s):
            tr.onset_s = float(t_s)

    def _predict(self, tr: _Track, now: float | None) -> np.ndarray:
        if now is None or tr.t_s is None:
            return tr.position
        return tr.position + tr.velocity * (now - tr.t_s)

    def update(self, contacts: Sequence[Contact], now: float | None = None) -> list[Contact]:
        """The contacts with their track ids (same order), ``force_n_held`` and ``onset_s``.

        Parameters
        ----------
        contacts : sequence of Contact
            One snapshot's contacts.
        now : float, optional
            The snapshot's time, seconds (monotonic). Without it positions are not predicted
            and events carry no time.
        """
        from scipy.optimize import linear_sum_assignment

        if now is not None:
            now = float(now)
            if self._now is not None and now < self._now:
                raise ValueError(f"Invalid now: {now!r} s is before the last snapshot's "
                                 f"{self._now!r} s")
            self._now = now
        ids = list(self._tracks)
        assigned = [-1] * len(contacts)
        if ids and contacts:
            A = np.array([self._predict(self._tracks[t], now) for t in ids])
            B = np.array([c.position for c in contacts])
            D = np.linalg.norm(A[:, None, :] - B[None, :, :], axis=2)
            cost = np.where(D <= self.gate_m, D, 1e6 * self.gate_m)
            r, c = linear_sum_assignment(cost)
            for a, b in zip(r, c):
                if D[a, b] <= self.gate_m:
                    assigned[b] = ids[a]
        matched = set(x for x in assigned if x >= 0)
        for t in ids:
            if t in matched:
                continue
            tr = self._tracks[t]
            if tr.missed == 0:
                tr.t_first_missed = now
            tr.missed += 1
            if tr.missed > self.max_missed:
                del self._tracks[t]
                self._events.append(TrackEvent("release", t, tr.t_first_missed, tr.peak))
        out = []
        for c, t in zip(contacts, assigned):
            pos = np.asarray(c.position, float)
            if t < 0:
                t = self._next
                self._next += 1
                self._tracks[t] = _Track(pos, np.zeros(3), now, 0, now, [], 0.0)
                self._events.append(TrackEvent("onset", t, now, float(c.force_n)))
            else:
                tr = self._tracks[t]
                if now is not None and tr.t_s is not None and now > tr.t_s:
                    tr.velocity = (pos - tr.position) / (now - tr.t_s)
                tr.position, tr.t_s, tr.missed = pos, now, 0
            tr = self._tracks[t]
            tr.peak = max(tr.peak, float(c.force_n))
            hist = tr.forces
            if hist and abs(c.force_n - np.mean(hist)) > self.force_jump * abs(np.mean(hist)):
                hist.clear()
            hist.append(float(c.force_n))
            del hist[:-self.force_window]
            out.append(replace(c, id=t, force_n_held=float(np.mean(hist)), onset_s=tr.onset_s))
        return out
