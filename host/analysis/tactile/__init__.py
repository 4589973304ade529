"""Tactile sensing: contacts and forces from the sheet wrapped on foam (docs/tactile.md).

The paper's application: "The number, shapes, and positions of contact objects are obtained
because the whole surface profile of the material is observed by the sheet. The contact forces
are also estimated from the surface deformation and Young's modulus of the material."

Pipeline for one snapshot (`TactileSensor.process`; docs/tactile.md, "Host analysis"):

1. Shape: `host.estimator.estimate` with the **rest shape as the prior** (``rest=``), every
   snapshot (a flat level sheet is the paper's unsolvable Case 1 for yaw: chaining priors would
   let its horizontal layout drift; heights need no yaw); the previous estimate only as the warm
   start (``previous=``).
2. Deformation (`deformation`): the estimate overlaid on the rest surface (moved by the drift
   baseline, step 6) by a trimmed rigid fit of the normal distances (`rest.normal_fit`: the
   sheet sliding along a curved body does not tilt it), leaving out the joints the contacts
   moved; then the displacement of every joint along the rest normal, **positive into the
   foam**, metres.
3. Contacts (`find_contacts`): joints above ``k_detect σ_i`` seed contacts, the joints above
   ``k_region σ_i`` form regions (a watershed cuts a region with several maxima); the regions
   only propose: every connected part is fitted with the contact model — a line of
   uniform-pressure discs per contact, the foam layer's closed-form response to it
   (`response`), forces linear, geometry by variable projection (`fit`) — and holds one
   contact more or fewer when that lowers the residual enough (``ambiguous`` when the data
   leave the count open).
4. Per contact: force (the model's amplitude) and its standard deviation (a sandwich with the
   rest's noise samples), centre, the half-depth footprint of the fitted dent (length, width,
   orientation, their standard deviations), the contact patch (the fitted pressure's moments),
   depth, region.
5. Tracking (`ContactTracker`): predicted positions, Hungarian matching within a gate, onsets
   and releases with their times (``now`` passed in), ``force_n_held``.
6. Drift (`TactileSensor`'s baseline): while nothing touches, the rest surface follows slow change
   (time constant ``baseline_tau_s``, default 60 s; frozen while a contact is present).

The force model is the virtual foam's (`virtual_sheet.foam`): a thin layer as a Vlasov
two-parameter foundation, ``p = k w − G_p ∇²w`` with ``k = E_oed / h``; it is linear and every
template of `response` carries one newton (``k ∫ w dA = 1``), so a fitted amplitude is a force.

Modules: `foam` (the force model), `response` (the templates; `_kernel` their C version),
`fit` (the contact fit), `rest` (rest shape, curvature, normal fit, deformation), `contacts`
(detection, count, per-contact figures), `tracking`, `sensor` (`TactileSensor`), `plot`. This
package needs numpy and scipy only (matplotlib for `plot`); it does not import `virtual_sheet`.
"""

from __future__ import annotations

from ..metrics import rigid_fit
from .contacts import Contact, ContactModel, DetectorSettings, find_contacts, lattice_index
from .foam import Foam
from .plot import plot_frame
from .rest import RestShape, deformation
from .sensor import TactileFrame, TactileSensor
from .tracking import ContactTracker, TrackEvent

__all__ = ["Foam", "RestShape", "Contact", "ContactModel", "DetectorSettings", "TactileFrame",
           "deformation", "find_contacts", "ContactTracker", "TrackEvent", "TactileSensor",
           "plot_frame", "rigid_fit", "lattice_index"]
