"""What the fused estimator needs of the lattice, built once per size: the units' links and
signs (loop closure, eq. 4), every link's cells and its position in them (the cells' normals),
and the fixed sparsity pattern of the yaw problem's Jacobian and normal matrix.

Conventions are docs/design.md's (`protocol.lattice.Lattice` is the one source of link indices).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import scipy.sparse as sp

from protocol.lattice import Lattice

#: eq. (4): d0 + d1 − d2 − d3 = 0 (`Lattice.units` numbering)
CLOSURE_SIGNS = np.array([1.0, 1.0, -1.0, -1.0])
#: unit slots holding i-links (their sum is a cell's A) and j-links (C): normal A × C
I_SLOTS = (1, 3)
J_SLOTS = (0, 2)


class LatticeTopology:
    """Index arrays of one lattice (no data): see the module docstring.

    Attributes
    ----------
    units : ndarray of int, shape (U, 4)
    pair_link, pair_cell : ndarray of int, shape (K2,)
        Every (link, cell it belongs to) pair: the normal rows' terms.
    inv_ncell : ndarray, shape (n_links,)
        1 / number of cells of a link (0 for a link in no cell).
    group : ndarray of int, shape (n_links,)
        Every link's group: ``i`` for the i-links at ``i``, ``rows − 1 + j`` for the j-links at
        ``j`` (`n_groups` of them, `group_size` links each, `group_matrix` the indicator).
    jac : scipy.sparse.csr_matrix
        The yaw Jacobian's pattern, rows: 2 per unit (closure x, y), then one per link (normal);
        ``jac_slot_*`` map the computed entries onto its ``data``.
    """

    def __init__(self, rows: int, cols: int) -> None:
        lat = Lattice(rows, cols)
        self.lattice = lat
        self.rows, self.cols = rows, cols
        n = lat.n_links
        self.n_links = n
        self.units = np.ascontiguousarray(lat.units.reshape(-1, 4))
        U = self.units.shape[0]
        self.n_units = U
        cell_of = [[] for _ in range(n)]
        for u in range(U):
            for s in range(4):
                cell_of[self.units[u, s]].append(u)
        pl, pc = [], []
        for k in range(n):
            for u in cell_of[k]:
                pl.append(k)
                pc.append(u)
        self.pair_link = np.array(pl, dtype=np.int64)
        self.pair_cell = np.array(pc, dtype=np.int64)
        ncell = np.bincount(self.pair_link, minlength=n)
        self.inv_ncell = np.where(ncell > 0, 1.0 / np.maximum(ncell, 1), 0.0)

        # Jacobian entries in a fixed order: closure (2U rows x 4), diagonal of the normal rows
        # (n), then every pair's 4 cell links (K2 x 4); summed into CSR slots.
        rows_c = np.repeat(np.arange(2 * U), 4)
        cols_c = np.repeat(self.units, 2, axis=0).ravel()
        rows_d = 2 * U + np.arange(n)
        cols_d = np.arange(n)
        rows_p = np.repeat(2 * U + self.pair_link, 4)
        cols_p = self.units[self.pair_cell].ravel()
        r = np.concatenate([rows_c, rows_d, rows_p])
        c = np.concatenate([cols_c, cols_d, cols_p])
        key = r * n + c
        ukey, inv = np.unique(key, return_inverse=True)
        self.jac_slots = inv
        self.n_rows = 2 * U + n
        indptr = np.searchsorted(ukey // n, np.arange(self.n_rows + 1))
        self.jac = sp.csr_matrix((np.zeros(ukey.size), (ukey % n).astype(np.int32), indptr),
                                 shape=(self.n_rows, n))
        self.jac_nnz = ukey.size
        self.jac_rows = np.repeat(np.arange(self.n_rows), np.diff(indptr))
        self.jac_cols = (ukey % n).astype(np.int64)
        self.jac_T = self.jac.T.tocsr()  # the pattern of Jᵀ and where J's entries go in it
        order = np.argsort(self.jac_cols * self.n_rows + self.jac_rows, kind="stable")
        self.jac_T_from = order
        # the links' groups: the i-links of one i (a row of links), the j-links of one j; on a
        # flat net every group's links are parallel, so turning a group about the normal keeps
        # every cell closed — the yaw modes the loops cannot see (docs/estimator.md §8)
        k = np.arange(n)
        n_i = lat.n_i_links
        self.group = np.where(k < n_i, k // cols, (rows - 1) + (k - n_i) % (cols - 1)).astype(np.int64)
        self.n_groups = (rows - 1) + (cols - 1)
        self.group_size = np.bincount(self.group, minlength=self.n_groups).astype(float)
        self.group_matrix = sp.csr_matrix((np.ones(n), (k, self.group)), shape=(n, self.n_groups))
        # the cells' normals averaged onto their links: (n_links x U), weights 1 / ncell
        self.cell_to_link = sp.csr_matrix((self.inv_ncell[self.pair_link],
                                           (self.pair_link, self.pair_cell)), shape=(n, U))
        # J's columns summed over each group: the rows' derivatives in a group's common yaw
        # offset, as (row, group) entries ``jg_rows, jg_group`` and where each entry of J goes
        gkey = self.jac_rows * self.n_groups + self.group[self.jac_cols]
        ug, jg_index = np.unique(gkey, return_inverse=True)
        self.jg_index = np.ascontiguousarray(jg_index.ravel(), dtype=np.int64)
        self.jg_rows = np.ascontiguousarray(ug // self.n_groups, dtype=np.int64)
        self.jg_group = ug % self.n_groups
        # those entries by row (sorted by row already): the yaw solve's coarse matrix
        self.jg_indptr = np.searchsorted(self.jg_rows, np.arange(self.n_rows + 1)).astype(np.int64)
        self.jg_group = np.ascontiguousarray(self.jg_group, dtype=np.int64)
        # the same pattern as the C kernel takes it (fixed integer widths, contiguous)
        self.jac_indptr32 = np.ascontiguousarray(self.jac.indptr, dtype=np.int32)
        self.jac_indices32 = np.ascontiguousarray(self.jac.indices, dtype=np.int32)
        self.jac_slots = np.ascontiguousarray(self.jac_slots, dtype=np.int64)
        self.jac_rows = np.ascontiguousarray(self.jac_rows, dtype=np.int64)


@lru_cache(maxsize=16)
def topology(rows: int, cols: int) -> LatticeTopology:
    return LatticeTopology(int(rows), int(cols))


@lru_cache(maxsize=16)
def _grid_eigenvalues(rows: int, cols: int) -> np.ndarray:
    """The lattice's graph Laplacian's eigenvalues, (rows, cols): the i-links make a path along
    ``i`` for every ``j`` and the j-links one along ``j`` for every ``i``, so the Laplacian is the
    Kronecker sum of two path Laplacians, whose eigenvectors are the DCT-II's cosines
    ``cos(π k (i + ½) / n)`` with eigenvalues ``4 sin²(π k / 2n)``. The constant (0, 0) is
    the translation no link measures: its inverse is taken as 0."""
    lr = 4.0 * np.sin(np.pi * np.arange(rows) / (2.0 * rows)) ** 2
    lc = 4.0 * np.sin(np.pi * np.arange(cols) / (2.0 * cols)) ** 2
    lam = lr[:, None] + lc[None, :]
    inv = np.zeros_like(lam)
    inv[lam > 0] = 1.0 / lam[lam > 0]
    inv.setflags(write=False)
    return inv


def joints_from_vectors(vectors: np.ndarray, rows: int, cols: int,
                        link_length: float) -> np.ndarray:
    """`host.analysis.estimator.joints_from_directions` for a lattice whose links are all valid,
    by the fast cosine transform instead of a sparse factorisation: ``min Σ ‖p_b − p_a − L d‖²``,
    joint (0, 0) at the origin. ``vectors`` (n_links, 3) in link order; returns (rows, cols, 3).

    The normal equations' right-hand side is every joint's links summed (``+L d`` where the link
    ends, ``−L d`` where it starts); their matrix is diagonal in the 2-D DCT-II's basis
    (`_grid_eigenvalues`)."""
    from scipy.fft import dctn, idctn
    # (3, n_links), C-ordered: the slices below are then views, not copies
    d = np.ascontiguousarray(np.asarray(vectors, dtype=float).T) * float(link_length)
    n_i = (rows - 1) * cols
    di = d[:, :n_i].reshape(3, rows - 1, cols)
    dj = d[:, n_i:].reshape(3, rows, cols - 1)
    b = np.zeros((3, rows, cols))
    b[:, 1:] += di
    b[:, :-1] -= di
    b[:, :, 1:] += dj
    b[:, :, :-1] -= dj
    h = dctn(b, type=2, axes=(1, 2), norm="ortho", overwrite_x=True)
    h *= _grid_eigenvalues(rows, cols)
    p = idctn(h, type=2, axes=(1, 2), norm="ortho", overwrite_x=True)
    p -= p[:, :1, :1]
    return np.ascontiguousarray(np.moveaxis(p, 0, -1))


def link_midpoints(joints: np.ndarray) -> np.ndarray:
    """Every link's midpoint (or any per-joint quantity's mean over its link's ends), shape
    (n_links, 3), from ``joints`` (rows, cols, 3), in link order (docs/design.md): slices of the
    grid, not a gather by `protocol.lattice.Lattice.endpoints`."""
    J = np.asarray(joints, dtype=float)
    return np.concatenate([(0.5 * (J[:-1] + J[1:])).reshape(-1, 3),
                           (0.5 * (J[:, :-1] + J[:, 1:])).reshape(-1, 3)])
