"""The sparse linear algebra of the yaw problem: SuperLU (always there) or CHOLMOD (optional), and
the kernel's supernodal triangular sweeps of a SuperLU factorisation."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

import host.analysis.estimator.kernel as kernel  # the switch, read at call time
from .kernel import ffi as _kffi, lib as _klib

__all__ = ["LINEAR_SOLVER", "cholmod_module", "backend", "factorise", "solve", "laplacian_kernel",
           "lap_solve", "KERNEL_FACTOR", "KernelLDL", "structural_symbolic"]

#: Sparse factorisation of the yaw problem: "splu" (scipy's SuperLU, always there; the default:
#: benchmarks/bench_estimator.py found no consistent gain from CHOLMOD on warm runs, -17 % to
#: +29 % snapshots/s by size), "cholmod" (scikit-sparse, optional: ``pip install
#: 'capture-sheet[fast]'``, needs libsuitesparse-dev) or "auto" (CHOLMOD when installed).
LINEAR_SOLVER = "splu"


def cholmod_module():
    """scikit-sparse's CHOLMOD module, or None when not installed (it is optional)."""
    try:
        from sksparse import cholmod
    except ImportError:  # pragma: no cover - depends on the installation
        return None
    return cholmod


def backend() -> str:
    """The factorisation `LINEAR_SOLVER` names: "splu" or "cholmod" ("auto": CHOLMOD when
    installed)."""
    if LINEAR_SOLVER == "auto":
        return "cholmod" if cholmod_module() is not None else "splu"
    return LINEAR_SOLVER


