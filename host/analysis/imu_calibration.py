"""Calibration of the gyroscopes and magnetometers of a 6/9-axis sheet, beside the
accelerometer's (`host.analysis.calibration`, whose capture — the sheet flat on a board turned
through held poses — this reuses). docs/calibration.md gives the procedure and the accuracy.

Gyroscope, chip ``k``: ``ω_meas = K Mᵀ ω + b + Γ f/g + noise`` (``K`` scale and cross-axis,
``M`` mounting, ``b`` bias, ``Γ`` g-sensitivity, ``f`` specific force). The correction is::

    ω_link = A (ω_meas − b − Γ f/g),    A ≈ (K Mᵀ)⁻¹

1. **Bias and g-sensitivity from the rests** (`fit_gyro_rest`): at rest ``ω = 0``, so each held
   pose's mean rate is ``b + Γ f̄/g`` with ``f̄`` the pose's mean specific force: 12 unknowns per
   chip, linear least squares over the poses (at least 4 with gravity in non-coplanar directions;
   the board's 12 give every term). Without ``Γ`` (``g_sensitivity=False``) the mean of the rests.
2. **Scale, cross-axis and mounting from the turns** (`fit_gyro_turns`): between two held poses
   the board turns; integrating the corrected rate over the turn must carry gravity's direction
   in the link frame at the first pose (``u_k``, from the calibrated accelerometers) to that of the
   next: ``R(A)ᵀ u_k = u_{k+1}`` with ``R(A) = Π exp([A ω̃_i Δt]×)``. Two equations per turn (a
   turn about gravity is invisible), 9 unknowns per chip: Gauss–Newton over all chips at once
   (each chip's 9 × 9 normal equations; the Jacobian by finite differences, one integration per
   column for every chip). This is the gyroscope half of Tedaldi, Pretto & Menegatti (ICRA 2014),
   on every chip, with the link frame set by the accelerometer calibration.

Each gyroscope part is kept only when its own residual vouches for it (`fit_capture`): a rest
residual above `REST_MAX_RESIDUAL_RPS` (a pose that was not still) keeps none, a turn residual
above `TURN_MAX_RESIDUAL_RAD` (rates that do not carry gravity through the turns: readings whose
stated instants are wrong) keeps the bias and g-sensitivity. A timing error the same in every turn
in proportion to it is a scale to the fit and cannot be seen there.

Magnetometer, chip ``k``: ``m = D B + h + noise`` (``D = W M_mᵀ``: soft iron and mounting, ``h``
hard iron). In a uniform field ``|B| = F`` the readings lie on the ellipsoid
``|D⁻¹(m − h)| = F``:

3. **Hard and soft iron from rotations** (`fit_mag_ellipsoid`): the general quadric
   ``mᵀ Q m + 2 vᵀ m = 1`` by linear least squares per chip (9 unknowns), its centre ``h`` and
   shape, then Gauss–Newton on the geometric residual ``|C (m − h)| − F`` with ``C`` symmetric
   (the geometric view of Vasconcelos et al. 2011). ``C``
   equals ``U D⁻¹`` for some rotation ``U``: the ellipsoid cannot see how the part is turned.
4. **The part's rotation from the rests** (`fit_mag_alignment`): in every held pose the angle
   between gravity and the field is the same (the field's dip): the rotation ``R`` (3 unknowns) and
   that angle (1) with ``û_k · R C (m̄_k − h) / F = −sin(dip)`` in every pose are fitted per chip
   by Gauss–Newton (Kok & Schön 2016 use the same constraint, jointly with the inertial data).

The field magnitude ``F`` is the local one (a geomagnetic model gives it; without it the
correction keeps ``det C = 1``, the shape without the size, which is all a heading needs).
Disturbances that move with the sheet are hard and soft iron; disturbances fixed in the world
(a steel table) are not, and show as a large fit residual (`MagCalibration.residual_t`).

>>> import numpy as np
>>> rng = np.random.Generator(np.random.MT19937(1))
>>> B = rng.standard_normal((400, 1, 3)); B *= 50e-6 / np.linalg.norm(B, axis=-1, keepdims=True)
>>> D = np.array([[[1.05, 0.02, 0.0], [0.02, 0.97, 0.01], [0.0, 0.01, 1.01]]])
>>> m = np.einsum("kij,tkj->tki", D, B) + np.array([20e-6, -5e-6, 8e-6])
>>> cal = fit_mag_ellipsoid(m, field_t=50e-6)
>>> np.round(cal.hard_iron_t[0] * 1e6, 6).tolist()
[20.0, -5.0, 8.0]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocol.rotations import rotvec_matrices
from .calibration import G0, Calibration, StaticDetector, project_so3, fit_board_poses

__all__ = ["still_segments", "gyro_still_segments", "segment_means", "GyroCalibration", "fit_gyro_rest", "fit_gyro_turns",
           "MagCalibration", "fit_mag_ellipsoid", "fit_mag_alignment", "CaptureCalibration", "fit_capture",
           "chip_imu_blocks"]


def _batch(name: str, a, ndim: int = 3) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.ndim != ndim or a.shape[-1] != 3:
        raise ValueError(f"Expected `{name}` to have shape {'(N, n_links, 3)' if ndim == 3 else '(n_links, 3)'}, "
                         f"got {a.shape}.")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"Invalid {name}: contains NaN or inf")
    return a


def still_segments(still, min_samples: int = 2) -> list[tuple[int, int]]:
    """Runs of True in ``still (N,)`` at least ``min_samples`` long, as ``(start, stop)`` slices.

    >>> still_segments([0, 1, 1, 1, 0, 1, 0, 1, 1], min_samples=2)
    [(1, 4), (7, 9)]
    """
    s = np.asarray(still, dtype=bool)
    if s.ndim != 1:
        raise ValueError(f"Expected `still` to have shape (N,), got {s.shape}.")
    edges = np.diff(np.concatenate([[0], s.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(int(a), int(b)) for a, b in zip(starts, stops) if b - a >= min_samples]


def gyro_still_segments(gyro_rps, segments: list[tuple[int, int]], max_rate_rps: float,
                        min_samples: int = 2) -> list[tuple[int, int]]:
    """Each segment of ``gyro_rps (N, n, 3)`` cut to its longest run of samples where the median
    over the chips of ``|ω − median of the segment|`` is at most ``max_rate_rps`` (a rigid board
    turns every chip at once; the median over time takes out the bias); segments whose longest
    run is shorter than ``min_samples`` are left out.

    >>> g = np.zeros((10, 2, 3)); g[7:, :, 0] = 0.1  # the board starts to turn at sample 7
    >>> gyro_still_segments(g, [(0, 10)], 0.01)
    [(0, 7)]
    """
    g = _batch("gyro_rps", gyro_rps)
    out = []
    for a, b in segments:
        d = np.linalg.norm(g[a:b] - np.median(g[a:b], axis=0), axis=-1)  # (L, n)
        runs = still_segments(np.median(d, axis=1) <= max_rate_rps, max(2, int(min_samples)))
        if runs:
            s, e = max(runs, key=lambda r: r[1] - r[0])
            out.append((a + s, a + e))
    return out


def segment_means(values, segments: list[tuple[int, int]]) -> np.ndarray:
    """Mean of ``values (N, n_links, 3)`` over each segment: ``(len(segments), n_links, 3)``."""
    v = _batch("values", values)
    if not segments:
        raise ValueError("No segments to average")
    return np.stack([v[a:b].mean(axis=0) for a, b in segments])


# ---------------------------------------------------------------------------------------------
# Gyroscope
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class GyroCalibration:
    """Per-chip gyroscope correction ``ω_link = A (ω_meas − b − Γ f/g)`` (module docstring).

    Attributes
    ----------
    bias_rps : ndarray, shape (n, 3)
        ``b``, rad/s, chip axes.
    g_sensitivity : ndarray, shape (n, 3, 3)
        ``Γ``, rad/s per g (zeros when not fitted).
    matrix : ndarray, shape (n, 3, 3)
        ``A`` (identity when not fitted).
    rest_residual_rps : ndarray, shape (n,)
        RMS of the rest fit's residual per chip, rad/s.
    turn_residual : ndarray, shape (n,)
        RMS of the turn fit's residual per chip (unit vectors: ≈ radians; 0 when not fitted).
    turns_used, turns_dropped : int
        Turns the scale fit integrated for every chip, and those it left out for a gap in the
        samples of at least one chip (`fit_gyro_turns`'s ``max_gap_s``; the other chips still use
        them); 0 when not fitted.
    scale_fitted : bool
        ``matrix`` was fitted from the turns (`fit_gyro_turns`); False: the identity, bias and
        g-sensitivity only.
    turns_rejected : int
        Turns left out for at least one chip for their residual (`fit_gyro_turns`' ``outlier_rad``;
        counted in ``turns_dropped`` too).
    """

    bias_rps: np.ndarray
    g_sensitivity: np.ndarray
    matrix: np.ndarray
    rest_residual_rps: np.ndarray
    turn_residual: np.ndarray
    turns_used: int = 0
    turns_dropped: int = 0
    scale_fitted: bool = False
    turns_rejected: int = 0

    @property
    def n_links(self) -> int:
        return self.bias_rps.shape[0]

    def apply(self, gyro_rps, accel_mps2=None) -> np.ndarray:
        """Corrected rates ``(..., n, 3)``, rad/s, link frames; ``accel_mps2`` (same shape: the
        chips' specific force in their own axes, bias and scale corrected — ``(r − b) / s`` of the
        accelerometer `Calibration`) for the g-sensitivity term (omitted: the term is left out)."""
        w = np.asarray(gyro_rps, dtype=float) - self.bias_rps
        if accel_mps2 is not None:
            w = w - np.einsum("kij,...kj->...ki", self.g_sensitivity, np.asarray(accel_mps2, dtype=float) / G0)
        return np.einsum("kij,...kj->...ki", self.matrix, w)


def fit_gyro_rest(rest_gyro_rps, rest_accel_mps2, *, g_sensitivity: bool = True) -> GyroCalibration:
    """Bias (and g-sensitivity) from held poses (module docstring, step 1).

    Parameters
    ----------
    rest_gyro_rps : ndarray, shape (K, n, 3)
        Each pose's mean rate, rad/s (`segment_means` over the still samples).
    rest_accel_mps2 : ndarray, shape (K, n, 3)
        Each pose's mean specific force, m/s², the chips' axes.
    g_sensitivity : bool
        Fit ``Γ`` too (needs K >= 4 poses whose gravity directions are not coplanar).

    Returns
    -------
    GyroCalibration
        With ``matrix`` the identity (`fit_gyro_turns` fits it).
    """
    w = _batch("rest_gyro_rps", rest_gyro_rps)
    f = _batch("rest_accel_mps2", rest_accel_mps2)
    if f.shape != w.shape:
        raise ValueError(f"Expected rest_accel_mps2 of shape {w.shape}, got {f.shape}.")
    K, n = w.shape[:2]
    if not g_sensitivity:
        b = w.mean(axis=0)
        res = np.sqrt(np.mean((w - b) ** 2, axis=(0, 2)))
        return GyroCalibration(b, np.zeros((n, 3, 3)), np.tile(np.eye(3), (n, 1, 1)), res, np.zeros(n))
    if K < 4:
        raise ValueError(f"fit_gyro_rest with g_sensitivity needs at least 4 poses, got {K}")
    X = np.concatenate([np.ones((K, n, 1)), f / G0], axis=-1)  # (K, n, 4)
    Xc = np.transpose(X, (1, 0, 2))  # (n, K, 4)
    N = Xc.transpose(0, 2, 1) @ Xc
    cond = np.linalg.cond(N)
    if np.any(~np.isfinite(cond)) or np.max(cond) > 1e8:
        raise ValueError("fit_gyro_rest: the poses' gravity directions are (nearly) coplanar; cannot "
                         "separate bias from g-sensitivity (turn the board to more distinct poses)")
    rhs = Xc.transpose(0, 2, 1) @ np.transpose(w, (1, 0, 2))  # (n, 4, 3)
    P = np.linalg.solve(N, rhs)  # (n, 4, 3): row 0 bias, rows 1..3 Γᵀ
    b = P[:, 0, :]
    G = np.transpose(P[:, 1:, :], (0, 2, 1))
    res = np.sqrt(np.mean((np.transpose(Xc @ P, (1, 0, 2)) - w) ** 2, axis=(0, 2)))
    return GyroCalibration(b, G, np.tile(np.eye(3), (n, 1, 1)), res, np.zeros(n))


def _carry(A: np.ndarray, w: np.ndarray, dt: np.ndarray, u0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gravity's direction ``u0 (J, n, 3)`` carried through the turns, ``R(A)ᵀ u0``, with ``R(A)``
    the product of the body-frame increments ``exp([A w̄_i Δt_i]×)`` (``w̄_i`` the mean of two
    successive samples), and its Jacobian in the 9 entries of ``A (n, 3, 3)``.

    Perturbing increment ``i`` by ``δφ`` turns the end by ``δθ = R_endᵀ R_{0..i+1} δφ`` (first
    order), and the carried vector by ``u × δθ``; ``δφ = δA w̄_i Δt_i``. ``w (J, L, n, 3)``,
    ``dt (J, L-1, n)``: each chip's own sample steps. Returns ``(u (J, n, 3), jac (J, n, 3, 9))``."""
    J_, L, n = w.shape[:3]
    R = np.broadcast_to(np.eye(3), (J_, n, 3, 3)).copy()
    S = np.zeros((J_, n, 3, 3, 3))  # Σ R_{0..i+1}[:, p] · (w̄_i Δt_i)_q
    for i in range(L - 1):
        mid = 0.5 * (w[:, i] + w[:, i + 1]) * dt[:, i, :, None]  # (J, n, 3)
        R = R @ rotvec_matrices(np.einsum("kij,tkj->tki", A, mid))
        S += R[..., :, :, None] * mid[..., None, None, :]
    u = np.einsum("tkji,tkj->tki", R, u0)
    dtheta = np.einsum("tkai,tkapq->tkipq", R, S).reshape(J_, n, 3, 9)  # R_endᵀ S
    jac = np.cross(u[..., :, None], dtheta, axisa=-2, axisb=-2, axisc=-2)
    return u, jac


