"""The foam under the sheet as the host knows it: ``k = E_oed / h`` and the spreading length."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Foam"]


@dataclass(frozen=True)
class Foam:
    """The foam under the sheet, as the host knows it (docs/tactile.md, "Foam model").

    Attributes
    ----------
    thickness_m : float
        ``h``, metres.
    youngs_modulus_pa : float
        ``E``, Pa.
    poisson : float
        ``ν``, in [0, 0.45].
    """

    thickness_m: float = 0.02
    youngs_modulus_pa: float = 20e3
    poisson: float = 0.25

    def __post_init__(self) -> None:
        for name in ("thickness_m", "youngs_modulus_pa"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"Invalid {name}: {v!r} (need a finite value > 0)")
        if not (0.0 <= self.poisson <= 0.45):
            raise ValueError(f"Invalid poisson: {self.poisson!r} (need 0 <= nu <= 0.45)")

    @property
    def k_pa_per_m(self) -> float:
        """``k = E_oed / h``, Pa/m, with ``E_oed = E (1 − ν) / ((1 + ν)(1 − 2ν))``."""
        nu = self.poisson
        e_oed = self.youngs_modulus_pa * (1 - nu) / ((1 + nu) * (1 - 2 * nu))
        return e_oed / self.thickness_m

    @property
    def shear_length_m(self) -> float:
        """Spreading length ``λ = h sqrt((1 − 2ν) / (6 (1 − ν)))`` of the layer, metres: a dent's
        tail decays about as ``exp(−r / λ)``."""
        nu = self.poisson
        return self.thickness_m * np.sqrt((1 - 2 * nu) / (6 * (1 - nu)))
