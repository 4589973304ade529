"""Shape estimator: from one snapshot of link readings to the 3D shape of the whole sheet.

Conventions are docs/design.md's and are not restated differently here: joints ``P[i, j]`` of shape
``(rows, cols, 3)`` in metres, world frame z up; link order and the 4-link units come from
`protocol.lattice.Lattice` only (``endpoints``, ``units``: ``d0 + d1 = d3 + d2``,
``n0 + n2 = n1 + n3``); sensor frame x along the link, z the sheet normal (top face); readings are
specific force (flat, top face up, reads ``(0, 0, +G0)``); ``R = Rz(γ) Ry(β) Rx(α)``; radians.

Two methods, same input, same output (`ShapeEstimate`):

``method="paper"`` (Hoshi & Shinoda, sections 2-3; the reference to beat)
    Roll and pitch from eq. (2) in closed form; per 4-link unit, eq. (8) by steepest descent
    from several starts; the units combined into the sheet. It lives in
    `host.analysis.paper_method`, which names every choice the paper leaves open
    (``paper_options=PaperOptions(...)``); this module only checks the input and dispatches.
    Missing links are not supported (the paper has none).

``method="global"`` (default)
    Roll and pitch as above. All yaws at once, one sparse nonlinear least-squares problem
    (Gauss-Newton with Levenberg-Marquardt damping, one yaw fixed as gauge), warm-started from
    the last snapshot (its yaws and its factorisation, reused while it still contracts well:
    `ShapeEstimator` holds them between its updates; `estimate` takes them as ``previous``). Terms,
    all in ``z_k = exp(iγ_k)`` (docs/estimator.md has the derivation and the measurements):

    * loop closure, eq. (4), xy part, per unit: ``Σ_m s_m cos β_m z_m = 0`` (exact);
    * the normal model (``model="cells"``, default): per link, its sensor y (known up to yaw)
      is perpendicular to the mean normal of its (one or two) cells, each cell's normal being
      ``A × C`` with ``A``, ``C`` the sums of its two i- and two j-link directions. This is the
      sheet normal a chip on the cloth sees, and it is exact on a Chebyshev net, where eq. (6)
      is not (``model="eq6"`` keeps the paper's assumption, weighted `NORMAL_WEIGHT`);
    * the prior (``prior="level"``, default): what the data cannot determine is held by
      pairs of yaw differences, never by absolute yaws — the bending of the lattice (parallel
      neighbours) where the region is level within the noise, and the corner angle of level
      cells (the paper's Case 1) — towards the rest shape's (``rest=``; default square cells).
      Their weights scale with the readings' noise, estimated per snapshot from the spread of
      ``|s|`` about g, so that noise-free readings meet only a floor and the prior never pulls
      where the data decide (a draped sheet's lattice lines zigzag in plan: "adaptive", the
      former default, held the bending everywhere); the target is never the previous
      estimate, so long runs do not drift.

    Before the yaws, the pitches are made consistent with one height per joint (the z part of
    eq. 4: ``pipeline.closed_pitches``, every link's height step weighted by the inverse of its
    noise, ``1/(cos² β + 0.05)``), and every roll residual is weighted by ``|cos β|`` of its
    link (the inverse of its roll's noise).

    The normal matrix has a fixed sparsity pattern per lattice, mask and model; pattern,
    fill-reducing ordering and index maps are computed once and cached. Then joints by least
    squares over all valid links, ``min Σ ‖p_b − p_a − L d‖²`` (heights follow from the pitches
    alone), with the graph Laplacian factorised once per lattice and mask. A link marked
    invalid contributes no constraint: its two units are dropped from the yaw problem and the
    link from the joint problem; its reported direction is the chord between its estimated
    joints. `ShapeEstimate.yaw_std` and ``joint_std`` state the data's uncertainty (computed on
    first access).

In both, joint ``(0, 0)`` is placed at the origin. The estimate is defined up to a rotation about
world z (yaw gauge); `overlay_error` and `error_percent_of_side` compare shapes as the paper does,
after a least-squares rigid overlay.

This package needs numpy and scipy only; it does not import `virtual_sheet`. One snapshot's
arithmetic (the yaw problem's coefficients, the chord steps' cost and gradient, SuperLU's
triangular sweeps, the flatness, directions, eq. (8) and solvability) runs in a small C kernel
when it is built (host/analysis/_kernel/, cffi, at install; `USE_KERNEL`), else in the numpy code
beside it, which gives the same numbers to rounding; `estimate_batch` always runs the numpy code.

The package, by concern (docs/design.md's layout table lists them too):

========================  ======================================================================
`.pipeline`               `estimate`: `.checks`, then angles -> closed pitches -> structure ->
                          prior weights -> solve -> joints and mask, stages `.batch` and
                          `.stateful` share
`.batch`                  `estimate_batch`: many snapshots of one structure solved together
`.stateful`               `ShapeEstimator`: a stream of snapshots, holding its warm start
`.checks`                 the checks every entry point makes (options, readings, mask, ...)
`.result`                 `ShapeEstimate` and the `Solution` state of a global solve
`.angles`                 roll and pitch (eq. 2), solvability (eq. 7)
`.structure`              per lattice, mask and model: sparsity pattern, ordering, Laplacian
`.yawproblem`             the yaw least-squares problem: cost, gradient, Gauss-Newton matrix
`.linalg`                 SuperLU / CHOLMOD and the kernel's triangular sweeps
`.solver`                 Gauss-Newton with chord steps and Anderson acceleration
`.priors`                 the priors' weights (`PRIORS`)
`.joints`                 links' directions and normals, the joints (`joints_from_directions`),
                          eq. (8), missing links
`.uncertainty`            `ShapeEstimate.yaw_std` and ``joint_std``
`.kernel`                 the compiled kernel and its switch ``USE_KERNEL``
========================  ======================================================================

The constants this package re-exports (``YAW_TOL_RAD``, ``USE_KERNEL``, ...) are the values at
import; a tunable is changed on the module that owns it (``estimator.solver.YAW_TOL_RAD``,
``estimator.kernel.USE_KERNEL``, ``estimator.linalg.LINEAR_SOLVER``), where the code reads it.
"""