#: `fit_gyro_turns`: a gap up to this long inside a turn is integrated across (150 ms in two of
#: eleven 1 s turns: 0.1 % of scale), a longer one leaves its turn out
TURN_MAX_GAP_S = 0.1
#: `fit_gyro_turns`: turns needed (two equations each, nine unknowns per chip)
MIN_TURNS = 5
#: `fit_capture`: the largest turn residual (`GyroCalibration.turn_residual`, radians: how far the
#: fitted integration still carries gravity from where the next pose has it) whose scale fit is
#: kept. Exact sample instants leave 0.0003 rad (0.017°: the 3x3 pty test on a quiet machine, 12
#: poses of 1.5 s) and 0.00007 rad (the simulated board at 145 Hz). Readings taken up to 100 ms
#: away from their stated instants (the same test's stalled virtual sheet at load 11-13) left
#: 1.1-4.0° and a scale 1.7-2.7 % off (0.13-0.17 % refitted over the true instants); on the
#: simulated board, such stalls at random in every turn left 0.3-2.9° and a scale 0.2-1.6 % off —
#: about 1 % of scale a degree. 0.2°: at most ~0.3 %.
TURN_MAX_RESIDUAL_RAD = float(np.radians(0.2))
#: `fit_gyro_turns`: a turn whose residual is this many times the median of a chip's turns (and
#: above ``outlier_rad``) is left out for that chip. The 3x3 pty test at load ~5 had one turn with
#: readings 36 ms from their instants: 0.23° over the ten turns, the scale 0.08 % off
OUTLIER_FACTOR = 3.0
#: `fit_capture`: a held pose's samples whose rates stray further than this from the pose's median
#: (the median over the chips) are not held (`gyro_still_segments`). The gyroscopes' noise is
#: 0.025 °/s a sample on the simulated chips; a detector set for 1 %-of-g accelerometer noise
#: (0.3 m/s²) let in turn ends at up to 35 °/s, and a bias 0.025 °/s off.
REST_MAX_RATE_RPS = float(np.radians(0.5))
#: `fit_capture`: the largest rest residual (`GyroCalibration.rest_residual_rps`: the held poses'
#: mean rates against the bias and g-sensitivity fitted to them) whose gyroscope fit is kept. Still
#: poses leave 0.004-0.007 °/s (the 3x3 pty test, 20-90 still snapshots a pose at 100 Hz) and
#: 0.0012 °/s (the simulated board, 4 s poses at 145 Hz). A board that kept turning through one
#: pose — about gravity, which no accelerometer sees — puts its rate into the bias: on the
#: simulated board, at 0.1-0.5 °/s, a residual of 0.013-0.066 °/s and a bias 0.011-0.060 °/s
#: off (the target: 0.01 °/s, docs/calibration.md).
REST_MAX_RESIDUAL_RPS = float(np.radians(0.02))


