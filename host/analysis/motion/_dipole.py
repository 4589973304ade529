"""A local magnetic disturbance's shape: a point dipole fitted to the links' fields.

A magnet or a steel part beside the sheet adds ``B = μ0/4π (3 r̂ (μ·r̂) − μ) / |r|³`` to Earth's
uniform field (docs/motion.md, "The magnetic field"). Per link nothing tells a smooth turn of the
field from a turn of the sheet; across the sheet the dipole's field falls off with the cube of the
distance while Earth's stays uniform, so the two are told apart by their shape: `fit_dipole` fits,
to every link's field in the world frame at its estimated position, a uniform field per link
family (the i-links, the j-links: a level sheet's unknown shear turns each family's fields alike)
plus one dipole. Given the dipole's position ``q`` the model is linear in the uniform fields and
the moment, so they are solved in closed form and only ``q`` is iterated (variable projection,
Levenberg-Marquardt on ``q`` with a forward-difference Jacobian).

The fitted dipole's field is then taken out of every link's reading (`MotionEstimator`), and what
is left is Earth's field: the heading tests and the sheet's heading see it undisturbed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: μ0 / 4π, T·m/A (CODATA 2018: μ0 = 1.25663706212e-6)
_C = 1.25663706212e-6 / (4.0 * np.pi)


@dataclass(frozen=True)
class DipoleFit:
    """A fitted disturbance: ``position_m`` (3,) and ``moment_am2`` (3,) in the frame of the
    points it was fitted to; ``uniform_t`` (families, 3) the uniform fields; ``rms_t`` the fit's
    RMS residual per component, ``rms_uniform_t`` that of uniform fields alone (no dipole)."""

    position_m: np.ndarray
    moment_am2: np.ndarray
    uniform_t: np.ndarray
    rms_t: float
    rms_uniform_t: float

    def field(self, points: np.ndarray) -> np.ndarray:
        """The dipole's field at ``points`` (n, 3), tesla."""
        return dipole_field(points, self.position_m, self.moment_am2)


