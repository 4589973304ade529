"""Exact sheet geometry: Chebyshev nets on height fields, link frames, ideal readings, angles.

Conventions are docs/design.md's ("Conventions every module shares") and are not restated differently
here: joints ``P[i, j]`` of shape ``(rows, cols, 3)`` in metres, world frame z up; link order and
link endpoints come from `protocol.lattice.Lattice` only; sensor frame x along the link towards the
higher-index joint, z the sheet normal on the top face, y = z × x; readings are specific force
(a flat sheet, top face up, reads ``(0, 0, +G0)``); ``R = Rz(γ) Ry(β) Rx(α)`` maps sensor to world.

Exact ground truth (docs/design.md "Exact ground truth"): a lattice of equal links with free joint
angles is a *Chebyshev net*. On a height field ``z = f(x, y)`` `chebyshev_net` places one by the
compass construction: two seed lines through an anchor joint, then every further joint at distance
``L`` from its two already placed neighbours, on the surface.

>>> import numpy as np
>>> P = chebyshev_net(lambda x, y: 0.0 * x, 3, 4, 0.01)
>>> P.shape
(3, 4, 3)
>>> ideal_readings(P)[0].round(5).tolist()
[0.0, 0.0, 9.80665]
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from protocol.constants import G0
from protocol.frames import roll_pitch
from protocol.lattice import Lattice

__all__ = ["chebyshev_net", "link_frames", "link_frames_jet", "link_midpoints", "ideal_readings", "specific_force", "roll_pitch",
           "link_angles", "link_lengths", "rotation_from_angles", "HeightFunction", "flat_net", "bracketed_root"]

#: A vectorised height field: ``height(x, y) -> z`` on arrays of equal shape (metres, world frame).
HeightFunction = Callable[[np.ndarray, np.ndarray], np.ndarray]

_NEWTON_MAX_ITER = 60
_LENGTH_RTOL = 1e-10  # construction's own acceptance test, tighter than the 1e-9 promised


# ---------------------------------------------------------------------------------------------
# Readings and angles
# ---------------------------------------------------------------------------------------------

def rotation_from_angles(alpha: np.ndarray, beta: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """``R = Rz(γ) Ry(β) Rx(α)`` (sensor -> world) for arrays of angles, shape ``(n, 3, 3)``."""
    a, b, g = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (alpha, beta, gamma))
    a, b, g = np.broadcast_arrays(a, b, g)
    ca, sa, cb, sb, cg, sg = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(g), np.sin(g)
    R = np.empty(a.shape + (3, 3))
    R[..., 0, 0] = cg * cb
    R[..., 0, 1] = cg * sb * sa - sg * ca
    R[..., 0, 2] = cg * sb * ca + sg * sa
    R[..., 1, 0] = sg * cb
    R[..., 1, 1] = sg * sb * sa + cg * ca
    R[..., 1, 2] = sg * sb * ca - cg * sa
    R[..., 2, 0] = -sb
    R[..., 2, 1] = cb * sa
    R[..., 2, 2] = cb * ca
    return R


# ---------------------------------------------------------------------------------------------
# Frames
# ---------------------------------------------------------------------------------------------

def _check_joints(joints: np.ndarray) -> np.ndarray:
    joints = np.asarray(joints, dtype=float)
    if joints.ndim != 3 or joints.shape[2] != 3 or joints.shape[0] < 2 or joints.shape[1] < 2:
        raise ValueError(f"Expected `joints` to have shape (rows, cols, 3) with rows, cols >= 2, "
                         f"got {joints.shape}.")
    if not np.all(np.isfinite(joints)):
        raise ValueError("Expected `joints` to be finite; got NaN or inf.")
    return joints


def link_lengths(joints: np.ndarray) -> np.ndarray:
    """Length of every link in lattice order, shape ``(n_links,)``, metres."""
    joints = _check_joints(joints)
    lat = Lattice(joints.shape[0], joints.shape[1])
    return np.linalg.norm(lat.link_vectors(joints), axis=1)


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` over the last axis, by components (the same products, without its overhead)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _unit(a: np.ndarray, ad: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """``a / |a|`` along the last axis, its time derivative if ``ad`` (the derivative of ``a``) is
    given (``(ad − u (u·ad)) / |a|``), and ``|a|`` (keepdims)."""
    norm = np.linalg.norm(a, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = a / norm
        ud = None if ad is None else (ad - u * np.sum(u * ad, axis=-1, keepdims=True)) / norm
    return u, ud, norm


def _link_pairs(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-joint ``values (..., rows, cols, k)`` at every link's lower and higher joint, each
    ``(..., n_links, k)`` in lattice order (docs/design.md: i-links then j-links, both row-major of
    the lower joint — the order of `Lattice.endpoints`)."""
    lead, k = values.shape[:-3], values.shape[-1]
    lo = np.concatenate([values[..., :-1, :, :].reshape(lead + (-1, k)),
                         values[..., :, :-1, :].reshape(lead + (-1, k))], axis=-2)
    hi = np.concatenate([values[..., 1:, :, :].reshape(lead + (-1, k)),
                         values[..., :, 1:, :].reshape(lead + (-1, k))], axis=-2)
    return lo, hi