def fit_gyro_turns(gyro_rps, t_s, segments: list[tuple[int, int]], gravity_link, cal: GyroCalibration,
                   accel_mps2=None, *, iterations: int = 6, max_gap_s: float | None = None,
                   outlier_rad: float | None = None, max_outlier_rounds: int = 3) -> GyroCalibration:
    """Scale, cross-axis and mounting of every gyroscope from the turns between held poses
    (module docstring, step 2).

    Parameters
    ----------
    gyro_rps : ndarray, shape (N, n, 3)
        The whole capture, rad/s, chip axes.
    t_s : ndarray, shape (N,) or (N, n)
        Sample instants, s: one per snapshot, or each chip's own (the SYNC's time plus the record's
        ``time_us``, docs/protocol.md §16.1: the instant the chip latched the reading, which a
        SYNC sent late does not move). Each chip's must not decrease; equal instants (a STALE
        record repeating the previous reading) add nothing to the turn.
    segments : list of (start, stop)
        The held poses, in time order (`still_segments`); each turn runs from the last sample of
        one to the first of the next.
    gravity_link : ndarray, shape (K, n, 3)
        Gravity's direction in each link frame at each pose (the calibrated accelerometers'
        mean, normalised).
    cal : GyroCalibration
        Bias and g-sensitivity (`fit_gyro_rest`), removed before integrating.
    accel_mps2 : ndarray, shape (N, n, 3), optional
        The capture's specific force, for the g-sensitivity term.
    max_gap_s : float, optional
        A turn with two consecutive samples further apart than this is left out: its rotation
        cannot be integrated from what came (a host that stopped sending SYNC for half a second in
        the middle of a turn). With each chip's own instants, per chip: a chip whose records were
        lost for longer leaves that turn out alone. Default: `TURN_MAX_GAP_S`, or 2.5 × the median
        sample step if that is longer. Two equations a turn, 9 unknowns a chip: every chip must keep
        at least `MIN_TURNS`.
    outlier_rad : float, optional
        Leave out, for a chip, its worst turn when that turn's residual is above this and
        `OUTLIER_FACTOR` times the median of its turns', and fit again (at most
        ``max_outlier_rounds`` times; never below `MIN_TURNS` turns): one turn whose readings'
        instants were wrong (a stalled sheet) otherwise spreads its error over the scale. None: no
        turn is left out for its residual.

    Returns
    -------
    GyroCalibration
        ``cal`` with ``matrix``, ``turn_residual``, ``turns_used`` and ``turns_dropped`` fitted.
    """
    g = _batch("gyro_rps", gyro_rps)
    N, n = g.shape[:2]
    t = np.asarray(t_s, dtype=float)
    if t.shape == (N,):
        if np.any(np.diff(t) <= 0):
            raise ValueError(f"Expected increasing `t_s` of shape ({N},), got {t.shape}.")
        t = np.repeat(t[:, None], n, axis=1)
    elif t.shape != (N, n) or not np.all(np.isfinite(t)) or np.any(np.diff(t, axis=0) < 0):
        raise ValueError(f"Expected `t_s` of shape ({N},) (increasing) or ({N}, {n}) (finite, not decreasing "
                         f"per chip), got {t.shape}.")
    u = _batch("gravity_link", gravity_link)
    K = len(segments)
    if u.shape != (K, n, 3):
        raise ValueError(f"Expected gravity_link of shape ({K}, {n}, 3), got {u.shape}.")
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    w = cal.apply(g, accel_mps2) if accel_mps2 is not None else g - cal.bias_rps
    w = np.einsum("kij,tkj->tki", np.linalg.inv(cal.matrix), w)  # rates before any matrix
    turns = [(segments[k][1] - 1, segments[k + 1][0] + 1) for k in range(K - 1)]
    gap = float(max_gap_s) if max_gap_s is not None else max(TURN_MAX_GAP_S,
                                                              2.5 * float(np.median(np.diff(t, axis=0))))
    # per turn and chip: no gap in that chip's samples
    ok = np.array([np.ones(n, dtype=bool) if b - a < 2 else np.max(np.diff(t[a:b], axis=0), axis=0) <= gap
                   for a, b in turns]).reshape(len(turns), n)
    keep = [k for k in range(len(turns)) if ok[k].any()]
    least = int(ok.sum(axis=0).min()) if n else 0
    if least < MIN_TURNS:
        gapped = int((~ok.all(axis=1)).sum())
        raise ValueError(f"fit_gyro_turns: {least} of {len(turns)} turns to fit, need {MIN_TURNS} "
                         f"(2 equations a turn, 9 unknowns a chip)"
                         + (f"; {gapped} have a gap of more than {1e3 * gap:.0f} ms in their samples "
                            f"(SYNCs not sent or snapshots lost while the board turned: a loaded host)"
                            if gapped else ""))
    turns = [turns[k] for k in keep]
    use = ok[keep].T.copy()  # (n, J): chip k integrates turn j
    Lmax = max(b - a for a, b in turns)
    J = len(turns)
    W = np.zeros((J, Lmax, n, 3))
    DT = np.zeros((J, Lmax - 1, n))
    for j, (a, b) in enumerate(turns):
        W[j, : b - a] = w[a:b]
        DT[j, : b - a - 1] = np.diff(t[a:b], axis=0)
    u0, u1 = u[:-1][keep], u[1:][keep]  # (J, n, 3)
    rejected = np.zeros_like(use)
    for _round in range(1 + (max_outlier_rounds if outlier_rad is not None else 0)):
        A = _gauss_newton_turns(W, DT, u0, u1, use, iterations)
        pred, _jac = _carry(A, W, DT, u0)
        sq = np.sum((pred - u1) ** 2, axis=-1).T  # (n, J)
        if outlier_rad is None:
            break
        # a chip's worst turn, when far off its others' (a turn whose instants alone were wrong),
        # is left out for it and the fit redone, while the chip keeps MIN_TURNS
        e = np.sqrt(np.where(use, sq, np.nan))
        worst = np.nanargmax(e, axis=1)
        med = np.nanmedian(e, axis=1)
        ew = e[np.arange(n), worst]
        out = (ew > outlier_rad) & (ew > OUTLIER_FACTOR * med) & (use.sum(axis=1) > MIN_TURNS)
        if not out.any():
            break
        use[out, worst[out]] = False
        rejected[out, worst[out]] = True
    res = np.sqrt(np.sum(sq * use, axis=1) / use.sum(axis=1))
    used = int(use.all(axis=0).sum())
    return GyroCalibration(cal.bias_rps, cal.g_sensitivity, A @ cal.matrix, cal.rest_residual_rps, res,
                           turns_used=used, turns_dropped=K - 1 - used, scale_fitted=True,
                           turns_rejected=int(rejected.any(axis=0).sum()))


