"""Tactile sensing: contacts and forces from the sheet wrapped on foam (docs/tactile.md).

The paper's application: "The number, shapes, and positions of contact objects are obtained
because the whole surface profile of the material is observed by the sheet. The contact forces
are also estimated from the surface deformation and Young's modulus of the material."

Pipeline for one snapshot (`TactileSensor.process`):

1. Shape: `host.estimator.estimate` with the **rest shape as the prior** (``previous=``), every
   snapshot (not the previous snapshot: a flat level sheet is the paper's unsolvable Case 1 for
   yaw, and chaining priors would let its horizontal layout drift; heights need no yaw).
2. Deformation (`deformation`): the estimate overlaid on the rest surface (moved by the drift
   baseline, step 6) by a trimmed rigid fit of the normal distances (`rest.normal_fit`: the
   sheet sliding along a curved body does not tilt it; over the joints that did not move, so
   contacts do not tilt the fit; when contacts are found, the fit is redone without their regions
   grown by one joint, and the contacts found again), then the displacement of every joint along
   the rest normal, **positive into the foam**, metres.
3. Contacts (`find_contacts`): joints above a threshold ``τ_i = max(k_detect σ_i, floor)`` (``σ_i``
   the joint's displacement noise, learned from an untouched period or, failing that, a robust
   spread of the current frame), grown from local maxima in descending order (a watershed):
   where two regions meet, the lower one is merged into the higher if its prominence above the
   meeting point is below ``max(k_prominence σ, prominence_fraction · its peak)`` or the peaks
   are closer than ``min_separation`` link lengths. Each region (plus a skirt of ``skirt``
   joints, for the shallow tail of the dent) is one contact.
4. Per contact: depth (largest displacement), position (the displacement-weighted centroid of
   the joints above half the depth, in fractional lattice indices, mapped onto the rest surface),
   shape (the half-depth footprint of the displacement interpolated 4x per link: its area and
   principal half-axes ``2 sqrt(eigenvalues)`` of its second moments in the rest tangent plane,
   so a uniform disc of radius ``a`` gives ``a``; orientation of the major axis from the
   lattice's i direction), ``merged`` when the region may hold two contacts, and force by the
   foam model (`Foam`): the layer's dent template (`contacts.dent_template`: the unloaded
   layer's ``K0(r/λ)`` tail around a cap between a punch's flat bottom and a sphere's
   paraboloid) fitted to the region and skirt, at the joints' foot points on the rest surface and
   with a local offset, ``F = k α ∫ t dA`` with ``k`` the layer's stiffness at the rest
   curvature; a ``merged`` contact (no round template fits it) reads the sampled integral
   ``Σ k_i w_i A_i`` instead (`DetectorSettings.force_model`). The total force is the sum.
5. Tracking (`ContactTracker`): contacts matched to the previous snapshot's by minimum total
   distance (Hungarian) within a gate; unmatched contacts get new ids; a track survives
   ``max_missed`` snapshots without a match; ``force_n_held`` the track's recent mean force.
6. Drift (`TactileSensor`'s baseline): while nothing touches, the rest surface follows slow change
   (time constant ``baseline_tau_s``, default 60 s; frozen while a contact is present).

The force model is the virtual foam's (`virtual_sheet.foam`): a thin layer as a Vlasov
two-parameter foundation, ``p = k w − G_p ∇²w`` with ``k = E_oed / h``; the shear term integrates
to zero, so ``F = k ∫ w dA`` exactly — the integral of the dent fitted to the joints is what is read
here.

Modules: `foam` (the force model), `rest` (rest shape, curvature, normal fit, deformation), `contacts` (detection and
per-contact figures), `tracking`, `sensor` (`TactileSensor`), `plot`. This package needs numpy and
scipy only (matplotlib for `plot`); it does not import `virtual_sheet`.
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
