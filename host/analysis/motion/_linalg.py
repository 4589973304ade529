"""The fused estimator's numerical pieces (`host.analysis.motion.fused`): rotations, small
matrix helpers, conjugate gradients, the per-link steps and the lattice step's terms in numpy,
and the dispatch to the C kernel (host/analysis/motion/_kernel/), which does the same steps
when built."""

from __future__ import annotations

import os

import numpy as np

from ._lattice import CLOSURE_SIGNS

try:  # the per-link steps in C (host/analysis/motion/_kernel/); optional
    if os.environ.get("CAPSHEET_NO_KERNEL"):
        raise ImportError("CAPSHEET_NO_KERNEL is set")
    from ._link_kernel import ffi as kernel_ffi, lib as kernel_lib
except ImportError:  # not built: the numpy code, the same numbers to rounding
    kernel_ffi = kernel_lib = None

#: Run the per-link steps in the compiled kernel when it is built (False: numpy).
USE_KERNEL = kernel_lib is not None


def rotation_matrices(rotvec: np.ndarray) -> np.ndarray:
    """``exp([v]×)`` for rotation vectors ``(..., 3)`` (Rodrigues), shape ``(..., 3, 3)``."""
    v = np.asarray(rotvec, dtype=float)
    th2 = np.einsum("...i,...i->...", v, v)
    th = np.sqrt(th2)
    small = th2 < 1e-12
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(th) / np.where(small, 1.0, th))
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(th)) / np.where(small, 1.0, th2))
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    out = np.empty(v.shape[:-1] + (3, 3))
    xx, yy, zz, xy, xz, yz = x * x, y * y, z * z, x * y, x * z, y * z
    out[..., 0, 0] = 1.0 - b * (yy + zz)
    out[..., 1, 1] = 1.0 - b * (xx + zz)
    out[..., 2, 2] = 1.0 - b * (xx + yy)
    out[..., 0, 1] = b * xy - a * z
    out[..., 1, 0] = b * xy + a * z
    out[..., 0, 2] = b * xz + a * y
    out[..., 2, 0] = b * xz - a * y
    out[..., 1, 2] = b * yz - a * x
    out[..., 2, 1] = b * yz + a * x
    return out


def skew(v: np.ndarray) -> np.ndarray:
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def inv_sym3(S: np.ndarray) -> np.ndarray:
    """Inverses of symmetric 3 x 3 matrices ``(n, 3, 3)`` by cofactors (no LAPACK call per
    matrix: the stack is small and many)."""
    a, b, c = S[:, 0, 0], S[:, 0, 1], S[:, 0, 2]
    d, e, f = S[:, 1, 1], S[:, 1, 2], S[:, 2, 2]
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    inv_det = 1.0 / (a * A + b * B + c * C)
    out = np.empty_like(S)
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = A, B, C
    out[:, 1, 0], out[:, 1, 1], out[:, 1, 2] = B, D, E
    out[:, 2, 0], out[:, 2, 1], out[:, 2, 2] = C, E, F
    out *= inv_det[:, None, None]
    return out


def pcg(matvec, b: np.ndarray, inv_diag: np.ndarray, rtol: float = 1e-9,
         maxiter: int = 200, coarse=None) -> np.ndarray:
    """Conjugate gradients with a Jacobi preconditioner, from zero. The yaw problem's matrix is
    its links' own predictions (diagonal) plus the lattice's coupling: diagonally dominant once
    the filter has settled, so a few iterations suffice (docs/estimator.md §8). ``coarse``
    (``group``, ``C⁻¹``) adds the groups' coarse correction ``Z C⁻¹ Zᵀ r`` to the
    preconditioner (``Z`` the groups' indicator, ``C = Zᵀ A Z``, `coarse_inverse`): the modes
    a group's links share, which the diagonal does not see and the loops may hold weakly."""
    def precondition(r):
        z = inv_diag * r
        if coarse is not None:
            group, cinv = coarse
            z = z + (cinv @ np.bincount(group, weights=r, minlength=cinv.shape[0]))[group]
        return z

    x = np.zeros_like(b)
    r = b.copy()
    z = precondition(r)
    pdir = z.copy()
    rz = float(r @ z)
    stop = rtol * rtol * float(b @ b)
    for _ in range(maxiter):
        if float(r @ r) <= stop:
            break
        q = matvec(pdir)
        alpha = rz / float(pdir @ q)
        x += alpha * pdir
        r -= alpha * q
        z = precondition(r)
        rz_new = float(r @ z)
        pdir = z + (rz_new / rz) * pdir
        rz = rz_new
    return x


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of ``(n, 3)`` arrays (np.cross's axis handling costs more than
    the products at these sizes)."""
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def mean_rows(a: np.ndarray) -> np.ndarray:
    """The mean of an ``(n, k)`` array's rows as one matrix-vector product: numpy's reduction
    along the first axis of a C-ordered ``(n, 3)`` array takes three numbers at a time (0.12 ms
    at 8,064 links, against 5 µs; the same mean to rounding)."""
    return (np.ones(a.shape[0]) @ a) / a.shape[0]


def rotate_all(Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``Q R_k`` for every frame ``R (n, 3, 3)``, as one 3 x 3n product."""
    n = R.shape[0]
    return np.ascontiguousarray((Q @ R.transpose(1, 0, 2).reshape(3, 3 * n))
                                .reshape(3, n, 3).transpose(1, 0, 2))


