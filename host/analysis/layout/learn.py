"""Which chip is on which link, from held poses of the sheet (docs/host.md, "Learning the layout").

Pure computation: the poses' mean readings per chip id (`poses.Pose`) in, a layout ``{uid: link}``
out, judged by the lattice's loop closure. Conventions (link order, sensor frame) are
docs/design.md's.

Why the poses of `PROCEDURE` decide it (each chip's reading ``r`` is gravity in its own frame; x
along its link towards the higher joint, z the sheet's normal, y = z × x):

* **tilt** (a ramp): every i-link reads ``(s, 0, c)·g`` and every j-link ``(0, −s, c)·g`` when
  the last row's edge is raised (s = sin of the slope); raising another edge flips the signs or
  swaps the components, but always so that the link that *pitches* (x moves) and the link that
  *rolls* (y moves) have x·y signs of opposite kind for i-pitching ramps and the same kind for
  j-pitching ramps (y = z × x is right-handed). So the ramp tells every chip's kind (i or j) — the
  pitching or the rolling group, by the sign rule — whichever edge was raised, and a chip whose
  sign is against its group's is mounted turned half round.
* **hump_i** (the row-0 and last-row edges pushed together): the sheet is a cylinder whose slope
  along i falls strictly from the row-0 side (climbing, +) to the last row (−). An i-link at half
  row i + ½ reads x = sin θ(i + ½), a j-link on row i reads y = −sin θ(i) (its normal is its two
  cells' mean): the order of those values is the order of the rows, and the sign says which end
  row 0 is, so no edge needs a name. **hump_j** orders the columns the same way (j-links by x,
  i-links by +y).
* The decision: each chip gets a first row and column from its rank, the expected reading of
  every (pose, row) and (pose, column) is the mean of the chips given it, and every chip is
  assigned to one link by `scipy.optimize.linear_sum_assignment` over the squared distance between
  its readings and each link's expected readings (one problem per kind); repeated until the
  assignment stays. A dead chip leaves its link to no one; a chip heard in only some poses is
  left out and named.
* Each chip's own error at rest (bias, misalignment) is taken out with its flat reading first
  (`flat_corrected`).
* The check: the poses' readings placed by the result go through the shape estimator, and every
  unit's loop closure and cells-model residual (`unit_residuals`, docs/estimator.md §2) must stay
  under the limit (`residual_limit`); a chip on the wrong link breaks the units around it.

Limits: the humps must be single humps with their ridges along the lattice (a hump's slope must
fall monotonically across the sheet, every row apart from its neighbours by more than the
readings' noise and the chips' misalignment); on a lattice of many rows the rows near the ridge
differ least.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from protocol.constants import G0
from protocol.lattice import AXIS_I, Lattice

__all__ = ["PROCEDURE", "LOOP_RESIDUAL_LIMIT", "LayoutLearnError", "LearnResult", "CheckResult",
           "learn_layout", "check_layout", "judge_pose", "unit_residuals"]

#: the poses, in order, with the prompt a user is given for each
PROCEDURE: tuple[tuple[str, str], ...] = (
    ("flat", "Lay the sheet flat on a table, top face up, and let go."),
    ("tilt", "Make the whole sheet a ramp: rest it flat on a board and raise one edge of the board "
             "(20-40 degrees, any edge), every part of the sheet sloping."),
    ("hump_i", "Lay it on the table and push the row-0 edge and the last-row edge (the edges the "
               "i-links run towards) towards each other until the sheet rises in one hump; hold it."),
    ("hump_j", "Lay it down again and push the other two edges (column 0 and the last column) towards "
               "each other: one hump, its ridge the other way; hold it."),
)

#: a unit's loop-closure residual (eq. 8: |d0 + d1 − d2 − d3|² + |n0 − n1 + n2 − n3|², unit
#: directions and normals) above which its four chips do not fit together. The poses' exact nets
#: leave 0.002 or less (the normal assumption's floor on the humps' bend, 8x8, noise 1 % g); two
#: neighbouring chips swapped leave 0.03 and more in their units
LOOP_RESIDUAL_LIMIT = 0.002

#: the limit rises with the units' median residual, up to `LOOP_RESIDUAL_CAP`: chips of their own
#: errors (an uncalibrated part's misalignment, which the flat pose takes out only where the sheet
#: lies flat) leave every unit a floor (median 7e-4, largest 0.004-0.009 on 8x8-32x32 sheets of
#: `capsheet virtual --chip-errors realistic` chips), that a layout with chips far out of place
#: does not hide (its median is itself over the cap)
LIMIT_OVER_MEDIAN = 10.0
LOOP_RESIDUAL_CAP = 0.01


def residual_limit(res: np.ndarray) -> float:
    """The unit residual above which a unit does not close, for a layout whose units' residuals are
    ``res``: `LOOP_RESIDUAL_LIMIT`, raised to `LIMIT_OVER_MEDIAN` times their median, at most
    `LOOP_RESIDUAL_CAP`."""
    med = float(np.nanmedian(res)) if np.isfinite(res).any() else 0.0
    return float(np.clip(LIMIT_OVER_MEDIAN * med, LOOP_RESIDUAL_LIMIT, LOOP_RESIDUAL_CAP))


#: a move the poses propose is confirmed when it lowers the largest residual of the units around it
#: this many times, to under `LOOP_RESIDUAL_LIMIT`, counting anything under `RESIDUAL_FLOOR` as that
#: floor (noise and jitter leave up to 1e-4 on lattices up to 32x32 at 1 % g)
CONFIRM_RATIO = 5.0
RESIDUAL_FLOOR = 1e-4

#: below this slope (sin) a chip is level in a pose: it says nothing of its kind there
_LEVEL_SIN = float(np.sin(np.radians(3.0)))


class LayoutLearnError(ValueError):
    """The poses do not decide the layout; the message says which pose and why, in one line."""


def _lattice(lattice) -> Lattice:
    if isinstance(lattice, Lattice):
        return lattice
    if isinstance(lattice, str):
        return Lattice.parse(lattice)
    return Lattice(*lattice)


def _unit_rows(readings: dict, uids: list[int]) -> np.ndarray:
    r = np.array([np.asarray(readings[u], dtype=float) for u in uids]).reshape(len(uids), 3)
    n = np.linalg.norm(r, axis=1, keepdims=True)
    if not np.all(np.isfinite(r)) or np.any(n == 0):
        raise LayoutLearnError("a pose holds a reading that is not finite or of zero length")
    return r / n


def judge_pose(step: str, readings: dict) -> str | None:
    """Whether a settled pose is the step asked for: None, or why not (one line).

    ``readings``: ``{uid: mean reading (3,)}``. flat: 90 % of the chips within 10° of level, top up;
    tilt: 90 % sloping more than 3°, the pitching and the rolling chips each sloping one way (a
    ramp, not a hump); hump_i / hump_j: half the chips sloping more than 3°, with slopes of both
    signs among the pitching chips (a hump, not a ramp)."""
    if not readings:
        return "no chip was heard"
    u = _unit_rows(readings, list(readings))
    level = u[:, 2] >= np.cos(np.radians(10.0))
    slope = np.hypot(u[:, 0], u[:, 1])
    if step == "flat":
        if level.mean() >= 0.9:
            return None
        upside = int((u[:, 2] < 0).sum())
        return (f"not level: {int((~level).sum())} of {len(u)} chips slope more than 10 degrees"
                + (f" ({upside} read upside down)" if upside else ""))
    sloped = slope > _LEVEL_SIN
    pitch = np.abs(u[:, 0]) >= np.abs(u[:, 1])
    if step == "tilt":
        if sloped.mean() < 0.9:
            return f"not a ramp: {int((~sloped).sum())} of {len(u)} chips lie level"
        for grp, comp in ((pitch & sloped, 0), (~pitch & sloped, 1)):
            if grp.sum():
                pos = (u[grp, comp] > 0).mean()
                if 0.1 < pos < 0.9:
                    return "not a ramp: the sheet slopes both ways (a hump or a fold?)"
        return None
    if step in ("hump_i", "hump_j"):
        if sloped.mean() < 0.5:
            return f"not a hump: {int((~sloped).sum())} of {len(u)} chips lie level"
        grp = pitch & sloped
        if grp.sum() == 0:
            return "not a hump: no chip slopes along its link"
        pos = (u[grp, 0] > 0).mean()
        if not 0.2 <= pos <= 0.8:
            return "not a hump: the sheet slopes one way only (a ramp?)"
        return None
    raise ValueError(f"Unknown step {step!r} (expected one of {', '.join(s for s, _ in PROCEDURE)})")


@dataclass
class LearnResult:
    """What `learn_layout` decided.

    Attributes
    ----------
    layout : dict
        ``{uid: link}`` for every chip placed.
    missing_links : list of int
        Links no chip was placed on (a dead chip, or fewer chips than links).
    unplaced : dict
        ``{uid: why}``: chips heard but not placed (not heard in every pose, or more chips of a kind
        than links).
    reversed_links : list of int
        Links whose chip reads as if mounted turned half round about its normal (x and y reversed).
    unit_residual : ndarray, shape (rows-1, cols-1)
        Each unit's loop-closure residual (eq. 8), the largest over the poses; NaN where a link of
        the unit has no chip.
    notes : list of str
        What the learner noticed and decided around (one line each).
    """

    layout: dict
    missing_links: list
    unplaced: dict
    reversed_links: list
    unit_residual: np.ndarray
    notes: list = field(default_factory=list)

    @property
    def limit(self) -> float:
        """The residual over which a unit does not close (`residual_limit`)."""
        return residual_limit(self.unit_residual)

    @property
    def bad_units(self) -> list[tuple[int, int]]:
        """Units ``(i, j)`` whose residual is over `limit`."""
        return [tuple(int(x) for x in ij) for ij in np.argwhere(self.unit_residual > self.limit)]

    @property
    def loop_closure_ok(self) -> bool:
        return not self.bad_units

    @property
    def max_residual(self) -> float | None:
        r = self.unit_residual
        return float(np.nanmax(r)) if np.isfinite(r).any() else None


def unit_residuals(readings: np.ndarray, valid: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Every unit's residual under the shape estimator's model for one snapshot: the estimator's
    solution (`host.analysis.estimator.estimate`), then per unit its loop closure
    ``|d0 + d1 − d2 − d3|²`` (eq. 4, unit link directions) plus, for each of its four links, the
    cells model's term ``(ROLL_WEIGHT · y_k · n̄_k)²`` (the link's sensor y against the mean normal
    of its cells, docs/estimator.md §2): both exact on an exact net, so a chip placed where its
    reading does not belong shows in the units around it. Shape (rows-1, cols-1); NaN where a link
    of the unit is invalid.

    ``readings`` (n_links, 3) m/s² in lattice order, ``valid`` (n_links,) bool."""
    from host.analysis.estimator import estimate
    from host.analysis.estimator.structure import units_int64
    from host.analysis.estimator.yawproblem import ROLL_WEIGHT

    readings = np.asarray(readings, dtype=float)
    valid = np.asarray(valid, dtype=bool)
    r = np.where(valid[:, None], readings, np.array([0.0, 0.0, G0]))
    est = estimate(r, rows, cols, 1.0, valid=valid)
    units = units_int64(rows, cols)  # (U, 4): j-link (i,j), i-link (i,j+1), j-link (i+1,j), i-link (i,j)
    d, n = est.directions, np.nan_to_num(est.normals)
    rd = d[units[:, 0]] + d[units[:, 1]] - d[units[:, 2]] - d[units[:, 3]]
    loop = np.sum(rd * rd, axis=1)
    # each cell's normal from its i-links' sum A and j-links' sum C; each link's mean over its cells
    A = d[units[:, 1]] + d[units[:, 3]]
    Cj = d[units[:, 0]] + d[units[:, 2]]
    m = np.cross(A, Cj)
    cell_n = m / np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-12)
    n_links = len(d)
    acc = np.zeros((n_links, 3))
    np.add.at(acc, units.ravel(), np.repeat(cell_n, 4, axis=0))
    y = np.cross(n, d)  # sensor y = z × x, in the world
    roll = (ROLL_WEIGHT * np.einsum("nk,nk->n", y, acc / np.maximum(np.linalg.norm(acc, axis=1, keepdims=True),
                                                                     1e-12))) ** 2
    res = loop + roll[units].sum(axis=1)
    res = np.where(valid[units].all(axis=1), res, np.nan)
    return res.reshape(rows - 1, cols - 1)


