"""The paper's estimator as Hoshi & Shinoda describe it (sections 2.2 and 3.1): the reference.

What the paper fixes:

1. Roll α and pitch β of every link in closed form from its reading (eq. 2).
2. Per 4-link unit, with one yaw fixed ("at least one of γ_i should be fixed [...] all we can do
   is to determine the relative yaw angles of γ1, γ2 and γ3 to γ0"), the other yaws minimise
   eq. (8), ``P = Σ_j (d0 + d1 − d2 − d3)_j² + (n0 − n1 + n2 − n3)_j²`` (loop closure, eq. 4, and
   the normal assumption, eq. 6), "by the steepest descent method", from "multiple initial
   values" because "(8) has several local minimums".
3. "After the same algorithm is applied to each lattice unit, the whole configuration is
   estimated by combining the estimated unit shapes."

What it leaves open, each a field of `PaperOptions` (docs/estimator.md, section 7, measures the
alternatives side by side on the paper's own experiment): the defaults read "trying multiple
initial values" as retrying while the result looks like a local minimum; the two readings that do
better there (a tolerant acceptance, or the square cell alone) do so by hardly ever trying a second
start, and the comparisons quote them beside the defaults.

* ``combine`` — how units become a sheet. ``"sync"`` (default): every unit solved on its own
  (its link 0 at yaw 0), then one rotation about z per unit chosen by least squares so that the
  units agree on the links they share (wrapped yaw differences, the unit grid's Laplacian, unit
  ``(0, 0)`` fixed), each link's yaw the circular mean of its units' estimates. ``"tree"``: the
  units solved on their own, each rotated to match its already placed neighbour along a spanning
  tree (row 0, then down every column), link yaws averaged as in ``"sync"``. ``"chain"``: units
  solved one after another from unit ``(0, 0)`` (anti-diagonal by anti-diagonal), each taking
  the yaws of the links it shares with units already solved as fixed (so an inner unit solves two
  yaws, not three) — capsheet's first implementation.
* ``starts`` — the initial values: ``"parallelogram"`` (default): parallelogram unit shapes
  with the corner angle between links 3 and 0 at ``n_starts`` values evenly spread over the
  circle (6: 60° apart), the square cell first; ``"random"``: ``n_starts`` uniformly random yaw
  triples from an MT19937 stream (``seed``).
* ``select``, ``accept`` — which result is kept: ``"first"`` (default) the first start, in
  order, whose eq. (8) ends at most ``accept`` (0.1: a unit that closes both its loops to a few
  tenths of a link), else the smallest; ``"min"``: the smallest eq. (8) of all starts.
* ``max_iter`` and the step rule — steepest descent with a step per unit and start that grows
  ×1.5 after a descent step and halves after a rejected one (no line search), stopped when the
  gradient's squared norm is below ``1e-14`` or after ``max_iter`` steps (default 300).
* ``joints`` — how link directions become joints: ``"lsq"`` (default) least squares over all
  links, ``min Σ ‖p_b − p_a − L d‖²``; ``"walk"`` joint by joint along row 0 and then down every
  column (each link used once).

Joint ``(0, 0)`` is at the origin; the estimate is defined up to a rotation about world z (the
paper: "the estimated shape still has the uncertainty of orientation"). Missing links are not
supported (the paper has none). This module needs numpy and scipy only.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from protocol.lattice import Lattice

__all__ = ["PaperOptions", "COMBINE", "STARTS", "JOINTS", "solve_yaws", "unit_yaws",
           "place_joints", "eq8_per_unit"]

COMBINE = ("sync", "tree", "chain")
STARTS = ("parallelogram", "random")
SELECT = ("first", "min")
JOINTS = ("lsq", "walk")

# eq. (4): d0 + d1 − d2 − d3 = 0;  eq. (6): n0 − n1 + n2 − n3 = 0  (Lattice.units numbering)
_S_D = np.array([1.0, 1.0, -1.0, -1.0])
_S_N = np.array([1.0, -1.0, 1.0, -1.0])
_GRAD_TOL = 1e-14


@dataclass(frozen=True)
class PaperOptions:
    """The choices the paper leaves open (module docstring and docs/estimator.md section 7).

    Attributes
    ----------
    combine : {"sync", "tree", "chain"}
        How the units' solutions become one sheet.
    starts : {"parallelogram", "random"}
        The kind of initial values.
    n_starts : int
        How many initial values per unit (>= 1).
    max_iter : int
        Steepest-descent steps per unit at most (>= 1).
    joints : {"lsq", "walk"}
        How link directions become joints.
    seed : int
        MT19937 seed of ``starts="random"``.
    """

    combine: str = "sync"
    starts: str = "parallelogram"
    n_starts: int = 6
    select: str = "first"
    accept: float = 0.1
    max_iter: int = 300
    joints: str = "lsq"
    seed: int = 2008

    def __post_init__(self) -> None:
        for name, allowed in (("combine", COMBINE), ("starts", STARTS), ("select", SELECT),
                              ("joints", JOINTS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"Invalid {name}: {getattr(self, name)!r} (expected one of "
                                 f"{allowed})")
        for name in ("n_starts", "max_iter", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < (name != "seed"):
                raise ValueError(f"Invalid {name}: {v!r} (need an integer >= "
                                 f"{int(name != 'seed')})")
        if not (isinstance(self.accept, (int, float)) and np.isfinite(self.accept)
                and self.accept >= 0):
            raise ValueError(f"Invalid accept: {self.accept!r} (need a finite value >= 0)")


# ---------------------------------------------------------------------------------------------
# eq. (8) per unit, steepest descent
# ---------------------------------------------------------------------------------------------

def _coefficients(alpha: np.ndarray, beta: np.ndarray, units: np.ndarray):
    """eq. (8)'s γ-dependent part in complex form: the xy parts of ``s_m d_m`` and ``s_m n_m``
    are ``cd_m e^{iγ_m}`` and ``cn_m e^{iγ_m}`` (docs/design.md section 5), shape (U, 4) each."""
    a, b = alpha[units], beta[units]
    return np.cos(b) * _S_D, (np.sin(b) * np.cos(a) - 1j * np.sin(a)) * _S_N


def _descend(cd, cn, g, free, max_iter: int):
    """Steepest descent on eq. (8) for every unit and start at once.

    cd, cn : complex (U, 1, 4); g : yaws (U, S, 4), changed only where ``free`` (U, 1, 4) is 1.
    Returns the yaws, eq. (8)'s γ-dependent part per (U, S) and the steps taken.
    """
    def value_grad(g):
        z = np.exp(1j * g)
        td, tn = cd * z, cn * z
        rd, rn = td.sum(-1), tn.sum(-1)
        P = rd.real ** 2 + rd.imag ** 2 + rn.real ** 2 + rn.imag ** 2
        grad = 2 * ((np.conj(td) * rd[..., None]).imag + (np.conj(tn) * rn[..., None]).imag)
        return P, grad * free

    P, grad = value_grad(g)
    step = np.full(P.shape, 0.1)
    it = 0
    for it in range(1, max_iter + 1):
        g_new = g - step[..., None] * grad
        P_new, grad_new = value_grad(g_new)
        better = P_new <= P
        g = np.where(better[..., None], g_new, g)
        P = np.where(better, P_new, P)
        grad = np.where(better[..., None], grad_new, grad)
        step = np.where(better, step * 1.5, step * 0.5)
        if np.all((np.sum(grad * grad, -1) < _GRAD_TOL) | (step < 1e-10)):
            break
    return g, P, it


def _start_shapes(opts: PaperOptions, n_units: int) -> np.ndarray:
    """Initial relative yaws (n_units, S, 4) with link 0 at 0: parallelograms of corner angle
    ``c`` between link 3 and link 0 (links 1, 3 at ``−c``, link 2 at 0), or random triples."""
    S = opts.n_starts
    if opts.starts == "parallelogram":
        c = np.pi / 2 + 2 * np.pi * np.arange(S) / S  # the square cell first
        g = np.stack([np.zeros(S), -c, np.zeros(S), -c], -1)
        return np.broadcast_to(g, (n_units, S, 4)).copy()
    rng = np.random.Generator(np.random.MT19937(opts.seed))
    g = rng.uniform(-np.pi, np.pi, (n_units, S, 4))
    g[..., 0] = 0.0
    return g


def _select(P: np.ndarray, opts: PaperOptions) -> np.ndarray:
    """Per unit (row of ``P``, (U, S)) the start whose result is kept: ``"min"`` the smallest
    eq. (8); ``"first"`` the first start (in order: the square cell first) that ends with eq. (8)
    at most ``accept``, else the smallest."""
    best = np.argmin(P, axis=1)
    if opts.select == "first":
        ok = P <= opts.accept
        best = np.where(ok.any(axis=1), np.argmax(ok, axis=1), best)
    return best


def unit_yaws(alpha: np.ndarray, beta: np.ndarray, rows: int, cols: int,
              opts: PaperOptions = PaperOptions()) -> tuple[np.ndarray, np.ndarray, int]:
    """Every unit solved on its own: link 0 at yaw 0, links 1-3 by steepest descent on eq. (8)
    from the initial values of ``opts``; the start with the smallest eq. (8) wins.

    Returns
    -------
    delta : ndarray, shape (rows-1, cols-1, 4)
        Yaws of the unit's links 0-3 relative to its link 0, radians.
    P : ndarray, shape (rows-1, cols-1)
        eq. (8)'s yaw-dependent part (xy components) at the solution.
    steps : int
        Steepest-descent steps taken (all units advance together).
    """
    units = Lattice(rows, cols).units.reshape(-1, 4)
    cd, cn = _coefficients(alpha, beta, units)
    free = np.array([0.0, 1.0, 1.0, 1.0])[None, None, :]
    g, P, it = _descend(cd[:, None, :], cn[:, None, :], _start_shapes(opts, len(units)), free,
                        opts.max_iter)
    best = _select(P, opts)
    k = np.arange(len(units))
    return (g[k, best].reshape(rows - 1, cols - 1, 4), P[k, best].reshape(rows - 1, cols - 1),
            it)


def _wrap(x):
    return (np.asarray(x) + np.pi) % (2 * np.pi) - np.pi


def _unit_edges(rows: int, cols: int):
    """Neighbouring units and the link they share: (u, v, link slot in u, link slot in v)."""
    R1, C1 = rows - 1, cols - 1
    uid = np.arange(R1 * C1).reshape(R1, C1)
    h = (uid[:, :-1].ravel(), uid[:, 1:].ravel(), 1, 3)  # u's link 1 is its right neighbour's 3
    v = (uid[:-1, :].ravel(), uid[1:, :].ravel(), 2, 0)  # u's link 2 is its lower neighbour's 0
    return h, v


@lru_cache(maxsize=16)
def _unit_laplacian(rows: int, cols: int):
    """Factorised Laplacian of the unit grid with unit 0 fixed (the rotations' least squares)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    n = (rows - 1) * (cols - 1)
    (hu, hv, _, _), (vu, vv, _, _) = _unit_edges(rows, cols)
    u, v = np.concatenate([hu, vu]), np.concatenate([hv, vv])
    m = len(u)
    B = sp.csr_matrix((np.r_[-np.ones(m), np.ones(m)], (np.r_[np.arange(m), np.arange(m)],
                                                          np.r_[u, v])), shape=(m, n))
    B = B[:, 1:]  # unit 0's rotation is the gauge
    return B, splu((B.T @ B).tocsc()) if n > 1 else None


def _link_mean(rows: int, cols: int, gamma_unit: np.ndarray) -> np.ndarray:
    """Each link's yaw: circular mean of the estimates of the (one or two) units holding it."""
    lat = Lattice(rows, cols)
    acc = np.zeros(lat.n_links, complex)
    np.add.at(acc, lat.units.reshape(-1), np.exp(1j * gamma_unit.reshape(-1)))
    return np.angle(acc)


def _combine_sync(delta: np.ndarray, rows: int, cols: int) -> np.ndarray:
    n = (rows - 1) * (cols - 1)
    d = delta.reshape(n, 4)
    (hu, hv, ha, hb), (vu, vv, va, vb) = _unit_edges(rows, cols)
    # φ_v − φ_u = wrap(δ_u[a] − δ_v[b]) for every shared link
    rhs = np.r_[_wrap(d[hu, ha] - d[hv, hb]), _wrap(d[vu, va] - d[vv, vb])]
    phi = np.zeros(n)
    if n > 1:
        B, lu = _unit_laplacian(rows, cols)
        phi[1:] = lu.solve(B.T @ rhs)
    return _link_mean(rows, cols, (d + phi[:, None]).reshape(delta.shape))


def _combine_tree(delta: np.ndarray, rows: int, cols: int) -> np.ndarray:
    R1, C1 = rows - 1, cols - 1
    phi = np.zeros((R1, C1))
    for j in range(1, C1):  # along row 0: unit (0, j-1)'s link 1 is unit (0, j)'s link 3
        phi[0, j] = phi[0, j - 1] + delta[0, j - 1, 1] - delta[0, j, 3]
    for i in range(1, R1):  # down every column: unit (i-1, j)'s link 2 is unit (i, j)'s link 0
        phi[i] = phi[i - 1] + delta[i - 1, :, 2] - delta[i, :, 0]
    return _link_mean(rows, cols, delta + phi[..., None])


def _combine_chain(alpha, beta, rows: int, cols: int, opts: PaperOptions):
    """Units one after another (anti-diagonals), each inheriting the yaws of its solved links."""
    lat = Lattice(rows, cols)
    units = lat.units
    cd_all, cn_all = _coefficients(alpha, beta, units.reshape(-1, 4))
    cd_all = cd_all.reshape(units.shape)
    cn_all = cn_all.reshape(units.shape)
    gamma = np.full(lat.n_links, np.nan)
    gamma[units[0, 0, 0]] = 0.0  # the root link
    R1, C1 = units.shape[:2]
    shapes = _start_shapes(opts, 1)[0]  # (S, 4) relative to link 0
    total = 0
    for k in range(R1 + C1 - 1):
        ii = np.arange(max(0, k - C1 + 1), min(R1 - 1, k) + 1)
        jj = k - ii
        lk = units[ii, jj]  # (U, 4)
        known = np.isfinite(gamma[lk])
        g_known = np.where(known, gamma[lk], 0.0)
        # a start: the shape rotated onto link 0 if it is known, else onto link 3
        ref = np.where(known[:, :1], g_known[:, :1], g_known[:, 3:4] - shapes[None, :, 3])
        g = ref[..., None] + shapes[None]
        g = np.where(known[:, None, :], g_known[:, None, :], g)
        g, P, it = _descend(cd_all[ii, jj][:, None, :], cn_all[ii, jj][:, None, :], g,
                            (~known)[:, None, :].astype(float), opts.max_iter)
        total += it
        best = _select(P, opts)
        gamma[lk] = np.where(known, gamma[lk], g[np.arange(len(lk)), best])
    return _wrap(gamma), total


def solve_yaws(alpha: np.ndarray, beta: np.ndarray, rows: int, cols: int,
               opts: PaperOptions = PaperOptions()) -> tuple[np.ndarray, int]:
    """Every link's yaw by the paper's method (gauge: the yaw of unit ``(0, 0)``'s link 0 is 0).

    Returns the yaws (n_links,), radians, and the steepest-descent steps taken.
    """
    if opts.combine == "chain":
        return _combine_chain(alpha, beta, rows, cols, opts)
    delta, _, it = unit_yaws(alpha, beta, rows, cols, opts)
    gamma = (_combine_sync if opts.combine == "sync" else _combine_tree)(delta, rows, cols)
    return _wrap(gamma - gamma[Lattice(rows, cols).units[0, 0, 0]]), it


# ---------------------------------------------------------------------------------------------
# joints
# ---------------------------------------------------------------------------------------------

@lru_cache(maxsize=16)
def _joint_laplacian(rows: int, cols: int):
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    lat = Lattice(rows, cols)
    e = lat.endpoints
    m, n = len(e), rows * cols
    B = sp.csr_matrix((np.r_[-np.ones(m), np.ones(m)], (np.r_[np.arange(m), np.arange(m)],
                                                          np.r_[e[:, 0], e[:, 1]])), shape=(m, n))
    B = B[:, 1:]  # joint (0, 0) at the origin
    return B, splu((B.T @ B).tocsc())


def place_joints(vectors: np.ndarray, rows: int, cols: int, how: str = "lsq") -> np.ndarray:
    """Joints (rows, cols, 3) from link vectors (n_links, 3), joint ``(0, 0)`` at the origin:
    least squares over all links (``"lsq"``) or walking along row 0, then down every column."""
    if how == "lsq":
        B, lu = _joint_laplacian(rows, cols)
        P = np.zeros((rows * cols, 3))
        P[1:] = lu.solve(np.asarray(B.T @ vectors))
        return P.reshape(rows, cols, 3)
    lat = Lattice(rows, cols)
    vi = vectors[:lat.n_i_links].reshape(rows - 1, cols, 3)
    vj = vectors[lat.n_i_links:].reshape(rows, cols - 1, 3)
    P = np.zeros((rows, cols, 3))
    P[0, 1:] = np.cumsum(vj[0], axis=0)
    P[1:] = P[0][None] + np.cumsum(vi, axis=0)
    return P


def directions_normals(alpha, beta, gamma) -> tuple[np.ndarray, np.ndarray]:
    """Every link's direction (sensor x) and normal (sensor z) in the world, (n_links, 3) each:
    the first and third columns of ``R = Rz(γ) Ry(β) Rx(α)`` (eq. 3 and 5)."""
    ca, sa, cb, sb, cg, sg = (np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta),
                              np.cos(gamma), np.sin(gamma))
    d = np.stack([cg * cb, sg * cb, -sb], axis=-1)
    n = np.stack([cg * sb * ca + sg * sa, sg * sb * ca - cg * sa, cb * ca], axis=-1)
    return d, n