def wrap(x):
    return (x + np.pi) % (2 * np.pi) - np.pi


def frames_from_angles(alpha, beta, gamma) -> np.ndarray:
    """``Rz(γ) Ry(β) Rx(α)`` (docs/design.md), shape (n, 3, 3)."""
    ca, sa, cb, sb, cg, sg = (np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta),
                              np.cos(gamma), np.sin(gamma))
    R = np.empty(alpha.shape + (3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 0, 2] = cg * cb, cg * sb * sa - sg * ca, cg * sb * ca + sg * sa
    R[:, 1, 0], R[:, 1, 1], R[:, 1, 2] = sg * cb, sg * sb * sa + cg * ca, sg * sb * ca - cg * sa
    R[:, 2, 0], R[:, 2, 1], R[:, 2, 2] = -sb, cb * sa, cb * ca
    return R


# ---------------------------------------------------------------------------------------------
# The per-link steps: numpy, and the same in C (host/analysis/motion/_kernel/link_filter.c) when
# built. Each updates its arrays in place; link_filter.h documents them.
# ---------------------------------------------------------------------------------------------

def _np_propagate(R, P, w0, w1, dt, q, qb) -> None:
    dth = 0.5 * (w0 + w1) * dt[:, None] + cross3(w0, w1) * (dt * dt / 12.0)[:, None]
    R[:] = R @ rotation_matrices(dth)
    G = R * dt[:, None, None]  # δθ' = δθ − R δb dt
    Ptt, Ptb, Pbb = P[:, :3, :3], P[:, :3, 3:], P[:, 3:, 3:]
    GPbb = G @ Pbb
    GPbt = G @ P[:, 3:, :3]
    Ptt_new = Ptt - GPbt - GPbt.transpose(0, 2, 1) + GPbb @ G.transpose(0, 2, 1)
    Ptt_new += q[:, None, None] * np.eye(3)
    P[:, :3, 3:] = Ptb - GPbb
    P[:, 3:, :3] = P[:, :3, 3:].transpose(0, 2, 1)
    P[:, :3, :3] = Ptt_new
    P[:, 3:, 3:] += qb[:, None, None] * np.eye(3)


def _np_accel(R, P, f, vec, r2, gate, valid, x, nis) -> None:
    Rt = R.transpose(0, 2, 1)
    y = f - np.einsum("kij,kj->ki", Rt, vec)
    H = Rt @ skew(vec)  # ∂(Rᵀ v)/∂δθ for R = exp([δθ]×) R̂
    HP = H @ P[:, :3, :]  # (n, 3, 6)
    S = HP[:, :, :3] @ H.transpose(0, 2, 1) + r2[:, None, None] * np.eye(3)
    Si = inv_sym3(S)
    m2 = np.einsum("ki,kij,kj->k", y, Si, y)
    nis[:] = np.where(valid, m2, np.nan)
    Si /= np.maximum(1.0, m2 / gate)[:, None, None]
    K = HP.transpose(0, 2, 1) @ Si  # (n, 6, 3)
    K[~valid] = 0.0
    x[:] = np.einsum("kij,kj->ki", K, np.where(valid[:, None], y, 0.0))  # a NaN reading: no step
    P -= K @ HP


def _np_yaw(P, mu, a_diag, x) -> None:
    c = P[:, :, 2].copy()  # (n, 6): covariance with the yaw error
    p = c[:, 2].copy()
    g = c / p[:, None]
    P -= np.einsum("ki,kj->kij", g, c * (1.0 - 1.0 / (a_diag * p))[:, None])
    x[:] = g * mu[:, None]


def _np_apply(R, bias, P, x) -> None:
    R[:] = rotation_matrices(x[:, :3]) @ R
    bias += x[:, 3:]
    P += P.transpose(0, 2, 1)
    P *= 0.5


NUMPY_STEPS = {"propagate": _np_propagate, "accel": _np_accel, "yaw": _np_yaw, "apply": _np_apply}


def np_lattice(R, P, topo, floor2, res, wts, jd, lat_diag) -> None:
    """The lattice step's residuals ``res``, weights ``wts``, Jacobian entries ``jd`` (in the
    pattern ``topo.jac``'s data order) and the diagonal of ``Jᵀ W J`` (`MotionEstimator`'s
    step 4; the C kernel's ``capsheet_mf_lattice`` computes the same)."""
    d = R[:, :, 0]
    Y = R[:, :, 1]
    units = topo.units
    n = R.shape[0]
    du = d[units]  # (U, 4, 3)
    # loop closure, xy part: residual and its derivative in each link's yaw
    r_cl = du[:, 0, :2] + du[:, 1, :2] - du[:, 2, :2] - du[:, 3, :2]  # (U, 2)
    ezd = np.empty((n, 3))  # e_z × d
    ezd[:, 0], ezd[:, 1], ezd[:, 2] = -d[:, 1], d[:, 0], 0.0
    ezd_u = ezd[units]  # (U, 4, 3)
    j_cl = (CLOSURE_SIGNS[None, :, None] * ezd_u[:, :, :2]).transpose(0, 2, 1)  # (U, 2, 4)
    # the cells' normals A × C and each link's sensor y against their mean
    A = du[:, 1] + du[:, 3]
    C = du[:, 0] + du[:, 2]
    N = cross3(A, C)
    nN = np.sqrt(np.einsum("ui,ui->u", N, N))
    ok = nN > 0.1  # a squashed cell has no normal: its terms drop out
    inv_nN = np.where(ok, 1.0 / np.where(ok, nN, 1.0), 0.0)
    nc = N * inv_nN[:, None]
    nbar = topo.cell_to_link @ nc
    r_n = np.einsum("ki,ki->k", Y, nbar)
    j_diag = Y[:, 0] * nbar[:, 1] - Y[:, 1] * nbar[:, 0]  # (e_z × Y) · n̄
    pl, pc = topo.pair_link, topo.pair_cell
    Yp = Y[pl]
    ncp = nc[pc]
    wkc = (Yp - ncp * np.einsum("ki,ki->k", ncp, Yp)[:, None]) \
        * (inv_nN[pc] * topo.inv_ncell[pl])[:, None]
    CxW = cross3(C[pc], wkc)
    WxA = cross3(wkc, A[pc])
    ez_c = ezd_u[pc]  # (K2, 4, 3)
    j_pair = np.empty((pl.size, 4))
    j_pair[:, 0] = np.einsum("ki,ki->k", ez_c[:, 0], WxA)
    j_pair[:, 2] = np.einsum("ki,ki->k", ez_c[:, 2], WxA)
    j_pair[:, 1] = np.einsum("ki,ki->k", ez_c[:, 1], CxW)
    j_pair[:, 3] = np.einsum("ki,ki->k", ez_c[:, 3], CxW)
    jd[:] = np.bincount(topo.jac_slots, weights=np.concatenate([j_cl.ravel(), j_diag,
                                                                 j_pair.ravel()]),
                        minlength=topo.jac_nnz)
    # weights: the tilt variance of the links involved plus the model's floor
    tilt = P[:, 0, 0] + P[:, 1, 1]
    w_cl = 1.0 / (tilt[units].sum(axis=1) + floor2)
    wts[:] = np.concatenate([np.repeat(w_cl, 2), 1.0 / (2.0 * tilt + floor2)])
    res[:] = np.concatenate([r_cl.ravel(), r_n])
    lat_diag[:] = np.bincount(topo.jac_cols, weights=wts[topo.jac_rows] * jd * jd, minlength=n)


_F64 = np.dtype(np.float64)


def kernel_args(name: str, args) -> list:
    """The C kernel's arguments: each array as a typed ``from_buffer`` cdata, which keeps its
    buffer alive while the list is (a ``cast`` of one does not: a boolean mask's uint8 copy was
    freed before the call, and numpy handed its memory to another thread's array while cffi had
    the interpreter lock released — a link's valid flag read as whatever was written there)."""
    out = []
    for a in args:
        if type(a) is np.ndarray and a.dtype is _F64 and a.flags.c_contiguous:  # the usual case
            out.append(kernel_ffi.from_buffer("double[]", a))
        elif isinstance(a, np.ndarray):
            if a.dtype == bool:
                out.append(kernel_ffi.from_buffer("uint8_t[]", a.astype(np.uint8)))
                continue
            if a.dtype in (np.int64, np.int32) and a.flags.c_contiguous:
                out.append(kernel_ffi.from_buffer(f"int{a.dtype.itemsize * 8}_t[]", a))
                continue
            if not a.flags.c_contiguous or a.dtype != np.float64:
                raise ValueError(f"kernel {name}: arrays must be C-contiguous float64")
            out.append(kernel_ffi.from_buffer("double[]", a))
        else:
            out.append(float(a))
    return out


def _i32(a: np.ndarray) -> np.ndarray:
    """A lattice's index array as the kernel's 32-bit one (`fixed_args` keeps it with the
    topology; a lattice's indices are far below 2³¹)."""
    return np.ascontiguousarray(a, dtype=np.int32)


def fixed_args(topo, name: str, arrays) -> list:
    """`kernel_args` of a lattice's fixed index arrays, made once per lattice and kept on its
    topology (the arrays live as long as it does; a callable ``arrays`` is called only then)."""
    cache = topo.__dict__.setdefault("_kernel_args", {})
    if name not in cache:
        cache[name] = kernel_args(name, arrays() if callable(arrays) else arrays)
    return cache[name]


def kernel_step(name: str, *args) -> None:
    getattr(kernel_lib, "capsheet_mf_" + name)(args[0].shape[0], *kernel_args(name, args))


def step(name: str, *args) -> None:
    """One per-link step (``propagate``, ``accel``, ``yaw``, ``apply``): the C kernel's when
    `USE_KERNEL`, else numpy's."""
    if USE_KERNEL:
        kernel_step(name, *args)
    else:
        NUMPY_STEPS[name](*args)


def step_apply(name: str, R, bias, P, *args, turn=None, turn_bias=None, cov=None):
    """Step ``accel`` or ``yaw`` (their arguments after ``R``/``P``, as `step` takes them), then
    its correction applied (`apply`), then every frame turned by ``turn`` (3 x 3, ``R <- turn
    R``) and, for ``accel``, every bias given ``Rᵀ (turn_bias[0], turn_bias[1], 0)`` with the
    turned ``R`` (the sheet's common corrections; either None: none): in C one pass, link by
    link. For ``yaw``, ``cov`` (``tilt_cov, yaw_add`` of `orientation_cov`) returns the
    updated state's `orientation_cov` (made in the same pass); else None."""
    x = args[-2] if name == "accel" else args[-1]
    if USE_KERNEL:
        extra = [kernel_ffi.NULL if a is None else kernel_ffi.from_buffer(
            "double[]", np.ascontiguousarray(a, dtype=float)) for a in (
            (turn, turn_bias) if name == "accel" else (turn,) + (cov or (None, None)))]
        out = None
        if name == "yaw":
            out = None if cov is None else np.empty((R.shape[0], 3, 3))
            extra.append(kernel_ffi.NULL if out is None
                         else kernel_ffi.from_buffer("double[]", out))
        getattr(kernel_lib, f"capsheet_mf_{name}_apply")(R.shape[0], *kernel_args(name, (R, bias, P)),
                                                          *kernel_args(name, args), *extra)
        return out
    NUMPY_STEPS[name](*((R, P) + args if name == "accel" else (P,) + args))
    NUMPY_STEPS["apply"](R, bias, P, x)
    if turn is not None:
        R[:] = rotate_all(turn, R)
    if turn_bias is not None:
        bias += R[:, 0, :] * turn_bias[0] + R[:, 1, :] * turn_bias[1]  # Rᵀ (b_x, b_y, 0)
    return None if cov is None or name != "yaw" else np_orientation_cov(P, *cov)


def lattice_terms(R, P, topo, floor2):
    """The lattice step's residuals, weights, Jacobian entries (``topo.jac``'s data order) and
    the diagonal of ``Jᵀ W J``: the C kernel's when `USE_KERNEL`, else numpy's (`np_lattice`)."""
    n, U = topo.n_links, topo.n_units
    res, wts = np.empty(topo.n_rows), np.empty(topo.n_rows)
    jd, lat_diag = np.empty(topo.jac_nnz), np.empty(n)
    if USE_KERNEL:
        work = np.empty(10 * U + 3 * n)
        kernel_lib.capsheet_mf_lattice(n, U, topo.pair_link.size, topo.jac_nnz,
                                       *kernel_args("lattice", (R, P)),
                                       *fixed_args(topo, "lattice", lambda: (
                                           _i32(topo.units), _i32(topo.pair_link),
                                           _i32(topo.pair_cell), topo.inv_ncell,
                                           _i32(topo.jac_slots), topo.jac_indptr32,
                                           topo.jac_indices32)),
                                       *kernel_args("lattice", (floor2, res, wts, jd, lat_diag,
                                                                work)))
    else:
        np_lattice(R, P, topo, floor2, res, wts, jd, lat_diag)
    return res, wts, jd, lat_diag


def normal_matvec(topo, jd, wts):
    """``x -> Jᵀ (wts ⊙ (J x))`` for the lattice step's conjugate gradients, ``J`` the pattern
    ``topo.jac`` with the entries ``jd`` (in C when `USE_KERNEL`: the same sums in the same
    order as scipy's two products)."""
    if not USE_KERNEL:
        J, JT = topo.jac, topo.jac_T
        return lambda x: JT @ (wts * (J @ x))
    n, nr = topo.n_links, topo.n_rows
    tmp = np.empty(nr)
    fixed = fixed_args(topo, "pattern", (topo.jac_indptr32, topo.jac_indices32)) \
        + kernel_args("normal", (jd, wts))
    tmp_c = kernel_ffi.from_buffer("double[]", tmp)

    def matvec(x):
        x = np.ascontiguousarray(x, dtype=np.float64)
        out = np.empty(n)
        kernel_lib.capsheet_mf_normal_matvec(nr, n, *fixed, kernel_ffi.from_buffer("double[]", x),
                                             tmp_c, kernel_ffi.from_buffer("double[]", out))
        return out
    return matvec


def coarse_inverse(topo, jg, wts, terms, mw) -> np.ndarray:
    """``C⁻¹`` with ``C = Zᵀ A Z`` the yaw problem's matrix on the groups' common offsets (``Z``
    the groups' indicator, n_groups x n_groups): the lattice's ``(J Z)ᵀ W (J Z)`` (``jg``: ``J``'s
    columns summed over each group, ``topo.jg_*``'s pattern), the nested prior's group level
    (``σ_a`` of `MotionEstimator._yaw_prior`; ``terms`` its ``D, dg, Eg, sE, I0``) and the
    magnetometers' weights summed per group."""
    _D, _dg, Eg, sE, I0 = terms
    ng = topo.n_groups
    if USE_KERNEL:
        C = np.empty((ng, ng))
        kernel_lib.capsheet_mf_coarse(topo.n_rows, ng, *fixed_args(topo, "coarse", (
            topo.jg_indptr, topo.jg_group)), *kernel_args("coarse", (jg, wts, C)))
    else:
        import scipy.sparse as sp
        JG = sp.csr_matrix((jg, (topo.jg_rows, topo.jg_group)), shape=(topo.n_rows, ng))
        C = (JG.T @ JG.multiply(wts[:, None]).tocsr()).toarray()
    C += np.diag(Eg + np.bincount(topo.group, weights=mw, minlength=ng))
    C += np.outer(Eg, Eg) * (I0 / (sE * sE) - 1.0 / sE)
    return np.linalg.inv(C)


def yaw_solve(topo, jd, wts, terms, mw, b, inv_diag, rtol: float = 1e-9,
               maxiter: int = 200, coarse_inv=None) -> np.ndarray:
    """`pcg` on the lattice step's yaw problem, all in the C kernel (``capsheet_mf_yaw_pcg``):
    ``Jᵀ W J`` from ``jd`` and ``wts``, the nested prior from ``terms`` (``D, dg, Eg, sE, I0``
    of `MotionEstimator._yaw_prior`) and the magnetometers' weights ``mw``."""
    D, dg, Eg, sE, I0 = terms
    n, nr, ng = topo.n_links, topo.n_rows, topo.n_groups
    x = np.empty(n)
    work = np.empty(nr + 4 * n + 4 * ng)
    a = fixed_args(topo, "pattern", (topo.jac_indptr32, topo.jac_indices32)) \
        + kernel_args("pcg", (jd, wts, D)) + fixed_args(topo, "group", (topo.group,)) \
        + kernel_args("pcg", (dg, Eg))
    c = kernel_args("pcg", (mw, b, inv_diag)) + [
        kernel_ffi.NULL if coarse_inv is None
        else kernel_ffi.from_buffer("double[]", np.ascontiguousarray(coarse_inv))]
    kernel_lib.capsheet_mf_yaw_pcg(n, nr, ng, *a, float(sE), float(I0), *c, float(rtol),
                                   int(maxiter), *kernel_args("pcg", (x, work)))
    return x


# ---------------------------------------------------------------------------------------------
# Whole-sheet pieces of a snapshot: the same in numpy and C (link_filter.h documents each)
# ---------------------------------------------------------------------------------------------

def np_dist_tests(group, n_groups, ok, resid, t_mag, t_dip, dt, tau, heading_unit, dist,
                  resid_avg, count):
    """The disturbance tests' averages, in place (`MotionEstimator._disturbance_tests`;
    link_filter.h says each term): returns ``dist`` (a new array when some link is not ok)."""
    resid = wrap(resid)
    wk = 1.0 / (1.0 + dist[:, 1] * dist[:, 1] + dist[:, 2] * dist[:, 2])
    wk[~ok] = 0.0
    wr = wk * resid
    wr[~ok] = 0.0  # a link not ok adds nothing (its residual may be anything)
    mean = np.bincount(group, weights=wr, minlength=n_groups) / np.maximum(
        np.bincount(group, weights=wk, minlength=n_groups), 1e-30)
    count += ok
    alpha = np.clip(np.maximum(dt / tau, 1.0 / np.maximum(count, 1.0)), 1e-6, 1.0)
    tests = np.stack([(resid - mean[group]) / heading_unit, t_mag, t_dip], axis=1)
    new = np.where(ok[:, None], dist + alpha[:, None] * (tests - dist), dist)
    resid_avg[:] = np.where(ok, resid_avg + alpha * (resid - resid_avg), resid_avg)
    dist[:] = new
    return dist


def dist_tests(group, n_groups, ok, resid, t_mag, t_dip, dt, tau, heading_unit, dist, resid_avg,
               count):
    """`np_dist_tests`, in C when `USE_KERNEL` (``dist``, ``resid_avg``, ``count`` in place)."""
    if not USE_KERNEL:
        return np_dist_tests(group, n_groups, ok, resid, t_mag, t_dip, dt, tau, heading_unit,
                             dist, resid_avg, count)
    n = resid.shape[0]
    sums = np.empty(2 * n_groups)
    kernel_lib.capsheet_mf_dist_tests(
        n, n_groups, *kernel_args("dist_tests", (group, ok, resid, t_mag, t_dip, dt)),
        float(tau), float(heading_unit), *kernel_args("dist_tests", (dist, resid_avg, count,
                                                                     sums)))
    return dist


def np_mag_weights(hz, ok, dist, P, count, dt, noise2, floor2, F, field_unit, dip_unit, tau,
                   lasts, scale2, h, warmup, e):
    """The magnetometers' weights, their information and their heading errors (``e``, zeroed
    where not ``ok``, in place) (`MotionEstimator._magnetometer`; link_filter.h says each
    term)."""
    hz2 = np.maximum(hz, 1e-30) ** 2
    var0 = noise2 / hz2 + floor2
    a = np.clip(np.maximum(dt / tau, 1.0 / np.maximum(count, 1.0)), 1e-6, 1.0)
    n2 = 2.0 * noise2 * a / (2.0 - a) + F * F * (P[:, 0, 0] + P[:, 1, 1])
    d2 = ((dist[:, 1] * field_unit) ** 2 + (dist[:, 2] * dip_unit) ** 2) * F * F
    d2 = np.maximum(d2 - 3.0 * n2, 0.0) * lasts
    wgt = var0 / (var0 + d2 / hz2) / (1.0 + dist[:, 0] ** 2 / scale2)
    weight = np.where(ok & (count * h >= warmup), wgt, 0.0)
    mw = np.where(ok, weight / np.where(ok, var0, 1.0), 0.0)
    e[~ok] = 0.0
    return weight, mw


def mag_weights(hz, ok, dist, P, count, dt, noise2, floor2, F, field_unit, dip_unit, tau, lasts,
                scale2, h, warmup, e):
    """`np_mag_weights`, in C when `USE_KERNEL`."""
    if not USE_KERNEL:
        return np_mag_weights(hz, ok, dist, P, count, dt, noise2, floor2, F, field_unit,
                              dip_unit, tau, lasts, scale2, h, warmup, e)
    n = hz.shape[0]
    weight, mw = np.empty(n), np.empty(n)
    kernel_lib.capsheet_mf_mag_weights(
        n, *kernel_args("mag_weights", (hz, ok, dist, P, count, dt)), float(noise2),
        float(floor2), float(F), float(field_unit), float(dip_unit), float(tau), float(lasts),
        float(scale2), float(h), float(warmup), *kernel_args("mag_weights", (weight, mw, e)))
    return weight, mw


def np_mag_terms(R, m, declination, field, dip, field_unit, dip_unit):
    """Each link's field turned into the world: its heading less the declination (rad,
    wrapped), its horizontal magnitude (T), and its magnitude and dip tests in their units
    (`MotionEstimator._magnetometer`)."""
    W = np.einsum("kij,kj->ki", R, m)
    hz = np.hypot(W[:, 0], W[:, 1])
    norm = np.linalg.norm(W, axis=1)
    e = wrap(np.arctan2(W[:, 1], W[:, 0]) - declination)
    t_field = (norm / field - 1.0) / field_unit
    t_dip = (np.arcsin(np.clip(-W[:, 2] / np.maximum(norm, 1e-30), -1, 1)) - dip) / dip_unit
    return e, hz, t_field, t_dip


def mag_terms(R, m, declination, field, dip, field_unit, dip_unit):
    """`np_mag_terms`, in C when `USE_KERNEL`."""
    if not USE_KERNEL:
        return np_mag_terms(R, m, declination, field, dip, field_unit, dip_unit)
    n = R.shape[0]
    out = [np.empty(n) for _ in range(4)]
    kernel_lib.capsheet_mf_mag_terms(n, *kernel_args("mag", (R, np.ascontiguousarray(m))),
                                     float(declination), float(field), float(dip),
                                     float(field_unit), float(dip_unit),
                                     *kernel_args("mag", out))
    return tuple(out)


def turn_all(Q, R) -> None:
    """``R_k <- Q R_k`` for every frame, in place (`rotate_all`; in C when `USE_KERNEL`)."""
    if USE_KERNEL:
        kernel_lib.capsheet_mf_rotate(R.shape[0], *kernel_args("rotate", (R, np.ascontiguousarray(Q))))
    else:
        R[:] = rotate_all(Q, R)


def np_orientation_cov(P, tilt_cov, yaw_add):
    C = P[:, :3, :3].copy()
    C[:, :2, :2] += tilt_cov
    if yaw_add is not None:
        C[:, 2, 2] += yaw_add
    return C


def orientation_cov(P, tilt_cov, yaw_add=None):
    """Every link's orientation covariance: ``P``'s rotation block, the common tilt's
    ``tilt_cov`` (2 x 2) added to its tilt and ``yaw_add`` (n,) to its yaw (in C when
    `USE_KERNEL`)."""
    if not USE_KERNEL:
        return np_orientation_cov(P, tilt_cov, yaw_add)
    n = P.shape[0]
    out = np.empty((n, 3, 3))
    tc = np.ascontiguousarray(tilt_cov, dtype=float)
    ya = kernel_ffi.NULL if yaw_add is None else kernel_ffi.from_buffer(
        "double[]", np.ascontiguousarray(yaw_add, dtype=float))
    P_c, tc_c, out_c = kernel_args("cov", (P, tc, out))
    kernel_lib.capsheet_mf_orientation_cov(n, P_c, tc_c, ya, out_c)
    return out


def np_ddot(R, w, wdot):
    body = w[:, 0:1] * w - np.einsum("ki,ki->k", w, w)[:, None] * np.array([1.0, 0.0, 0.0])
    body[:, 1] += wdot[:, 2]  # + ω̇ × e_x
    body[:, 2] -= wdot[:, 1]
    return np.einsum("kij,kj->ki", R, body)


def ddot(R, w, wdot):
    """Each link direction's second derivative, world: ``R (ω × (ω × e_x) + ω̇ × e_x)`` (in C
    when `USE_KERNEL`)."""
    if not USE_KERNEL:
        return np_ddot(R, w, wdot)
    out = np.empty((R.shape[0], 3))
    kernel_lib.capsheet_mf_ddot(R.shape[0], *kernel_args("ddot", (
        np.ascontiguousarray(R, dtype=float), np.ascontiguousarray(w, dtype=float),
        np.ascontiguousarray(wdot, dtype=float), out)))
    return out


def ddot_rates(R, w, wm1, wm2, dt, second_order: bool):
    """`ddot` with ``ω̇`` the rates' backward difference over ``dt`` (n,) from the last two
    ``wm1``, ``wm2``: second order ``(3 ω − 4 ω₋₁ + ω₋₂) / (2 dt)`` or first ``(ω − ω₋₁) / dt``
    (in C when `USE_KERNEL`, one pass, the same numbers)."""
    if not USE_KERNEL:
        h = dt[:, None]
        wdot = (3.0 * w - 4.0 * wm1 + wm2) / (2.0 * h) if second_order else (w - wm1) / h
        return np_ddot(R, w, wdot)
    out = np.empty((R.shape[0], 3))
    kernel_lib.capsheet_mf_ddot_rates(R.shape[0], *kernel_args("ddot", (R, w, wm1, wm2, dt)),
                                      int(second_order), kernel_ffi.from_buffer("double[]", out))
    return out


def robust_mode(r: np.ndarray, w: np.ndarray, width: float, start: float | None = None,
                iterations: int = 8) -> float | None:
    """The mode of the values ``r`` (weights ``w`` >= 0) by Tukey's biweight: iteratively
    reweighted means, each value weighted ``w (1 − ((r − ψ)/width)²)²`` within ``width`` of the
    current ``ψ`` and 0 beyond, from ``start`` (default: the weighted median). The values a
    disturbance turns a little, which pull a mean and a median their way, do not pull it once
    they are ``width`` off the values that agree. None when nothing has weight."""
    if start is not None and USE_KERNEL:  # the estimator's every snapshot: in C
        psi = kernel_lib.capsheet_mf_robust_mode(
            r.size, *kernel_args("mode", (np.ascontiguousarray(r, dtype=float),
                                          np.ascontiguousarray(w, dtype=float))),
            float(width), float(start), max(1, iterations // 2))
        return None if np.isnan(psi) else float(psi)
    return np_robust_mode(r, w, width, start, iterations)


def np_robust_mode(r, w, width, start=None, iterations=8):
    """`robust_mode` in numpy (the reference of its C kernel, and its start by the weighted
    median)."""
    keep = w > 0
    if not keep.any():
        return None
    r, w = r[keep], w[keep]
    if start is None:
        order = np.argsort(r)
        cw = np.cumsum(w[order])
        psi = float(r[order][np.searchsorted(cw, 0.5 * cw[-1])])
    else:
        psi = float(start)
    for _ in range(iterations if start is None else max(1, iterations // 2)):
        u = (r - psi) / width
        t = 1.0 - u * u
        wt = np.where(t > 0.0, w * t * t, 0.0)
        s = float(wt.sum())
        if s <= 0.0:
            return None
        psi = float(wt @ r) / s
    return psi


def group_info(topo, jd, wts, lat_diag):
    """What the loops say of each group's common yaw offset (`MotionEstimator._lattice_update`):
    ``jg`` (J's columns summed per group, ``topo.jg_*``'s pattern), each group's information
    ``info`` (1/rad²) and ``seen``, that information against its links' own from the lattice
    (in C when `USE_KERNEL`)."""
    ng = topo.n_groups
    if not USE_KERNEL:
        jg = np.bincount(topo.jg_index, weights=jd, minlength=topo.jg_rows.size)
        info = np.bincount(topo.jg_group, weights=wts[topo.jg_rows] * jg * jg, minlength=ng)
        seen = info / np.maximum(np.bincount(topo.group, weights=lat_diag, minlength=ng), 1e-300)
        return jg, info, seen
    jg, info, seen = np.empty(topo.jg_rows.size), np.empty(ng), np.empty(ng)
    kernel_lib.capsheet_mf_group_info(jd.size, jg.size, ng, topo.n_links, *fixed_args(
        topo, "info", lambda: (_i32(topo.jg_index), )), *kernel_args("info", (jd,)), *fixed_args(
        topo, "info_pattern", lambda: (_i32(topo.jg_rows), _i32(topo.jg_group))),
        *kernel_args("info", (wts,)),
        *fixed_args(topo, "group", (topo.group,)), *kernel_args("info", (lat_diag, jg, info, seen)))
    return jg, info, seen


def jt_times(topo, jd, v):
    """``Jᵀ v`` for the lattice step's Jacobian (the pattern ``topo.jac`` with the entries
    ``jd``; in C when `USE_KERNEL`, the same sums in the same order as scipy's product)."""
    if not USE_KERNEL:
        JT = topo.jac_T
        JT.data = jd[topo.jac_T_from]
        return JT @ v
    out = np.empty(topo.n_links)
    kernel_lib.capsheet_mf_jt_times(topo.n_rows, topo.n_links, *fixed_args(
        topo, "pattern", (topo.jac_indptr32, topo.jac_indices32)),
        *kernel_args("jt", (jd, np.ascontiguousarray(v, dtype=np.float64), out)))
    return out
