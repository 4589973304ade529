"""The rest shape (joints, normals, areas, noise) and the deformation against it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from protocol.lattice import joint_normals

from ..estimator import ShapeEstimate
from ..metrics import rigid_fit

__all__ = ["RestShape", "deformation", "normal_fit"]


def _joint_areas(P: np.ndarray) -> np.ndarray:
    """Rest area of every joint: a quarter of each adjacent cell (trapezoid rule), m²."""
    d1 = P[1:, 1:] - P[:-1, :-1]
    d2 = P[:-1, 1:] - P[1:, :-1]
    cell = 0.5 * np.linalg.norm(np.cross(d1, d2), axis=-1)
    out = np.zeros(P.shape[:2])
    out[:-1, :-1] += cell / 4
    out[1:, 1:] += cell / 4
    out[:-1, 1:] += cell / 4
    out[1:, :-1] += cell / 4
    return out


def _curvatures(P: np.ndarray, normals: np.ndarray, half: int = 2) -> np.ndarray:
    """Principal curvatures of the surface through the joints, shape ``(rows, cols, 2)``, 1/m,
    positive where the surface curves away from its normal (convex, as a foam ball's top).

    At every joint, the joints within ``half`` lattice steps (a 5 x 5 window at the default,
    clipped at the edges) are written in the joint's tangent frame and a quadric
    ``z = a x²/2 + b x y + c y²/2 + p x + q y + r`` is fitted by least squares; the curvatures
    are the eigenvalues of ``−[[a, b], [b, c]]``, larger first. The window smooths a learned
    rest's noise (curvature is a second difference).
    """
    rows, cols = P.shape[:2]
    out = np.zeros((rows, cols, 2))
    for i in range(rows):
        for j in range(cols):
            n = normals[i, j]
            e1 = np.cross([0.0, 1.0, 0.0] if abs(n[0]) > 0.9 else [1.0, 0.0, 0.0], n)
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(n, e1)
            X = P[max(i - half, 0):i + half + 1, max(j - half, 0):j + half + 1].reshape(-1, 3)
            X = X - P[i, j]
            x, y, z = X @ e1, X @ e2, X @ n
            A = np.stack([0.5 * x * x, x * y, 0.5 * y * y, x, y, np.ones_like(x)], axis=1)
            a, b, c = np.linalg.lstsq(A, z, rcond=None)[0][:3]
            out[i, j] = np.linalg.eigvalsh(-np.array([[a, b], [b, c]]))[::-1]
    return out


def _yaws_of(P: np.ndarray) -> np.ndarray:
    """Yaw of every link (docs/design.md link order) from joints: sensor x is ``Rz(γ) Ry(β) e_x``, so
    ``γ = atan2(d_y, d_x)`` of the link vector."""
    di = (P[1:, :] - P[:-1, :]).reshape(-1, 3)
    dj = (P[:, 1:] - P[:, :-1]).reshape(-1, 3)
    d = np.concatenate([di, dj])
    return np.arctan2(d[:, 1], d[:, 0])


@dataclass(frozen=True, eq=False)
class _Prior:
    """What `estimate` reads from ``previous``: joints and yaws."""

    joints: np.ndarray
    yaws: np.ndarray


@dataclass(frozen=True, eq=False)
class RestShape:
    """The sheet untouched: joints, normals, joint areas and displacement noise.

    Attributes
    ----------
    joints : ndarray, shape (rows, cols, 3)
        Metres, the frame the deformation is reported in.
    link_length : float
        ``L``, metres.
    noise_m : ndarray, shape (rows, cols), optional
        Standard deviation of every joint's normal displacement while untouched, metres (None:
        unknown; `find_contacts` then uses a robust spread of each frame).
    yaws : ndarray, shape (n_links,), optional
        Link yaws for the estimator's prior (default: from the joints).
    noise_samples_m : ndarray, shape (S, rows, cols), optional
        The untouched snapshots' normal displacements from their mean, metres (`learn` keeps
        them): the joints' noise is correlated (heights are integrated slopes), and the contact
        fit states its uncertainties from these samples (a sandwich estimate) instead of
        assuming independent joints.

    Derived: ``normals`` (rows, cols, 3), out of the foam; ``areas`` (rows, cols), m², a quarter
    of every adjacent cell; ``curvatures`` (rows, cols, 2), the principal curvatures, 1/m,
    positive where convex (`Foam.k_at` makes the layer softer there).
    """

    joints: np.ndarray
    link_length: float
    noise_m: np.ndarray | None = None
    yaws: np.ndarray | None = None
    noise_samples_m: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        P = np.array(self.joints, dtype=float)
        if P.ndim != 3 or P.shape[2] != 3 or min(P.shape[:2]) < 2:
            raise ValueError(f"Expected `joints` to have shape (rows, cols, 3), got {P.shape}.")
        object.__setattr__(self, "joints", P)
        if self.noise_m is not None and np.shape(self.noise_m) != P.shape[:2]:
            raise ValueError(f"Expected `noise_m` to have shape {P.shape[:2]}, got "
                             f"{np.shape(self.noise_m)}.")
        yaws = _yaws_of(P) if self.yaws is None else np.asarray(self.yaws, float)
        object.__setattr__(self, "yaws", yaws)
        object.__setattr__(self, "normals", joint_normals(P))
        object.__setattr__(self, "areas", _joint_areas(P))
        object.__setattr__(self, "curvatures", _curvatures(P, self.normals))

    @property
    def rows(self) -> int:
        return self.joints.shape[0]

    @property
    def cols(self) -> int:
        return self.joints.shape[1]

    def k_map(self, foam) -> np.ndarray:
        """``foam.k_at(self.curvatures)``, Pa/m, shape (rows, cols), cached per foam."""
        cache = self.__dict__.setdefault("_k_cache", {})
        if foam not in cache:
            cache[foam] = foam.k_at(self.curvatures)
        return cache[foam]

    @property
    def prior(self) -> _Prior:
        """The estimator's ``previous=``: the rest joints and yaws."""
        return _Prior(self.joints, self.yaws)

    @classmethod
    def from_joints(cls, joints: np.ndarray, link_length: float,
                    noise_m: np.ndarray | None = None) -> "RestShape":
        """A known rest shape (e.g. the body's design), joints ``(rows, cols, 3)`` in metres."""
        return cls(joints=joints, link_length=float(link_length), noise_m=noise_m)

    @classmethod
    def learn(cls, snapshots: Sequence[ShapeEstimate | np.ndarray],
              link_length: float | None = None, noise_floor_fraction: float = 1.0
              ) -> "RestShape":
        """Learn the rest shape from an untouched period.

        Every snapshot's joints are overlaid on the first (rigid least squares), averaged; the
        noise of every joint is the standard deviation of its normal displacement from the mean,
        raised to its upper confidence bound ``× (1 + 2 / sqrt(2 (n − 1)))`` for ``n`` snapshots
        (a standard deviation from 32 snapshots is uncertain by ±13 %; a 5σ threshold from an
        underestimate passes noise: the sphere's corner did at 0.3 % g), then the largest over
        every joint's 3 x 3 neighbourhood (edge and corner joints are the noisiest and their
        estimates the least certain), floored at ``noise_floor_fraction`` × the median over joints.

        Parameters
        ----------
        snapshots : sequence of ShapeEstimate or ndarray, shape (rows, cols, 3)
            At least 2 (better 20+) shapes of the untouched sheet.
        link_length : float, optional
            ``L``, metres (default: from the estimates).
        """
        snaps = list(snapshots)
        if len(snaps) < 2:
            raise ValueError(f"RestShape.learn needs at least 2 snapshots, got {len(snaps)}.")
        if link_length is None:
            if not isinstance(snaps[0], ShapeEstimate):
                raise ValueError("RestShape.learn: give link_length with plain joint arrays.")
            link_length = snaps[0].link_length
        P = [np.asarray(s.joints if isinstance(s, ShapeEstimate) else s, float) for s in snaps]
        shape = P[0].shape
        if any(p.shape != shape for p in P):
            raise ValueError(f"RestShape.learn: snapshots of different shapes "
                             f"{sorted({p.shape for p in P})}.")
        ref = P[0].reshape(-1, 3)
        al = np.array([rigid_fit(p.reshape(-1, 3), ref) for p in P])
        mean = al.mean(axis=0)
        al = np.array([rigid_fit(a, mean) for a in al])
        mean = al.mean(axis=0).reshape(shape)
        n = joint_normals(mean)
        d = np.einsum("sjk,jk->sj", al - mean.reshape(-1, 3), n.reshape(-1, 3))
        from scipy.ndimage import maximum_filter
        noise = d.std(axis=0, ddof=1).reshape(shape[:2]) * (1 + 2 / np.sqrt(2 * (len(P) - 1)))
        noise = maximum_filter(noise, size=3, mode="nearest")
        noise = np.maximum(noise, noise_floor_fraction * np.median(noise))
        yaws = None
        if all(isinstance(s, ShapeEstimate) for s in snaps):
            y = np.array([s.yaws for s in snaps])
            yaws = np.angle(np.exp(1j * y).mean(axis=0))
        return cls(joints=mean, link_length=float(link_length), noise_m=noise, yaws=yaws,
                   noise_samples_m=(d - d.mean(axis=0)).reshape((len(P),) + shape[:2]))


