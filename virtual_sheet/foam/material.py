"""The foam layer: thickness, Young's modulus, Poisson's ratio; ``k`` and the spreading length."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FoamLayer", "oedometric_modulus", "column_compliance"]


def require_positive(value: float, name: str, unit: str) -> float:
    v = float(value)
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"Invalid {name}: {value!r} {unit} (need a finite value > 0)")
    return v


def oedometric_modulus(youngs_modulus_pa: float, poisson: float) -> float:
    """Constrained (oedometric) modulus ``E (1 − ν) / ((1 + ν)(1 − 2ν))``, Pa; ``E`` at ``ν = 0``."""
    E, nu = float(youngs_modulus_pa), float(poisson)
    return E * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu))


def column_compliance(thickness_m: float, k1: float = 0.0, k2: float = 0.0) -> float:
    """``∫_0^h ds / ((1 − κ1 s)(1 − κ2 s))``, metres: the layer's depth as seen by a column of foam
    that tapers with the core's curvature (``κ1, κ2`` the outer surface's principal curvatures,
    1/m, positive where convex; ``h`` for a flat layer). A column under an outer area ``dA`` has
    the area ``(1 − κ1 s)(1 − κ2 s) dA`` at depth ``s``; carrying the same force through every
    depth, it compresses by ``p ∫ ds / (E_oed (1 − κ1 s)(1 − κ2 s))``, so ``k = E_oed / this``:
    ``R h / (R − h)`` on a sphere, ``R ln(R / (R − h))`` on a cylinder.

    >>> round(column_compliance(0.02, 10.0, 10.0) / 0.02, 6)   # sphere R = 0.1 m: 1 / (1 - h/R)
    1.25
    """
    h = float(thickness_m)
    if not all(1.0 - float(k) * h > 0 for k in (k1, k2)):
        raise ValueError(f"Invalid curvature ({k1!r}, {k2!r}) 1/m for a layer {h!r} m thick "
                         "(need curvature x thickness < 1: the core would have no radius left)")
    x, wts = np.polynomial.legendre.leggauss(16)
    s = 0.5 * h * (x + 1.0)
    return float(0.5 * h * np.sum(wts / ((1.0 - k1 * s) * (1.0 - k2 * s))))


@dataclass(frozen=True)
class FoamLayer:
    """The foam: thickness ``h``, Young's modulus ``E``, Poisson's ratio ``ν`` (module docstring).

    Attributes
    ----------
    thickness_m : float
        ``h``, metres (default 20 mm).
    youngs_modulus_pa : float
        ``E``, Pa (default 20 kPa: soft polyurethane foam is 5-100 kPa).
    poisson : float
        ``ν``, in [0, 0.45] (default 0.25; open-cell foam is 0-0.3).
    spreading : bool
        False: plain Winkler (λ = 0), for checks against the closed forms.
    curvature_m_inv : tuple of float
        Principal curvatures ``(κ1, κ2)`` of the outer surface, 1/m, positive where convex
        (default flat; the bodies set it: ``(1/R, 0)`` cylinder, ``(1/R, 1/R)`` sphere). The
        layer tapers towards the core, which makes it softer: `column_compliance`.
    """

    thickness_m: float = 0.02
    youngs_modulus_pa: float = 20e3
    poisson: float = 0.25
    spreading: bool = True
    curvature_m_inv: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        require_positive(self.thickness_m, "thickness_m", "m")
        require_positive(self.youngs_modulus_pa, "youngs_modulus_pa", "Pa")
        if not (0.0 <= float(self.poisson) <= 0.45):
            raise ValueError(f"Invalid poisson: {self.poisson!r} (need 0 <= nu <= 0.45)")
        if len(self.curvature_m_inv) != 2:
            raise ValueError(f"Invalid curvature_m_inv: {self.curvature_m_inv!r} (expected two "
                             "principal curvatures, 1/m)")
        column_compliance(self.thickness_m, *self.curvature_m_inv)

    @property
    def k_pa_per_m(self) -> float:
        """Foundation modulus ``k = E_oed / h``, Pa/m (pressure per metre of deflection); on a
        curved core ``E_oed / column_compliance(h, κ1, κ2)``."""
        return (oedometric_modulus(self.youngs_modulus_pa, self.poisson)
                / column_compliance(self.thickness_m, *self.curvature_m_inv))

    @property
    def shear_length_m(self) -> float:
        """Spreading length ``λ = h sqrt((1 − 2ν) / (6 (1 − ν)))``, metres."""
        if not self.spreading:
            return 0.0
        nu = float(self.poisson)
        return self.thickness_m * np.sqrt((1.0 - 2.0 * nu) / (6.0 * (1.0 - nu)))
