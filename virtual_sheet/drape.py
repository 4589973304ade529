"""The paper's spring-mass sheet (section 3.1), laid over an arbitrary surface by relaxation.

"The link is modeled as a very hard spring so that the link length does not change, and the joint
as a mass. [...] the model is laid over a target shape by iterative calculation." Here the links
are infinitely stiff springs and the relaxation is position-based: each sweep restores every link
to its rest length ``L`` (the links in four colour classes — i-links of even/odd ``i``, j-links
of even/odd ``j`` — so that no two links of a class share a joint and each class is solved
exactly, Gauss-Seidel style, both joints moving equally as equal masses), then moves every joint
to its closest point on the target surface (the contact constraint). Sweeps repeat until the
largest relative link-length error is below ``tol`` with every joint on the surface.

The target is anything with ``project(points) -> closest points`` and an ``anchor`` point, so
non-height-fields work: `Cylinder` (a sheet wrapped round it), `Sphere`, and `HeightField`.
The result is a Chebyshev net on the surface, like `geometry.chebyshev_net` but by the paper's
method; the net is laid from the anchor outwards first (initial guess, ``init="compass"``), or
laid flat over the target and relaxed (``init="flat"``: the paper's "laid over a target shape by
iterative calculation", what `host.cli.paper`'s Fig. 9 and 10 use).

Sensor axes ("the direction of the sensor axes are simulated"): `geometry.link_frames` takes a
link's sensor z from the sheet itself (the mean normal of its cells, all a spring-mass model
knows); `surface_frames` takes it from the target instead (the surface normal under the link's
midpoint, what a chip lying on the body would see), so an estimator's normal model is not exact
by construction.

>>> P, info = drape(Cylinder(0.03), 14, 14, 0.01)
>>> info.converged, info.max_length_error < 1e-9, info.max_surface_distance < 1e-12
(True, True, True)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Protocol, runtime_checkable

import numpy as np

from protocol.lattice import Lattice, joint_normals

__all__ = ["Surface", "Sphere", "Cylinder", "HeightField", "DrapeInfo", "drape", "surface_frames",
           "surface_readings"]


def _points(points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim < 1 or p.shape[-1] != 3:
        raise ValueError(f"Expected `points` to have shape (..., 3), got {p.shape}.")
    return p


def _vec3(value, name: str) -> np.ndarray:
    v = np.asarray(value, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"Invalid {name}: {value!r} (expected 3 finite numbers)")
    return v


@runtime_checkable
class Surface(Protocol):
    """A target surface: ``project(points (..., 3)) -> closest points (..., 3)`` (metres, world
    frame) and ``anchor``, the surface point where the sheet's centre joint is laid by default."""

    @property
    def anchor(self) -> np.ndarray: ...

    def project(self, points: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class Sphere:
    """Sphere of ``radius`` (m) about ``centre``; anchor at its top."""

    radius: float
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"Invalid sphere radius: {self.radius!r} m (need > 0)")
        _vec3(self.centre, "sphere centre")

    @property
    def anchor(self) -> np.ndarray:
        return np.asarray(self.centre, float) + (0.0, 0.0, self.radius)

    def project(self, points: np.ndarray) -> np.ndarray:
        c = np.asarray(self.centre, float)
        w = _points(points) - c
        n = np.linalg.norm(w, axis=-1, keepdims=True)
        if np.any(n == 0):
            raise ValueError("Cannot project the sphere's centre onto the sphere.")
        return c + self.radius * w / n

    def normal(self, points: np.ndarray) -> np.ndarray:
        """Outward unit normal at the surface points nearest ``points`` (..., 3)."""
        return (self.project(points) - np.asarray(self.centre, float)) / self.radius