def layout_residuals(lat: Lattice, poses: dict, layout: dict) -> np.ndarray:
    """The largest unit residual over the poses that slope (tilt, hump_i, hump_j) with the chips
    placed by ``layout`` ({uid: link}); (rows-1, cols-1)."""
    out = np.full((lat.rows - 1, lat.cols - 1), np.nan)
    for name in ("tilt", "hump_i", "hump_j"):
        if name not in poses:
            continue
        readings = np.zeros((lat.n_links, 3))
        valid = np.zeros(lat.n_links, dtype=bool)
        for uid, link in layout.items():
            r = poses[name].get(uid)
            if r is not None and 0 <= link < lat.n_links:
                readings[link], valid[link] = r, True
        res = unit_residuals(readings, valid, lat.rows, lat.cols)
        out = np.fmax(out, res)
    return out


def flat_corrected(poses: dict) -> dict:
    """The poses with each chip's own error at rest taken out, when a flat pose is given: a chip
    whose flat reading is ``f`` (the sheet's level direction being the chips' median there,
    ``ẑ g``) has ``f − ẑ g`` subtracted from its reading in every pose. That removes a chip's bias
    exactly and its axes' misalignment where the sheet lies flat (an uncalibrated part: 30 mg and
    1.5°, each as large as the difference between neighbouring rows of a big sheet's hump); the
    misalignment left grows with how far a pose turns the chip from flat. Chips not heard flat are
    left as they are."""
    flat = poses.get("flat")
    if not flat:
        return poses
    uids = list(flat)
    f = np.array([np.asarray(flat[u], dtype=float) for u in uids]).reshape(len(uids), 3)
    if not np.all(np.isfinite(f)):
        return poses
    z = np.median(f / np.linalg.norm(f, axis=1, keepdims=True), axis=0)
    ref = z / np.linalg.norm(z) * np.median(np.linalg.norm(f, axis=1))
    off = {u: f[k] - ref for k, u in enumerate(uids)}
    return {name: ({u: np.asarray(r, dtype=float) - off[u] if u in off else r for u, r in p.items()}
                   if name != "flat" else p) for name, p in poses.items()}