def _frames(joints: np.ndarray, velocities: np.ndarray | None = None):
    """`link_frames` on ``(..., rows, cols, 3)`` joints and, with joint velocities, the body-frame
    angular velocity of every frame (the time derivative of each step of the definition)."""
    rows, cols = joints.shape[-3:-1]
    lead = joints.shape[:-3]
    V = velocities
    a, b = _link_pairs(joints)
    vec = b - a
    if V is not None:
        va, vb = _link_pairs(V)
        vecd = vb - va
    x, xd, length = _unit(vec, vecd if V is not None else None)
    if np.any(length <= 0.0):
        raise ValueError("Zero-length link: cannot define the sensor x axis.")

    # cell (i, j): normal of the cross product of its diagonals, top face side
    d1 = joints[..., 1:, 1:, :] - joints[..., :-1, :-1, :]
    d2 = joints[..., :-1, 1:, :] - joints[..., 1:, :-1, :]
    c = cross3(d1, d2)
    cd = None
    if V is not None:
        d1d = V[..., 1:, 1:, :] - V[..., :-1, :-1, :]
        d2d = V[..., :-1, 1:, :] - V[..., 1:, :-1, :]
        cd = cross3(d1d, d2) + cross3(d1, d2d)
    cn, cnd, cnorm = _unit(c, cd)
    if np.any(cnorm <= 0.0):
        raise ValueError("Degenerate lattice cell (zero area): cannot define the sheet normal.")

    def per_link(cells: np.ndarray) -> np.ndarray:
        # i-link (i, j)->(i+1, j) borders cells (i, j-1) and (i, j); j-link (i, j)->(i, j+1)
        # borders cells (i-1, j) and (i, j): pad the cells with zeros and add the two neighbours.
        pad_j = np.zeros(lead + (rows - 1, cols + 1, 3))
        pad_j[..., :, 1:-1, :] = cells
        n_i = (pad_j[..., :, :-1, :] + pad_j[..., :, 1:, :]).reshape(lead + (-1, 3))
        pad_i = np.zeros(lead + (rows + 1, cols - 1, 3))
        pad_i[..., 1:-1, :, :] = cells
        n_j = (pad_i[..., :-1, :, :] + pad_i[..., 1:, :, :]).reshape(lead + (-1, 3))
        return np.concatenate([n_i, n_j], axis=-2)  # lattice order

    n = per_link(cn)
    nx = np.sum(n * x, axis=-1, keepdims=True)
    w = n - nx * x
    wd = None
    if V is not None:
        nd = per_link(cnd)
        nxd = np.sum(nd * x, axis=-1, keepdims=True) + np.sum(n * xd, axis=-1, keepdims=True)
        wd = nd - nxd * x - nx * xd
    z, zd, zn = _unit(w, wd)
    if np.any(zn <= 1e-12):
        raise ValueError("Sheet normal parallel to a link (folded sheet): cannot define sensor z.")
    y = cross3(z, x)
    R = np.stack([x, y, z], axis=-1)
    if V is None:
        return R, None
    yd = cross3(zd, x) + cross3(z, xd)
    # Rᵀ Ṙ = [ω]×: ω_x = z·ẏ, ω_y = x·ż, ω_z = y·ẋ (columns of R are x, y, z)
    omega = np.stack([np.sum(z * yd, axis=-1), np.sum(x * zd, axis=-1), np.sum(y * xd, axis=-1)],
                     axis=-1)
    return R, omega