@dataclass(frozen=True)
class Cylinder:
    """Infinite circular cylinder of ``radius`` (m) about the line through ``centre`` along
    ``axis`` (default along y: horizontal); anchor on its top line (highest z)."""

    radius: float
    axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"Invalid cylinder radius: {self.radius!r} m (need > 0)")
        a = _vec3(self.axis, "cylinder axis")
        if np.linalg.norm(a) == 0:
            raise ValueError(f"Invalid cylinder axis: {self.axis!r} (zero vector)")
        _vec3(self.centre, "cylinder centre")

    @property
    def _a(self) -> np.ndarray:
        a = np.asarray(self.axis, float)
        return a / np.linalg.norm(a)

    @property
    def anchor(self) -> np.ndarray:
        a = self._a
        up = np.array([0.0, 0.0, 1.0]) - a[2] * a
        if np.linalg.norm(up) < 1e-9:  # vertical axis: anchor on the +x side
            up = np.array([1.0, 0.0, 0.0]) - a[0] * a
        return np.asarray(self.centre, float) + self.radius * up / np.linalg.norm(up)

    def project(self, points: np.ndarray) -> np.ndarray:
        a, c = self._a, np.asarray(self.centre, float)
        w = _points(points) - c
        along = np.sum(w * a, axis=-1, keepdims=True)
        perp = w - along * a
        n = np.linalg.norm(perp, axis=-1, keepdims=True)
        if np.any(n == 0):
            raise ValueError("Cannot project a point on the cylinder's axis onto the cylinder.")
        return c + along * a + self.radius * perp / n

    def normal(self, points: np.ndarray) -> np.ndarray:
        """Outward unit normal at the surface points nearest ``points`` (..., 3)."""
        a, c = self._a, np.asarray(self.centre, float)
        w = self.project(points) - c
        return (w - np.sum(w * a, axis=-1, keepdims=True) * a) / self.radius


@dataclass(frozen=True)
class HeightField:
    """Surface ``z = f(x, y)`` (vectorised, metres); projection by Gauss-Newton on the distance
    (finite-difference gradient, ``step_m``); anchor at ``(0, 0, f(0, 0))``."""

    f: Callable[[np.ndarray, np.ndarray], np.ndarray]
    step_m: float = 1e-7
    max_iter: int = 50

    def __post_init__(self) -> None:
        if not callable(self.f):
            raise ValueError(f"Invalid height field: {self.f!r} is not callable")
        if not (self.step_m > 0):
            raise ValueError(f"Invalid step_m: {self.step_m!r} (need > 0)")

    def _z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.broadcast_to(np.asarray(self.f(x, y), float), np.shape(x))

    @property
    def anchor(self) -> np.ndarray:
        return np.array([0.0, 0.0, float(self._z(np.array(0.0), np.array(0.0)))])

    def project(self, points: np.ndarray) -> np.ndarray:
        p = _points(points)
        shape = p.shape
        p = p.reshape(-1, 3)
        x, y = p[:, 0].copy(), p[:, 1].copy()
        h = self.step_m
        for _ in range(self.max_iter):
            z = self._z(x, y)
            fx = (self._z(x + h, y) - self._z(x - h, y)) / (2 * h)
            fy = (self._z(x, y + h) - self._z(x, y - h)) / (2 * h)
            rx, ry, rz = x - p[:, 0], y - p[:, 1], z - p[:, 2]
            # Gauss-Newton on |(x, y, f) - p|²: J = [[1, 0], [0, 1], [fx, fy]].
            g0, g1 = rx + fx * rz, ry + fy * rz
            a, b, d = 1 + fx * fx, fx * fy, 1 + fy * fy
            det = a * d - b * b
            dx, dy = (d * g0 - b * g1) / det, (a * g1 - b * g0) / det
            x, y = x - dx, y - dy
            if not np.all(np.isfinite(x + y)):
                raise ValueError("Height-field projection failed (NaN): point outside the domain?")
            if np.max(np.abs(dx) + np.abs(dy)) <= 1e-15 * (1 + np.max(np.abs(p[:, :2]))):
                break
        return np.column_stack([x, y, self._z(x, y)]).reshape(shape)

    def normal(self, points: np.ndarray) -> np.ndarray:
        """Upward unit normal ``(−f_x, −f_y, 1)/|…|`` at the surface points nearest ``points``
        (..., 3); the gradient by central differences of ``step_m``."""
        q = self.project(points)
        x, y, h = q[..., 0], q[..., 1], self.step_m
        fx = (self._z(x + h, y) - self._z(x - h, y)) / (2 * h)
        fy = (self._z(x, y + h) - self._z(x, y - h)) / (2 * h)
        n = np.stack([-fx, -fy, np.ones_like(fx)], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)


