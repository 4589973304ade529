"""Built-in sheet shapes and time-varying scenes, all exact (every link ``L`` long).

Shapes are height fields ``z = f(x, y)`` covered by `geometry.chebyshev_net` (centre-anchored,
so every sheet is centred on the origin horizontally, its centre joint at the top of bumps and
caps), except "flat" and "tilted", which are a square flat net, rotated rigidly.

Default sizes scale with the sheet's side ``S = max(max(rows, cols) − 1, 2) · L`` so that a default
shape works for any lattice; all are overridable in metres/radians:

========== ====================================================================================
flat       level sheet, z = 0 (the paper's Case 1: yaw unobservable)
tilted     flat sheet rotated by ``tilt_x`` (about world x, default 0.3 rad) then ``tilt_y``
           (about world y, default 0.2 rad)
gaussian   the paper's bump (section 3.2, Fig. 9) ``amplitude · exp(−r² / 2 sigma²)``;
           defaults ``amplitude = sigma = S/4`` (14×14, L = 1 cm: 3.25 cm high, 3.25 cm wide;
           steepest slope 31°)
sphere     spherical cap of ``radius`` (default ``S``), top at z = 0
cylinder   cylinder of ``radius`` (default ``S``), top line at z = 0, axis horizontal at
           ``axis_angle`` from +x (default π/2: axis along y, the sheet bends along x)
saddle     ``curvature/2 · (x² − y²)`` with ``curvature`` default ``1.5 / S``
heightmap  a 2-D array (``path`` to a .npy file, or ``array``), bilinear, over ``extent``
========== ====================================================================================

Every shape also takes the net options of `chebyshev_net` — ``angle``, ``shear``, ``origin`` —
(for "flat"/"tilted", ``angle`` and ``shear`` shape the flat net the same way).

>>> P = make_sheet("gaussian", 14, 14, 0.01)
>>> P.shape, round(float(P[7, 7, 2]), 4)
((14, 14, 3), 0.0325)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from protocol.lattice import Lattice
from .geometry import HeightFunction, chebyshev_net, flat_net  # flat_net: re-exported (it lived here)

__all__ = ["SHAPES", "SCENES", "ShapeSpec", "SceneSpec", "make_sheet", "height_field",
           "Scene", "StaticScene", "GrowScene", "TiltScene", "PressScene", "make_scene",
           "flat_net"]

_NET_OPTIONS = ("angle", "shear", "origin")


def _side(rows: int, cols: int, link_length: float) -> float:
    """Reference size ``S`` for default shape parameters (at least 2 L so tiny sheets fit)."""
    return max(max(rows, cols) - 1, 2) * float(link_length)


def _rot_xy(tilt_x: float, tilt_y: float) -> np.ndarray:
    """``Ry(tilt_y) @ Rx(tilt_x)``: world-frame rotation of a flat sheet."""
    cx, sx, cy, sy = np.cos(tilt_x), np.sin(tilt_x), np.cos(tilt_y), np.sin(tilt_y)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    return ry @ rx


# ---------------------------------------------------------------------------------------------
# Height fields
# ---------------------------------------------------------------------------------------------

def _gaussian(side: float, amplitude: float | None = None, sigma: float | None = None,
              centre: tuple[float, float] = (0.0, 0.0)) -> HeightFunction:
    a = side / 4 if amplitude is None else float(amplitude)
    s = side / 4 if sigma is None else float(sigma)
    if not (np.isfinite(a) and np.isfinite(s) and s > 0):
        raise ValueError(f"Invalid gaussian: amplitude={amplitude!r} m, sigma={sigma!r} m "
                         "(need finite values, sigma > 0)")
    cx, cy = float(centre[0]), float(centre[1])
    return lambda x, y: a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))


def _sphere(side: float, radius: float | None = None) -> HeightFunction:
    r = side if radius is None else float(radius)
    if not (np.isfinite(r) and r > 0):
        raise ValueError(f"Invalid sphere radius: {radius!r} m (need > 0)")

    def f(x, y):
        d2 = r * r - x * x - y * y
        with np.errstate(invalid="ignore"):
            return np.where(d2 >= 0, np.sqrt(np.maximum(d2, 0.0)), np.nan) - r
    return f


def _cylinder(side: float, radius: float | None = None, axis_angle: float = np.pi / 2) -> HeightFunction:
    r = side if radius is None else float(radius)
    if not (np.isfinite(r) and r > 0):
        raise ValueError(f"Invalid cylinder radius: {radius!r} m (need > 0)")
    nx, ny = -np.sin(axis_angle), np.cos(axis_angle)  # horizontal normal to the axis

    def f(x, y):
        d = x * nx + y * ny
        d2 = r * r - d * d
        with np.errstate(invalid="ignore"):
            return np.where(d2 >= 0, np.sqrt(np.maximum(d2, 0.0)), np.nan) - r
    return f


def _saddle(side: float, curvature: float | None = None) -> HeightFunction:
    k = 1.5 / side if curvature is None else float(curvature)
    if not np.isfinite(k):
        raise ValueError(f"Invalid saddle curvature: {curvature!r} 1/m")
    return lambda x, y: 0.5 * k * (x * x - y * y)


def _plane(side: float, slope_x: float = 0.0, slope_y: float = 0.0) -> HeightFunction:
    return lambda x, y: slope_x * x + slope_y * y + 0.0 * x


def _heightmap(side: float, path: str | None = None, array: np.ndarray | None = None,
               extent: tuple[float, float, float, float] | None = None,
               z_scale: float = 1.0) -> HeightFunction:
    """Bilinear height field from ``array[iy, ix]`` (rows along y, columns along x, image-like)
    over ``extent = (x_min, x_max, y_min, y_max)`` metres (default a square of side ``2 S``
    centred on the origin); heights in metres times ``z_scale``; NaN outside the extent."""
    from scipy.interpolate import RegularGridInterpolator

    if (path is None) == (array is None):
        raise ValueError("heightmap needs exactly one of `path` (a .npy file) or `array`")
    data = np.load(path) if path is not None else np.asarray(array)
    data = np.asarray(data, dtype=float)
    if data.ndim != 2 or min(data.shape) < 2:
        raise ValueError(f"Expected the heightmap to have shape (ny, nx) with ny, nx >= 2, "
                         f"got {data.shape}.")
    if not np.all(np.isfinite(data)):
        raise ValueError("Expected the heightmap to be finite; got NaN or inf.")
    if extent is None:
        extent = (-side, side, -side, side)
    x0, x1, y0, y1 = (float(e) for e in extent)
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"Invalid heightmap extent: {extent!r} (need x_min < x_max, y_min < y_max)")
    gy = np.linspace(y0, y1, data.shape[0])
    gx = np.linspace(x0, x1, data.shape[1])
    interp = RegularGridInterpolator((gy, gx), data * float(z_scale), method="linear",
                                     bounds_error=False, fill_value=np.nan)

    def f(x, y):
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        return interp(np.stack([y.ravel(), x.ravel()], axis=1)).reshape(x.shape)
    return f


@dataclass(frozen=True)
class ShapeSpec:
    """A built-in shape: its one-line description and its height-field factory
    ``factory(side_m, **params) -> height`` (None for the rigid flat shapes)."""

    name: str
    description: str
    factory: Callable[..., HeightFunction] | None


SHAPES: dict[str, ShapeSpec] = {s.name: s for s in [
    ShapeSpec("flat", "level flat sheet (yaw unobservable: the paper's Case 1)", None),
    ShapeSpec("tilted", "flat sheet tilted by tilt_x, tilt_y rad (default 0.3, 0.2)", None),
    ShapeSpec("gaussian", "the paper's Gaussian bump; amplitude, sigma m (default S/4 each)",
              _gaussian),
    ShapeSpec("sphere", "spherical cap; radius m (default S, the sheet's side)", _sphere),
    ShapeSpec("cylinder", "cylinder, top line at z=0; radius m (default S), axis_angle rad",
              _cylinder),
    ShapeSpec("saddle", "hyperbolic paraboloid curvature/2 (x²-y²); curvature 1/m (default 1.5/S)",
              _saddle),
    ShapeSpec("heightmap", "bilinear height field from a .npy array (path=, extent=, z_scale=)",
              _heightmap),
]}


def _split(params: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    net = {k: params.pop(k) for k in _NET_OPTIONS if k in params}
    return net, params


def height_field(shape: str, rows: int, cols: int, link_length: float = 0.01,
                 **params: Any) -> HeightFunction:
    """The height function of a height-field shape (see the module table), with its defaults
    for a ``rows x cols`` sheet of link ``link_length``."""
    spec = _spec(shape)
    if spec.factory is None:
        if shape == "flat":
            _reject(shape, params)
            return _plane(0.0)
        raise ValueError(f"Shape {shape!r} is a rigid flat sheet, not a height field; "
                         "use make_sheet")
    try:
        return spec.factory(_side(rows, cols, link_length), **params)
    except TypeError as exc:
        raise ValueError(f"Invalid parameters for shape {shape!r}: {exc}") from exc


def _spec(shape: str) -> ShapeSpec:
    try:
        return SHAPES[shape]
    except KeyError:
        raise ValueError(f"Unknown shape {shape!r}; known shapes: {', '.join(SHAPES)}") from None


def _reject(name: str, params: dict[str, Any]) -> None:
    if params:
        raise ValueError(f"Invalid parameters for {name!r}: {', '.join(sorted(params))}")


def make_sheet(shape: str, rows: int, cols: int, link_length: float = 0.01,
               **params: Any) -> np.ndarray:
    """Joints of a built-in shape, every link exactly ``link_length``.

    Parameters
    ----------
    shape : str
        A key of `SHAPES`.
    rows, cols : int
        Joints along i and j.
    link_length : float, optional
        ``L``, metres (default 1 cm).
    **params
        The shape's parameters (module table) and the net options ``angle``, ``shear``,
        ``origin`` of `chebyshev_net`.

    Returns
    -------
    ndarray, shape (rows, cols, 3)
        Joints, metres, world frame, centred on the origin horizontally.

    Raises
    ------
    ValueError
        Unknown shape or parameter, or the net cannot be placed (see `chebyshev_net`).
    """
    spec = _spec(shape)
    net, params = _split(dict(params))
    if spec.name == "flat":
        _reject(shape, params)
        return flat_net(rows, cols, link_length, **net)
    if spec.name == "tilted":
        tilt_x = float(params.pop("tilt_x", 0.3))
        tilt_y = float(params.pop("tilt_y", 0.2))
        _reject(shape, params)
        if not (abs(tilt_x) < np.pi / 2 and abs(tilt_y) < np.pi / 2):
            raise ValueError(f"Invalid tilt: tilt_x={tilt_x!r}, tilt_y={tilt_y!r} rad "
                             "(need |tilt| < pi/2)")
        P = flat_net(rows, cols, link_length, **net)
        return P @ _rot_xy(tilt_x, tilt_y).T
    return chebyshev_net(height_field(shape, rows, cols, link_length, **params), rows, cols,
                         link_length, **net)


# ---------------------------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------------------------

@runtime_checkable
class Scene(Protocol):
    """A time-varying sheet: ``joints(t_s) -> (rows, cols, 3)`` metres, world frame, exact links."""

    rows: int
    cols: int
    link_length: float

    def joints(self, t_s: float) -> np.ndarray: ...


def _raised_cosine(t_s: float, period_s: float) -> float:
    """0 at t = 0, 1 at half a period, back to 0: ``(1 − cos 2πt/T) / 2``."""
    return 0.5 * (1.0 - np.cos(2.0 * np.pi * float(t_s) / period_s))


def _check_period(period_s: float) -> None:
    if not (np.isfinite(period_s) and period_s > 0):
        raise ValueError(f"Invalid period_s: {period_s!r} (need > 0 s)")


@dataclass(frozen=True)
class StaticScene:
    """A sheet that does not move (wraps any joints array)."""

    static_joints: np.ndarray

    def __post_init__(self) -> None:
        P = np.array(self.static_joints, dtype=float)
        if P.ndim != 3 or P.shape[2] != 3 or P.shape[0] < 2 or P.shape[1] < 2:
            raise ValueError(f"Expected `joints` to have shape (rows, cols, 3), got {P.shape}.")
        P.setflags(write=False)
        object.__setattr__(self, "static_joints", P)

    @property
    def rows(self) -> int:
        return self.static_joints.shape[0]

    @property
    def cols(self) -> int:
        return self.static_joints.shape[1]

    @property
    def link_length(self) -> float:
        d = self.static_joints[1, 0] - self.static_joints[0, 0]
        return float(np.linalg.norm(d))

    def joints(self, t_s: float) -> np.ndarray:
        return self.static_joints.copy()


@dataclass(frozen=True)
class GrowScene:
    """A Gaussian bump whose height rises from 0 to ``amplitude`` and back, period ``period_s``."""

    rows: int
    cols: int
    link_length: float = 0.01
    amplitude: float | None = None  #: metres; default S/4 (as the "gaussian" shape)
    sigma: float | None = None  #: metres; default S/4
    period_s: float = 4.0

    def __post_init__(self) -> None:
        Lattice(self.rows, self.cols)
        _check_period(self.period_s)

    def joints(self, t_s: float) -> np.ndarray:
        side = _side(self.rows, self.cols, self.link_length)
        amp = side / 4 if self.amplitude is None else self.amplitude
        h = _gaussian(side, amp * _raised_cosine(t_s, self.period_s), self.sigma)
        return chebyshev_net(h, self.rows, self.cols, self.link_length)


@dataclass(frozen=True)
class TiltScene:
    """A flat sheet tilting rigidly: ``tilt_x = max_tilt · sin(2πt/T)``, and ``tilt_y`` a quarter
    period later at half the amplitude (so it rocks about both axes)."""

    rows: int
    cols: int
    link_length: float = 0.01
    max_tilt: float = 0.4  #: radians
    period_s: float = 4.0

    def __post_init__(self) -> None:
        Lattice(self.rows, self.cols)
        _check_period(self.period_s)
        if not abs(self.max_tilt) < np.pi / 2:
            raise ValueError(f"Invalid max_tilt: {self.max_tilt!r} rad (need |max_tilt| < pi/2)")

    def joints(self, t_s: float) -> np.ndarray:
        w = 2.0 * np.pi * float(t_s) / self.period_s
        R = _rot_xy(self.max_tilt * np.sin(w), 0.5 * self.max_tilt * np.cos(w))
        return flat_net(self.rows, self.cols, self.link_length) @ R.T


@dataclass(frozen=True)
class PressScene:
    """An indenter pressing into a level sheet (a tactile sensor at rest): a downward Gaussian
    dent of depth ``depth · (1 − cos 2πt/T)/2`` and width ``sigma`` at ``centre``."""

    rows: int
    cols: int
    link_length: float = 0.01
    depth: float | None = None  #: metres; default S/8
    sigma: float | None = None  #: metres; default S/8
    centre: tuple[float, float] = (0.0, 0.0)  #: metres, world xy
    period_s: float = 2.0

    def __post_init__(self) -> None:
        Lattice(self.rows, self.cols)
        _check_period(self.period_s)

    def joints(self, t_s: float) -> np.ndarray:
        side = _side(self.rows, self.cols, self.link_length)
        depth = side / 8 if self.depth is None else self.depth
        sigma = side / 8 if self.sigma is None else self.sigma
        h = _gaussian(side, -depth * _raised_cosine(t_s, self.period_s), sigma, self.centre)
        return chebyshev_net(h, self.rows, self.cols, self.link_length)


@dataclass(frozen=True)
class SceneSpec:
    """A built-in scene: one-line description and its class."""

    name: str
    description: str
    factory: Callable[..., Scene]


SCENES: dict[str, SceneSpec] = {s.name: s for s in [
    SceneSpec("grow", "a Gaussian bump rising and falling (amplitude, sigma m; period_s)",
              GrowScene),
    SceneSpec("tilt", "a flat sheet rocking about x and y (max_tilt rad; period_s)", TiltScene),
    SceneSpec("press", "an indenter pressing a dent into a level sheet (depth, sigma, centre; "
              "period_s)", PressScene),
    SceneSpec("board", "the sheet flat on a board turned through held calibration poses "
              "(hold_s, move_s, jitter_rad; virtual_sheet/board.py)", lambda *a, **k: _board_scene(*a, **k)),
]}


def _board_scene(*args: Any, **kwargs: Any) -> Scene:
    from .board import BoardPoseScene  # imported late: a scene others rarely need
    return BoardPoseScene(*args, **kwargs)


def make_scene(name: str, rows: int, cols: int, link_length: float = 0.01,
               **params: Any) -> Scene:
    """A scene by name: a key of `SCENES`, or of `SHAPES` (a `StaticScene` of that shape,
    ``params`` passed to `make_sheet`)."""
    if name in SCENES:
        try:
            return SCENES[name].factory(rows, cols, link_length, **params)
        except TypeError as exc:
            raise ValueError(f"Invalid parameters for scene {name!r}: {exc}") from exc
    if name in SHAPES:
        return StaticScene(make_sheet(name, rows, cols, link_length, **params))
    raise ValueError(f"Unknown scene {name!r}; known scenes: {', '.join(SCENES)}, "
                     f"or a static shape: {', '.join(SHAPES)}")