def _kernel(points: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``K`` (n, 3, 3), symmetric, with ``dipole_field = K μ``."""
    r = points - q
    d2 = np.maximum(np.einsum("ki,ki->k", r, r), 1e-12)
    s = (_C / (d2 * np.sqrt(d2)))
    K = (3.0 * s / d2)[:, None, None] * (r[:, :, None] * r[:, None, :])
    K[:, 0, 0] -= s
    K[:, 1, 1] -= s
    K[:, 2, 2] -= s
    return K


def dipole_field(points: np.ndarray, position, moment) -> np.ndarray:
    """A point dipole's field at ``points`` (n, 3), m: tesla, shape (n, 3)."""
    return np.einsum("kij,j->ki", _kernel(np.asarray(points, float), np.asarray(position, float)),
                     np.asarray(moment, float))


def _solve(points, fields, onehot, q):
    """The uniform fields and the moment that fit best for a dipole at ``q``, and the residual
    (``onehot``: (n, families), each point's family)."""
    n, n_fam = onehot.shape
    K = _kernel(points, q)
    # columns: per family a uniform field (3 each), then the moment (3), scaled to unit size
    Kf = K.reshape(3 * n, 3)  # rows (k, i)
    ks = float(np.sqrt(np.einsum("ij,ij->", Kf, Kf) / n)) or 1.0
    A = K.transpose(1, 0, 2).reshape(3, 3 * n)  # K symmetric: A @ x sums K_k x_k
    m = 3 * n_fam + 3
    N = np.zeros((m, m))
    b = np.empty(m)
    counts = onehot.sum(axis=0)
    sk = (onehot.T @ K.reshape(n, 9)).reshape(n_fam, 3, 3) / ks
    sw = onehot.T @ fields
    for f in range(n_fam):
        s = slice(3 * f, 3 * f + 3)
        N[s, s] = np.eye(3) * counts[f]
        N[s, -3:] = sk[f]
        N[-3:, s] = sk[f].T
        b[s] = sw[f]
    N[-3:, -3:] = (A @ Kf) / (ks * ks)
    b[-3:] = (A @ fields.ravel()) / ks
    try:
        x = np.linalg.solve(N, b)
    except np.linalg.LinAlgError:
        return None
    U = x[:-3].reshape(n_fam, 3)
    mu = x[-3:] / ks
    res = fields - onehot @ U - (Kf @ mu).reshape(n, 3)
    return U, mu, res


def fit_dipole(points: np.ndarray, fields: np.ndarray, family: np.ndarray, start: np.ndarray,
               iterations: int = 4, min_distance_m: float = 0.0) -> DipoleFit | None:
    """Fit uniform fields per family plus a point dipole to ``fields`` (n, 3), tesla, world frame,
    at ``points`` (n, 3), m (module docstring).

    Parameters
    ----------
    family : ndarray of int, shape (n,)
        Each point's family (0 .. families − 1): one uniform field each.
    start : ndarray, shape (3,) or (k, 3)
        The dipole's starting position(s); from several, the best one is iterated.
    min_distance_m : float
        The dipole is kept at least this far from every point (a magnet inside the sheet is
        not a dipole the links could tell from their own errors).

    Returns None when no start gives a solvable fit.
    """
    points = np.asarray(points, float)
    fields = np.asarray(fields, float)
    family = np.asarray(family, dtype=np.intp)
    n_fam = int(family.max()) + 1
    onehot = (family[:, None] == np.arange(n_fam)).astype(float)
    starts = np.atleast_2d(np.asarray(start, float))

    def cost(q):
        if min_distance_m > 0 and np.min(np.sum((points - q) ** 2, axis=1)) < min_distance_m ** 2:
            return np.inf, None
        s = _solve(points, fields, onehot, q)
        if s is None:
            return np.inf, None
        return float(np.sum(s[2] ** 2)), s

    best = min(((cost(q), q) for q in starts), key=lambda c: c[0][0])
    (c0, sol), q = best
    if sol is None:
        return None
    scale = float(np.ptp(points, axis=0).max()) or 1.0
    lam = 1e-3
    for _ in range(iterations):
        h = 1e-4 * scale
        r0 = sol[2].ravel()
        J = np.empty((r0.size, 3))
        for i in range(3):
            dq = np.zeros(3)
            dq[i] = h
            s = _solve(points, fields, onehot, q + dq)
            if s is None:
                return None
            J[:, i] = (s[2].ravel() - r0) / h
        JtJ = J.T @ J
        g = J.T @ r0
        for _try in range(6):
            step = -np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ) + 1e-30), g)
            c1, s1 = cost(q + step)
            if c1 < c0:
                q, c0, sol = q + step, c1, s1
                lam = max(lam / 4.0, 1e-6)
                break
            lam *= 8.0
        else:
            break
    U, mu, res = sol
    n = points.shape[0]
    # uniform fields alone: each family's mean
    counts = np.bincount(family, minlength=n_fam)
    means = np.stack([np.bincount(family, weights=fields[:, i], minlength=n_fam) for i in range(3)],
                     axis=1) / np.maximum(counts, 1)[:, None]
    rms_u = float(np.sqrt(np.mean((fields - means[family]) ** 2)))
    return DipoleFit(np.array(q), mu, U, float(np.sqrt(c0 / (3 * n))), rms_u)


#: a fit is tried again this many snapshots after one was rejected (doubling up to `_RETRY_MAX`)
_RETRY_MIN, _RETRY_MAX = 8, 128
#: the links a fit uses at most (a stride over the valid links beyond): the dipole has 6 numbers,
#: a few hundred links fix them, and the fit's cost grows with the links
_FIT_LINKS = 512


