"""A sheet on a foam body with indenters pressed and released over time."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Sequence

import numpy as np

from protocol.lattice import Lattice

from .bodies import FoamBody
from .indenters import Press, TrueContact
from .material import FoamLayer, require_positive
from .solver import Deflection, solve_contact

__all__ = ["FoamScene", "Creep", "TrueFootprint"]


@dataclass(frozen=True)
class TrueFootprint:
    """The exact footprints of one active press, from the solved deflection and pressure
    (surface coordinates; half-axes ``2 sqrt(eigenvalue)`` of second central moments, so a
    uniform disc of radius ``a`` gives ``a``).

    Attributes
    ----------
    index : int
        Its `Press` in the scene.
    pressure_centre_m : ndarray, shape (2,)
        Centre of its pressure, metres.
    pressure_axes_m : tuple of float
        Half-axes (major, minor) of its pressure distribution (pressure-weighted moments):
        the contact patch.
    pressure_angle_rad : float
        Major axis from surface +u, in (−π/2, π/2].
    dent_axes_m : tuple of float
        Half-axes (major, minor) of its half-depth footprint: the region where its own dent
        (the layer's response to its pressure alone: the layer is linear) is at least half its
        deepest, uniform weights.
    dent_angle_rad : float
        Its major axis from surface +u, in (−π/2, π/2].
    dent_area_m2 : float
    """

    index: int
    pressure_centre_m: np.ndarray
    pressure_axes_m: tuple[float, float]
    pressure_angle_rad: float
    dent_axes_m: tuple[float, float]
    dent_angle_rad: float
    dent_area_m2: float


def _moment_axes(xy: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, tuple, float]:
    """Weighted centre, half-axes ``2 sqrt(eig)`` (major, minor) and major-axis angle."""
    mu = w @ xy / w.sum()
    X = xy - mu
    C = X.T @ (X * w[:, None]) / w.sum()
    ev, evec = np.linalg.eigh(C)
    ang = float(np.arctan2(evec[1, 1], evec[0, 1]))
    ang = ang - np.pi if ang > np.pi / 2 else ang + np.pi if ang <= -np.pi / 2 else ang
    return mu, (float(2 * np.sqrt(max(ev[1], 0.0))), float(2 * np.sqrt(max(ev[0], 0.0)))), ang


@dataclass(frozen=True)
class Creep:
    """Slow change of the untouched surface: foam creep, settling, temperature (docs/tactile.md,
    "Drift"). A broad sag into the foam, Gaussian of width ``width_m`` about ``centre_m``
    (surface coordinates), deepening as ``depth_m (1 − exp(−t / tau_s))``, plus a uniform
    settling of ``uniform_m`` with the same time course. Superposed on the indentation (the layer
    is linear); it carries no force of its own (the scene's true contacts are the presses).

    Attributes
    ----------
    depth_m, width_m, uniform_m : float
        Metres (final sag depth at the centre, Gaussian standard deviation, uniform part).
    tau_s : float
        Time constant, seconds.
    centre_m : tuple of float
        ``(u, v)``, metres.
    """

    depth_m: float = 1e-3
    width_m: float = 0.03
    tau_s: float = 600.0
    uniform_m: float = 0.0
    centre_m: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        require_positive(self.width_m, "creep width_m", "m")
        require_positive(self.tau_s, "creep tau_s", "s")
        if not (np.isfinite(self.depth_m) and np.isfinite(self.uniform_m)):
            raise ValueError(f"Invalid creep depth_m/uniform_m: {self.depth_m!r}, "
                             f"{self.uniform_m!r} (need finite metres)")

    def at(self, U: np.ndarray, V: np.ndarray, t_s: float) -> np.ndarray:
        """Sag into the foam at surface coordinates ``U, V`` and time ``t_s``, metres."""
        g = 1.0 - np.exp(-max(float(t_s), 0.0) / self.tau_s)
        r2 = (U - self.centre_m[0]) ** 2 + (V - self.centre_m[1]) ** 2
        return g * (self.depth_m * np.exp(-0.5 * r2 / self.width_m ** 2) + self.uniform_m)


@dataclass(frozen=True, eq=False)
class FoamScene:
    """A sheet on a foam body with indenters pressed and released over time.

    Like the scenes of `virtual_sheet.shapes`: ``joints(t_s)`` gives the sheet's joints, shape
    ``(rows, cols, 3)``, metres, world frame, every link ``link_length``; ``contacts(t_s)`` the
    true contacts active at ``t_s`` (force > ``min_force_n``).

    Attributes
    ----------
    body : FoamBody
        `FoamBlock` (default), `FoamCylinder` or `FoamSphere`.
    presses : sequence of Press
    rows, cols : int
    link_length : float
        ``L``, metres.
    grid_step_m : float, optional
        Deflection grid spacing, metres (default ``L / 6``).
    margin_m : float, optional
        Grid extent beyond the sheet, metres (default ``6 λ + 3 L``: the spreading has died out,
        ``e^{-6}``, and the FFT's periodic images do not touch).
    min_force_n : float
        Contacts below this force are not reported as active (default 1 mN).
    creep : Creep, optional
        Slow change of the untouched surface (default none).
    """

    body: FoamBody
    presses: Sequence[Press]
    rows: int = 14
    cols: int = 14
    link_length: float = 0.01
    grid_step_m: float | None = None
    margin_m: float | None = None
    min_force_n: float = 1e-3
    creep: Creep | None = None

    def __post_init__(self) -> None:
        Lattice(self.rows, self.cols)
        require_positive(self.link_length, "link_length", "m")
        object.__setattr__(self, "presses", tuple(self.presses))
        object.__setattr__(self, "_cache", {})

    @property
    def layer(self) -> FoamLayer:
        """The body's foam with its curvature (`FoamBody.contact_layer`)."""
        return self.body.contact_layer

    @cached_property
    def _grid(self) -> tuple[np.ndarray, float]:
        L = self.link_length
        step = L / 6 if self.grid_step_m is None else require_positive(self.grid_step_m, "grid_step_m", "m")
        margin = (6 * self.layer.shear_length_m + 3 * L if self.margin_m is None
                  else float(self.margin_m))
        half = 0.5 * max(self.rows, self.cols) * L + margin
        from scipy.fft import next_fast_len
        n = next_fast_len(int(np.ceil(2 * half / step)), real=True)
        u = (np.arange(n) - n // 2) * step
        return u, step

    @cached_property
    def rest_joints(self) -> np.ndarray:
        """The sheet on the undeformed body, shape ``(rows, cols, 3)``, metres, world frame."""
        P = self.body.rest_sheet(self.rows, self.cols, self.link_length)
        P.setflags(write=False)
        return P

    def deflection(self, t_s: float) -> Deflection | None:
        """The surface deflection at ``t_s`` (None when nothing presses), cached per time."""
        key = ("defl", float(t_s))
        if key in self._cache:
            return self._cache[key]
        active = [(i, p.force_at(t_s), p.position_at(t_s)) for i, p in enumerate(self.presses)]
        active = [a for a in active if a[1] > 0]
        if not active and self.creep is None:
            return None
        u, step = self._grid
        U, V = np.meshgrid(u, u, indexing="ij")
        if active:
            profiles = [self.presses[i].indenter.profile(U - c[0], V - c[1]) for i, _, c in active]
            p, depths, w = solve_contact(self.layer, profiles, [F for _, F, _ in active], step)
        else:
            p, depths, w = np.zeros(U.shape), [], np.zeros(U.shape)
        if self.creep is not None:  # the indenters rest on the sagged surface: superposed
            w = w + self.creep.at(U, V, t_s)
        out = Deflection(u=u, v=u.copy(), w=w, pressure=p, step_m=step,
                         depths_m={i: d for (i, _, _), d in zip(active, depths)})
        if len(self._cache) > 256:
            self._cache.clear()
        self._cache[key] = out
        return out

    def joints(self, t_s: float) -> np.ndarray:
        """The sheet's joints at ``t_s``, shape ``(rows, cols, 3)``, metres, world frame."""
        key = ("joints", float(t_s))
        if key not in self._cache:
            d = self.deflection(t_s)
            if len(self._cache) > 256:
                self._cache.clear()
            self._cache[key] = self.body.sheet(d, self.rows, self.cols, self.link_length,
                                               np.array(self.rest_joints))
        return self._cache[key].copy()

    def footprints(self, t_s: float) -> list[TrueFootprint]:
        """The exact footprints of the presses active at ``t_s`` (`TrueFootprint`), in
        `presses` order. A cell of positive pressure belongs to the press whose tip touches it
        (the smallest gap between tip and deflected surface); every other cell to the press
        whose contact is nearest (a Voronoi partition of the surface by contact patches)."""
        from scipy.ndimage import distance_transform_edt

        defl = self.deflection(t_s)
        if defl is None:
            return []
        active = [i for i, p in enumerate(self.presses) if p.force_at(t_s) > self.min_force_n]
        U, V = np.meshgrid(defl.u, defl.v, indexing="ij")
        gap = []
        for i in active:
            c = self.presses[i].position_at(t_s)
            g = self.presses[i].indenter.profile(U - c[0], V - c[1])
            gap.append(g - defl.depths_m.get(i, 0.0) + defl.w)
        touch = np.argmin(np.array(gap), axis=0)
        dist = []
        for n in range(len(active)):
            patch = (defl.pressure > 0) & (touch == n)
            dist.append(distance_transform_edt(~patch) if patch.any()
                        else np.full(U.shape, np.inf))
        own = np.argmin(np.array(dist), axis=0)
        xy = np.stack([U.ravel(), V.ravel()], axis=1)
        from scipy.fft import irfft2, rfft2

        from .solver import compliance
        n_grid = U.shape[0]
        comp = compliance(self.layer, n_grid, defl.step_m)
        out = []
        for n, i in enumerate(active):
            mine = own == n
            pm = np.where(mine, defl.pressure, 0.0)
            p = pm.ravel()
            pc, pax, pang = _moment_axes(xy[p > 0], p[p > 0])
            w = irfft2(rfft2(pm) * comp, s=U.shape).ravel()   # its own dent
            half = w >= 0.5 * w.max()
            _, dax, dang = _moment_axes(xy[half], np.ones(int(half.sum())))
            out.append(TrueFootprint(i, pc, pax, pang, dax, dang,
                                     float(half.sum() * defl.step_m ** 2)))
        return out

    def contacts(self, t_s: float) -> list[TrueContact]:
        """The true contacts active at ``t_s``, in `presses` order."""
        k = self.layer.k_pa_per_m
        out = []
        defl = None
        for idx, press in enumerate(self.presses):
            F = press.force_at(t_s)
            if F <= self.min_force_n:
                continue
            if defl is None:
                defl = self.deflection(t_s)
            c = press.position_at(t_s)
            d = defl.depths_m[idx]
            a, b = press.indenter.footprint(press.indenter.depth_from_force(k, F))
            r = np.linspace(-a, a, 41)
            gu, gv = np.meshgrid(r, r * b / max(a, 1e-300), indexing="ij")
            ang = float(getattr(press.indenter, "angle_rad", 0.0))
            cu, cv = np.cos(ang) * gu - np.sin(ang) * gv, np.sin(ang) * gu + np.cos(ang) * gv
            wmax = float(np.max(defl.at(c[0] + cu, c[1] + cv)))
            out.append(TrueContact(index=idx, kind=press.indenter.kind, position_uv=c,
                                   position=self.body.surface_point(c), force_n=F, depth_m=d,
                                   max_deflection_m=wmax, footprint_m=(a, b), angle_rad=ang))
        return out