def link_midpoints(values: np.ndarray) -> np.ndarray:
    """The mean of every link's two joints' values: ``(..., rows, cols, k)`` -> ``(..., n_links, k)``,
    lattice order. Of joint positions: where each link's chip sits; of joint accelerations: the
    chip's own acceleration (the midpoint of a rigid link moves as the mean of its ends)."""
    v = np.asarray(values, dtype=float)
    if v.ndim < 3 or v.shape[-3] < 2 or v.shape[-2] < 2:
        raise ValueError(f"Expected `values` to have shape (..., rows, cols, k) with rows, cols >= 2, "
                         f"got {v.shape}.")
    lo, hi = _link_pairs(v)
    return 0.5 * (lo + hi)


def link_frames(joints: np.ndarray) -> np.ndarray:
    """Rotation sensor -> world of every link, shape ``(n_links, 3, 3)``, lattice order.

    Columns are the sensor axes in world coordinates:

    * x: unit vector along the link, towards the higher-index joint (`Lattice.endpoints`);
    * z: the sheet normal at the link, top face side, made exactly orthogonal to x;
    * y = z × x.

    Definition of the link normal: the unit normals of the (one or two) lattice cells that share
    the link (each the normalised cross product of the cell's diagonals
    ``(P[i+1,j+1] − P[i,j]) × (P[i,j+1] − P[i+1,j])``: +z for a flat sheet with i along +x, j
    along +y) are averaged; that average, minus its component along x (Gram-Schmidt), normalised,
    is z. This is the surface normal at the link's midpoint to first order (exactly so inside a
    sheet bent round a cylinder; a link on the sheet's edge has one cell only, so its normal leans
    by half that cell's bend), and it keeps the paper's normal assumption (eq. 6) approximate, as
    on a real sheet. A flat sheet with i along +x and j along +y has z = +z on every link.

    Parameters
    ----------
    joints : ndarray, shape (rows, cols, 3)
        Joint positions, metres, world frame.

    Returns
    -------
    ndarray, shape (n_links, 3, 3)
        ``R`` with ``R @ v_sensor = v_world``; orthonormal, ``det R = +1``.
    """
    return _frames(_check_joints(joints))[0]


