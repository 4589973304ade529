"""What an estimate returns: `ShapeEstimate`, and the `Solution` state of its global solve."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import NamedTuple

import numpy as np

from .structure import Structure
from .uncertainty import yaw_joint_std
from .yawproblem import YawProblem

__all__ = ["Solution", "ShapeEstimate"]


class Solution(NamedTuple):
    """The state of one global solve: what the uncertainty and the next snapshot's warm start
    need (`ShapeEstimate.solution`)."""

    #: the lattice's, mask's and model's fixed structure (sparsity pattern, ordering, Laplacian)
    structure: Structure
    #: the Gauss-Newton matrix's last factorisation (`linalg.factorise`'s), or None (what the
    #: next snapshot's chord steps reuse while its structure is the same)
    factorisation: tuple | None
    #: the snapshot's yaw problem (its coefficients and prior weights)
    problem: YawProblem
    #: the yaws it converged to, (n_links,), radians
    yaws: np.ndarray
    #: how ``factorisation``'s chord steps contracted (`solver.Contraction`), or None: what lets
    #: the next snapshot's solve stop after one step
    contraction: object | None = None
    #: the chord steps of the first snapshot solved wholly on ``factorisation`` (None: none yet)
    base_steps: int | None = None
    #: the snapshots in a row on it that took `solver.STALE_STEPS` more than ``base_steps``:
    #: at `solver.STALE_RUN` the next snapshot factorises afresh before its first step
    stale_run: int = 0


@dataclass(frozen=True, eq=False)
class ShapeEstimate:
    """One estimated shape of the sheet.

    Attributes
    ----------
    joints : ndarray, shape (rows, cols, 3)
        Joint positions, metres, world frame (z up), joint ``(0, 0)`` at the origin.
    directions : ndarray, shape (n_links, 3)
        Unit direction of every link (sensor x in world), lattice order. For an invalid link, the
        normalised chord between its estimated joints.
    residual : float
        Sum over all units with four valid links of eq. (8) (loop closure and normal assumption,
        x, y and z), at the final yaws: the same measure for both methods (dimensionless).
    solvability : ndarray, shape (rows-1, cols-1)
        Per unit, ``λ3/λ1`` of eq. (7)'s 4x6 matrix (singular values, largest first); below 0.1 the
        unit's yaws are poorly determined (paper section 2.3). NaN for units with a missing link.
    normals : ndarray, shape (n_links, 3)
        Sensor z of every link in world coordinates (unit); NaN for invalid links.
    yaws : ndarray, shape (n_links,)
        Yaw γ of every link, radians (what ``previous`` warm-starts from); prior value if invalid.
    alpha, beta : ndarray, shape (n_links,)
        Roll and pitch from eq. (2), radians; NaN for invalid links.
    valid : ndarray of bool, shape (n_links,)
        The mask used.
    link_length : float
        ``L``, metres.
    method : str
        ``"global"`` or ``"paper"``.
    iterations : int
        Gauss-Newton iterations (global) or steepest-descent steps (paper,
        `host.analysis.paper_method`).
    factorisations : int
        Sparse factorisations of the Gauss-Newton matrix made for this snapshot (global; 0 when
        the previous snapshot's factorisation sufficed).
    timings : dict
        Wall time of the stages, seconds: ``"angles"``, ``"yaw"``, ``"joints"``, ``"total"``.
    """

    joints: np.ndarray
    directions: np.ndarray
    residual: float
    solvability: np.ndarray
    normals: np.ndarray
    yaws: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray
    valid: np.ndarray
    link_length: float
    method: str
    iterations: int
    factorisations: int
    timings: dict = field(default_factory=dict)
    #: the reading noise (per axis, % of g) `yaw_std` and `joint_std` are stated for
    noise_pct_g: float = 1.0
    #: the global solve behind this estimate (`Solution`: structure, factorisation, yaw problem,
    #: yaws): what `yaw_std` and ``joint_std`` are computed from and what ``previous=`` warm-starts
    #: from; None for ``method="paper"``
    solution: Solution | None = field(default=None, repr=False)
    #: where an estimate ``previous=`` this one falls back to starting from when this one lacks a
    #: link the next snapshot has (`pipeline.WarmStart.covering`): the warm start of the latest
    #: estimate of the chain that had at least the links of the one before it; None: a cold start
    warm_fallback: object = field(default=None, repr=False)

    @cached_property
    def yaw_std(self) -> np.ndarray:
        """Per link, the standard deviation of its yaw, radians, shape (n_links,), for readings of
        `noise_pct_g` per axis: from the global problem's normal matrix at the estimate
        (docs/estimator.md), relative to the sheet's mean yaw. Where the data do not determine a
        yaw (Case 1, a squashed unit) it is large (the prior's floor: ≫ 1 rad). NaN for
        ``method="paper"`` and for missing links."""
        return yaw_joint_std(self)[0]

    @cached_property
    def joint_std(self) -> np.ndarray:
        """Per joint, the standard deviation of its position (3-D RMS), metres, shape
        (rows, cols), for readings of `noise_pct_g` per axis, from the yaws' uncertainty
        (`yaw_std`) carried through the joint least squares, after removing the mean
        translation. NaN for ``method="paper"``."""
        return yaw_joint_std(self)[1]

    @property
    def rows(self) -> int:
        return self.joints.shape[0]

    @property
    def cols(self) -> int:
        return self.joints.shape[1]