@dataclass(frozen=True)
class DrapeInfo:
    """What `drape` achieved.

    Attributes
    ----------
    converged : bool
        ``max_length_error <= tol`` within ``iterations`` sweeps.
    iterations : int
        Relaxation sweeps done.
    newton_steps : int
        Newton steps tried (the stiff-link limit solved at once, once the sweeps are close).
    max_length_error : float
        ``max |‖P_b − P_a‖ / L − 1|`` over all links (relative).
    max_surface_distance : float
        ``max ‖P − project(P)‖`` over all joints, metres.
    history : tuple of float
        ``max_length_error`` after every ``check_every`` sweeps (convergence record).
    """

    converged: bool
    iterations: int
    newton_steps: int
    max_length_error: float
    max_surface_distance: float
    history: tuple[float, ...] = field(default=(), repr=False)


def _length_error(P: np.ndarray, lat: Lattice, L: float) -> float:
    return float(np.max(np.abs(np.linalg.norm(lat.link_vectors(P), axis=1) / L - 1.0)))


def _fix_links(pa: np.ndarray, pb: np.ndarray, L: float) -> tuple[np.ndarray, np.ndarray]:
    """Move both ends of every link equally along it so its length becomes ``L``."""
    d = pb - pa
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    corr = 0.5 * (1.0 - L / np.maximum(n, 1e-300)) * d
    return pa + corr, pb - corr


def _sweep(P: np.ndarray, L: float) -> None:
    """One Gauss-Seidel sweep over the four link colour classes, in place."""
    for s in (0, 1):  # i-links (i, j)->(i+1, j) with i = s mod 2
        a, b = P[s:-1:2], P[s + 1::2]
        m = min(a.shape[0], b.shape[0])
        P[s:s + 2 * m:2], P[s + 1:s + 2 * m:2] = _fix_links(a[:m], b[:m], L)
    for s in (0, 1):  # j-links (i, j)->(i, j+1) with j = s mod 2
        a, b = P[:, s:-1:2], P[:, s + 1::2]
        m = min(a.shape[1], b.shape[1])
        P[:, s:s + 2 * m:2], P[:, s + 1:s + 2 * m:2] = _fix_links(a[:, :m], b[:, :m], L)




def _newton_step(surface: Surface, P: np.ndarray, lat: Lattice, L: float) -> np.ndarray:
    """One minimum-norm Gauss-Newton step on all link lengths at once, every joint moving in its
    tangent plane, then projected back onto the surface (the stiff-spring limit, solved)."""
    from scipy.sparse import csr_matrix, identity
    from scipy.sparse.linalg import spsolve

    rows, cols = P.shape[:2]
    flat = P.reshape(-1, 3)
    nrm = joint_normals(P).reshape(-1, 3)
    e1 = np.cross(nrm, np.array([1.0, 0.0, 0.0]))
    alt = np.cross(nrm, np.array([0.0, 1.0, 0.0]))
    pick = np.linalg.norm(alt, axis=1) > np.linalg.norm(e1, axis=1)
    e1[pick] = alt[pick]
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(nrm, e1)
    T = np.stack([e1, e2], axis=2)  # (n_joints, 3, 2)

    ends = lat.endpoints
    d = flat[ends[:, 1]] - flat[ends[:, 0]]
    length = np.linalg.norm(d, axis=1)
    c = length - L
    u = d / length[:, None]
    gb = np.einsum("li,lik->lk", u, T[ends[:, 1]])  # d c / d δ_b, (n_links, 2)
    ga = -np.einsum("li,lik->lk", u, T[ends[:, 0]])
    n_l = len(c)
    r = np.repeat(np.arange(n_l), 4)
    col = np.stack([2 * ends[:, 0], 2 * ends[:, 0] + 1, 2 * ends[:, 1], 2 * ends[:, 1] + 1], 1)
    J = csr_matrix((np.concatenate([ga, gb], axis=1).ravel(), (r, col.ravel())),
                   shape=(n_l, 2 * rows * cols))
    A = (J @ J.T).tocsc()
    A = A + 1e-12 * identity(n_l, format="csc")
    y = spsolve(A, c)
    delta = -(J.T @ y).reshape(-1, 2)
    flat = flat + np.einsum("nik,nk->ni", T, delta)
    return surface.project(flat.reshape(rows, cols, 3))


