"""The global yaw least-squares problem of one snapshot (or a batch of one structure): its
coefficients, cost, gradient, Jacobian blocks and Gauss-Newton matrix, in numpy and in the
kernel."""

from __future__ import annotations

import copy

import numpy as np
import scipy.sparse as sp

import host.analysis.estimator.kernel as kernel  # the switch, read at call time
from .angles import angle_trig
from .kernel import ffi as _kffi, lib as _klib
from .linalg import factorise, solve
from .priors import ABS_PRIOR_FLOOR
from .structure import KERNEL_INDEX_FIELDS, Structure

__all__ = ["NORMAL_WEIGHT", "ROLL_WEIGHT", "YawProblem", "roll_weights"]

#: Weight of the normal-assumption residuals (eq. 6) relative to the loop closure (eq. 4).
NORMAL_WEIGHT = 0.2
#: Weight of the roll residuals (model "cells") relative to the loop closure (eq. 4); measured
#: best at 5 % g among 0.03-3 (docs/estimator.md).
ROLL_WEIGHT = 0.3


def roll_weights(st, beta) -> np.ndarray:
    """The roll residuals' weights (..., K): `ROLL_WEIGHT` over the link's number of cells, times
    ``|cos β|`` of the link. A roll residual's noise is its roll's, and a reading's roll
    ``atan2(s_y, s_z)`` has the standard deviation σ / cos β (σ per axis, in g): each residual
    weighted by the inverse of its noise (docs/estimator.md §2 has the sweep)."""
    return ROLL_WEIGHT * st.roll_inv_ncell * np.abs(np.cos(beta[..., st.roll_links]))


# eq. (4): d0 + d1 - d2 - d3 = 0;  eq. (6): n0 - n1 + n2 - n3 = 0  (Lattice.units numbering)
_S_D = np.array([1.0, 1.0, -1.0, -1.0])
_S_N = np.array([1.0, -1.0, 1.0, -1.0])


def _wrap(x: np.ndarray) -> np.ndarray:
    return (x + np.pi) % (2 * np.pi) - np.pi


def _cell_normals(D, Az, Cz):
    """Per cell (last axis of ``D``: its 4 links' xy directions), ``A``, ``C`` the sums of its
    i- and j-link directions (xy complex; ``Az``, ``Cz`` their z), and the unit normal of
    ``m = A × C``: ``(Axy, Cxy, nxy, nz, 1/|m|)``. A squashed cell (A ∥ C) has no normal:
    ``1/|m|`` is 0 there, so its roll terms drop out."""
    Axy = D[..., 1] + D[..., 3]
    Cxy = D[..., 0] + D[..., 2]
    mxy = 1j * (Az * Cxy - Cz * Axy)
    mz = (Axy.conj() * Cxy).imag
    mm = np.sqrt(mxy.real ** 2 + mxy.imag ** 2 + mz * mz)
    inv = np.where(mm > 1e-9, 1.0 / np.maximum(mm, 1e-300), 0.0)
    return Axy, Cxy, mxy * inv, mz * inv, inv


def _wrap_fast(x: np.ndarray) -> np.ndarray:
    """``x`` wrapped to [−π, π] (rounding, cheaper than a float modulo)."""
    return x - _TWO_PI * np.rint(x * (1.0 / _TWO_PI))


_TWO_PI = 2.0 * np.pi
#: eq. (4) signs turn the loop terms t = ±cos β e^{iγ} back into the links' xy directions
_SIGN_D = _S_D


def _scatter(idx: np.ndarray, w: np.ndarray, size: int) -> np.ndarray:
    """``Σ w`` into ``size`` bins by ``idx`` (m,) over ``w``'s last axis (..., m): a bincount,
    one per leading row (at most one leading axis, the batch)."""
    # astype: numpy's bincount of no entries is int64 even with float weights (a snapshot with no
    # model cell: the in-place gradient sums then raised a casting error)
    if w.ndim == 1:
        return np.bincount(idx, weights=w, minlength=size).astype(float, copy=False)
    B = w.shape[0]
    off = (idx[None, :] + size * np.arange(B)[:, None]).ravel()
    return np.bincount(off, weights=w.reshape(-1), minlength=B * size).astype(float, copy=False).reshape(B, size)


def _sumsq_last(x: np.ndarray):
    """``Σ |x|²`` over the last axis (a 0-d value for a 1-d ``x``), without BLAS."""
    if np.iscomplexobj(x):
        return np.add.reduce(x.real * x.real, axis=-1) + np.add.reduce(x.imag * x.imag, axis=-1)
    return np.add.reduce(x * x, axis=-1)


