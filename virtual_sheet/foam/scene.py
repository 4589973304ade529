"""A sheet on a foam body with indenters pressed and released over time."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Sequence

import numpy as np

from protocol.lattice import Lattice

from .bodies import FoamBody
from .indenters import Press, TrueContact
from .material import FoamLayer, _positive
from .solver import Deflection, solve_contact

__all__ = ["FoamScene", "Creep"]


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
        _positive(self.width_m, "creep width_m", "m")
        _positive(self.tau_s, "creep tau_s", "s")
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
        _positive(self.link_length, "link_length", "m")
        object.__setattr__(self, "presses", tuple(self.presses))
        object.__setattr__(self, "_cache", {})

    @property
    def layer(self) -> FoamLayer:
        """The body's foam with its curvature (`FoamBody.contact_layer`)."""
        return self.body.contact_layer

    @cached_property
    def _grid(self) -> tuple[np.ndarray, float]:
        L = self.link_length
        step = L / 6 if self.grid_step_m is None else _positive(self.grid_step_m, "grid_step_m", "m")
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