def _gauss_newton_turns(W, DT, u0, u1, use, iterations: int) -> np.ndarray:
    """`fit_gyro_turns`' matrices ``(n, 3, 3)``: Gauss–Newton from the identity over the turns each
    chip uses (``use (n, J)``)."""
    n = use.shape[0]
    rows = np.repeat(use, 3, axis=1).astype(float)  # (n, 3J): a chip's left-out turns weigh nothing
    A = np.tile(np.eye(3), (n, 1, 1))
    for _ in range(iterations):
        pred, jac = _carry(A, W, DT, u0)
        r = (pred - u1).transpose(1, 0, 2).reshape(n, -1) * rows  # (n, 3J)
        Jm = jac.transpose(1, 0, 2, 3).reshape(n, -1, 9) * rows[..., None]  # (n, 3J, 9)
        H = Jm.transpose(0, 2, 1) @ Jm
        step = np.linalg.solve(H + 1e-12 * np.eye(9), Jm.transpose(0, 2, 1) @ r[..., None])[..., 0]
        A = A - step.reshape(n, 3, 3)
        if np.max(np.abs(step)) < 1e-10:
            break
    return A


# ---------------------------------------------------------------------------------------------
# Magnetometer
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class MagCalibration:
    """Per-chip magnetometer correction ``B_link = R C (m − h)`` (module docstring).

    Attributes
    ----------
    hard_iron_t : ndarray, shape (n, 3)
        ``h``, tesla, the part's axes.
    correction : ndarray, shape (n, 3, 3)
        ``C``, symmetric positive definite: ``|C (m − h)| = F``.
    alignment : ndarray, shape (n, 3, 3)
        ``R``, the part's axes into the link frame (`fit_mag_alignment`; identity until fitted).
    field_t : ndarray, shape (n,)
        ``F`` per chip: the given field, or the ellipsoid's mean radius when none was given.
    residual_t : ndarray, shape (n,)
        RMS of ``|C (m − h)| − F`` over the fitted samples, tesla; inf for a chip whose readings
        fit no ellipsoid (its other fields NaN): a disturbance fixed in the world, a broken part.
    dip_rad : ndarray, shape (n,)
        The field's dip seen by each chip (`fit_mag_alignment`; NaN until fitted).
    """

    hard_iron_t: np.ndarray
    correction: np.ndarray
    alignment: np.ndarray
    field_t: np.ndarray
    residual_t: np.ndarray
    dip_rad: np.ndarray

    @property
    def n_links(self) -> int:
        return self.hard_iron_t.shape[0]

    def apply(self, mag_t) -> np.ndarray:
        """Corrected field ``(..., n, 3)``, tesla, link frames."""
        m = np.asarray(mag_t, dtype=float) - self.hard_iron_t
        return np.einsum("kij,...kj->...ki", self.alignment @ self.correction, m)


