"""The foam under the sheet as the host knows it: ``k = E_oed / h`` and the spreading length."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Foam", "column_compliance"]


def column_compliance(thickness_m: float, k1=0.0, k2=0.0):
    """``∫_0^h ds / ((1 − κ1 s)(1 − κ2 s))``, metres (``virtual_sheet.foam.column_compliance``'s
    model, here for arrays): a foam column under the outer area ``dA`` of a core with principal
    curvatures ``κ1, κ2`` (1/m, positive where convex) has the area ``(1 − κ1 s)(1 − κ2 s) dA``
    at depth ``s``, so ``k = E_oed / this``; ``h`` on a flat core. Curvatures are clipped to
    ``0.9 / h`` (a noisy rest shape must not make the layer vanish).

    >>> round(float(column_compliance(0.02, 10.0, 0.0)) / 0.02, 4)   # cylinder R = 0.1 m
    1.1157
    """
    h = float(thickness_m)
    k1 = np.minimum(np.asarray(k1, float), 0.9 / h)[..., None]
    k2 = np.minimum(np.asarray(k2, float), 0.9 / h)[..., None]
    x, wts = np.polynomial.legendre.leggauss(16)
    s = 0.5 * h * (x + 1.0)
    return 0.5 * h * np.sum(wts / ((1.0 - k1 * s) * (1.0 - k2 * s)), axis=-1)


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

    def k_at(self, curvatures_m_inv: np.ndarray) -> np.ndarray:
        """``k`` where the rest surface has principal curvatures ``curvatures_m_inv`` (shape
        ``(..., 2)``, 1/m, positive where convex; `RestShape.curvatures`), Pa/m, shape ``(...)``."""
        c = np.asarray(curvatures_m_inv, float)
        nu = self.poisson
        e_oed = self.youngs_modulus_pa * (1 - nu) / ((1 + nu) * (1 - 2 * nu))
        return e_oed / column_compliance(self.thickness_m, c[..., 0], c[..., 1])

    @property
    def shear_length_m(self) -> float:
        """Spreading length ``λ = h sqrt((1 − 2ν) / (6 (1 − ν)))`` of the layer, metres: a dent's
        tail decays about as ``exp(−r / λ)``."""
        nu = self.poisson
        return self.thickness_m * np.sqrt((1 - 2 * nu) / (6 * (1 - nu)))