from __future__ import annotations

from ..metrics import error_percent_of_side, overlay, overlay_error
from . import (angles, batch, checks, joints, kernel, linalg, pipeline, priors, result, solver,
               stateful, structure, uncertainty, yawproblem)
from .angles import G0, roll_pitch, solvability, solvability_units
from .batch import estimate_batch
from .kernel import USE_KERNEL
from .linalg import LINEAR_SOLVER
from .checks import METHODS, MODELS, READING_NORM_RANGE
from .joints import joints_from_directions
from .pipeline import estimate
from .priors import (ABS_PRIOR_FLOOR, BEND_STD_RAD, DEFAULT_PRIOR, FIXED_PRIOR_WEIGHT,
                     FLAT_RADIUS, FLAT_TILT_NOISE, PRIOR_WEIGHT_MIN, PRIORS, SHEAR_WEIGHT,
                     SHEAR_WEIGHT_REST)
from .result import ShapeEstimate, Solution
from .solver import BATCH_MAX_ITER, BATCH_REFACTOR, MAX_ITER, YAW_TOL_NOISE, YAW_TOL_RAD
from .stateful import ShapeEstimator
from .structure import JOINT_PRIOR_WEIGHT, ND_LEAF, ND_MIN_VARS
from .uncertainty import UNCERTAINTY_SAMPLES
from .yawproblem import NORMAL_WEIGHT, ROLL_WEIGHT

__all__ = [
    # estimating
    "estimate", "estimate_batch", "ShapeEstimator", "ShapeEstimate", "Solution",
    "roll_pitch", "solvability", "solvability_units", "joints_from_directions",
    # comparing shapes (host.analysis.metrics)
    "overlay", "overlay_error", "error_percent_of_side",
    # choices and constants (values at import; set a tunable on its module)
    "METHODS", "MODELS", "PRIORS", "DEFAULT_PRIOR", "G0", "READING_NORM_RANGE", "USE_KERNEL",
    "LINEAR_SOLVER",
    "YAW_TOL_RAD", "YAW_TOL_NOISE", "MAX_ITER", "BATCH_MAX_ITER", "BATCH_REFACTOR",
    "NORMAL_WEIGHT", "ROLL_WEIGHT", "ABS_PRIOR_FLOOR", "FIXED_PRIOR_WEIGHT", "BEND_STD_RAD",
    "SHEAR_WEIGHT", "SHEAR_WEIGHT_REST", "FLAT_TILT_NOISE", "FLAT_RADIUS", "PRIOR_WEIGHT_MIN",
    "JOINT_PRIOR_WEIGHT", "ND_MIN_VARS", "ND_LEAF", "UNCERTAINTY_SAMPLES",
    # the modules, for what a benchmark or a test reaches below the pipeline (each has __all__)
    "angles", "batch", "checks", "joints", "kernel", "linalg", "pipeline", "priors", "result",
    "solver", "stateful", "structure", "uncertainty", "yawproblem",
]
