"""The contact fit: forces and footprints from the dent, by the layer's linear response.

Every contact is a line of uniform-pressure discs (`response.line_response`: centre, half-width
``a``, half-length ``ℓ``, angle ``θ``; ``ℓ = 0`` is a round contact) with a force ``F``; the
displacement over the contacts' supports is modelled as

    d_i = Σ_c F_c T_c(x_i) + o_{c(i)} + noise,

``T_c`` the unit-force response (so ``F_c`` is newtons, nothing integrated), ``o_c`` an offset
over contact ``c``'s own support (the joints' heights come from integrated slopes: their error
is smooth, a local level absorbs most of it). The forces and offsets enter linearly; for any
geometry they are the linear least-squares solution, and only the geometry is iterated
(variable projection, Golub & Pereyra 1973, with Kaufman's Jacobian; Levenberg-Marquardt steps;
a contact's length and direction as one vector ``q = ℓ (cos θ, sin θ)``, in which the response is
smooth also for a round contact).
The covariance of the solution, scaled by the residual, gives every figure's standard deviation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .response import line_response, pressure_half_axes

__all__ = ["ContactGeometry", "FitResult", "fit_contacts"]

#: Geometry parameters per contact: centre (2), half-width a, half-length ℓ, angle θ.
NPAR = 5


@dataclass(frozen=True)
class ContactGeometry:
    """A contact's pressure geometry in its tangent frame (metres, radians)."""

    u: float
    v: float
    a: float
    half_length: float
    angle: float

    def as_array(self) -> np.ndarray:
        return np.array([self.u, self.v, self.a, self.half_length, self.angle])


