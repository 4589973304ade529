"""Foam bodies (block, cylinder, sphere) and the sheet laid on their indented surface."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..drape import drape
from ..geometry import chebyshev_net
from ..geometry import flat_net
from .material import FoamLayer, require_positive
from .solver import Deflection

__all__ = ["FoamBody", "FoamBlock", "FoamCylinder", "FoamSphere"]


class FoamBody:
    """Base of the foam bodies: a `FoamLayer` on a rigid core, the sheet on its surface.

    Subclasses define surface coordinates ``(u, v)`` (metres along the surface), ``surface_point``
    (the undeformed surface, world frame), ``normal_at`` and ``sheet(deflection)`` (the sheet's
    joints on the indented surface).
    """

    layer: FoamLayer

    @property
    def contact_layer(self) -> FoamLayer:
        """The layer as the contact solver sees it: `layer` with this body's curvature."""
        return self.layer

    def surface_point(self, uv: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def normal_at(self, uv: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def rest_sheet(self, rows: int, cols: int, link_length: float) -> np.ndarray:
        raise NotImplementedError

    def sheet(self, deflection: Deflection | None, rows: int, cols: int, link_length: float,
              rest: np.ndarray) -> np.ndarray:
        raise NotImplementedError


@dataclass(frozen=True, eq=False)
class FoamBlock(FoamBody):
    """A foam block, top face level at ``z = 0``; surface coordinates are world ``(x, y)``, normal
    +z. The sheet is a centre-anchored Chebyshev net (exact, `geometry.chebyshev_net`)."""

    layer: FoamLayer = FoamLayer()

    def surface_point(self, uv):
        uv = np.asarray(uv, float)
        return np.concatenate([uv, np.zeros(uv.shape[:-1] + (1,))], axis=-1)

    def normal_at(self, uv):
        uv = np.asarray(uv, float)
        return np.broadcast_to(np.array([0.0, 0.0, 1.0]), uv.shape[:-1] + (3,)).copy()

    def rest_sheet(self, rows, cols, link_length):
        return flat_net(rows, cols, link_length)

    def sheet(self, deflection, rows, cols, link_length, rest):
        if deflection is None:
            return rest.copy()
        return chebyshev_net(lambda x, y: -deflection.at(x, y), rows, cols, link_length)


class _RadialSurface:
    """A `drape.Surface`: radius ``R − w(u, v)`` about ``centre`` along the direction of a point
    (projection is radial: exact on the undeformed surface, within O(slope²) when indented)."""

    def __init__(self, body, deflection: Deflection | None):
        self.body, self.deflection = body, deflection

    @property
    def anchor(self) -> np.ndarray:
        return self.body.surface_point(np.zeros(2))

    def project(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, float)
        uv = self.body.uv_of(p)
        r = self.body.radius_m
        if self.deflection is not None:
            r = r - self.deflection.at(uv[..., 0], uv[..., 1])
        c = self.body.centre
        d = p - c
        return c + np.asarray(r)[..., None] * d / np.linalg.norm(d, axis=-1, keepdims=True)


@dataclass(frozen=True, eq=False)
class FoamCylinder(FoamBody):
    """A foam cylinder of outer radius ``radius_m``, axis along world y, top line at ``z = 0``
    (axis at ``z = −R``). Surface coordinates: ``u = R θ`` (arc length from the top line towards
    +x), ``v = y``. The sheet is draped (`drape.drape`), its i lines round the cylinder."""

    radius_m: float = 0.06
    layer: FoamLayer = FoamLayer()

    def __post_init__(self) -> None:
        require_positive(self.radius_m, "cylinder radius_m", "m")
        if not self.layer.thickness_m < self.radius_m:
            raise ValueError(f"Invalid cylinder radius_m: {self.radius_m!r} m (need more than the "
                             f"foam's thickness {self.layer.thickness_m!r} m)")

    @property
    def contact_layer(self) -> FoamLayer:
        return replace(self.layer, curvature_m_inv=(1.0 / self.radius_m, 0.0))

    @property
    def centre(self) -> np.ndarray:
        return np.array([0.0, 0.0, -self.radius_m])

    def surface_point(self, uv):
        uv = np.asarray(uv, float)
        th = uv[..., 0] / self.radius_m
        R = self.radius_m
        return np.stack([R * np.sin(th), uv[..., 1], R * np.cos(th) - R], axis=-1)

    def normal_at(self, uv):
        uv = np.asarray(uv, float)
        th = uv[..., 0] / self.radius_m
        return np.stack([np.sin(th), 0.0 * th, np.cos(th)], axis=-1)

    def uv_of(self, p):
        """Surface coordinates of world points (radially projected), shape ``(..., 2)``."""
        d = np.asarray(p, float) - self.centre
        th = np.arctan2(d[..., 0], d[..., 2])
        return np.stack([self.radius_m * th, d[..., 1]], axis=-1)

    def rest_sheet(self, rows, cols, link_length):
        return _drape(_CylSurface(self, None), rows, cols, link_length, None)

    def sheet(self, deflection, rows, cols, link_length, rest):
        if deflection is None:
            return rest.copy()
        return _drape(_CylSurface(self, deflection), rows, cols, link_length, rest)


class _CylSurface(_RadialSurface):
    """Radial projection about the cylinder's axis (y kept)."""

    def project(self, points):
        p = np.asarray(points, float)
        uv = self.body.uv_of(p)
        r = np.full(p.shape[:-1], self.body.radius_m)
        if self.deflection is not None:
            r = r - self.deflection.at(uv[..., 0], uv[..., 1])
        c = self.body.centre
        d = p - c
        d[..., 1] = 0.0
        out = c + r[..., None] * d / np.linalg.norm(d, axis=-1, keepdims=True)
        out[..., 1] = p[..., 1]
        return out


@dataclass(frozen=True, eq=False)
class FoamSphere(FoamBody):
    """A foam ball of outer radius ``radius_m``, top at ``z = 0`` (centre at ``z = −R``). Surface
    coordinates: azimuthal equidistant about the top, ``(u, v) = R θ (cos φ, sin φ)`` with ``θ``
    the polar angle and ``φ`` the azimuth from +x (so ``(u, v) ≈ (x, y)`` near the top; distances
    along meridians are exact). The sheet is draped (`drape.drape`)."""

    radius_m: float = 0.08
    layer: FoamLayer = FoamLayer()

    def __post_init__(self) -> None:
        require_positive(self.radius_m, "sphere radius_m", "m")
        if not self.layer.thickness_m < self.radius_m:
            raise ValueError(f"Invalid sphere radius_m: {self.radius_m!r} m (need more than the "
                             f"foam's thickness {self.layer.thickness_m!r} m)")

    @property
    def contact_layer(self) -> FoamLayer:
        return replace(self.layer, curvature_m_inv=(1.0 / self.radius_m, 1.0 / self.radius_m))

    @property
    def centre(self) -> np.ndarray:
        return np.array([0.0, 0.0, -self.radius_m])

    def _dir(self, uv):
        uv = np.asarray(uv, float)
        rho = np.hypot(uv[..., 0], uv[..., 1])
        th = rho / self.radius_m
        phi = np.arctan2(uv[..., 1], uv[..., 0])
        return np.stack([np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), np.cos(th)], axis=-1)

    def surface_point(self, uv):
        return self.centre + self.radius_m * self._dir(uv)

    def normal_at(self, uv):
        return self._dir(uv)

    def uv_of(self, p):
        d = np.asarray(p, float) - self.centre
        th = np.arctan2(np.hypot(d[..., 0], d[..., 1]), d[..., 2])
        phi = np.arctan2(d[..., 1], d[..., 0])
        rho = self.radius_m * th
        return np.stack([rho * np.cos(phi), rho * np.sin(phi)], axis=-1)

    def rest_sheet(self, rows, cols, link_length):
        return _drape(_RadialSurface(self, None), rows, cols, link_length, None)

    def sheet(self, deflection, rows, cols, link_length, rest):
        if deflection is None:
            return rest.copy()
        return _drape(_RadialSurface(self, deflection), rows, cols, link_length, rest)


def _drape(surface, rows, cols, L, init) -> np.ndarray:
    P, info = drape(surface, rows, cols, L, init="compass" if init is None else init, tol=1e-9)
    if not info.converged:
        raise ValueError(f"Foam sheet: drape did not converge (link error "
                         f"{info.max_length_error:.3g}); indentation too steep for the links?")
    return P