def link_frames_jet(joints: np.ndarray, velocities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`link_frames` of moving joints, and every frame's angular velocity.

    The frames are those of `link_frames` at each instant; the angular velocity is the exact time
    derivative of that definition (chain rule through the link direction, the cells' normals, their
    average and the Gram-Schmidt step), expressed in the frame itself: ``Rᵀ Ṙ = [ω]×``, what a
    gyroscope on the link measures.

    Parameters
    ----------
    joints : ndarray, shape (..., rows, cols, 3)
        Joint positions, metres, world frame (any leading dimensions, e.g. time).
    velocities : ndarray, same shape
        Their time derivatives, m/s.

    Returns
    -------
    frames : ndarray, shape (..., n_links, 3, 3)
        Rotations sensor -> world, lattice order.
    omega : ndarray, shape (..., n_links, 3)
        Angular velocity of each frame, rad/s, in that frame (body frame).
    """
    P = np.asarray(joints, dtype=float)
    V = np.asarray(velocities, dtype=float)
    if P.ndim < 3 or P.shape[-1] != 3 or P.shape[-3] < 2 or P.shape[-2] < 2:
        raise ValueError(f"Expected `joints` to have shape (..., rows, cols, 3) with rows, cols >= 2, "
                         f"got {P.shape}.")
    if V.shape != P.shape:
        raise ValueError(f"Expected `velocities` to have the shape of `joints` {P.shape}, got {V.shape}.")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(V))):
        raise ValueError("Expected `joints` and `velocities` to be finite; got NaN or inf.")
    return _frames(P, V)


def specific_force(frames: np.ndarray, accel_world_mps2: np.ndarray | None = None) -> np.ndarray:
    """Specific force in every sensor frame: ``Rᵀ (a + (0, 0, +G0))``, shape ``(n_links, 3)``, m/s².

    Parameters
    ----------
    frames : ndarray, shape (n_links, 3, 3)
        Rotations sensor -> world (`link_frames`).
    accel_world_mps2 : ndarray, shape (3,) or (n_links, 3), optional
        Motion acceleration of each link, world frame, m/s² (breaks the paper's Assumption 1).
    """
    frames = np.asarray(frames, dtype=float)
    if frames.ndim != 3 or frames.shape[1:] != (3, 3):
        raise ValueError(f"Expected `frames` to have shape (n_links, 3, 3), got {frames.shape}.")
    f_world = np.zeros((frames.shape[0], 3))
    f_world[:, 2] = G0
    if accel_world_mps2 is not None:
        a = np.asarray(accel_world_mps2, dtype=float)
        if a.shape not in ((3,), (frames.shape[0], 3)):
            raise ValueError(f"Expected `accel_world_mps2` to have shape (3,) or "
                             f"({frames.shape[0]}, 3), got {a.shape}.")
        f_world = f_world + a
    return np.einsum("nij,ni->nj", frames, f_world)


def ideal_readings(joints: np.ndarray) -> np.ndarray:
    """Noise-free readings of every link: specific force ``Rᵀ (0, 0, +G0)``, sensor frame.

    Parameters
    ----------
    joints : ndarray, shape (rows, cols, 3)
        Joint positions, metres, world frame.

    Returns
    -------
    ndarray, shape (n_links, 3)
        Specific force, m/s², sensor frame, lattice order.
    """
    return specific_force(link_frames(joints))


def link_angles(joints: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Roll, pitch and yaw of every link's frame: ``R = Rz(γ) Ry(β) Rx(α)`` (docs/design.md).

    Returns
    -------
    alpha, beta, gamma : ndarray, shape (n_links,)
        Radians; α, γ in (−π, π], β in [−π/2, π/2].
    """
    R = link_frames(joints)
    beta = np.arctan2(-R[:, 2, 0], np.hypot(R[:, 0, 0], R[:, 1, 0]))
    alpha = np.arctan2(R[:, 2, 1], R[:, 2, 2])
    gamma = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    return alpha, beta, gamma


# ---------------------------------------------------------------------------------------------
# Chebyshev net by the compass construction
# ---------------------------------------------------------------------------------------------

def _height(height: HeightFunction, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    z = np.asarray(height(x, y), dtype=float)
    z = np.broadcast_to(z, np.shape(x)).astype(float)
    return z


def _gradient(height: HeightFunction, x: np.ndarray, y: np.ndarray, step: float):
    """Central-difference gradient of the height field (only the Newton Jacobian uses it)."""
    hx = (_height(height, x + step, y) - _height(height, x - step, y)) / (2 * step)
    hy = (_height(height, x, y + step) - _height(height, x, y - step)) / (2 * step)
    return hx, hy


def bracketed_root(f, lo: float, hi: float, f_lo: float, f_hi: float, tol: float) -> float:
    """A root of ``f`` between ``lo`` and ``hi`` (``f_lo < 0 < f_hi``, their values), to ``tol`` plus
    a few units in the last place: the Illinois method (false position that halves the value kept at
    an end that has not moved twice in a row), falling back to the midpoint when rounding puts the
    step on an end; every step stays inside the bracket. What scipy's ``brentq`` did here, without
    importing scipy.optimize: ~0.9 s of CPU at the start of every process that builds a curved sheet
    (``capsheet virtual``'s default shape), for a root a dozen evaluations find."""
    a, b, fa, fb = lo, hi, f_lo, f_hi  # fa, fb: the values the secant uses (halved when stale)
    stale = 0  # +1: a moved last, -1: b moved last
    for _ in range(200):
        if b - a <= tol + 4.0 * np.finfo(float).eps * max(abs(a), abs(b)):
            break
        t = b - fb * (b - a) / (fb - fa)
        if not a < t < b:
            t = 0.5 * (a + b)
        ft = f(t)
        if ft == 0.0:
            return t
        if ft < 0.0:
            a, fa, f_lo = t, ft, ft
            if stale == 1:
                fb *= 0.5
            stale = 1
        else:
            b, fb, f_hi = t, ft, ft
            if stale == -1:
                fa *= 0.5
            stale = -1
    return a if -f_lo < f_hi else b


def _seed_line(height: HeightFunction, start: np.ndarray, direction: np.ndarray, n: int,
               L: float) -> np.ndarray:
    """``n`` joints after ``start`` (excluded) along horizontal ``direction``, each at 3D distance
    ``L`` from the previous: a curve on the surface over a straight line in the xy plane."""
    out = np.empty((n, 3))
    p = start
    u = direction
    for k in range(n):
        def f(t, p=p):
            z = float(_height(height, np.array(p[0] + t * u[0]), np.array(p[1] + t * u[1])))
            return np.sqrt(t * t + (z - p[2]) ** 2) - L
        # f(0) = -L < 0 and f(L) >= 0: the root is bracketed
        f_hi = f(L)
        if not np.isfinite(f_hi):
            raise ValueError(f"Chebyshev net: height field undefined near ({p[0] + L * u[0]:.6g}, "
                             f"{p[1] + L * u[1]:.6g}) while seeding a boundary line.")
        t = L if f_hi == 0.0 else bracketed_root(f, 0.0, L, -L, f_hi, tol=1e-16 * L)
        x, y = p[0] + t * u[0], p[1] + t * u[1]
        p = np.array([x, y, float(_height(height, np.array(x), np.array(y)))])
        out[k] = p
    return out


def _compass(height: HeightFunction, A: np.ndarray, B: np.ndarray, C: np.ndarray, L: float,
             ii: np.ndarray, jj: np.ndarray) -> np.ndarray:
    """New joints ``P`` (shape ``(m, 3)``) on the surface with ``|P−A| = |P−B| = L``, the root on
    the far side from ``C`` (Newton from the parallelogram point ``A + B − C``)."""
    def where(bad: np.ndarray) -> str:
        k = int(np.flatnonzero(bad)[0]) if np.any(bad) else 0
        return f"joint ({int(ii[k])}, {int(jj[k])}) and {int(np.count_nonzero(bad)) - 1} more"

    start = A + B - C
    q = start[:, :2].copy()
    step = 1e-6 * L
    L2 = L * L
    converged = False
    for _ in range(_NEWTON_MAX_ITER):
        z = _height(height, q[:, 0], q[:, 1])
        P = np.column_stack([q, z])
        dA, dB = P - A, P - B
        F = np.column_stack([np.sum(dA * dA, 1) - L2, np.sum(dB * dB, 1) - L2])
        if not np.all(np.isfinite(F)):
            bad = ~np.all(np.isfinite(F), axis=1)
            raise ValueError(f"Chebyshev net: height field undefined (NaN/inf) at {where(bad)} "
                             "joints; the sheet leaves the shape's domain.")
        if np.max(np.abs(F)) <= 1e-13 * L2:  # lengths to ~5e-14 relative
            converged = True
            break
        hx, hy = _gradient(height, q[:, 0], q[:, 1], step)
        # dP/dx = (1, 0, hx), dP/dy = (0, 1, hy); dF/dq = 2 (P − A)·dP/dq.
        J = np.empty((q.shape[0], 2, 2))
        J[:, 0, 0] = 2 * (dA[:, 0] + dA[:, 2] * hx)
        J[:, 0, 1] = 2 * (dA[:, 1] + dA[:, 2] * hy)
        J[:, 1, 0] = 2 * (dB[:, 0] + dB[:, 2] * hx)
        J[:, 1, 1] = 2 * (dB[:, 1] + dB[:, 2] * hy)
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        if np.any(np.abs(det) <= 1e-12 * L2):
            bad = np.abs(det) <= 1e-12 * L2
            raise ValueError(f"Chebyshev net: construction fails at {where(bad)} (two links "
                             "nearly collinear: the net folds or squashes; shape too steep?).")
        dx = (J[:, 1, 1] * F[:, 0] - J[:, 0, 1] * F[:, 1]) / det
        dy = (-J[:, 1, 0] * F[:, 0] + J[:, 0, 0] * F[:, 1]) / det
        # Damp steps longer than L/2: keeps Newton in the basin of the far root.
        sl = np.hypot(dx, dy)
        scale = np.minimum(1.0, 0.5 * L / np.maximum(sl, 1e-300))
        q[:, 0] -= scale * dx
        q[:, 1] -= scale * dy
    if not converged:
        bad = np.max(np.abs(F), axis=1) > 1e-13 * L2
        raise ValueError(f"Chebyshev net: Newton did not converge at {where(bad)} "
                         "(the two compass circles do not meet on the surface; shape too steep?).")
    # The near root is C itself; reject it and any folded cell (orientation flips).
    n_old = np.cross(A - C, B - C)
    n_new = np.cross(P - B, P - A)
    bad = (np.sum(n_old * n_new, 1) <= 0.0) | (np.linalg.norm(P - C, axis=1) < 0.2 * L)
    if np.any(bad):
        raise ValueError(f"Chebyshev net: the lattice folds at {where(bad)} "
                         "(shape too steep or too curved for this sheet).")
    return P


def compass_diagonals(rows: int, cols: int, ic: int, jc: int):
    """The order of the compass construction after the seed lines through anchor ``(ic, jc)``:
    anti-diagonal ``k = a + b`` (``a, b >= 1`` steps from the anchor) of all four quadrants at once,
    each joint needing only joints of diagonals ``k − 1`` and ``k − 2``. Yields per diagonal
    ``(ii, jj, si, sj)``: the joints' indices and their quadrant's signs, so that the two placed
    neighbours are ``(ii − si, jj)`` and ``(ii, jj − sj)`` and the opposite corner
    ``(ii − si, jj − sj)``."""
    quadrants = [(si, n_a, sj, n_b) for si, n_a in ((1, rows - 1 - ic), (-1, ic))
                 for sj, n_b in ((1, cols - 1 - jc), (-1, jc)) if n_a and n_b]
    k_max = max((n_a + n_b for _, n_a, _, n_b in quadrants), default=1)
    for k in range(2, k_max + 1):
        ii_l, jj_l, si_l, sj_l = [], [], [], []
        for si, n_a, sj, n_b in quadrants:
            a = np.arange(max(1, k - n_b), min(n_a, k - 1) + 1)
            ii_l.append(ic + si * a)
            jj_l.append(jc + sj * (k - a))
            si_l.append(np.full(a.shape, si))
            sj_l.append(np.full(a.shape, sj))
        ii, jj = np.concatenate(ii_l), np.concatenate(jj_l)
        if ii.size:
            yield ii, jj, np.concatenate(si_l), np.concatenate(sj_l)


def chebyshev_net(height: HeightFunction, rows: int, cols: int, link_length: float, *,
                  origin: tuple[float, float] = (0.0, 0.0), angle: float = 0.0,
                  shear: float = 0.0, anchor: str = "centre") -> np.ndarray:
    """Place an exact Chebyshev net (all links of length ``L``) on the height field ``z = height(x, y)``.

    Compass construction (docs/design.md "Exact ground truth"): the two seed lines through the anchor
    joint — along i (horizontal direction ``angle`` from +x) and along j (direction
    ``angle + π/2 + shear``) — are curves on the surface over straight lines in the xy plane, each
    step of 3D length exactly ``L``. Every other joint is then placed, anti-diagonal by
    anti-diagonal (vectorised), at distance ``L`` from its two placed neighbours ``A``, ``B`` and on
    the surface, by Newton from the parallelogram point ``A + B − C``.

    Parameters
    ----------
    height : callable
        Vectorised ``height(x, y) -> z`` (arrays of equal shape, metres). NaN outside its domain.
    rows, cols : int
        Joints along i and j, each >= 2.
    link_length : float
        ``L`` in metres, > 0.
    origin : (float, float), optional
        Horizontal position (x, y) of the anchor joint, metres.
    angle : float, optional
        Rotation of the i direction about world z, radians.
    shear : float, optional
        Extra angle between the seed lines beyond π/2, radians, ``|shear| < π/2``.
    anchor : {"centre", "corner"}, optional
        "centre" (default): the seed lines pass through joint ``(rows // 2, cols // 2)`` and the
        net grows into four quadrants, so the sheet is centred on ``origin``. "corner": the seed
        lines are the boundary lines ``i = 0`` and ``j = 0`` and ``P[0, 0]`` sits at ``origin``.

    Returns
    -------
    ndarray, shape (rows, cols, 3)
        Joints, metres, world frame; every link ``L`` to 1e-10 relative.

    Raises
    ------
    ValueError
        Invalid arguments, or the construction fails (the net would fold or squash, Newton does
        not converge, or the sheet leaves the height field's domain). The message says where.
    """
    Lattice(rows, cols)  # validates rows/cols
    L = float(link_length)
    if not (np.isfinite(L) and L > 0):
        raise ValueError(f"Invalid link_length: {link_length!r} (need a finite value > 0 m)")
    if not abs(shear) < np.pi / 2:
        raise ValueError(f"Invalid shear: {shear!r} rad (need |shear| < pi/2)")
    if anchor not in ("centre", "corner"):
        raise ValueError(f"Invalid anchor: {anchor!r} (expected 'centre' or 'corner')")
    u = np.array([np.cos(angle), np.sin(angle)])
    v = np.array([np.cos(angle + np.pi / 2 + shear), np.sin(angle + np.pi / 2 + shear)])

    ic, jc = (rows // 2, cols // 2) if anchor == "centre" else (0, 0)
    P = np.full((rows, cols, 3), np.nan)
    x0, y0 = float(origin[0]), float(origin[1])
    z0 = float(_height(height, np.array(x0), np.array(y0)))
    if not np.isfinite(z0):
        raise ValueError(f"Chebyshev net: height field undefined at the origin ({x0}, {y0}).")
    P[ic, jc] = (x0, y0, z0)
    if rows - 1 - ic:
        P[ic + 1:, jc] = _seed_line(height, P[ic, jc], u, rows - 1 - ic, L)
    if ic:
        P[ic - 1::-1, jc] = _seed_line(height, P[ic, jc], -u, ic, L)
    if cols - 1 - jc:
        P[ic, jc + 1:] = _seed_line(height, P[ic, jc], v, cols - 1 - jc, L)
    if jc:
        P[ic, jc - 1::-1] = _seed_line(height, P[ic, jc], -v, jc, L)

    for ii, jj, si, sj in compass_diagonals(rows, cols, ic, jc):
        P[ii, jj] = _compass(height, P[ii - si, jj], P[ii, jj - sj], P[ii - si, jj - sj], L,
                             ii, jj)
    err = np.max(np.abs(link_lengths(P) / L - 1.0))
    if not err <= _LENGTH_RTOL:
        raise ValueError(f"Chebyshev net: link lengths off by {err:.3g} relative (tolerance "
                         f"{_LENGTH_RTOL:g}); the height field may be discontinuous.")
    return P


def flat_net(rows: int, cols: int, link_length: float, *, angle: float = 0.0, shear: float = 0.0,
             origin: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """A level flat net, centred on ``origin``: joint ``(i, j)`` at ``(i − i_c) L u + (j − j_c) L v``
    with ``u``/``v`` the i/j directions of `chebyshev_net` (``i_c, j_c = rows // 2, cols // 2``).

    Returns
    -------
    ndarray, shape (rows, cols, 3)
        Joints, metres, world frame, z = 0.
    """
    Lattice(rows, cols)
    if not abs(shear) < np.pi / 2:
        raise ValueError(f"Invalid shear: {shear!r} rad (need |shear| < pi/2)")
    L = float(link_length)
    if not (np.isfinite(L) and L > 0):
        raise ValueError(f"Invalid link_length: {link_length!r} (need a finite value > 0 m)")
    u = np.array([np.cos(angle), np.sin(angle), 0.0])
    v = np.array([np.cos(angle + np.pi / 2 + shear), np.sin(angle + np.pi / 2 + shear), 0.0])
    i = (np.arange(rows) - rows // 2)[:, None, None]
    j = (np.arange(cols) - cols // 2)[None, :, None]
    P = L * (i * u + j * v)
    P[..., 0] += origin[0]
    P[..., 1] += origin[1]
    return P