@dataclass(frozen=True, eq=False)
class FitResult:
    """What `fit_contacts` found.

    Attributes
    ----------
    geometry : list of ContactGeometry
    force_n : ndarray, shape (m,)
    offset_m : ndarray, shape (m,)
    cov : ndarray, shape (p, p)
        Covariance of ``[F_1..F_m, o_1..o_G, g_1..g_m]`` (geometry in `ContactGeometry` order),
        scaled by the residual's variance.
    rss : float
        Sum of squared residuals, m².
    residual : ndarray, shape (n,)
        Displacement minus the model, metres.
    responses : ndarray, shape (n, m)
        Every contact's unit-force response at the joints, metres per newton (its dent is
        ``force_n[c] * responses[:, c]``).
    n : int
        Joints in the fit.
    iterations : int
    """

    geometry: list
    force_n: np.ndarray
    offset_m: np.ndarray
    cov: np.ndarray
    rss: float
    n: int
    iterations: int
    residual: np.ndarray | None = None
    responses: np.ndarray | None = None

    def force_std(self) -> np.ndarray:
        m = len(self.geometry)
        return np.sqrt(np.maximum(np.diag(self.cov)[:m], 0.0))

    def parameter_cov(self, c: int) -> np.ndarray:
        """Covariance of contact ``c``'s fitted parameters ``(u, v, a, q_x, q_y)``, shape
        (5, 5), ``q = ℓ (cos θ, sin θ)``: smooth also for a round contact (where ``θ`` has no
        variance to speak of)."""
        i0 = len(self.force_n) + len(self.offset_m) + NPAR * c
        return self.cov[i0:i0 + NPAR, i0:i0 + NPAR]

    def half_axes(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        """Pressure half-axes (major, minor) of contact ``c`` and their standard deviations,
        metres (`response.pressure_half_axes`; delta method over ``a`` and ``ℓ``)."""
        g = self.geometry[c]
        ax = np.array(pressure_half_axes(g.a, g.half_length))
        Cq = self.parameter_cov(c)
        e = np.array([np.cos(g.angle), np.sin(g.angle)])
        # (a, ℓ) with dℓ = e · dq; then d(major)/d(a, ℓ) = (a, 4ℓ/3) / major, d(minor) = (1, 0)
        C = np.array([[Cq[2, 2], Cq[2, 3:5] @ e], [Cq[2, 3:5] @ e, e @ Cq[3:5, 3:5] @ e]])
        J = np.array([[g.a / ax[0], 4.0 * g.half_length / (3.0 * ax[0])], [1.0, 0.0]])
        return ax, np.sqrt(np.maximum(np.diag(J @ C @ J.T), 0.0))


def _model(XY, owner, g, m, lam, ks, jac):
    """Unit-force responses (n, m) and their geometry Jacobians (list of (n, 5))."""
    T = np.empty((XY[0].shape[0], m))
    Js = []
    for c in range(m):
        u, v, a, qx, qy = g[NPAR * c:NPAR * c + NPAR]
        hl, th = float(np.hypot(qx, qy)), float(np.arctan2(qy, qx))
        if jac:
            T[:, c], J = line_response(XY[c], np.array([u, v]), a, hl, th, lam, ks[c], True)
            Js.append(J)
        else:
            T[:, c] = line_response(XY[c], np.array([u, v]), a, hl, th, lam, ks[c])
    return T, Js


def fit_contacts(d: np.ndarray, XY: list, owner: np.ndarray, start: list, lam: float,
                 ks: list, bounds: list, max_iter: int = 12, tol: float = 2e-3,
                 ftol: float = 1e-3,
                 prior_a: float | None = None, prior_a_std: float = 1.0,
                 prior_length_std: float | None = None, noise_m: float = 1e-4,
                 noise_samples: np.ndarray | None = None) -> FitResult:
    """Fit the contacts' forces, offsets and geometry (module docstring).

    Parameters
    ----------
    d : ndarray, shape (n,)
        Displacement of the joints in the fit, metres, positive into the foam.
    XY : list of ndarray, shape (n, 2)
        The same joints in every contact's tangent frame, metres.
    owner : ndarray of int, shape (n,)
        The offset a joint carries (0, 1, ...: one per group of joints, usually one per
        contact's own support).
    start : list of ContactGeometry
    lam : float
        Spreading length, metres.
    ks : list of float
        The layer's stiffness at every contact, Pa/m.
    bounds : list of (lo, hi) arrays, shape (5,) each
        Box bounds of every contact's geometry.
    max_iter : int
        Levenberg-Marquardt iterations at most.
    tol, ftol : float
        Stop when no parameter moved by more than ``tol`` of 1 cm, or the cost fell by less
        than ``ftol`` of itself: the rest is far below the noise.
    prior_a, prior_a_std : float, optional
        A Gaussian prior on every contact's half-width ``a``, metres (`DetectorSettings`).
    prior_length_std : float, optional
        A Gaussian prior on every contact's half-length ``ℓ`` (its vector ``q``) about 0,
        metres: a round contact stays round where the data barely prefer a short line.
    noise_m : float
        The joints' displacement noise, metres: the prior's weight is that of one joint.
    noise_samples : ndarray, shape (S, n), optional
        Samples of the joints' noise (an untouched period's displacements from their mean,
        `RestShape.noise_samples_m`): the covariance is then the sandwich
        ``H⁻¹ (Aᵀ Σ A + prior) H⁻¹`` with ``Σ`` their covariance, which holds for correlated
        noise; without them the residual's variance, joints independent.
    """
    m = len(start)
    n = d.shape[0]
    n_off = int(owner.max()) + 1
    O = np.zeros((n, n_off))
    O[np.arange(n), owner] = 1.0
    # parameters (u, v, a, q_x, q_y), q = ℓ (cos θ, sin θ); ℓ's bound becomes a box on q
    g = np.concatenate([[s.u, s.v, s.a, s.half_length * np.cos(s.angle),
                         s.half_length * np.sin(s.angle)] for s in start])
    lo = np.concatenate([[b[0][0], b[0][1], b[0][2], -b[1][3], -b[1][3]] for b in bounds])
    hi = np.concatenate([[b[1][0], b[1][1], b[1][2], b[1][3], b[1][3]] for b in bounds])
    g = np.clip(g, lo, hi)
    scale = np.full(NPAR * m, 1e-2)   # convergence: in units of 1 cm

    def solve(g, jac):
        T, Js = _model(XY, owner, g, m, lam, ks, jac)
        B = np.concatenate([T, O], axis=1)
        Q, R = np.linalg.qr(B)
        beta = np.linalg.solve(R, Q.T @ d)
        r = d - B @ beta
        return T, Js, B, Q, beta, r

    # Gaussian priors, each weighted like one joint of noise ``noise_m``: the half-width
    # ``a`` towards ``prior_a``; the half-length vector ``q`` towards 0 (a round contact)
    ia = np.concatenate([np.arange(m) * NPAR + 2] + ([np.arange(m) * NPAR + 3,
                                                       np.arange(m) * NPAR + 4]
                                                      if prior_length_std else []))
    mu_p = np.zeros(ia.size)
    w_p = np.zeros(ia.size)
    if prior_a is not None:
        mu_p[:m] = prior_a
        w_p[:m] = noise_m / prior_a_std
    if prior_length_std:
        w_p[m:] = noise_m / prior_length_std
    wp = w_p

    def prior(g):
        return w_p * (g[ia] - mu_p)

    T, Js, B, Q, beta, r = solve(g, True)
    pr = prior(g)
    cost = float(r @ r + pr @ pr)
    mu = 1e-3
    it = 0
    for it in range(1, max_iter + 1):
        X = np.concatenate([beta[c] * Js[c] for c in range(m)], axis=1)
        Jr = -(X - Q @ (Q.T @ X))
        A = Jr.T @ Jr
        gr = Jr.T @ r
        A[ia, ia] += wp * wp
        gr[ia] += wp * pr
        # Marquardt's scaling, floored: a direction the data do not see (a round contact's
        # angle, its length near zero) is damped like the weakest one they do
        dA = np.maximum(np.diag(A), 1e-6 * float(np.max(np.diag(A))))
        improved = False
        for _ in range(10):
            step = np.linalg.solve(A + mu * np.diag(dA), -gr)
            gn = np.clip(g + step, lo, hi)
            _, _, _, _, _, rn = solve(gn, False)     # the trial: values only
            prn = prior(gn)
            cn = float(rn @ rn + prn @ prn)
            if cn <= cost:
                improved = True
                moved = float(np.max(np.abs(gn - g) / scale))
                gained = (cost - cn) / max(cost, 1e-300)
                g, pr, cost = gn, prn, cn
                T, Js, B, Q, beta, r = solve(g, True)
                mu = max(mu / 3.0, 1e-9)
                break
            mu *= 4.0
        if not improved or moved < tol or gained < ftol:
            break
    # covariance of all parameters (forces, offsets, geometry) by the full Jacobian
    X = np.concatenate([beta[c] * Js[c] for c in range(m)], axis=1)
    A = np.concatenate([B, X], axis=1)
    H = A.T @ A
    H[m + n_off + ia, m + n_off + ia] += wp * wp
    try:
        Hi = np.linalg.pinv(H)
    except np.linalg.LinAlgError:
        Hi = np.full(H.shape, np.nan)
    if noise_samples is not None:
        S = np.asarray(noise_samples, float) @ A          # (S, p): every sample's projection
        M = S.T @ S / (S.shape[0] - 1)
        M[m + n_off + ia, m + n_off + ia] += (wp * noise_m) ** 2
        cov = Hi @ M @ Hi
    else:
        dof = max(n - A.shape[1], 1)
        cov = Hi * (float(r @ r) / dof)
    geo = []
    for c in range(m):
        u, v, a, qx, qy = map(float, g[NPAR * c:NPAR * c + NPAR])
        geo.append(ContactGeometry(u, v, a, float(np.hypot(qx, qy)), float(np.arctan2(qy, qx))))
    return FitResult(geometry=geo, force_n=beta[:m].copy(), offset_m=beta[m:].copy(), cov=cov,
                     rss=float(r @ r), n=n, iterations=it, residual=r, responses=T)
