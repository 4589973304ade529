"""Lattice addressing: which link a chip's link index names (docs/design.md, "Link order").

A sheet of ``rows x cols`` joints ``P[i, j]`` has two kinds of link:

* i-links ``(i, j) -> (i+1, j)``, ``(rows-1) * cols`` of them, first, in row-major order of ``(i, j)``;
* j-links ``(i, j) -> (i, j+1)``, ``rows * (cols-1)`` of them, next, in row-major order.

A link's index in that order is its lattice address, carried on the wire by ASSIGN (docs/protocol.md,
section 3). Every module uses this one definition; nothing else computes link indices.

>>> lat = Lattice(3, 4)
>>> lat.n_links
17
>>> lat.link(0), lat.link(8), lat.link(16)
(Link(index=0, axis=0, i=0, j=0), Link(index=8, axis=1, i=0, j=0), Link(index=16, axis=1, i=2, j=2))
>>> lat.index_of(1, 2, 2)
16
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

__all__ = ["Lattice", "Link", "AXIS_I", "AXIS_J", "joint_normals"]

AXIS_I = 0  #: link (i, j) -> (i+1, j)
AXIS_J = 1  #: link (i, j) -> (i, j+1)


@dataclass(frozen=True, slots=True)
class Link:
    """One link of the lattice: its index, its axis and its lower joint ``(i, j)``."""

    index: int
    axis: int
    i: int
    j: int

    @property
    def joints(self) -> tuple[tuple[int, int], tuple[int, int]]:
        """The two joints ``((i, j), (i', j'))``, lower index first (sensor x points to the second)."""
        if self.axis == AXIS_I:
            return (self.i, self.j), (self.i + 1, self.j)
        return (self.i, self.j), (self.i, self.j + 1)


@dataclass(frozen=True)
class Lattice:
    """A ``rows x cols``-joint lattice and its link addressing.

    Parameters
    ----------
    rows, cols : int
        Number of joints along i and j, each >= 2.
    """

    rows: int
    cols: int

    def __post_init__(self) -> None:
        for name in ("rows", "cols"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 2:
                raise ValueError(f"Invalid lattice {name}: {value!r} (need an integer >= 2)")

    @classmethod
    def parse(cls, text: str) -> "Lattice":
        """Parse ``"14x14"`` (joints, rows x cols)."""
        try:
            r, c = text.lower().split("x")
            return cls(int(r), int(c))
        except ValueError as exc:
            raise ValueError(f"Invalid lattice size {text!r}: expected ROWSxCOLS, e.g. 14x14") from exc

    @property
    def n_i_links(self) -> int:
        return (self.rows - 1) * self.cols

    @property
    def n_j_links(self) -> int:
        return self.rows * (self.cols - 1)

    @property
    def n_links(self) -> int:
        return self.n_i_links + self.n_j_links

    @property
    def n_joints(self) -> int:
        return self.rows * self.cols

    @property
    def n_units(self) -> int:
        """Number of 4-link units (closed loops), ``(rows-1) * (cols-1)``."""
        return (self.rows - 1) * (self.cols - 1)

    def index_of(self, axis: int, i: int, j: int) -> int:
        """Link index of the link on ``axis`` whose lower joint is ``(i, j)``."""
        if axis == AXIS_I:
            if not (0 <= i < self.rows - 1 and 0 <= j < self.cols):
                raise ValueError(f"Invalid i-link joint ({i}, {j}) for lattice {self.rows}x{self.cols}")
            return i * self.cols + j
        if axis == AXIS_J:
            if not (0 <= i < self.rows and 0 <= j < self.cols - 1):
                raise ValueError(f"Invalid j-link joint ({i}, {j}) for lattice {self.rows}x{self.cols}")
            return self.n_i_links + i * (self.cols - 1) + j
        raise ValueError(f"Invalid link axis: {axis!r} (0 = i-link, 1 = j-link)")

    def link(self, index: int) -> Link:
        """The link at lattice address ``index``."""
        if not 0 <= index < self.n_links:
            raise ValueError(f"Invalid link index {index} for lattice {self.rows}x{self.cols} "
                             f"({self.n_links} links)")
        if index < self.n_i_links:
            i, j = divmod(index, self.cols)
            return Link(index, AXIS_I, i, j)
        i, j = divmod(index - self.n_i_links, self.cols - 1)
        return Link(index, AXIS_J, i, j)

    @cached_property
    def endpoints(self) -> np.ndarray:
        """Flat joint indices ``(a, b)`` of every link, shape ``(n_links, 2)``; joint ``(i, j)`` is
        ``i * cols + j`` and the sensor x axis points from ``a`` to ``b``."""
        r, c = self.rows, self.cols
        jid = np.arange(r * c).reshape(r, c)
        a_i, b_i = jid[:-1, :].ravel(), jid[1:, :].ravel()
        a_j, b_j = jid[:, :-1].ravel(), jid[:, 1:].ravel()
        out = np.stack([np.concatenate([a_i, a_j]), np.concatenate([b_i, b_j])], axis=1)
        out.setflags(write=False)
        return out

    @cached_property
    def units(self) -> np.ndarray:
        """Link indices of every 4-link unit, shape ``(rows-1, cols-1, 4)``.

        For the unit with lower corner ``(i, j)`` the four links are, in the paper's numbering
        (Fig. 5, eq. 4: ``d0 + d1 = d3 + d2``):

        * 0: j-link ``(i, j) -> (i, j+1)``
        * 1: i-link ``(i, j+1) -> (i+1, j+1)``
        * 2: j-link ``(i+1, j) -> (i+1, j+1)``
        * 3: i-link ``(i, j) -> (i+1, j)``

        so that both routes go from ``(i, j)`` to ``(i+1, j+1)``: ``d0 + d1 = d3 + d2``.
        """
        r, c = self.rows, self.cols
        ii, jj = np.meshgrid(np.arange(r - 1), np.arange(c - 1), indexing="ij")
        n_i = self.n_i_links
        l0 = n_i + ii * (c - 1) + jj
        l1 = (ii * c) + jj + 1
        l2 = n_i + (ii + 1) * (c - 1) + jj
        l3 = ii * c + jj
        out = np.stack([l0, l1, l2, l3], axis=-1)
        out.setflags(write=False)
        return out

    def link_vectors(self, joints: np.ndarray) -> np.ndarray:
        """Vectors ``P[b] - P[a]`` of every link, shape ``(n_links, 3)``, from joints ``(rows, cols, 3)``."""
        joints = np.asarray(joints, dtype=float)
        if joints.shape != (self.rows, self.cols, 3):
            raise ValueError(f"Expected `joints` to have shape ({self.rows}, {self.cols}, 3), "
                             f"got {joints.shape}.")
        flat = joints.reshape(-1, 3)
        e = self.endpoints
        return flat[e[:, 1]] - flat[e[:, 0]]


def joint_normals(joints: np.ndarray) -> np.ndarray:
    """Unit normals at the joints, top face: the average of the adjacent cells' unit normals, each
    the cross product of the cell's diagonals. Shape ``(rows, cols, 3)`` in, the same out.

    >>> i, j = np.meshgrid(np.arange(3.0), np.arange(4.0), indexing="ij")
    >>> joint_normals(np.stack([i, j, 0 * i], axis=-1))[1, 2].tolist()
    [0.0, 0.0, 1.0]
    """
    P = np.asarray(joints, dtype=float)
    if P.ndim != 3 or P.shape[-1] != 3 or P.shape[0] < 2 or P.shape[1] < 2:
        raise ValueError(f"Expected `joints` to have shape (rows, cols, 3), got {P.shape}.")
    n = np.cross(P[1:, 1:] - P[:-1, :-1], P[:-1, 1:] - P[1:, :-1])
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    out = np.zeros_like(P)
    out[:-1, :-1] += n
    out[1:, 1:] += n
    out[:-1, 1:] += n
    out[1:, :-1] += n
    return out / np.maximum(np.linalg.norm(out, axis=-1, keepdims=True), 1e-300)