def _ranks(v: np.ndarray) -> np.ndarray:
    """0 for the largest value, 1 for the next ..."""
    r = np.empty(len(v), dtype=np.int64)
    r[np.argsort(-v, kind="stable")] = np.arange(len(v))
    return r


def _group_means(x: np.ndarray, groups: np.ndarray, n: int) -> np.ndarray:
    """Mean of the rows of ``x`` (m, 3) in each of ``n`` groups; an empty group takes its
    neighbours' (linear in the group index)."""
    out = np.full((n, 3), np.nan)
    for g in range(n):
        sel = groups == g
        if sel.any():
            out[g] = x[sel].mean(axis=0)
    have = np.flatnonzero(np.isfinite(out[:, 0]))
    if len(have) == 0:
        return np.zeros((n, 3))
    for k in range(3):
        out[:, k] = np.interp(np.arange(n), have, out[have, k])
    return out


def _assign_kind(A: np.ndarray, B: np.ndarray, row0: np.ndarray, col0: np.ndarray, n_rows: int,
                 n_cols: int, max_rounds: int = 12) -> tuple[np.ndarray, np.ndarray, int]:
    """Chips of one kind to its ``n_rows x n_cols`` positions: ``A``, ``B`` (m, 3) their unit
    readings in the row-ordering and the column-ordering pose, ``row0``, ``col0`` the first guess.
    Returns (row, col) per chip (-1: not placed) and the rounds taken."""
    from scipy.optimize import linear_sum_assignment

    row, col = row0.copy(), col0.copy()
    m = len(A)
    pos_r = np.repeat(np.arange(n_rows), n_cols)
    pos_c = np.tile(np.arange(n_cols), n_rows)
    for rounds in range(1, max_rounds + 1):
        placed = row >= 0
        MA = _group_means(A[placed], row[placed], n_rows)
        MB = _group_means(B[placed], col[placed], n_cols)
        DA = ((A[:, None, :] - MA[None]) ** 2).sum(axis=2)  # (m, n_rows)
        DB = ((B[:, None, :] - MB[None]) ** 2).sum(axis=2)  # (m, n_cols)
        cost = DA[:, pos_r] + DB[:, pos_c]
        ci, pi = linear_sum_assignment(cost)
        new_r = np.full(m, -1)
        new_c = np.full(m, -1)
        new_r[ci], new_c[ci] = pos_r[pi], pos_c[pi]
        if np.array_equal(new_r, row) and np.array_equal(new_c, col):
            return row, col, rounds
        row, col = new_r, new_c
    return row, col, max_rounds