def _initial_net(surface: Surface, rows: int, cols: int, L: float, anchor: np.ndarray,
                 u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Lay the net from the centre joint outwards: seed lines stepped along the surface, then
    each joint from the parallelogram point ``A + B − C`` with a few projected Newton steps
    towards ``|P − A| = |P − B| = L``. Approximate; the relaxation makes it exact."""
    ic, jc = rows // 2, cols // 2
    P = np.full((rows, cols, 3), np.nan)
    P[ic, jc] = surface.project(anchor[None])[0]

    def seed(start: np.ndarray, direction: np.ndarray, n: int) -> np.ndarray:
        out, p, t = np.empty((n, 3)), start, direction
        for k in range(n):
            q = surface.project((p + L * t)[None])[0]
            for _ in range(4):  # re-aim along the surface, keep the step L
                t = (q - p) / np.linalg.norm(q - p)
                q = surface.project((p + L * t)[None])[0]
            out[k], p = q, q
        return out

    if rows - 1 - ic:
        P[ic + 1:, jc] = seed(P[ic, jc], u, rows - 1 - ic)
    if ic:
        P[ic - 1::-1, jc] = seed(P[ic, jc], -u, ic)
    if cols - 1 - jc:
        P[ic, jc + 1:] = seed(P[ic, jc], v, cols - 1 - jc)
    if jc:
        P[ic, jc - 1::-1] = seed(P[ic, jc], -v, jc)

    quadrants = [(si, n_a, sj, n_b) for si, n_a in ((1, rows - 1 - ic), (-1, ic))
                 for sj, n_b in ((1, cols - 1 - jc), (-1, jc)) if n_a and n_b]
    for k in range(2, max((q[1] + q[3] for q in quadrants), default=1) + 1):
        idx = [(ic + si * a, jc + sj * (k - a), si, sj) for si, n_a, sj, n_b in quadrants
               for a in range(max(1, k - n_b), min(n_a, k - 1) + 1)]
        if not idx:
            continue
        ii, jj, si, sj = (np.array(c) for c in zip(*idx))
        A, B, C = P[ii - si, jj], P[ii, jj - sj], P[ii - si, jj - sj]
        X = surface.project(A + B - C)
        for _ in range(6):
            dA, dB = X - A, X - B
            F = np.stack([np.sum(dA * dA, 1) - L * L, np.sum(dB * dB, 1) - L * L], axis=1)
            J = 2 * np.stack([dA, dB], axis=1)  # (m, 2, 3); minimum-norm Newton step
            JJt = J @ np.swapaxes(J, 1, 2)
            det = JJt[:, 0, 0] * JJt[:, 1, 1] - JJt[:, 0, 1] * JJt[:, 1, 0]
            ok = np.abs(det) > 1e-20 * L ** 4
            inv = np.zeros_like(JJt)
            inv[ok, 0, 0], inv[ok, 1, 1] = JJt[ok, 1, 1] / det[ok], JJt[ok, 0, 0] / det[ok]
            inv[ok, 0, 1], inv[ok, 1, 0] = -JJt[ok, 0, 1] / det[ok], -JJt[ok, 1, 0] / det[ok]
            step = np.einsum("mki,mkl,ml->mi", J, inv, F)
            X = surface.project(X - step)
        P[ii, jj] = X
    return P


def drape(surface: Surface, rows: int, cols: int, link_length: float, *,
          iterations: int = 20_000, tol: float = 1e-10, anchor=None,
          direction=(1.0, 0.0, 0.0), shear: float = 0.0, init: str | np.ndarray = "compass",
          check_every: int = 10, newton_below: float = 1e-3, max_newton: int = 20
          ) -> tuple[np.ndarray, DrapeInfo]:
    """Lay the spring-mass sheet over ``surface`` and relax it (paper section 3.1).

    Parameters
    ----------
    surface : Surface
        Target: `Sphere`, `Cylinder`, `HeightField` or anything with ``project`` and ``anchor``.
    rows, cols : int
        Joints along i and j.
    link_length : float
        Rest length ``L`` of every link, metres.
    iterations : int, optional
        Maximum relaxation sweeps.
    tol : float, optional
        Target ``max |‖link‖ / L − 1|``.
    anchor : array_like, shape (3,), optional
        Where the centre joint ``(rows // 2, cols // 2)`` goes (projected onto the surface);
        default ``surface.anchor``.
    direction : array_like, shape (3,), optional
        Initial direction of the i lines at the anchor (world frame; projected by the surface).
    shear : float, optional
        Initial angle between the i and j lines beyond π/2, radians, about the world vertical.
    init : {"compass", "flat"} or ndarray, shape (rows, cols, 3), optional
        Initial placement. "compass" (default): laid outwards from the anchor joint by joint,
        already close to exact, so few sweeps are needed. "flat": the flat square net in the
        plane through the anchor spanned by ``direction`` and its turn, projected onto the
        surface — the paper's plain "laid over, then iterated"; fine on gentle targets, slow or
        trapped in a crumpled net on strongly curved ones (a cylinder of radius < S/2). An array:
        these joints (projected first), e.g. a previous drape to follow a moving target.
    check_every : int, optional
        Sweeps between convergence checks.
    newton_below, max_newton : float, int, optional
        Once the link error is below ``newton_below``, up to ``max_newton`` Newton steps solve
        all links at once (each joint moving in its tangent plane, then projected); a step that
        does not reduce the error hands back to the sweeps. ``max_newton=0``: sweeps only.

    Returns
    -------
    joints : ndarray, shape (rows, cols, 3)
        Metres, world frame; every joint on the surface (projected last).
    info : DrapeInfo
        Achieved link-length error and distance to the surface.
    """
    lat = Lattice(rows, cols)
    L = float(link_length)
    if not (np.isfinite(L) and L > 0):
        raise ValueError(f"Invalid link_length: {link_length!r} (need a finite value > 0 m)")
    if not (int(iterations) >= 0 and tol > 0 and int(check_every) >= 1):
        raise ValueError(f"Invalid iterations/tol/check_every: {iterations!r}, {tol!r}, "
                         f"{check_every!r}")
    if not abs(shear) < np.pi / 2:
        raise ValueError(f"Invalid shear: {shear!r} rad (need |shear| < pi/2)")
    a0 = np.asarray(surface.anchor if anchor is None else _vec3(anchor, "anchor"), float)
    u = _vec3(direction, "direction")
    if np.linalg.norm(u[:2]) == 0:
        raise ValueError(f"Invalid direction: {direction!r} (needs a horizontal component)")
    u = u / np.linalg.norm(u)
    c, s = np.cos(np.pi / 2 + shear), np.sin(np.pi / 2 + shear)
    v = np.array([c * u[0] - s * u[1], s * u[0] + c * u[1], u[2]])  # u turned about world z
    v /= np.linalg.norm(v)

    if isinstance(init, np.ndarray):
        if init.shape != (rows, cols, 3):
            raise ValueError(f"Expected `init` to have shape ({rows}, {cols}, 3), got {init.shape}.")
        P = surface.project(np.array(init, dtype=float))
    elif init == "compass":
        P = _initial_net(surface, rows, cols, L, a0, u, v)
    elif init == "flat":
        i = (np.arange(rows) - rows // 2)[:, None, None]
        j = (np.arange(cols) - cols // 2)[None, :, None]
        P = surface.project(surface.project(a0[None])[0] + L * (i * u + j * v))
    else:
        raise ValueError(f"Invalid init: {init!r} (expected 'compass', 'flat' or an array)")
    if not np.all(np.isfinite(P)):
        raise ValueError("Drape: the initial net left the surface (NaN); surface too small?")
    history = [_length_error(P, lat, L)]
    done = newton = 0
    err = history[0]
    while err > tol and done < iterations:
        if err <= newton_below and newton < max_newton:
            # Close to the net: solve the stiff links at once (quadratic convergence).
            P_new = _newton_step(surface, P, lat, L)
            err_new = _length_error(P_new, lat, L)
            newton += 1
            if np.isfinite(err_new) and err_new < err:
                P, err = P_new, err_new
                history.append(err)
                continue
            newton = max_newton  # no progress: keep relaxing instead
        n = min(int(check_every), int(iterations) - done)
        for _ in range(n):
            _sweep(P, L)
            P = surface.project(P)
        done += n
        err = _length_error(P, lat, L)
        history.append(err)
        if not np.isfinite(err):
            raise ValueError("Drape: relaxation diverged (NaN).")
    dist = float(np.max(np.linalg.norm(P - surface.project(P), axis=-1)))
    return P, DrapeInfo(converged=bool(err <= tol), iterations=done, newton_steps=newton,
                        max_length_error=err, max_surface_distance=dist, history=tuple(history))


def surface_frames(joints: np.ndarray, surface) -> np.ndarray:
    """Sensor frames (sensor -> world, (n_links, 3, 3), lattice order) of a sheet lying on
    ``surface``: x along the link (docs/design.md), z the surface's normal under the link's
    midpoint (``surface.normal``) made orthogonal to x, on the sheet's top face (the side of
    `geometry.link_frames`' z), y = z × x.

    Parameters
    ----------
    joints : ndarray, shape (rows, cols, 3)
        The draped joints, metres (on the surface: `drape` projects them last).
    surface : Sphere, Cylinder or HeightField
        Anything with ``normal(points) -> unit normals``.
    """
    from .geometry import link_frames

    if not callable(getattr(surface, "normal", None)):
        raise ValueError(f"Invalid surface: {surface!r} has no normal(points) method")
    cells = link_frames(joints)  # checks the joints; its z fixes the top face
    P = np.asarray(joints, float)
    lat = Lattice(P.shape[0], P.shape[1])
    flat = P.reshape(-1, 3)
    e = lat.endpoints
    x = cells[:, :, 0]
    n = surface.normal(0.5 * (flat[e[:, 0]] + flat[e[:, 1]]))
    n = np.where(np.sum(n * cells[:, :, 2], axis=1, keepdims=True) < 0, -n, n)
    z = n - np.sum(n * x, axis=1, keepdims=True) * x
    zn = np.linalg.norm(z, axis=1, keepdims=True)
    if np.any(zn <= 1e-12):
        raise ValueError("Surface normal parallel to a link: cannot define sensor z.")
    z = z / zn
    return np.stack([x, np.cross(z, x), z], axis=2)


def surface_readings(joints: np.ndarray, surface) -> np.ndarray:
    """Noise-free readings (specific force, m/s², (n_links, 3)) of a sheet lying on ``surface``,
    sensor z from the surface (`surface_frames`)."""
    from .geometry import specific_force

    return specific_force(surface_frames(joints, surface))