def factorise(st: "Structure", A, sweeps: bool = True):
    """Factorise the (permuted, SPD) Gauss-Newton matrix with the chosen backend: SuperLU on
    the fixed ordering, or CHOLMOD with its symbolic analysis (METIS) cached per structure."""
    if backend() == "cholmod":
        cm = cholmod_module()
        sym = st.derived.get("cholmod_sym")
        if sym is None:
            sym = st.derived["cholmod_sym"] = cm.analyze(A, mode="supernodal", ordering_method="metis")
        return ("cholmod", sym.cholesky(A))
    if KERNEL_FACTOR and kernel.USE_KERNEL and sweeps and st is not None:
        sym = structural_symbolic(st)
        got = None if sym is None else _kernel_factor(A, sym)
        if got is not None:
            return got
    lu = splu(A, permc_spec="NATURAL", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
    # the kernel's sweeps serve one right-hand side at a time (the chord steps); ``sweeps=False``
    # for a factorisation solved only with many at once (the uncertainty's)
    return ("splu", lu, _triangular(lu, st) if kernel.USE_KERNEL and sweeps else None)


def structural_symbolic(st):
    """The supernodes (`_ldl_symbolic`) of L's structural pattern for ``st``'s Gauss-Newton
    matrix, made once per structure (``st.derived``): from SuperLU's factor of a matrix of the
    structure's pattern whose every entry is nonzero (an M-matrix: −1 off the diagonal, each
    diagonal entry over its column's count, whose elimination fills exactly where the pattern
    does, never cancelling to zero). Not from a numeric factor: a level sheet's matrix has zeros
    that SuperLU's factor then lacks, and supernodes made from it made every later factorisation
    of the structure round differently (an estimate depended on what was estimated before).
    None when SuperLU pivoted anyway."""
    got = st.derived.get("ldl_structural", False)
    if got is not False:
        return got
    n, ptr, idx = st.n_var, st.csc_indptr, st.csc_indices
    col = np.repeat(np.arange(n), np.diff(ptr))
    val = np.where(idx == col, np.diff(ptr)[col] + 1.0, -1.0)
    lu = splu(sp.csc_matrix((val, idx, ptr), shape=(n, n)), permc_spec="NATURAL",
              diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
    got = None
    if np.array_equal(lu.perm_r, np.arange(n)) and np.array_equal(lu.perm_c, np.arange(n)):
        L = lu.L
        got = _ldl_symbolic(n, np.ascontiguousarray(L.indptr, np.int32),
                            np.ascontiguousarray(L.indices, np.int32))
    st.derived["ldl_structural"] = got
    return got


#: Whether `factorise` makes the factorisations after a structure's first in the kernel
#: (``capsheet_ldl_factor``: L D Lᵀ on the supernodes of SuperLU's first factor, the same
#: numbers to rounding) instead of SuperLU's LU. At 64x64 a factorisation was ~70 ms in SuperLU,
#: and a moving sheet needs one every ~40 snapshots (docs/estimator.md §6).
KERNEL_FACTOR = True


class KernelLDL:
    """A factorisation made by the kernel (`_kernel_factor`): L D Lᵀ in double on the
    supernodes of ``sym``. `solve` takes one right-hand side (n,) or several (n, k), as SuperLU's
    factorisation object does (`solve`'s callers with many columns: `estimate_batch`)."""

    def __init__(self, lval: np.ndarray, diag: np.ndarray, sym: dict):
        self.lval, self.diag, self.sym = lval, diag, sym
        self.shape = (diag.size, diag.size)

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.asarray(b, dtype=np.float64)
        cols = b.reshape(b.shape[0], -1).T.copy()  # (k, n), each solved in place
        work = np.empty(self.sym["work_size"])
        fb = _kffi.from_buffer
        args = (self.sym["n_super"], *self.sym["c_args"][:5], fb("double[]", self.lval),
                fb("double[]", self.diag))
        for x in cols:
            _klib.capsheet_ldl_solve_d(x.size, *args, fb("double[]", x), fb("double[]", work))
        return cols.T.reshape(b.shape)


def _kernel_factor(A, sym: dict):
    """``("splu", KernelLDL, sweeps)`` for the SPD matrix ``A`` (CSC, the structure's pattern)
    factorised in the kernel on the supernodes ``sym`` (`_ldl_symbolic`), or None when it is
    not positive definite or an entry falls outside the supernodes' pattern (then SuperLU)."""
    n = A.shape[0]
    ns, nval = sym["n_super"], sym["n_val"]
    lval, diag = np.empty(max(nval, 1)), np.empty(max(n, 1))
    val = np.empty(max(nval, 1), np.float32)
    fb = _kffi.from_buffer
    status = _klib.capsheet_ldl_factor(
        n, fb("int32_t[]", np.ascontiguousarray(A.indptr, np.int32)),
        fb("int32_t[]", np.ascontiguousarray(A.indices, np.int32)),
        fb("double[]", np.ascontiguousarray(A.data, np.float64)), ns, *sym["c_args"][:5],
        fb("double[]", lval), fb("double[]", diag), fb("float[]", val), nval,
        fb("int32_t[]", np.empty(2 * n + 3 * ns + 1, np.int32)),
        fb("double[]", np.empty(sym["work_size"])))
    if status != 0:
        return None
    diag = diag[:n]
    ptrs = (ns, *sym["c_args"][:5], fb("float[]", val), fb("double[]", diag))
    return ("splu", KernelLDL(lval, diag, sym), ((val, diag, sym), ptrs))


def _triangular(lu, st=None):
    """SuperLU's factors as the kernel's supernodal ``capsheet_ldl_solve`` takes them: the
    matrix is SPD and factorised without pivoting, so ``U = D Lᵀ`` and L (unit lower) with U's
    diagonal D is the whole factorisation; L's columns are grouped into supernodes (consecutive
    columns sharing their rows below), each stored as a dense block so that a solve runs on
    contiguous memory instead of scattered single entries, its values in float32 (the solve is
    bound by memory; the chord step matrix is approximate anyway and the iteration's fixed point,
    grad = 0, does not depend on it). The supernodes depend only on L's
    pattern, fixed for a structure: built once and cached on ``st``. None when SuperLU permuted
    rows or columns (it was asked not to: the ordering is the structure's)."""
    n = lu.shape[0]
    if not (np.array_equal(lu.perm_r, np.arange(n)) and np.array_equal(lu.perm_c, np.arange(n))):
        return None
    L = lu.L
    ptr = np.ascontiguousarray(L.indptr, np.int32)
    idx = np.ascontiguousarray(L.indices, np.int32)
    sym = st.derived.get("ldl_symbolic") if st is not None else None
    if sym is None or not (np.array_equal(sym["l_ptr"], ptr) and np.array_equal(sym["l_idx"], idx)):
        sym = _ldl_symbolic(n, ptr, idx)
        if st is not None:
            st.derived["ldl_symbolic"] = sym
    fb = _kffi.from_buffer
    val = np.zeros(sym["n_val"], np.float32)
    diag = np.ascontiguousarray(lu.U.diagonal(), np.float64)
    _klib.capsheet_ldl_fill(sym["n_super"], fb("int32_t[]", ptr), fb("int32_t[]", idx),
                            fb("double[]", np.ascontiguousarray(L.data, np.float64)),
                            *sym["c_args"][:5], fb("int32_t[]", np.full(max(n, 1), -1, np.int32)),
                            fb("float[]", val))
    ptrs = (sym["n_super"], *sym["c_args"][:5], fb("float[]", val), fb("double[]", diag))
    return (val, diag, sym), ptrs


def _ldl_symbolic(n: int, l_ptr: np.ndarray, l_idx: np.ndarray) -> dict:
    """L's supernodes (fundamental: column j+1 joins j's when j's first row below the diagonal
    is j+1 and j+1 has exactly j's other rows) and the layout `capsheet_ldl_solve` reads."""
    col = np.repeat(np.arange(n), np.diff(l_ptr))
    keep = l_idx > col
    ci, ri = col[keep], l_idx[keep].astype(np.int64)
    order = np.lexsort((ri, ci))  # rows sorted within each column
    ci, ri = ci[order], ri[order]
    cnt = np.bincount(ci, minlength=n)
    ptr = np.zeros(n + 1, np.int64)
    np.cumsum(cnt, out=ptr[1:])
    first = np.full(n, -1, np.int64)
    nz = cnt > 0
    first[nz] = ri[ptr[:-1][nz]]
    cand = np.flatnonzero((first[:-1] == np.arange(1, n)) & (cnt[1:] == cnt[:-1] - 1))
    m = cnt[cand + 1]
    if m.sum():  # the rows themselves agree (the counts suffice for an exact symbolic pattern)
        rep = np.repeat(np.arange(cand.size), m)
        off = np.arange(int(m.sum())) - np.repeat(np.cumsum(m) - m, m)
        same = ri[ptr[cand][rep] + 1 + off] == ri[ptr[cand + 1][rep] + off]
        cand = cand[np.bincount(rep[~same], minlength=cand.size) == 0]
    cont = np.zeros(n, bool)
    cont[cand + 1] = True
    sn_col = np.append(np.flatnonzero(~cont), n).astype(np.int32)
    ns = sn_col.size - 1
    w = np.diff(sn_col).astype(np.int64)
    last = sn_col[1:].astype(np.int64) - 1
    nb = cnt[last]
    sn_row = np.zeros(ns + 1, np.int64)
    np.cumsum(nb, out=sn_row[1:])
    rep = np.repeat(np.arange(ns), nb)
    rows = np.ascontiguousarray(ri[ptr[last][rep] + np.arange(rep.size) - sn_row[:-1][rep]], np.int32)
    base = np.zeros(ns + 1, np.int64)
    np.cumsum(w * w + w * nb, out=base[1:])
    sn_diag = np.ascontiguousarray(base[:-1])
    sn_below = np.ascontiguousarray(base[:-1] + w * w)
    fb = _kffi.from_buffer
    arrays = (sn_col, sn_row, rows, sn_diag, sn_below)
    work = np.empty(max(int(nb.max()) if ns else 0, 1))
    c_args = (fb("int32_t[]", sn_col), fb("int64_t[]", sn_row), fb("int32_t[]", rows),
              fb("int64_t[]", sn_diag), fb("int64_t[]", sn_below))
    return {"l_ptr": l_ptr.copy(), "l_idx": l_idx.copy(), "n_super": ns, "n_val": int(base[-1]),
            "arrays": arrays, "c_args": c_args, "work_size": work.size}


def solve(fac, b):
    """``A⁻¹ b`` with a factorisation from `factorise`; one right-hand side (b (n,)) of a SuperLU
    factorisation goes through the kernel's triangular sweeps when it is built."""
    kind, f = fac[0], fac[1]
    if kind == "cholmod":
        return f(b)
    tri = fac[2] if len(fac) > 2 else None
    if tri is None or b.ndim != 1 or not kernel.USE_KERNEL:
        return f.solve(b)
    x = np.array(b, dtype=np.float64)  # a copy: solved in place
    work = np.empty(tri[0][2]["work_size"])  # per call: solves may run in several threads
    _klib.capsheet_ldl_solve(x.size, *tri[1], _kffi.from_buffer("double[]", x),
                             _kffi.from_buffer("double[]", work))
    return x


def laplacian_kernel(st):
    """The joints' Laplacian of structure ``st`` (``B^T B + JOINT_PRIOR_WEIGHT I``) as the kernel's
    ``capsheet_lap_t``: ordered by SuperLU's minimum degree (the ordering ``st.lap_lu`` uses),
    factorised once without pivoting (SPD) and kept in supernodes with double values, so that a
    solve (`lap_solve`, the heights of `pipeline.closed_pitches`, the joints) runs in C without
    SuperLU's per-call overhead; the numbers are SuperLU's to rounding. Made once per structure
    (``st.derived``); None when the kernel is not built or SuperLU pivoted anyway."""
    got = st.derived.get("lap_kernel", False)
    if got is not False:
        return got
    got = None
    if _klib is not None:
        from scipy.sparse.linalg import splu as _splu
        lap = st.lap_matrix
        n = lap.shape[0]
        pos = np.asarray(st.lap_lu.perm_c, dtype=np.int64)  # joint -> position
        inv = np.argsort(pos)
        Ap = lap[inv][:, inv].tocsc()
        lu = _splu(Ap, permc_spec="NATURAL", diag_pivot_thresh=0.0,
                   options=dict(SymmetricMode=True))
        if np.array_equal(lu.perm_r, np.arange(n)) and np.array_equal(lu.perm_c, np.arange(n)):
            L = lu.L
            ptr = np.ascontiguousarray(L.indptr, np.int32)
            idx = np.ascontiguousarray(L.indices, np.int32)
            sym = _ldl_symbolic(n, ptr, idx)
            fb = _kffi.from_buffer
            val = np.zeros(max(sym["n_val"], 1))
            diag = np.ascontiguousarray(lu.U.diagonal(), np.float64)
            _klib.capsheet_ldl_fill_d(sym["n_super"], fb("int32_t[]", ptr), fb("int32_t[]", idx),
                                      fb("double[]", np.ascontiguousarray(L.data, np.float64)),
                                      *sym["c_args"][:5],
                                      fb("int32_t[]", np.full(max(n, 1), -1, np.int32)),
                                      fb("double[]", val))
            c = _kffi.new("capsheet_lap_t *")
            c.n, c.pos = n, fb("int64_t[]", pos)
            c.n_super = sym["n_super"]
            c.sn_col, c.sn_row, c.rows, c.sn_diag, c.sn_below = sym["c_args"][:5]
            c.val, c.diag = fb("double[]", val), fb("double[]", diag)
            c.ldl_work_size = sym["work_size"]
            got = (c, (pos, val, diag, sym))  # the arrays the pointers point into, kept alive
    st.derived["lap_kernel"] = got
    return got


def lap_solve(st, b):
    """``st``'s Laplacian solved for ``b`` (n_joints,) or (n_joints, k): up to 4 columns in the
    kernel (`laplacian_kernel`, the factor read once for all) when it is built and switched on,
    else SuperLU's (``st.lap_lu``)."""
    lk = laplacian_kernel(st) if kernel.USE_KERNEL else None
    if lk is None or b.ndim > 2 or b.ndim == 2 and b.shape[1] > 4:  # many columns: SuperLU's
        return st.lap_lu.solve(b)
    x = np.array(b, dtype=np.float64, order="C")  # a copy: solved in place
    k = 1 if x.ndim == 1 else x.shape[1]
    work = np.empty(k * (x.shape[0] + lk[1][3]["work_size"]))
    _klib.capsheet_lap_solve(lk[0], k, _kffi.from_buffer("double[]", x),
                             _kffi.from_buffer("double[]", work))
    return x
