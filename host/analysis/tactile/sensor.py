"""The streaming sensor: readings in, tracked contacts out (`TactileSensor.process`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..estimator import ShapeEstimate, estimate
from .contacts import Contact, DetectorSettings, _dilate, find_contacts
from .foam import Foam
from .rest import RestShape, deformation
from .tracking import ContactTracker

__all__ = ["TactileFrame", "TactileSensor"]


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
    """

    t_s: float | None
    estimate: ShapeEstimate
    displacement: np.ndarray
    contacts: list[Contact]
    total_force_n: float


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
    """

    def __init__(self, rest: RestShape, foam: Foam, settings: DetectorSettings | None = None,
                 gate: float = 2.0, max_missed: int = 2):
        self.rest = rest
        self.foam = foam
        self.settings = settings or DetectorSettings()
        self.tracker = ContactTracker(gate * rest.link_length, max_missed)

    @staticmethod
    def learn_rest(readings: Sequence[np.ndarray], rows: int, cols: int, link_length: float,
                   valid: np.ndarray | None = None, prior: RestShape | None = None
                   ) -> RestShape:
        """Learn the rest shape from snapshots of an untouched sheet, shape ``(n_links, 3)``
        each, m/s² (the estimator with ``prior`` or its own rest layout as prior)."""
        prev = None if prior is None else prior.prior
        ests = [estimate(r, rows, cols, link_length, valid=valid, previous=prev)
                for r in readings]
        return RestShape.learn(ests)

    def process(self, readings: np.ndarray, valid: np.ndarray | None = None,
                t_s: float | None = None) -> TactileFrame:
        """One snapshot: readings ``(n_links, 3)`` m/s², sensor frames, DESIGN.md link order."""
        est = estimate(readings, self.rest.rows, self.rest.cols, self.rest.link_length,
                       valid=valid, previous=self.rest.prior)
        d, _ = deformation(est.joints, self.rest)
        found = find_contacts(d, self.rest, self.foam, self.settings)
        if found:  # second pass: fit the rigid overlay without the dents and their tails
            moved = np.zeros(d.shape, bool)
            for c in found:
                moved |= c.region
            moved = _dilate(moved)
            d, _ = deformation(est.joints, self.rest, exclude=moved)
            found = find_contacts(d, self.rest, self.foam, self.settings)
        contacts = self.tracker.update(found)
        return TactileFrame(t_s=t_s, estimate=est, displacement=d, contacts=contacts,
                            total_force_n=float(sum(c.force_n for c in contacts)))