def learn_layout(lattice, poses: dict) -> LearnResult:
    """Decide every link's chip from the poses (module docstring).

    Parameters
    ----------
    lattice : Lattice or "ROWSxCOLS"
        The sheet's joints.
    poses : dict
        ``{"tilt": {uid: reading}, "hump_i": {...}, "hump_j": {...}}`` (``"flat"`` may be given
        too, and is not needed): each chip's mean reading (3,), m/s², sensor frame, in that pose.

    Raises `LayoutLearnError` when the poses do not decide it (a pose missing or not what it should be).
    """
    lat = _lattice(lattice)
    for name in ("tilt", "hump_i", "hump_j"):
        if name not in poses or not poses[name]:
            raise LayoutLearnError(f"the {name} pose is missing")
    poses = flat_corrected(poses)
    sets = [set(int(u) for u in poses[n]) for n in ("tilt", "hump_i", "hump_j")]
    uids = sorted(set.intersection(*sets))
    unplaced = {u: "not heard in every pose" for u in sorted(set.union(*sets) - set(uids))}
    notes: list[str] = []
    if not uids:
        raise LayoutLearnError("no chip was heard in every pose")
    T = _unit_rows(poses["tilt"], uids)
    A = _unit_rows(poses["hump_i"], uids)
    B = _unit_rows(poses["hump_j"], uids)
    # kind from the ramp: who pitches, who rolls, and the sign rule of y = z × x
    a, b = T[:, 0], T[:, 1]
    sloped = np.hypot(a, b) > _LEVEL_SIN
    pitch = np.abs(a) >= np.abs(b)
    if (pitch & sloped).sum() == 0 or (~pitch & sloped).sum() == 0:
        raise LayoutLearnError("the tilt pose does not tell the kinds apart: the chips all slope along "
                               "the same axis (is it a ramp, every part sloping?)")
    s_p = np.sign(np.median(a[pitch & sloped]))
    s_r = np.sign(np.median(b[~pitch & sloped]))
    i_pitch = s_p * s_r < 0
    is_i = pitch if i_pitch else ~pitch
    if (~sloped).any():
        notes.append(f"{int((~sloped).sum())} chips lay level in the tilt pose; their kind is taken from "
                     "which axis they lean along there")
    # orientation: a chip leaning against its kind's group is turned half round
    comp_i, sign_i = (0, s_p) if i_pitch else (1, s_r)
    comp_j, sign_j = (1, s_r) if i_pitch else (0, s_p)
    comp = np.where(is_i, comp_i, comp_j)
    lean = T[np.arange(len(uids)), comp] * np.where(is_i, sign_i, sign_j)
    flipped = sloped & (lean < 0)
    flip = np.where(flipped, -1.0, 1.0)[:, None] * np.array([1.0, 1.0, 0.0]) + np.array([0.0, 0.0, 1.0])
    A, B = A * flip, B * flip
    # which hump is which: in hump_i the i-links pitch (their x moves), in hump_j they roll
    if is_i.any() and np.var(A[is_i, 1]) > np.var(A[is_i, 0]) and np.var(B[is_i, 0]) > np.var(B[is_i, 1]):
        A, B = B, A
        notes.append("the two humps came the other way round (the first across the columns): taken as such")
    n_i, n_j = int(is_i.sum()), int((~is_i).sum())
    R, C = lat.rows, lat.cols
    idx_i, idx_j = np.flatnonzero(is_i), np.flatnonzero(~is_i)
    layout: dict[int, int] = {}
    for idx, rows_k, cols_k, vr, vc, axis in (
            (idx_i, R - 1, C, A[idx_i, 0], B[idx_i, 1], AXIS_I),
            (idx_j, R, C - 1, -A[idx_j, 1], B[idx_j, 0], 1 - AXIS_I)):
        m = len(idx)
        if m == 0:
            continue
        if m > rows_k * cols_k:
            notes.append(f"{m} chips read as {'i' if axis == AXIS_I else 'j'}-links, the lattice has "
                         f"{rows_k * cols_k}: the extra are left out")
        row0 = np.minimum(_ranks(vr) * rows_k // m, rows_k - 1)
        col0 = np.minimum(_ranks(vc) * cols_k // m, cols_k - 1)
        row, col, _ = _assign_kind(A[idx], B[idx], row0, col0, rows_k, cols_k)
        for k, c in enumerate(idx.tolist()):
            if row[k] < 0:
                unplaced[uids[c]] = "more chips of its kind than links"
                continue
            layout[uids[c]] = lat.index_of(axis, int(row[k]), int(col[k]))
    missing = sorted(set(range(lat.n_links)) - set(layout.values()))
    reversed_links = sorted(layout[uids[c]] for c in np.flatnonzero(flipped).tolist() if uids[c] in layout)
    if n_i != lat.n_i_links or n_j != lat.n_j_links:
        notes.append(f"{n_i} chips read as i-links ({lat.n_i_links} on the lattice), {n_j} as j-links "
                     f"({lat.n_j_links})")
    res = layout_residuals(lat, poses, layout)
    return LearnResult(layout, missing, unplaced, reversed_links, res, notes)


@dataclass
class CheckResult:
    """What `check_layout` found.

    Attributes
    ----------
    ok : bool
        The layout fits the sheet: every chip answered, none unknown, every unit closes.
    findings : list of str
        One line each: swaps, a replaced chip, silent or unknown chips, loops that do not close.
    fixed : dict
        The layout with every confident fix applied (a lone replacement, swaps the residuals confirm).
    fixed_all : bool
        Every finding is fixed in ``fixed``.
    unit_residual : ndarray or None
        Each unit's residual with the layout as given (after a lone replacement), the largest over
        the poses; None without poses.
    """

    ok: bool
    findings: list
    fixed: dict
    fixed_all: bool
    unit_residual: np.ndarray | None = None


def _units_of_links(lat: Lattice, links) -> list[tuple[int, int]]:
    """The units ``(i, j)`` a set of links belongs to."""
    out = set()
    for k in links:
        ln = lat.link(int(k))
        if ln.axis == AXIS_I:
            cand = [(ln.i, ln.j - 1), (ln.i, ln.j)]
        else:
            cand = [(ln.i - 1, ln.j), (ln.i, ln.j)]
        out.update((i, j) for i, j in cand if 0 <= i < lat.rows - 1 and 0 <= j < lat.cols - 1)
    return sorted(out)


def check_layout(lattice, poses: dict, layout: dict) -> CheckResult:
    """Hold an existing layout ({uid: link}) to the sheet: which chips answered, and, given the poses
    of `PROCEDURE` (tilt, hump_i, hump_j), whether each unit's loops close with the chips where the
    layout puts them.

    * One chip of the layout silent and one unknown chip answering: the new chip takes the silent
      one's link (a replaced chip), said as such.
    * Units over the limit (`residual_limit`): the learned layout (`learn_layout`) proposes where their
      chips belong; each cycle of links whose chips it moves (two: "look swapped") is reported
      when moving them brings every unit around them under the limit.

    ``poses``: ``{pose: {uid: reading}}``; with only ``"flat"`` (or nothing but the ids heard, as
    ``{"flat": {uid: reading}}``) only the ids are checked.
    """
    lat = _lattice(lattice)
    heard_sets = [set(int(u) for u in p) for p in poses.values() if p]
    heard = set.intersection(*heard_sets) if heard_sets else set()
    heard_any = set.union(*heard_sets) if heard_sets else set()
    findings: list[str] = []
    fixed = {int(u): int(k) for u, k in layout.items()}
    bad_links = sorted(k for k in fixed.values() if not 0 <= k < lat.n_links)
    if bad_links:
        raise LayoutLearnError(f"the layout names links {bad_links[:5]} outside a {lat.rows}x{lat.cols} "
                               f"lattice ({lat.n_links} links)")
    silent = sorted(u for u in fixed if u not in heard_any)
    unknown = sorted(u for u in heard_any if u not in fixed)
    unresolved = False
    if len(silent) == 1 and len(unknown) == 1:
        old, new = silent[0], unknown[0]
        link = fixed.pop(old)
        fixed[new] = link
        findings.append(f"chip 0x{new:016X} replaces 0x{old:016X} on link {link} (the one chip that did not "
                        f"answer; the one new chip takes its link)")
        silent, unknown = [], []
    else:
        for u in silent:
            findings.append(f"chip 0x{u:016X} on link {fixed[u]} did not answer")
        for u in unknown:
            findings.append(f"chip 0x{u:016X} answered and is not in the layout")
        unresolved = bool(silent or unknown)
    sloping = all(n in poses and poses[n] for n in ("tilt", "hump_i", "hump_j"))
    if not sloping:
        return CheckResult(not findings, findings, fixed, not unresolved, None)
    raw, poses = poses, flat_corrected(poses)
    res = layout_residuals(lat, poses, fixed)
    limit = residual_limit(res)
    floor = max(RESIDUAL_FLOOR, float(np.nanmedian(res)) if np.isfinite(res).any() else 0.0)
    learned = learn_layout(lat, raw)
    at_fixed = {k: u for u, k in fixed.items()}
    # cycles of links: the chip the layout has on link a, the learner puts on link b (a -> b)
    moves = {}
    for u, k in fixed.items():
        k2 = learned.layout.get(u)
        if k2 is not None and k2 != k:
            moves[k] = k2
    seen: set[int] = set()
    for start in sorted(moves):
        if start in seen:
            continue
        cyc, k = [], start
        while k in moves and k not in seen:
            seen.add(k)
            cyc.append(k)
            k = moves[k]
        trial = dict(fixed)
        for a_link in cyc:
            u = at_fixed[a_link]
            trial[u] = moves[a_link]
        units = _units_of_links(lat, cyc)
        before = max((res[i, j] for i, j in units if np.isfinite(res[i, j])), default=0.0)
        after_all = layout_residuals(lat, poses, trial)
        after = max((after_all[i, j] for i, j in units if np.isfinite(after_all[i, j])), default=0.0)
        closed = k == start
        what = (f"links {cyc[0]} and {cyc[1]} look swapped" if len(cyc) == 2 and closed else
                f"links {', '.join(map(str, cyc))} look {'rotated' if closed else 'moved'} "
                f"(each chip belongs on the next{'' if closed else '; the last onto a link no known chip answered for'})")
        if after <= limit and before >= CONFIRM_RATIO * max(after, floor):
            findings.append(f"{what}: loop closure in their units {before:.3g} as laid out, {after:.3g} "
                            f"moved")
            fixed = trial
            res = after_all
        else:
            findings.append(f"{what} by the poses, but the loop closure does not confirm it "
                            f"({before:.3g} as laid out, {after:.3g} moved): not fixed")
            unresolved = True
    for u in unknown:
        if u in learned.layout:
            findings.append(f"  the poses put unknown chip 0x{u:016X} on link {learned.layout[u]}"
                            + (f" (the layout has 0x{at_fixed[learned.layout[u]]:016X} there)"
                               if learned.layout[u] in at_fixed else ""))
    still = np.argwhere(res > limit)
    if len(still):
        cells = ", ".join(f"({i},{j})" for i, j in still[:6].tolist())
        findings.append(f"{len(still)} units do not close (residual over {limit:.3g}): {cells}"
                        + (" ..." if len(still) > 6 else ""))
        unresolved = True
    for k in learned.reversed_links:
        findings.append(f"link {k}: its chip reads turned half round (x and y reversed): remount it")
        unresolved = True
    return CheckResult(not findings, findings, fixed, not unresolved, res)