#: Weight of the tangential (point-to-point) residuals against the normal ones in `normal_fit`:
#: just enough to fix the motions the normals cannot see (sliding along a plane, rotation about a
#: sphere's centre or a cylinder's axis), small enough that the sheet's sliding does not tilt the fit.
TANGENTIAL_WEIGHT = 1e-2


def _rotation(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` (Rodrigues), radians."""
    th = float(np.linalg.norm(w))
    if th < 1e-300:
        return np.eye(3)
    a = w / th
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(th) * K + (1.0 - np.cos(th)) * (K @ K)


def normal_fit(src: np.ndarray, dst: np.ndarray, normals: np.ndarray, weights: np.ndarray,
               tangential_weight: float = TANGENTIAL_WEIGHT, iterations: int = 6,
               start: np.ndarray | None = None) -> np.ndarray:
    """``src`` moved rigidly onto ``dst`` by the normal distances (point-to-plane least squares).

    Starts from `host.analysis.metrics.rigid_fit` (point-to-point, weighted), then minimises
    ``Σ w_i [((q_i − p_i') · n_i)² + ε ‖q_i − p_i'‖²]`` over small rotations and translations
    (Gauss-Newton, ``ε = tangential_weight``). Why: the sheet lies on the foam without being
    glued to it; its links keep their length, so a dent pulls the sheet in sideways (the joints
    slide along the surface by up to ~0.2 mm at 2 N). On a curved body a point-to-point overlay
    turns that sliding into a rotation or translation with a normal component, reading every
    joint too shallow (−15 to −25 % of the force on the cylinder and the sphere, with the moved
    joints already excluded). The normal distances are blind to sliding; ``ε`` only fixes the
    motions that move no joint off the rest surface (those are the body's symmetries).

    Parameters
    ----------
    src, dst : ndarray, shape (n, 3)
        Points, metres (``dst`` the rest joints).
    normals : ndarray, shape (n, 3)
        Unit rest normals at ``dst``.
    weights : ndarray, shape (n,)
        Non-negative weight of every point (0: not in the fit).
    start : ndarray, shape (n, 3), optional
        ``src`` already moved close (a previous fit): the Gauss-Newton steps start there
        instead of at the point-to-point overlay.

    Returns
    -------
    ndarray, shape (n, 3)
        ``src`` after the rigid motion, metres, ``dst``'s frame.
    """
    w = np.asarray(weights, float)
    p = rigid_fit(src, dst, w) if start is None else np.asarray(start, float)
    n = np.asarray(normals, float)
    eps = float(tangential_weight)
    W = w.sum()
    for _ in range(iterations):
        c = (w @ p) / W
        x = p - c
        A = np.concatenate([_cross(x, n), n], axis=1)   # d(normal residual)/d(rotation, shift)
        e = dst - p
        r = np.sum(e * n, axis=1)
        Aw = A * w[:, None]
        M = Aw.T @ A
        b = Aw.T @ r
        # ε × point-to-point, in closed form (x is centred, so rotation and shift decouple):
        # Σ w (|x|² I − x xᵀ) for the rotation, W I for the shift; right side Σ w x × e, Σ w e
        xw = x * w[:, None]
        M[:3, :3] += eps * (np.sum(xw * x) * np.eye(3) - xw.T @ x)
        M[3:, 3:] += eps * W * np.eye(3)
        b[:3] += eps * np.sum(_cross(xw, e), axis=0)
        b[3:] += eps * (w @ e)
        step = np.linalg.solve(M, b)
        p = x @ _rotation(step[:3]).T + c + step[3:]
        if np.max(np.abs(step)) < 1e-9:   # 1 nm, 1 nrad
            break
    return p


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of two ``(n, 3)`` arrays (np.cross without its axis handling)."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def deformation(joints: np.ndarray, rest: RestShape, *, exclude: np.ndarray | None = None,
                trim_sigma: float = 3.0, trim_floor_m: float | None = None, iterations: int = 4,
                baseline_m: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Normal displacement of every joint against the rest shape.

    The joints are overlaid on the rest joints by a rigid fit of the normal distances
    (`normal_fit`: the sheet's sliding along the surface does not tilt it) that ignores moved
    joints (iterated: weight 0 for ``|d| > max(trim_sigma · σ, trim_floor_m)``, ``σ`` a robust
    spread of ``d``), then ``d_i = (rest_i − joints_i) · n_i`` with ``n_i`` the rest normal (top
    face, pointing out of the foam).

    Parameters
    ----------
    joints : ndarray, shape (rows, cols, 3)
        Estimated joints, metres, any rigid placement (the estimator's gauge).
    rest : RestShape
    exclude : ndarray of bool, shape (rows, cols), optional
        Joints known to be moved (e.g. contacts found in a first pass with their skirts): left
        out of the fit, so the dents' shallow tails do not bias it.
    baseline_m : ndarray, shape (rows, cols), optional
        The rest surface's slow drift along its normals, metres, positive into the foam
        (`TactileSensor`'s baseline): the joints are compared with ``rest − baseline n``.

    Returns
    -------
    displacement : ndarray, shape (rows, cols)
        Metres, positive into the foam, from the drifted rest surface.
    aligned : ndarray, shape (rows, cols, 3)
        The joints overlaid on the rest shape, metres, rest frame.
    """
    P = np.asarray(joints, float)
    if P.shape != rest.joints.shape:
        raise ValueError(f"Expected `joints` to have shape {rest.joints.shape}, got {P.shape}.")
    src, dst = P.reshape(-1, 3), rest.joints.reshape(-1, 3)
    n = rest.normals.reshape(-1, 3)
    if baseline_m is not None:
        dst = dst - np.asarray(baseline_m, float).reshape(-1, 1) * n
    floor = 0.01 * rest.link_length if trim_floor_m is None else float(trim_floor_m)
    allowed = np.ones(len(src), bool) if exclude is None else ~np.asarray(exclude, bool).ravel()
    if allowed.sum() < 4:
        allowed = np.ones(len(src), bool)
    moved = rigid_fit(src, dst, allowed.astype(float))
    kept = None
    for _ in range(iterations):
        d = np.sum((dst - moved) * n, axis=1)
        r = d - np.median(d[allowed])
        s = 1.4826 * np.median(np.abs(r[allowed]))
        keep = allowed & (np.abs(r) <= max(trim_sigma * s, floor))
        if keep.sum() < 6:
            keep = allowed
        if kept is not None and np.array_equal(keep, kept):
            break   # the same joints as the last fit: it would not move
        kept = keep
        moved = normal_fit(src, dst, n, keep.astype(float), start=moved)
    d = np.sum((dst - moved) * n, axis=1)
    return d.reshape(P.shape[:2]), moved.reshape(P.shape)