class LocalField:
    """Tracks a local disturbance across snapshots for `MotionEstimator`: a dipole fitted to the
    links' fields (`fit_dipole`), warm-started from the last snapshot's (the sheet moves, the
    disturbance is fixed in the world, so in the estimate's frame it moves with the sheet), and
    taken out of the readings while the fit is significant.

    Parameters
    ----------
    family : ndarray of int, shape (n_links,)
        0 for the i-links, 1 for the j-links.
    significance : float
        The F statistic of the dipole's six numbers against uniform fields alone above which
        the fit is used (0: never fitted).
    min_distance_m : float
        How near a link the dipole may sit.
    span_m : float
        The sheet's side: the starting grid of a fresh fit lies ``span_m / 4`` about its centre.
    position_std_m : float
        How far each link's estimated position may be from its true one (0: the fit's field is
        taken as exact): with it `model_var_t2` says how much of a link's field the fit cannot
        know, the dipole's gradient times that distance.
    """

    def __init__(self, family: np.ndarray, significance: float, min_distance_m: float,
                 span_m: float, position_std_m: float = 0.0) -> None:
        self.family = np.asarray(family, dtype=np.intp)
        self.significance = float(significance)
        self.min_distance_m = float(min_distance_m)
        self.span_m = float(span_m)
        self.position_std_m = float(position_std_m)
        #: per link, the variance of what the used fit's field leaves out (T² per component),
        #: None while no fit is used: where the field changes by µT per millimetre (next to the
        #: magnet) an estimated position millimetres off leaves µT in the corrected reading,
        #: which is the fit's error, not a disturbance it has not explained
        self.model_var_t2: np.ndarray | None = None
        self.fit: DipoleFit | None = None
        self.f_stat = 0.0
        self._wait = 0
        self._retry = _RETRY_MIN

    def remove(self, R: np.ndarray, m: np.ndarray, points, v: np.ndarray) -> np.ndarray:
        """The readings ``m`` (n, 3, link frames) less the fitted dipole's field (``Rᵀ B_d`` at
        each link's ``points``, world: an array, or a callable that makes it when it is needed),
        or ``m`` itself while no fit is significant."""
        self.model_var_t2 = None
        if self.significance <= 0:
            return m
        if self.fit is None:
            if self._wait > 0:
                self._wait -= 1
                return m
        if callable(points):
            points = points()
        idx = np.flatnonzero(v)
        if idx.size < 16:
            self.fit = None
            return m
        if idx.size > _FIT_LINKS:
            idx = idx[:: -(-idx.size // _FIT_LINKS)]
        W = np.einsum("kij,kj->ki", R[idx], m[idx])
        p = points[idx]
        if self.fit is not None:
            starts, its = self.fit.position_m, 1
        else:
            c, s = p.mean(axis=0), self.span_m / 4.0
            corners = [[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
            starts = c + s * np.array(corners)
            its = 8
        fit = fit_dipole(p, W, self.family[idx], starts, its, self.min_distance_m)
        self.f_stat = 0.0
        if fit is not None and fit.rms_t > 0:
            n_fam = int(self.family[idx].max()) + 1
            dof = 3 * idx.size - 3 * n_fam - 6
            self.f_stat = ((fit.rms_uniform_t ** 2 - fit.rms_t ** 2) * 3 * idx.size / 6.0) / (
                fit.rms_t ** 2 * 3 * idx.size / dof)
        if fit is None or self.f_stat < self.significance:
            self.fit = None
            self._wait = self._retry
            self._retry = min(2 * self._retry, _RETRY_MAX)
            return m
        self.fit = fit
        self._retry = _RETRY_MIN
        d = fit.field(points)
        if self.position_std_m > 0:
            # a dipole's field falls as 1/r³: its gradient is at most 3 |B| / r along r
            r = np.linalg.norm(points - fit.position_m, axis=1)
            g = 3.0 * np.linalg.norm(d, axis=1) / np.maximum(r, 1e-9)
            self.model_var_t2 = (g * self.position_std_m) ** 2
        return np.where(v[:, None], m - np.einsum("kji,kj->ki", R, d), m)
