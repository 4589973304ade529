"""Everything about a lattice, mask and model that does not depend on the readings: the yaw
problem's sparsity pattern, its fill-reducing ordering (minimum degree, or nested dissection on
large lattices), the index maps of the Gauss-Newton matrix and the joints' Laplacian, cached."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from protocol.lattice import Lattice

from .kernel import ffi as _kffi

__all__ = ["JOINT_PRIOR_WEIGHT", "Structure", "ND_MIN_VARS", "ND_LEAF", "nested_dissection",
           "KERNEL_INDEX_FIELDS", "kernel_arrays", "lattice_of", "units_int64", "cached_structure",
           "structure_of"]

#: Weight of the joints' prior (keeps components cut off by missing links defined), per m².
JOINT_PRIOR_WEIGHT = 1e-9


class Structure:
    """Everything about a lattice, mask and model that does not depend on the readings.

    The yaw problem's residuals come in blocks with a fixed set of variables per row: the loop
    closure (eq. 4, and eq. 6 for ``model="eq6"``) per active unit on its 4 links, and for
    ``model="cells"`` one roll residual per link on the link and the other links of its (one or
    two) cells, 7 variables. The Gauss-Newton matrix ``JᵀJ + diag`` therefore has a fixed pattern;
    its fill-reducing ordering and the CSC slot of every block product are computed here once.
    """

    def __init__(self, rows: int, cols: int, valid: np.ndarray, model: str):
        lat = Lattice(rows, cols)
        self.lattice = lat
        #: what later stages derive from the structure and keep with it, by name (the symbolic
        #: analysis of its factorisation, the kernel's arrays, the prior's bridging pairs, ...):
        #: made once per structure, read by the stage that made it
        self.derived: dict = {}
        self.rows, self.cols = rows, cols
        self.model = model
        n = lat.n_links
        self.n_links = n
        self.valid = valid
        self.all_valid = bool(valid.all())
        units = lat.units.reshape(-1, 4)
        self.unit_ok = valid[units].all(axis=1)  # (n_units,)
        self.units = units[self.unit_ok]  # active units (U, 4)
        U = self.units.shape[0]
        self.n_units = U

        # rest yaws: i-links along +x (0), j-links along +y (pi/2)
        self.rest_yaw = np.zeros(n)
        self.rest_yaw[lat.n_i_links:] = np.pi / 2

        # gauge: the valid link in an active unit nearest the lattice centre (index space)
        ep = lat.endpoints
        jid = np.arange(rows * cols)
        ji, jj = jid // cols, jid % cols
        mid_i = 0.5 * (ji[ep[:, 0]] + ji[ep[:, 1]]) - (rows - 1) / 2
        mid_j = 0.5 * (jj[ep[:, 0]] + jj[ep[:, 1]]) - (cols - 1) / 2
        in_unit = np.zeros(n, bool)
        in_unit[self.units.ravel()] = True
        self.in_unit = in_unit
        cand = np.flatnonzero(in_unit) if U else np.flatnonzero(valid)
        self.gauge = int(cand[np.argmin(mid_i[cand] ** 2 + mid_j[cand] ** 2 + 1e-3 * cand)])

        # variables: valid links except the gauge; nv is the dummy variable (gauge, padding)
        var = np.full(n, -1)
        var_links = np.flatnonzero(valid & (np.arange(n) != self.gauge))
        var[var_links] = np.arange(var_links.size)
        self.var_links = var_links
        nv = var_links.size
        self.n_var = nv
        var_d = np.where(var >= 0, var, nv)
        self.unit_var = var_d[self.units]  # (U, 4)

        blocks = [self.unit_var]
        if model == "cells":
            # every link's active cells (at most 2), and its position in each
            flat = self.units.ravel()
            order = np.argsort(flat, kind="stable")
            fl = flat[order]
            uid, pos = order // 4, order % 4
            first = np.r_[True, fl[1:] != fl[:-1]][:fl.size]  # fl is empty when no cell is whole
            slot = np.zeros(fl.size, int)
            slot[~first] = 1
            cell = np.full((n, 2), U)
            cpos = np.zeros((n, 2), int)
            cell[fl, slot] = uid
            cpos[fl, slot] = pos
            ncell = np.bincount(fl, minlength=n)
            k = np.flatnonzero(ncell > 0)
            self.roll_links = k
            self.roll_cells = cell[k]  # (K, 2), U = no cell
            self.roll_pos = cpos[k]  # (K, 2)
            self.roll_inv_ncell = 1.0 / ncell[k]
            others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
            self.roll_others = others[self.roll_pos]  # (K, 2, 3) positions of the other links
            uv_ext = np.vstack([self.unit_var, np.full((1, 4), nv)])
            cols_o = uv_ext[self.roll_cells[:, :, None], self.roll_others]  # (K, 2, 3)
            self.roll_var = np.concatenate([var_d[k][:, None], cols_o.reshape(-1, 6)], axis=1)
            # fast gathers: a missing second cell points at the first, with weight 0
            K = k.size
            self.roll_c0 = self.roll_cells[:, 0]
            has1 = self.roll_cells[:, 1] < U
            self.roll_c1 = np.where(has1, self.roll_cells[:, 1], self.roll_c0)
            self.roll_ws1 = has1.astype(float)
            base = (np.arange(K) * 8)[:, None]
            self.roll_idx_self = base + np.array([0, 4]) + self.roll_pos  # into (K, 2, 4) flat
            self.roll_idx_oth = (base[:, :, None] + np.array([0, 4])[None, :, None]
                                 + self.roll_others).reshape(K, 6)
            blocks.append(self.roll_var)

        # bending prior: pairs of parallel neighbours (i-links (i,j)-(i+1,j) and (i,j)-(i,j+1),
        # j-links likewise), both valid
        ni = lat.n_i_links
        iid = np.arange(ni).reshape(rows - 1, cols)
        jidx = ni + np.arange(rows * (cols - 1)).reshape(rows, cols - 1)
        pairs = np.concatenate([
            np.stack([iid[:-1].ravel(), iid[1:].ravel()], 1),
            np.stack([iid[:, :-1].ravel(), iid[:, 1:].ravel()], 1),
            np.stack([jidx[:, :-1].ravel(), jidx[:, 1:].ravel()], 1),
            np.stack([jidx[:-1].ravel(), jidx[1:].ravel()], 1)]).reshape(-1, 2)
        pairs = pairs[valid[pairs].all(axis=1)]
        self.n_bend = pairs.shape[0]
        # shear prior: per unit, its j-link 0 against its i-link 3 (the cell's corner angle)
        shear = units[:, [0, 3]]
        ok = valid[shear].all(axis=1)
        self.shear_unit = np.flatnonzero(ok)  # unit (all units' numbering) of every shear pair
        pairs = np.concatenate([pairs, shear[ok]])
        self.pairs = pairs
        self.pair_var = var_d[pairs]
        blocks.append(self.pair_var)

        # pattern of the normal matrix: every block's outer products + the diagonal
        ents = []
        for cols_b in blocks:
            p = cols_b.shape[1]
            bi = np.repeat(cols_b, p, axis=1).ravel()
            bj = np.tile(cols_b, (1, p)).ravel()
            ents.append((bi, bj))
        allr = np.concatenate([e[0] for e in ents] + [np.arange(nv)])
        allc = np.concatenate([e[1] for e in ents] + [np.arange(nv)])
        keep = (allr < nv) & (allc < nv)
        rr, cc = allr[keep], allc[keep]
        if nv:
            pat = sp.csc_matrix((np.ones(rr.size), (rr, cc)), shape=(nv, nv))
            pat.sum_duplicates()
            pat = pat + sp.identity(nv, format="csc") * (4.0 * pat.max() + 1.0)
            if nv >= ND_MIN_VARS:  # large: nested dissection on the links' positions
                mid = np.stack([mid_i[var_links], mid_j[var_links]], axis=1)
                perm = np.argsort(nested_dissection(pat.tocsr(), mid))
            else:  # small: minimum degree fills less
                perm = splu(pat.tocsc(), permc_spec="MMD_AT_PLUS_A").perm_c
        else:
            perm = np.arange(0)
        pos_v = np.asarray(perm, dtype=np.int64)
        key = pos_v[cc] * max(nv, 1) + pos_v[rr]
        ukey, inv = np.unique(key, return_inverse=True)
        self.nnz = ukey.size
        self.csc_indices = (ukey % max(nv, 1)).astype(np.int32)
        col = ukey // max(nv, 1)
        self.csc_indptr = np.searchsorted(col, np.arange(nv + 1)).astype(np.int32)
        slot_all = np.full(allr.size, self.nnz, dtype=np.int64)
        slot_all[np.flatnonzero(keep)] = inv
        self.block_slots = []
        at = 0
        for bi, _ in ents:
            self.block_slots.append(slot_all[at:at + bi.size])
            at += bi.size
        self.diag_slot = slot_all[at:at + nv]
        self.perm_of_var = pos_v
        self.perm_inv = np.argsort(pos_v)

        # joints: Laplacian of the valid links + a weak prior, factorised once
        vl = np.flatnonzero(valid)
        self.valid_links = vl
        a, b = ep[vl, 0], ep[vl, 1]
        nj = rows * cols
        B = sp.csr_matrix((np.concatenate([-np.ones(vl.size), np.ones(vl.size)]),
                           (np.concatenate([np.arange(vl.size)] * 2), np.concatenate([a, b]))),
                          shape=(vl.size, nj))
        self.incidence = B.tocsr()
        self.incidence_T = B.T.tocsr()
        lap = (B.T @ B + JOINT_PRIOR_WEIGHT * sp.identity(nj)).tocsc()
        self.lap_matrix = lap  # the kernel's own factorisation is made from it (`linalg.laplacian_kernel`)
        self.lap_lu = splu(lap, permc_spec="MMD_AT_PLUS_A")

        # rest layout of the joints (prior for isolated parts), L = 1
        self.rest_joints_unit = np.stack([ji.astype(float), jj.astype(float),
                                          np.zeros(nj)], axis=1)

    def kernel_arrays(self) -> dict:
        return kernel_arrays(self)


#: `Structure.kernel_arrays`' index arrays, by their field name in ``capsheet_yaw_t``
#: `Structure`: from this many yaw variables on (about 28x28 joints), the Gauss-Newton matrix is
#: ordered by nested dissection instead of SuperLU's minimum degree. Fill of L (bench_estimator's
#: Gaussian): 14x14 MMD 11.7k / ND 13.3k, 32x32 130k / 121k, 64x64 909k / 716k.
ND_MIN_VARS = 1500
#: ... and parts of at most this many variables are not split further.
ND_LEAF = 16


def nested_dissection(adj, xy: np.ndarray, leaf: int = ND_LEAF) -> np.ndarray:
    """An elimination order (position -> variable) by geometric nested dissection: split the
    variables at the median of their longer extent, take as separator the smaller of the two
    sides' boundaries (the variables with a neighbour across), order each side recursively and
    the separator last. ``adj``: the symmetric pattern (CSR, any values); ``xy`` (nv, 2) the
    variables' positions."""
    nv = xy.shape[0]
    out: list[np.ndarray] = []
    side = np.zeros(nv, np.int8)  # scratch: 1 left part, 2 right part of the current split
    stack = [(np.arange(nv), False)]
    while stack:  # explicit stack: (nodes, emit) — emit=True places a separator
        nodes, emit = stack.pop()
        if emit or nodes.size <= leaf:
            out.append(nodes)
            continue
        c = xy[nodes]
        ax = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        order = np.argsort(c[:, ax], kind="stable")
        left = np.zeros(nodes.size, bool)
        left[order[:nodes.size // 2]] = True
        side[nodes[left]] = 1
        side[nodes[~left]] = 2
        sub = adj[nodes]
        nb_side = side[sub.indices]
        row = np.repeat(np.arange(nodes.size), np.diff(sub.indptr))
        touch_r = np.bincount(row[nb_side == 2], minlength=nodes.size) > 0
        touch_l = np.bincount(row[nb_side == 1], minlength=nodes.size) > 0
        side[nodes] = 0
        sep_l, sep_r = left & touch_r, ~left & touch_l
        sep = sep_l if sep_l.sum() <= sep_r.sum() else sep_r
        # popped last-in first: left part, then right part, then the separator
        stack.append((nodes[sep], True))
        stack.append((nodes[~left & ~sep], False))
        stack.append((nodes[left & ~sep], False))
    return np.concatenate(out) if out else np.arange(0)


KERNEL_INDEX_FIELDS = ("units", "unit_var", "roll_links", "roll_c0", "roll_c1", "roll_var0",
                        "pairs", "pair_var", "var_links")


def kernel_arrays(st: "Structure") -> dict:
    """The structure's arrays as the kernel reads them (int64/float64, contiguous) with their
    cffi pointers, and a work buffer (one snapshot at a time uses it): made once, kept on ``st``."""
    ka = st.derived.get("kernel")
    if ka is not None:
        return ka
    src = {"units": st.units, "unit_var": st.unit_var, "roll_links": st.roll_links,
           "roll_c0": st.roll_c0, "roll_c1": st.roll_c1, "roll_var0": st.roll_var[:, 0],
           "pairs": st.pairs, "pair_var": st.pair_var, "var_links": st.var_links}
    ka = {}
    for name, a in src.items():
        a = np.ascontiguousarray(a, dtype=np.int64)
        ka[name] = (a, _kffi.from_buffer("int64_t[]", a))
    a = np.ascontiguousarray(st.roll_ws1, dtype=np.float64)
    ka["roll_ws1"] = (a, _kffi.from_buffer("double[]", a))
    ka["sizes"] = (st.n_units, st.roll_links.size, st.pairs.shape[0], st.n_var)
    ka["work"] = np.empty(19 * max(st.n_units, 1) + 2 * st.n_links)
    st.derived["kernel"] = ka
    return ka


@lru_cache(maxsize=64)
def lattice_of(rows: int, cols: int) -> Lattice:
    """One `Lattice` per size, so its cached ``endpoints``/``units`` are computed once."""
    return Lattice(rows, cols)


@lru_cache(maxsize=64)
def units_int64(rows: int, cols: int) -> np.ndarray:
    """All units' links (n_units, 4), int64, contiguous: what the kernel's `solvability` reads."""
    return np.ascontiguousarray(lattice_of(rows, cols).units.reshape(-1, 4), dtype=np.int64)


def _build(rows: int, cols: int, mask_bytes: bytes | None, model: str) -> Structure:
    n = Lattice(rows, cols).n_links
    valid = np.ones(n, bool) if mask_bytes is None else np.frombuffer(mask_bytes, dtype=bool).copy()
    return Structure(rows, cols, valid, model)


#: structures of masks kept (`structure_of`): the newest few
MASKED_KEPT = 2
_cached_full = lru_cache(maxsize=16)(_build)
_cached_masked = lru_cache(maxsize=MASKED_KEPT)(_build)


def cached_structure(rows: int, cols: int, mask_bytes: bytes | None, model: str) -> Structure:
    """The `Structure` of a lattice, mask (its bytes; None: all valid) and model, built once: 16
    kept with all links valid, the `MASKED_KEPT` newest masks (``cached_structure.cache_clear()``
    forgets them all: a benchmark's cold start; ``cache_info()`` is the masked ones')."""
    return (_cached_full if mask_bytes is None else _cached_masked)(rows, cols, mask_bytes, model)


def _clear_structures() -> None:
    _cached_full.cache_clear()
    _cached_masked.cache_clear()


cached_structure.cache_clear = _clear_structures
cached_structure.cache_info = _cached_masked.cache_info


def structure_of(rows: int, cols: int, valid: np.ndarray | None, model: str = "cells") -> Structure:
    """The (cached) `Structure` of a lattice, mask of valid links (None: all) and model.

    A structure with its factorisation is ~1.1 MB at 14x14. A live host estimates the newest
    snapshot, and on a loaded machine an incomplete one now and then, each missing another link:
    one cache of 16 for every mask kept 16 such one-off structures (~18 MB) and, replacing them,
    fragmented the heap — the host's resident size crept up by megabytes in a soak run.
    So masks have a cache of their own, of the `MASKED_KEPT` newest: a chip that stays missing
    repeats its mask (the warm start reuses the structure's factorisation), one-offs go soon.
    """
    if valid is None or valid.all():
        return cached_structure(rows, cols, None, model)
    return cached_structure(rows, cols, valid.tobytes(), model)