class YawProblem:
    """The global yaw least-squares problem for one snapshot (see the module docstring), or for
    a batch of snapshots of one structure at once: ``alpha``, ``beta`` (B, n_links), and
    ``prior_w``/``bend_w`` per snapshot or shared; every method then works row-wise on a
    leading batch axis (`estimate_batch`), with the same arithmetic.

    Cost ``½ Σ |loop|² (+ ½ Σ |eq6|²) + ½ Σ roll² + ½ Σ_pairs λ_p (wrap(γ_k − γ_l) − δ_kl)²
    (+ ½ Σ λ wrap(γ − τ)²)``; the complex form of every term is in docs/estimator.md.
    """

    #: per-snapshot attributes and their number of axes without the batch axis (`take`)
    _PER_SNAPSHOT = {"c_loop": 2, "c_n": 2, "Az": 1, "Cz": 1, "y_c": 1, "y_z": 1, "lam": 1,
                     "lam_b": 1, "w": 1}

    def __init__(self, st: Structure, alpha, beta, target, prior_w, bend_w, trig=None):
        self.st = st
        self.target = target[st.var_links]
        self.lam = prior_w  # (nv,) prior weight per variable
        self.abs_prior = bool(np.any(prior_w > ABS_PRIOR_FLOOR))
        if target is st.rest_yaw:  # the default target: its pair differences once per structure
            pt = st.derived.get("rest_pair_t")
            if pt is None:
                pt = st.derived["rest_pair_t"] = _wrap(target[st.pairs[:, 0]] - target[st.pairs[:, 1]])
            self.pair_t = pt
        else:
            self.pair_t = _wrap(target[st.pairs[:, 0]] - target[st.pairs[:, 1]])
        self.lam_b = bend_w  # (n_pairs,)
        if kernel.USE_KERNEL and st.model == "cells" and np.ndim(alpha) == 1:  # one snapshot: the kernel
            self._coeffs_kernel(alpha, beta, trig)
            return
        ca, sa, cb, sb = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)
        u = st.units
        cbu = cb[..., u]
        self.c_loop = cbu * _S_D  # (U, 4) real
        if st.model == "eq6":
            self.c_n = (sb[..., u] * ca[..., u] - 1j * sa[..., u]) * (_S_N * NORMAL_WEIGHT)
        else:
            k = st.roll_links
            sbu = sb[..., u]
            self.Az = -(sbu[..., 1] + sbu[..., 3])  # z of the cell's i-link sum A (yaw-free)
            self.Cz = -(sbu[..., 0] + sbu[..., 2])  # z of its j-link sum C
            self.y_c = (sb[..., k] * sa[..., k] + 1j * ca[..., k])  # sensor y, xy before the yaw
            self.y_z = cb[..., k] * sa[..., k]
            self.w = roll_weights(st, beta)

    def _coeffs_kernel(self, alpha, beta, trig=None):
        """`__init__`'s yaw-free coefficients (model "cells", one snapshot) in the kernel;
        ``trig``: the links' `angle_trig`, if already made."""
        st = self.st
        sk = st.kernel_arrays()
        U, K = st.n_units, st.roll_links.size
        if trig is None:
            trig = angle_trig(alpha, beta)
        self.c_loop, self.Az, self.Cz = np.empty((U, 4)), np.empty(U), np.empty(U)
        self.y_c, self.y_z = np.empty(K, dtype=complex), np.empty(K)
        fb = _kffi.from_buffer
        _klib.capsheet_yaw_coeffs(U, sk["units"][1], K, sk["roll_links"][1],
                                  fb("double[]", trig), fb("double[]", self.c_loop),
                                  fb("double[]", self.Az), fb("double[]", self.Cz),
                                  fb("double[]", self.y_c.view(np.float64)),
                                  fb("double[]", self.y_z))
        # `roll_weights` with the table's cos β (the same to rounding; a cosine per link saved)
        self.w = ROLL_WEIGHT * st.roll_inv_ncell * np.abs(trig[st.roll_links, 2])

    def take(self, idx):
        """The problem of the snapshots ``idx`` of a batch (an int: one snapshot, no batch axis)."""
        sub = copy.copy(self)
        sub.__dict__.pop("_kp", None)  # the kernel's view of one snapshot's arrays
        sub.__dict__.pop("_cs", None)
        for name, nd in self._PER_SNAPSHOT.items():
            v = getattr(self, name, None)
            if v is not None and np.ndim(v) == nd + 1:
                setattr(sub, name, v[idx])
        return sub

    def evaluate(self, gamma, jac: bool = True):
        """Cost, gradient over the variables, and the Jacobian blocks (for `factor`; None when
        ``jac`` is False: the roll terms' gradient then comes from `_roll_grad`, without
        forming their Jacobian)."""
        st = self.st
        if not jac and st.model == "cells" and kernel.USE_KERNEL and gamma.ndim == 1:
            return self._evaluate_kernel(gamma)
        nv1 = st.n_var + 1
        z = np.exp(1j * gamma)
        zu = z[..., st.units]
        t = self.c_loop * zu  # (U, 4) complex; ∂r/∂γ_m = i t_m
        r = t.sum(axis=-1)
        cost2 = _sumsq_last(r)
        gu = (t.conj() * r[..., None]).imag  # (U, 4)
        blocks = [t]
        if st.model == "eq6":
            tn = self.c_n * zu
            rn = tn.sum(axis=-1)
            cost2 = cost2 + _sumsq_last(rn)
            gu += (tn.conj() * rn[..., None]).imag
            blocks = [np.stack([t, tn], axis=-2)]
        lead = gamma.shape[:-1]
        if st.model == "cells" and not jac:
            rr, gn, gd = self._roll_grad(z, t)
            cost2 = cost2 + _sumsq_last(rr)
            grad = _scatter(st.unit_var.ravel(), (gu + gn).reshape(lead + (-1,)), nv1)
            grad += _scatter(st.roll_var[:, 0], gd, nv1)
            blocks = None
        else:
            grad = _scatter(st.unit_var.ravel(), gu.reshape(lead + (-1,)), nv1).astype(float)
        if st.model == "cells" and jac:
            Jr, rr = self._roll(z, t)
            cost2 = cost2 + _sumsq_last(rr)
            grad += _scatter(st.roll_var.ravel(), (Jr * rr[..., None]).reshape(lead + (-1,)),
                             nv1)
            blocks.append(Jr)
        pr = st.pairs
        eb = _wrap_fast(gamma[..., pr[:, 0]] - gamma[..., pr[:, 1]] - self.pair_t)
        wb = self.lam_b * eb
        cost2 = cost2 + np.add.reduce(wb * eb, axis=-1)
        grad += _scatter(st.pair_var[:, 0], wb, nv1)
        grad -= _scatter(st.pair_var[:, 1], wb, nv1)
        grad = grad[..., :st.n_var]
        if self.abs_prior:  # otherwise the floor only sits on the diagonal (`factor`)
            e = _wrap_fast(gamma[..., st.var_links] - self.target)
            cost2 = cost2 + np.add.reduce(self.lam * e * e, axis=-1)
            grad += self.lam * e
        return 0.5 * cost2, grad, blocks

    def _evaluate_kernel(self, gamma):
        """`evaluate` with ``jac=False`` for one snapshot, model "cells", in the compiled kernel
        (host/analysis/_kernel/yaw_eval.c: the same terms as `evaluate` and `_roll_grad`)."""
        kp = self.__dict__.get("_kp")
        if kp is None:
            kp = self._kp = self._kernel_problem()
        st = self.st
        g = np.ascontiguousarray(gamma, dtype=float)
        grad = np.empty(st.n_var + 1)
        fb = _kffi.from_buffer
        cost = _klib.capsheet_yaw_eval_cs(kp[0], fb("double[]", g), fb("double[]", self.link_cs(g)),
                                          fb("double[]", grad), kp[1])
        return cost, grad[:st.n_var], None

    def link_cs(self, gamma) -> np.ndarray:
        """(cos γ, sin γ) of every link, interleaved (2 n_links,), as the kernel reads them: the
        ones kept for these very yaws (`keep_cs`: a chord step's, or the previous snapshot's end
        point when it is this one's start), else computed and kept."""
        kept = self.__dict__.get("_cs")
        if kept is not None and np.array_equal(kept[0], gamma):
            return kept[1]
        cs = np.empty(2 * gamma.size)
        g = np.ascontiguousarray(gamma, dtype=float)
        _klib.capsheet_link_cs(g.size, _kffi.from_buffer("double[]", g),
                               _kffi.from_buffer("double[]", cs))
        self._cs = (g.copy(), cs)
        return cs

    def keep_cs(self, gamma, cs) -> None:
        """Keep ``cs`` as `link_cs` of ``gamma`` (copied: the caller may change either)."""
        self._cs = (np.array(gamma, dtype=float), np.array(cs, dtype=float))

    def chord_kernel(self, gamma, cost, grad, lu, tol, max_iter, refactor_ratio, anderson_cos,
                     chain=None, chain_safety=0.0, predict_within=3.0, refactor_patience=1,
                     refactor_far=0.0, refactor_growth=np.inf):
        """`solve_global`'s chord iterations on the kept factorisation ``lu`` in the kernel
        (``capsheet_chord``: the same steps, acceleration, tests and counts as the Python
        loop; ``max_iter``, ``refactor_ratio``, ``anderson_cos``: the solver's `MAX_ITER`,
        `REFACTOR_RATIO`, `ANDERSON_COS`; ``chain``, ``chain_safety``: its `solver.Contraction`
        or None, and `solver.CHAIN_SAFETY`). ``gamma``
        is updated in place. Returns (status, iterations, cost, grad, prev_smax, steps); status 0
        converged, 1 the cost rose, 2 a poor contraction (refactorise for both), 3 out of
        iterations; steps: the first two steps' largest entries, as taken."""
        kp = self.__dict__.get("_kp")
        if kp is None:
            kp = self._kp = self._kernel_problem()
        st = self.st
        nv = st.n_var
        (val, diag, sym), ptrs = lu[2]
        fb = _kffi.from_buffer
        c = _kffi.new("capsheet_chord_t *")
        c.n_links, c.max_iter, c.tol = gamma.size, max_iter, float(tol)
        c.refactor_ratio, c.anderson_cos = refactor_ratio, anderson_cos
        c.predict_within = predict_within
        c.refactor_patience, c.refactor_far = int(refactor_patience), float(refactor_far)
        c.refactor_growth = float(refactor_growth)
        if chain is not None:
            c.chain_rho, c.chain_kappa, c.chain_safety = chain.rho, chain.kappa, float(chain_safety)
        pi = np.ascontiguousarray(st.perm_inv, np.int64)
        pv = np.ascontiguousarray(st.perm_of_var, np.int64)
        c.perm_inv, c.perm_of_var = fb("int64_t[]", pi), fb("int64_t[]", pv)
        c.n_super = ptrs[0]
        c.sn_col, c.sn_row, c.rows, c.sn_diag, c.sn_below = ptrs[1:6]
        c.val, c.diag = ptrs[6], ptrs[7]
        c.ldl_work_size = sym["work_size"]
        g = np.zeros(nv + 1)
        g[:nv] = grad
        out_cost = _kffi.new("double *", float(cost))
        its = _kffi.new("int64_t *", 0)
        ps = _kffi.new("double *", np.inf)
        work = np.empty(6 * nv + gamma.size + 1 + sym["work_size"] + 19 * max(st.n_units, 1)
                        + 6 * st.n_links)
        assert gamma.dtype == np.float64 and gamma.flags.c_contiguous
        steps = _kffi.new("double[2]")
        cs_in = self.link_cs(gamma)
        cs_out = np.empty(2 * gamma.size)
        c.cs_in, c.cs_out = fb("double[]", cs_in), fb("double[]", cs_out)
        status = _klib.capsheet_chord(kp[0], fb("double[]", gamma), out_cost, fb("double[]", g), c,
                                      its, ps, steps, fb("double[]", work))
        self._cs = (gamma.copy(), cs_out)
        n = min(int(its[0]), 2)
        return (int(status), int(its[0]), float(out_cost[0]), g[:nv], float(ps[0]),
                [float(steps[k]) for k in range(n)])

    def _kernel_problem(self):
        """The kernel's ``capsheet_yaw_t`` for this snapshot, its work buffer, and the arrays
        it points into (kept alive with it). The structure's index arrays are shared
        (`Structure.kernel_arrays`)."""
        st = self.st
        sk = st.kernel_arrays()
        keep = [sk]
        fb = _kffi.from_buffer

        def ptr(a):
            a = np.ascontiguousarray(a, dtype=np.float64)
            keep.append(a)
            return fb("double[]", a)

        p = _kffi.new("capsheet_yaw_t *")
        p.n_units, p.n_roll, p.n_pairs, p.n_var = sk["sizes"]
        p.n_links = st.n_links
        for name in KERNEL_INDEX_FIELDS:
            setattr(p, name, sk[name][1])
        p.roll_ws1, p.w = sk["roll_ws1"][1], ptr(self.w)
        p.c_loop, p.Az, p.Cz = ptr(self.c_loop), ptr(self.Az), ptr(self.Cz)
        p.y_c = ptr(np.ascontiguousarray(self.y_c, dtype=complex).view(np.float64))
        p.y_z, p.pair_t = ptr(self.y_z), ptr(self.pair_t)
        p.lam_b = ptr(self.lam_b if np.ndim(self.lam_b) else np.full(st.pairs.shape[0], self.lam_b))
        p.target = ptr(self.target)
        p.lam = ptr(self.lam if np.ndim(self.lam) else np.full(st.n_var, self.lam))
        p.abs_prior = 1 if self.abs_prior else 0
        return p, fb("double[]", sk["work"]), keep

    def rows(self, gamma) -> np.ndarray:
        """The data residuals as real rows: loop (and eq. 6) real parts, imaginary parts, then
        the roll residuals (the order `yaw_joint_std` weights them in)."""
        st = self.st
        z = np.exp(1j * gamma)
        zu = z[..., st.units]
        t = self.c_loop * zu
        r = t.sum(axis=-1)
        if st.model == "eq6":
            r = np.concatenate([r, (self.c_n * zu).sum(axis=-1)], axis=-1)
            return np.concatenate([r.real, r.imag], axis=-1)
        return np.concatenate([r.real, r.imag, self._roll(z, t)[1]], axis=-1)

    def _roll_terms(self, z, t):
        """What `_roll` and `_roll_grad` share: the links' xy directions per unit ``D`` (U, 4),
        ``cos β e^{iγ}``; the cells' ``A``, ``C`` (xy), normals ``n`` (xy, z) and ``1/|m|``; each roll
        link's sensor y (xy complex ``yxy`` and its conjugate ``yc``), its cells' mean normal
        (xy ``Nxy``) and the roll residuals ``res = w · y_k · N_k`` (K,)."""
        st = self.st
        D = t * _SIGN_D
        Axy, Cxy, nxy, nz, inv = _cell_normals(D, self.Az, self.Cz)
        c0, c1, ws1 = st.roll_c0, st.roll_c1, st.roll_ws1
        yxy = self.y_c * z[..., st.roll_links]
        Nxy = nxy[..., c0] + ws1 * nxy[..., c1]
        Nz = nz[..., c0] + ws1 * nz[..., c1]
        yc = yxy.conj()
        res = self.w * ((yc * Nxy).real + self.y_z * Nz)
        return D, Axy, Cxy, nxy, nz, inv, yxy, yc, Nxy, res

    def _dm(self, D, Axy, Cxy):
        """``∂m/∂γ`` of every cell per unit link (U, 4): xy (complex) and z (`_roll`'s docstring)."""
        Az, Cz = self.Az, self.Cz
        dmxy = D * np.stack([-Az, Cz, -Az, Cz], axis=-1)
        X = np.stack([Axy, Cxy, Axy, Cxy], axis=-1)
        dmz = (X.conj() * D).real * np.array([1.0, -1.0, 1.0, -1.0])
        return dmxy, dmz

    def _roll(self, z, t):
        """Roll residuals ``w · y_k · N_k`` and their Jacobian rows (K, 7).

        Per cell: ``A``, ``C`` the sums of its i- and j-link directions (xy complex, z real),
        ``m = A × C``, ``n = m/|m|``; a link's ``N`` is the mean of its cells' ``n``.
        ``∂m/∂γ`` for an i-link ``a``: ``(C_z a, −Re(ā C))``; for a j-link ``c``:
        ``(−A_z c, Re(Ā c))`` (xy, z), with ``a``, ``c`` the links' xy directions.
        """
        st = self.st
        D, Axy, Cxy, nxy, nz, inv, yxy, yc, Nxy, res = self._roll_terms(z, t)
        dmxy, dmz = self._dm(D, Axy, Cxy)
        nd = (nxy.conj()[..., None] * dmxy).real + nz[..., None] * dmz  # n · ∂m  (U, 4)
        c0, c1, ws1 = st.roll_c0, st.roll_c1, st.roll_ws1
        yz = self.y_z
        w = self.w
        K = c0.size
        lead = yxy.shape[:-1]
        Jraw = np.empty(lead + (K, 2, 4))
        for s_, c, ws in ((0, c0, None), (1, c1, ws1)):
            ynu = (yc * nxy[..., c]).real + yz * nz[..., c]  # y · n_c  (K,)
            ydm = (yc[..., None] * dmxy[..., c, :]).real + yz[..., None] * dmz[..., c, :]
            sc = inv[..., c] if ws is None else inv[..., c] * ws
            Jraw[..., s_, :] = (ydm - ynu[..., None] * nd[..., c, :]) * sc[..., None]
        flat = Jraw.reshape(lead + (-1,))
        J = np.empty(lead + (K, 7))
        sidx = st.roll_idx_self
        J[..., 0] = w * ((yc * Nxy).imag + flat[..., sidx[:, 0]] + flat[..., sidx[:, 1]])
        J[..., 1:] = w[..., None] * flat[..., st.roll_idx_oth]
        return J, res

    def _roll_grad(self, z, t):
        """Roll residuals and their gradient ``Jᵀ res`` without the Jacobian (reverse mode):
        (res (K,), per unit and position the part through the cell normals (U, 4), per roll
        link the part through its own sensor y (K,)).

        With ``ρ_k = w_k res_k``, cell ``c`` collects ``Y_c = Σ_k ρ_k y_k`` over its links (both
        cells of a link: the mean's weights), and ``Y · ∂n = Q · ∂m`` with
        ``Q = (Y − (Y·n) n)/|m|`` (``∂n = (∂m − n (n·∂m))/|m|``): the same terms as `_roll`'s rows
        summed, in a few passes over the cells instead of one per Jacobian entry.
        """
        st = self.st
        D, Axy, Cxy, nxy, nz, inv, yxy, yc, Nxy, res = self._roll_terms(z, t)
        c0, c1, ws1 = st.roll_c0, st.roll_c1, st.roll_ws1
        yz = self.y_z
        rho = self.w * res
        gd = rho * (yc * Nxy).imag  # through y_k = y_c e^{iγ_k}: ∂(ȳ N)/∂γ_k = Im(ȳ N)
        U = st.n_units
        cells = np.concatenate([c0, c1])
        ry, rz = rho * yxy, rho * yz
        r1 = ws1 * rho
        wx = np.concatenate([ry.real, (r1 * yxy).real], axis=-1)
        wy = np.concatenate([ry.imag, (r1 * yxy).imag], axis=-1)
        wz = np.concatenate([rz, r1 * yz], axis=-1)
        Yxy = _scatter(cells, wx, U) + 1j * _scatter(cells, wy, U)
        Yz = _scatter(cells, wz, U)
        Yn = (Yxy.conj() * nxy).real + Yz * nz
        Qxy = (Yxy - Yn * nxy) * inv
        Qz = (Yz - Yn * nz) * inv
        dmxy, dmz = self._dm(D, Axy, Cxy)
        gn = (Qxy.conj()[..., None] * dmxy).real + Qz[..., None] * dmz
        return res, gn, gd

    def factor(self, blocks, mu):
        """Factorise the Gauss-Newton matrix ``JᵀJ + diag(λ) + μ I`` (permuted, fixed pattern)
        of one snapshot (``blocks`` from `evaluate` without a batch axis)."""
        return factorise(self.st, self.matrix(blocks, mu))

    def matrix(self, blocks, mu=0.0):
        """The Gauss-Newton matrix `factor` factorises (CSC, the structure's ordering)."""
        st = self.st
        t = blocks[0]
        if t.ndim == 3:  # eq6: (U, 2, 4)
            Hd = np.einsum("uem,uen->umn", t.conj(), t).real
        else:
            Hd = (t.conj()[:, :, None] * t[:, None, :]).real
        w = [Hd.ravel()]
        if st.model == "cells":
            Jr = blocks[1]
            w.append((Jr[:, :, None] * Jr[:, None, :]).ravel())
        w.append((self.lam_b[:, None] * np.array([1.0, -1.0, -1.0, 1.0])).ravel())
        data = np.zeros(st.nnz + 1)
        for sl, wt in zip(st.block_slots, w):
            data += np.bincount(sl, weights=wt, minlength=st.nnz + 1)
        data = data[:st.nnz]
        data[st.diag_slot] += self.lam + mu
        return sp.csc_matrix((data, st.csc_indices, st.csc_indptr), shape=(st.n_var, st.n_var))

    def step(self, lu, grad):
        """The (chord) Gauss-Newton step ``−A⁻¹ grad``, row-wise for a batch (B, nv)."""
        st = self.st
        b = -grad[..., st.perm_inv]
        if b.ndim == 1:
            return solve(lu, b)[st.perm_of_var]
        return solve(lu, np.ascontiguousarray(b.T)).T[:, st.perm_of_var]
