"""The foam layer: thickness, Young's modulus, Poisson's ratio; ``k`` and the spreading length."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FoamLayer", "oedometric_modulus"]


def _positive(value: float, name: str, unit: str) -> float:
    v = float(value)
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"Invalid {name}: {value!r} {unit} (need a finite value > 0)")
    return v


def oedometric_modulus(youngs_modulus_pa: float, poisson: float) -> float:
    """Constrained (oedometric) modulus ``E (1 − ν) / ((1 + ν)(1 − 2ν))``, Pa; ``E`` at ``ν = 0``."""
    E, nu = float(youngs_modulus_pa), float(poisson)
    return E * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu))


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
    """

    thickness_m: float = 0.02
    youngs_modulus_pa: float = 20e3
    poisson: float = 0.25
    spreading: bool = True  #: False: plain Winkler (λ = 0), for checks against the closed forms

    def __post_init__(self) -> None:
        _positive(self.thickness_m, "thickness_m", "m")
        _positive(self.youngs_modulus_pa, "youngs_modulus_pa", "Pa")
        if not (0.0 <= float(self.poisson) <= 0.45):
            raise ValueError(f"Invalid poisson: {self.poisson!r} (need 0 <= nu <= 0.45)")

    @property
    def k_pa_per_m(self) -> float:
        """Foundation modulus ``k = E_oed / h``, Pa/m (pressure per metre of deflection)."""
        return oedometric_modulus(self.youngs_modulus_pa, self.poisson) / self.thickness_m

    @property
    def shear_length_m(self) -> float:
        """Spreading length ``λ = h sqrt((1 − 2ν) / (6 (1 − ν)))``, metres."""
        if not self.spreading:
            return 0.0
        nu = float(self.poisson)
        return self.thickness_m * np.sqrt((1.0 - 2.0 * nu) / (6.0 * (1.0 - nu)))
