"""Foam bodies wrapped in the sheet, indenters pressing them with known forces (docs/tactile.md).

The tactile sensor of the paper is "a compressible material, such as urethane foam, wrapped by the
sheet"; forces follow "from the surface deformation and Young's modulus of the material". This
module is the virtual version: a foam layer of thickness ``h``, Young's modulus ``E`` and Poisson's
ratio ``ν`` on a rigid core (a block's top face, a cylinder, a sphere), indenters (sphere, flat
punch, capsule "finger", rectangular "edge") pressed into it with a known normal force, and the
sheet laid over the indented surface with every link keeping its length ``L``.

Foam model: a thin layer as a Vlasov two-parameter foundation
-----------------------------------------------------------------
A layer bonded to a rigid base, with the vertical displacement decaying linearly through the
thickness (Vlasov & Leontiev 1966; Kerr 1964), reacts to a surface deflection ``w`` (positive into
the foam, metres) with the pressure

    p = k w − G_p ∇²w,   k = E_oed / h,   G_p = G h / 3,

``E_oed = E (1 − ν) / ((1 + ν)(1 − 2ν))`` the oedometric (constrained) modulus, ``G = E / 2(1 + ν)``.
``k`` alone is Winkler's foundation (each point a spring, ``p = k w``); ``G_p`` couples neighbours
through the layer's shear, so the deflection spreads beyond the indenter over the length

    λ = sqrt(G_p / k) = h sqrt((1 − 2ν) / (6 (1 − ν)))      (h/√6 ≈ 0.41 h for ν = 0).

Two properties make the force readable from the shape: the shear term integrates to zero over the
surface (the deflection dies out), so the **total force is exactly** ``F = k ∫ w dA`` — Winkler's
integral — whatever the spreading; and the model is linear, so several indenters superpose.

Contact: each indenter is rigid; its tip profile ``g(u, v)`` (height above its lowest point,
paraboloidal for curved tips, ``+inf`` off a flat punch's face) is pressed to a depth ``δ`` such
that the foam surface touches it where the pressure is positive and stays below it elsewhere
(``w ≥ δ − g``, equality where ``p > 0``, ``p ≥ 0``), with ``∫ p dA = F``. The layer's response
``ŵ = p̂ / (k (1 + λ² q²))`` is exact on a periodic FFT grid; the complementarity problem is solved
by the constrained conjugate-gradient method of Polonsky & Keer (Wear 231, 1999) — the standard
FFT contact solver — one indenter at a time with the others' deflection as background (a few
Gauss-Seidel sweeps when several press at once). With ``λ = 0`` (``FoamLayer(spreading=False)``)
it reduces to Winkler's closed forms (``k`` in Pa/m), which give the depths as a check and the
solver its first guess:

========= ======================================= ==========================================
sphere    radius R, ``g = r² / 2R``               ``F = π k R δ²``
punch     flat circle, radius a                   ``F = π k a² δ``
capsule   radius R, segment half-length ℓ, angle  ``F = k (8/3 ℓ sqrt(2R) δ^{3/2} + π R δ²)``
rect      flat, half-sides a × b, angle           ``F = 4 k a b δ``
========= ======================================= ==========================================

With spreading, the same force gives a shallower, wider dent (the punch's pressure concentrates
at its rim), but ``F = k ∫ w dA`` still holds exactly.
Given a target force, `Indenter.depth_from_force` inverts ``F(δ)`` (closed form or bracketed root).
The linear model holds for strains ``δ / h`` up to ~20 % (foam's linear-elastic range before its
plateau); the scenes below stay there by default.

The sheet on the surface: the surface of the indented body is sampled on a fine grid (``L/6``),
interpolated by bicubic splines, and the sheet is laid on it with every link exactly ``L``: on the
block by the compass construction (`geometry.chebyshev_net`, centre-anchored, exact), on the
cylinder and sphere by the paper's spring-mass relaxation (`drape.drape`, warm-started from the
rest drape). The sheet's own bending stiffness is neglected against the foam's.

>>> layer = FoamLayer(thickness_m=0.02, youngs_modulus_pa=30e3, poisson=0.25)
>>> round(layer.k_pa_per_m), round(float(layer.shear_length_m) * 1000, 2)
(1800000, 6.67)
>>> ind = SphereIndenter(0.015)
>>> d = ind.depth_from_force(layer.k_pa_per_m, 1.0)
>>> round(float(d) * 1000, 3), round(float(ind.force_from_depth(layer.k_pa_per_m, d)), 9)
(3.434, 1.0)
"""

from __future__ import annotations

from .bodies import FoamBlock, FoamBody, FoamCylinder, FoamSphere
from .indenters import (CapsuleIndenter, FlatPunch, Indenter, Press, RectPunch, SphereIndenter,
                        TrueContact)
from .material import FoamLayer, column_compliance, oedometric_modulus
from .scene import Creep, FoamScene, TrueFootprint
from .solver import Deflection, solve_contact

__all__ = ["FoamLayer", "oedometric_modulus", "Indenter", "SphereIndenter", "FlatPunch",
           "CapsuleIndenter", "RectPunch", "Press", "TrueContact", "FoamBody", "FoamBlock",
           "FoamCylinder", "FoamSphere", "FoamScene", "Deflection", "solve_contact",
           "column_compliance", "Creep", "TrueFootprint"]