def _sym(p: np.ndarray) -> np.ndarray:
    """6 parameters -> symmetric 3 × 3 (order xx, yy, zz, xy, xz, yz)."""
    S = np.empty(p.shape[:-1] + (3, 3))
    S[..., 0, 0], S[..., 1, 1], S[..., 2, 2] = p[..., 0], p[..., 1], p[..., 2]
    S[..., 0, 1] = S[..., 1, 0] = p[..., 3]
    S[..., 0, 2] = S[..., 2, 0] = p[..., 4]
    S[..., 1, 2] = S[..., 2, 1] = p[..., 5]
    return S


def _sqrtm_spd(Q: np.ndarray) -> np.ndarray:
    lam, V = np.linalg.eigh(Q)
    return (V * np.sqrt(lam)[..., None, :]) @ np.transpose(V, (0, 2, 1))


def fit_mag_ellipsoid(mag_t, field_t: float | None = None, *, iterations: int = 8,
                      max_samples: int = 4000) -> MagCalibration:
    """Hard and soft iron of every magnetometer from readings in many orientations of a uniform
    field (module docstring, step 3).

    Parameters
    ----------
    mag_t : ndarray, shape (N, n, 3)
        Readings, tesla, the parts' axes.
    field_t : float, optional
        The local field's magnitude ``F``, tesla (default: each ellipsoid's geometric mean radius,
        so ``det C = 1``: the shape without the size).
    max_samples : int
        At most this many readings are fitted: a longer capture is averaged over blocks of
        ``⌈N / max_samples⌉`` consecutive samples (the fit's cost grows with the count; averaging
        keeps the noise reduction that picking every k-th sample would lose — on the 14 × 14
        benchmark capture the soft-iron error halves. A block of 4 samples at 145 Hz during a
        board's 5 rad/s turn shrinks the field by 0.04 %).

    Returns
    -------
    MagCalibration
        ``alignment`` the identity (`fit_mag_alignment` fits it).
    """
    m = _batch("mag_t", mag_t)
    N, n = m.shape[:2]
    if N < 9:
        raise ValueError(f"fit_mag_ellipsoid needs at least 9 readings per chip, got {N}")
    if field_t is not None and not (np.isfinite(field_t) and field_t > 0):
        raise ValueError(f"Invalid field_t: {field_t!r} (need > 0 tesla)")
    if N > max_samples:
        k = -(-N // max_samples)
        m = m[: N // k * k].reshape(N // k, k, n, 3).mean(axis=1)
    # work about each chip's mean reading, in units of the readings' spread (conditioning: the hard
    # iron can be larger than the field)
    centre = m.mean(axis=0)  # (n, 3)
    scale = np.sqrt(np.mean(np.sum((m - centre) ** 2, axis=-1)))
    x = np.transpose((m - centre) / scale, (1, 0, 2))  # (n, N, 3)
    X, Y, Z = x[..., 0], x[..., 1], x[..., 2]
    D = np.stack([X * X, Y * Y, Z * Z, 2 * X * Y, 2 * X * Z, 2 * Y * Z, 2 * X, 2 * Y, 2 * Z], axis=-1)
    Ntn = D.transpose(0, 2, 1) @ D
    ok = np.linalg.cond(Ntn) < 1e12  # the orientations span a quadric
    if not ok.any():
        raise ValueError("fit_mag_ellipsoid: the orientations do not span an ellipsoid (rotate every way)")
    p = np.zeros((n, 9))
    p[ok] = np.linalg.solve(Ntn[ok], D[ok].sum(axis=1)[..., None])[..., 0]
    p[~ok, :3] = 1.0
    Q = _sym(p[:, :6])
    c = -np.linalg.solve(Q, p[:, 6:, None])[..., 0]
    Qn = Q / (1.0 + np.einsum("ki,kij,kj->k", c, Q, c))[:, None, None]
    ok &= np.all(np.linalg.eigvalsh(Qn) > 0, axis=-1)  # ... and that quadric is an ellipsoid
    if not ok.any():
        raise ValueError("fit_mag_ellipsoid: the readings do not lie on an ellipsoid for any chip (rotate "
                         "every way; a world-fixed disturbance or too few orientations?)")
    # geometric refinement on the chips that have an ellipsoid: r = |C (x − h)| − 1, parameters h (3)
    # and C (6, symmetric); the others are reported as failed (NaN, residual inf)
    C0 = _sqrtm_spd(Qn[ok])  # |C (x − c)| = 1
    par = np.concatenate([c[ok], C0[:, [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]], axis=-1)
    xo = x[ok]
    for _ in range(iterations):
        h, C = par[:, :3], _sym(par[:, 3:])
        d = xo - h[:, None, :]
        y = np.einsum("kij,ktj->kti", C, d)
        ny = np.linalg.norm(y, axis=-1)
        r = ny - 1.0
        yh = y / ny[..., None]
        Jh = -np.einsum("kti,kij->ktj", yh, C)  # ∂r/∂h
        JC = np.stack([yh[..., 0] * d[..., 0], yh[..., 1] * d[..., 1], yh[..., 2] * d[..., 2],
                       yh[..., 0] * d[..., 1] + yh[..., 1] * d[..., 0],
                       yh[..., 0] * d[..., 2] + yh[..., 2] * d[..., 0],
                       yh[..., 1] * d[..., 2] + yh[..., 2] * d[..., 1]], axis=-1)
        Jm = np.concatenate([Jh, JC], axis=-1)  # (n_ok, N, 9)
        H = Jm.transpose(0, 2, 1) @ Jm
        step = np.linalg.solve(H, (Jm.transpose(0, 2, 1) @ r[..., None]))[..., 0]
        par = par - step
        if np.max(np.abs(step)) < 1e-10:
            break
    h = np.full((n, 3), np.nan)
    C = np.full((n, 3, 3), np.nan)
    h[ok], C[ok] = centre[ok] + par[:, :3] * scale, _sym(par[:, 3:]) / scale
    radius = np.linalg.norm(np.einsum("kij,tkj->tki", C, m - h), axis=-1)  # ≈ 1
    # C now maps the ellipsoid to the unit sphere; F: the given field, or its geometric mean radius
    F = np.cbrt(1.0 / np.linalg.det(C)) if field_t is None else np.full(n, float(field_t))
    C = C * F[:, None, None]
    res = np.sqrt(np.mean((radius - 1.0) ** 2, axis=0)) * F
    ok &= np.isfinite(res) & (res < 0.5 * F)  # a refinement that ran away: no ellipsoid either
    h[~ok], C[~ok], F[~ok], res[~ok] = np.nan, np.nan, np.nan, np.inf
    return MagCalibration(h, C, np.tile(np.eye(3), (n, 1, 1)), F, res, np.full(n, np.nan))


def fit_mag_alignment(cal: MagCalibration, rest_mag_t, rest_gravity_link, *,
                      iterations: int = 10) -> MagCalibration:
    """The rotation of every magnetometer into its link frame, from held poses (module docstring,
    step 4): ``R`` and the dip ``δ`` per chip with ``û_k · R b̂_k = −sin δ`` in every pose ``k``
    (``û`` gravity's specific-force direction, up; ``b̂`` the corrected field direction).

    Parameters
    ----------
    cal : MagCalibration
        From `fit_mag_ellipsoid`.
    rest_mag_t : ndarray, shape (K, n, 3)
        Each pose's mean reading, tesla, the parts' axes.
    rest_gravity_link : ndarray, shape (K, n, 3)
        Each pose's specific force direction in the link frames (calibrated accelerometers).

    Returns
    -------
    MagCalibration
        ``cal`` with ``alignment`` and ``dip_rad``.
    """
    mg = _batch("rest_mag_t", rest_mag_t)
    ug = _batch("rest_gravity_link", rest_gravity_link)
    K, n = mg.shape[:2]
    if ug.shape != mg.shape or n != cal.n_links:
        raise ValueError(f"Expected rest_gravity_link of shape {mg.shape} for {cal.n_links} chips, got {ug.shape}.")
    if K < 5:
        raise ValueError(f"fit_mag_alignment needs at least 5 held poses, got {K}")
    good = np.isfinite(cal.residual_t)  # chips whose ellipsoid fit failed stay NaN
    if not good.any():
        raise ValueError("fit_mag_alignment: no chip has a magnetometer correction to align")
    b = np.einsum("kij,tkj->tki", cal.correction[good], (mg - cal.hard_iron_t)[:, good])
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    u = ug[:, good] / np.linalg.norm(ug[:, good], axis=-1, keepdims=True)
    n_all, n = n, int(good.sum())
    # start: R = I, s = mean of û·b̂; Gauss–Newton on (rotation increment, s), analytic Jacobian
    R = np.tile(np.eye(3), (n, 1, 1))
    s = np.mean(np.sum(u * b, axis=-1), axis=0)
    for _ in range(iterations):
        Rb = np.einsum("kij,tkj->tki", R, b)  # (K, n, 3)
        r = np.sum(u * Rb, axis=-1) - s  # (K, n)
        # R ← exp([δ]×) R: ∂(û·Rb)/∂δ = (Rb × û)... û·(δ × Rb) = δ·(Rb × û)
        Jd = np.cross(Rb, u)  # (K, n, 3)
        Jm = np.concatenate([Jd, -np.ones((K, n, 1))], axis=-1).transpose(1, 0, 2)  # (n, K, 4)
        H = Jm.transpose(0, 2, 1) @ Jm
        step = np.linalg.solve(H + 1e-12 * np.eye(4), Jm.transpose(0, 2, 1) @ r.T[..., None])[..., 0]
        R = rotvec_matrices(-step[:, :3]) @ R
        s = s - step[:, 3]
        if np.max(np.abs(step)) < 1e-12:
            break
    R_all = np.full((n_all, 3, 3), np.nan)
    R_all[good] = np.stack([project_so3(Rk) for Rk in R])
    dip = np.full(n_all, np.nan)
    dip[good] = np.arcsin(np.clip(-s, -1.0, 1.0))
    return MagCalibration(cal.hard_iron_t, cal.correction, R_all, cal.field_t, cal.residual_t, dip)


# ---------------------------------------------------------------------------------------------
# The whole capture
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CaptureCalibration:
    """Everything `fit_capture` found: the accelerometers' `Calibration`, the gyroscopes' and the
    magnetometers' (None without those sensors), and the held poses it used (sample slices).
    A gyroscope fit judged bad is not kept (`gyro_refused` says why): a rest residual above its
    limit leaves ``gyro`` None, a turn residual above its limit leaves the bias and g-sensitivity
    (``scale_fitted`` False)."""

    accel: Calibration
    gyro: GyroCalibration | None
    mag: MagCalibration | None
    segments: tuple[tuple[int, int], ...]
    #: why the gyroscope fit, or its scale part, was not kept (one line naming the figure judged by
    #: and its limit); "" when it was kept whole or there are no gyroscopes
    gyro_refused: str = ""
    #: the fit that was judged and not kept (its figures), None when ``gyro`` is the whole fit
    gyro_rejected: GyroCalibration | None = None
    #: the limits the gyroscope fit was judged against (`fit_capture`)
    max_turn_residual_rad: float = TURN_MAX_RESIDUAL_RAD
    max_rest_residual_rps: float = REST_MAX_RESIDUAL_RPS


def fit_capture(t_s, accel_mps2, rows: int, cols: int, gyro_rps=None, mag_t=None, *, window: int = 25,
                threshold_mps2: float = 0.098, field_t: float | None = None,
                min_hold_samples: int | None = None, max_turn_residual_rad: float = TURN_MAX_RESIDUAL_RAD,
                max_rest_residual_rps: float = REST_MAX_RESIDUAL_RPS,
                max_rest_rate_rps: float = REST_MAX_RATE_RPS) -> CaptureCalibration:
    """Calibrate every sensor of every chip from one board capture (docs/calibration.md): the
    sheet flat on the board, turned through held poses, sampled throughout.

    1. Held poses: `calibration.StaticDetector` (``window``, ``threshold_mps2``) on the
       accelerometers; each still run, less ``window`` samples at both ends (the detector lags the
       start of a turn by a few samples), of at least ``min_hold_samples`` (default 4 windows).
       With gyroscopes, each run is cut to its longest part where the chips' rates stay within
       ``max_rest_rate_rps`` of the run's median (`gyro_still_segments`): a detector loose enough
       for noisy accelerometers lets the ends of turns in.
    2. Accelerometers: `calibration.fit_board_poses` on the poses' means.
    3. Gyroscopes: `fit_gyro_rest` (bias, g-sensitivity against the bias- and scale-corrected
       specific force), then `fit_gyro_turns` (gravity's direction per pose from step 2). Each is
       judged by what it leaves: a rest residual above ``max_rest_residual_rps`` (a held pose
       that was not still) keeps no gyroscope fit; a turn residual above ``max_turn_residual_rad``
       (the rates do not carry gravity from pose to pose: readings whose instants are wrong, a
       board that bent) keeps the bias and g-sensitivity only. ``gyro_refused`` says which and
       the figure.
    4. Magnetometers: `fit_mag_ellipsoid` on every sample, then `fit_mag_alignment` on the poses.

    Parameters
    ----------
    t_s : ndarray, shape (N,) or (N, n)
        Sample instants: one per snapshot, or each chip's own (`fit_gyro_turns`).
    accel_mps2 : ndarray, shape (N, n, 3)
        As converted with the chips' reported calibration (the fit's reference).
    rows, cols : int
    gyro_rps, mag_t : ndarray, shape (N, n, 3), optional
    """
    a = _batch("accel_mps2", accel_mps2)
    N, n = a.shape[:2]
    det = StaticDetector(n, window=window, threshold_mps2=threshold_mps2)
    still = np.array([det.update(x) for x in a])
    least = 4 * window if min_hold_samples is None else int(min_hold_samples)
    segs = [(s + window, e - window) for s, e in still_segments(still, least + 2 * window)]
    if gyro_rps is not None and segs:  # the gyroscopes see a turn's start the accelerometers do not
        segs = gyro_still_segments(_batch("gyro_rps", gyro_rps), segs, max_rest_rate_rps, least)
    if len(segs) < 6:
        raise ValueError(f"fit_capture: found {len(segs)} held poses (need at least 6; hold each pose "
                         f"still for more than {(least + 3 * window)} samples)")
    am = segment_means(a, segs)
    acal = fit_board_poses(am, rows, cols)
    u = acal.apply(am)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    gcal = mcal = rejected = None
    refused = ""
    if gyro_rps is not None:
        g = _batch("gyro_rps", gyro_rps)
        f_chip = (a - acal.bias) / acal.scale
        rest = fit_gyro_rest(segment_means(g, segs), segment_means(f_chip, segs))
        gcal, refused, rejected = _judged_gyro(rest, lambda: fit_gyro_turns(g, t_s, segs, u, rest, f_chip,
                                                                             outlier_rad=max_turn_residual_rad),
                                               max_turn_residual_rad, max_rest_residual_rps)
    if mag_t is not None:
        m = _batch("mag_t", mag_t)
        mcal = fit_mag_alignment(fit_mag_ellipsoid(m, field_t), segment_means(m, segs), u)
    return CaptureCalibration(acal, gcal, mcal, tuple(segs), refused, rejected, float(max_turn_residual_rad),
                              float(max_rest_residual_rps))


def _judged_gyro(rest: GyroCalibration, turns, max_turn_rad: float, max_rest_rps: float):
    """The part of the gyroscope fit its own residuals vouch for (`fit_capture`, step 3):
    ``(kept or None, why not all of it or "", the fit not kept or None)``; ``turns()`` fits the
    scale."""
    worst = int(np.argmax(rest.rest_residual_rps))
    if rest.rest_residual_rps[worst] > max_rest_rps:
        return None, (f"gyroscope not fitted: the held poses' mean rates miss the fitted bias and "
                      f"g-sensitivity by {np.degrees(rest.rest_residual_rps[worst]):.3f} °/s RMS (link {worst}; "
                      f"limit {np.degrees(max_rest_rps):.3f} °/s): the board was not still while held "
                      f"(turning slowly?)"), rest
    full = turns()
    worst = int(np.argmax(full.turn_residual))
    if full.turn_residual[worst] > max_turn_rad:
        return rest, (f"gyroscope scale and cross-axis not fitted (bias and g-sensitivity kept): the "
                      f"fitted rates still carry gravity {np.degrees(full.turn_residual[worst]):.2f}° RMS "
                      f"from where the next pose has it (link {worst}, {full.turns_used} turns; limit "
                      f"{np.degrees(max_turn_rad):.2f}°): readings whose instants are wrong (a stalled "
                      f"host or sheet) or a board that bent"), full
    return full, "", None


# ---------------------------------------------------------------------------------------------
# Onto the chips (docs/protocol.md §17)
# ---------------------------------------------------------------------------------------------

def chip_imu_blocks(gyro: GyroCalibration | None, mag: MagCalibration | None, accel: Calibration,
                    ref_offset_counts, ref_sensitivity, current: dict | None = None) -> list[dict]:
    """What to write to each chip (CAL_IMU_WRITE, §17.1) so that it sends what ``gyro`` and ``mag``
    correct to: ``[{block: [values]}]`` per chip (blocks 0..2 with ``gyro``, 3..4 with ``mag``).

    The fit was made on what the chips sent, converted at the nominal sensitivities, while each
    chip applied its ``current`` calibration (``{block: [values]}`` per chip; None: nominal), with
    the specific force ``f`` of the bias- and scale-corrected accelerometer (``accel`` relative to
    the chips' CAL_DATA ``ref_offset_counts``, ``ref_sensitivity``, ±2 g counts). The chip computes
    ``A (g − s (b + Γ f₀))`` with ``f₀ = counts / 1024`` g (§17.3), so the two compose: with the
    chip's ``(A₀, b₀, Γ₀)`` and the fit's ``(A₁, b₁, Γ₁)``, and ``f = D f₀ + e`` (``D``, ``e`` from
    CAL_DATA and the accelerometer fit)::

        A = A₁ A₀,   b = b₀ + A₀⁻¹ (b₁ + Γ₁ e),   Γ = Γ₀ + A₀⁻¹ Γ₁ D

    and for the magnetometer ``S = M₁ S₀``, ``h = h₀ + S₀⁻¹ h₁`` (``M₁ = R C`` of the fit).
    A chip whose magnetometer fit failed (NaN) keeps its current magnetometer blocks.
    """
    off = np.asarray(ref_offset_counts, dtype=float)
    sens = np.asarray(ref_sensitivity, dtype=float)
    n = off.shape[0]
    nominal = {0: np.eye(3), 1: np.zeros(3), 2: np.zeros((3, 3)), 3: np.eye(3), 4: np.zeros(3)}
    out = []
    for k in range(n):
        cur = {b: np.asarray(v, dtype=float).reshape(nominal[b].shape)
               for b, v in ((current[k] if current is not None else {}) or {}).items()}
        c = {b: cur.get(b, nominal[b]) for b in nominal}
        blocks: dict[int, list[float]] = {}
        if gyro is not None:
            D = np.diag(1024.0 / (sens[k] * accel.scale[k]))
            e = -(off[k] / sens[k] + accel.bias[k] / G0) / accel.scale[k]
            A0inv = np.linalg.inv(c[0])
            A = gyro.matrix[k] @ c[0]
            b = c[1] + A0inv @ (gyro.bias_rps[k] + gyro.g_sensitivity[k] @ e)
            G = c[2] + A0inv @ gyro.g_sensitivity[k] @ D
            blocks.update({0: A.ravel().tolist(), 1: b.tolist(), 2: G.ravel().tolist()})
        if mag is not None and np.all(np.isfinite(mag.correction[k])) and np.all(np.isfinite(mag.hard_iron_t[k])):
            M1 = mag.alignment[k] @ mag.correction[k]
            blocks.update({3: (M1 @ c[3]).ravel().tolist(), 4: (c[4] + np.linalg.inv(c[3]) @ mag.hard_iron_t[k]).tolist()})
        out.append(blocks)
    return out