def eq8_per_unit(units: np.ndarray, d: np.ndarray, n: np.ndarray) -> np.ndarray:
    """eq. (8) (x, y and z) of every unit (..., 4) given the links' directions and normals."""
    du, nu = d[units], n[units]
    rd = du[..., 0, :] + du[..., 1, :] - du[..., 2, :] - du[..., 3, :]
    rn = nu[..., 0, :] - nu[..., 1, :] + nu[..., 2, :] - nu[..., 3, :]
    return np.sum(rd * rd + rn * rn, axis=-1)


def estimate(alpha: np.ndarray, beta: np.ndarray, rows: int, cols: int, link_length: float,
             opts: PaperOptions = PaperOptions()) -> dict:
    """The paper's estimate from checked angles: yaws, directions, normals, joints, eq. (8).

    ``host.analysis.estimator.estimate(..., method="paper", paper=opts)`` checks the input and
    calls this; it returns the fields of a `ShapeEstimate` that depend on the method.
    """
    t1 = time.perf_counter()
    gamma, steps = solve_yaws(alpha, beta, rows, cols, opts)
    t2 = time.perf_counter()
    d, nrm = directions_normals(alpha, beta, gamma)
    joints = place_joints(float(link_length) * d, rows, cols, opts.joints)
    units = Lattice(rows, cols).units.reshape(-1, 4)
    return {"yaws": gamma, "directions": d, "normals": nrm, "joints": joints,
            "residual": float(eq8_per_unit(units, d, nrm).sum()), "iterations": int(steps),
            "t_yaw": t2 - t1}
