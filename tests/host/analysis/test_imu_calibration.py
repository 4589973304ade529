"""Gyroscope and magnetometer calibration recovers the simulator's hidden
truth from one board capture: bias and g-sensitivity from the rests, scale / cross-axis / mounting
from the turns, hard and soft iron from the rotations, the magnetometer's turn from the dip.

The truth is the virtual chips' fixed errors (`virtual_sheet.imu`), never the fit's own output.
Rotations common to every chip are unidentifiable (docs/calibration.md): compared in the board's
frame with that common rotation removed, as bench_calibration does for the accelerometers."""

import numpy as np
import pytest

from host.analysis.calibration import link_frames_on_board
from host.analysis.imu_calibration import (fit_capture, fit_gyro_rest, fit_mag_ellipsoid, segment_means,
                                           still_segments)
from virtual_sheet.imu import imu_array, simulate
from virtual_sheet.magfield import Dipole, EarthField, MagneticField
from virtual_sheet.motion import make_motion_scene

L = 0.01
ROWS = COLS = 3
FIELD = EarthField(48e-6, np.radians(62.0), 0.3)


def _capture(env: MagneticField, seed: int = 7):
    board = make_motion_scene("board", ROWS, COLS, L, hold_s=4.0, move_s=1.0, seed=5)
    imu = imu_array(12, "accel+gyro+mag", seed=seed, field=env)
    runs = list(simulate(board, imu, board.period_s))
    cat = {k: np.concatenate([getattr(r, k) for _t, r in runs]) for k in ("t_s", "accel_mps2", "gyro_rps", "mag_t")}
    return imu, cat


@pytest.fixture(scope="module")
def captured():
    imu, c = _capture(MagneticField(FIELD))
    cal = fit_capture(c["t_s"], c["accel_mps2"], ROWS, COLS, c["gyro_rps"], c["mag_t"], field_t=FIELD.magnitude_t)
    return imu, c, cal


def _without_common_rotation(P: np.ndarray) -> np.ndarray:
    """Per-chip matrices expressed in the board frame, less the rotation common to every chip."""
    R0 = link_frames_on_board(ROWS, COLS)
    Pb = R0 @ P @ np.transpose(R0, (0, 2, 1))
    U, _s, Vt = np.linalg.svd(Pb.mean(axis=0))
    return np.einsum("ji,kjl->kil", U @ Vt, Pb)


def test_the_capture_finds_every_held_pose(captured):
    _imu, _c, cal = captured
    assert len(cal.segments) == 12
    assert all(b - a > 300 for a, b in cal.segments)  # 4 s holds at 145 Hz, less the detector's margins


def test_gyro_bias_and_g_sensitivity_are_recovered_from_the_rests(captured):
    imu, _c, cal = captured
    e = imu.gyro_errors
    # the turn-on bias (0.5 °/s spread) to the bias instability's level (3 °/h = 0.0008 °/s, 3 sigma)
    assert np.degrees(np.abs(cal.gyro.bias_rps - e.bias_rps).max()) < 0.004
    assert np.degrees(np.abs(e.bias_rps).max()) > 0.3
    assert np.degrees(np.abs(cal.gyro.g_sensitivity - e.g_sensitivity).max()) < 0.01  # of 0.1 °/s/g


def test_gyro_scale_cross_axis_and_mounting_are_recovered_from_the_turns(captured):
    imu, _c, cal = captured
    truth = imu.gyro_errors.scale @ np.transpose(imu.accel_errors.misalignment, (0, 2, 1))  # K Mᵀ
    E = _without_common_rotation(cal.gyro.matrix @ truth)  # ≈ I
    assert np.abs(np.diagonal(E, axis1=1, axis2=2) - 1).max() < 2e-4  # scale, of 0.5 % spread
    off = E - np.diagonal(E, axis1=1, axis2=2)[..., None] * np.eye(3)
    assert np.degrees(np.abs(off).max()) < 0.02  # cross-axis and mounting, of 1.25 % and 1.5°
    raw = _without_common_rotation(truth)
    assert np.degrees(np.abs(raw - np.eye(3)).max()) > 1.0  # there was something to find


def test_magnetometer_hard_and_soft_iron_and_its_turn_are_recovered(captured):
    imu, _c, cal = captured
    e = imu.mag_errors
    assert np.abs(cal.mag.hard_iron_t - e.hard_iron_t).max() < 0.2e-6  # of 30 µT spread
    s = np.linalg.svd(cal.mag.correction @ e.distortion, compute_uv=False)
    assert np.abs(s - 1).max() < 0.005  # soft iron, of 2 %
    E = _without_common_rotation(cal.mag.alignment @ cal.mag.correction @ e.distortion)
    assert np.degrees(np.abs(E - np.eye(3)).max()) < 0.3  # mounting, of 1.5°
    np.testing.assert_allclose(np.degrees(cal.mag.dip_rad), 62.0, atol=0.1)
    assert np.all(cal.mag.residual_t < 0.6e-6)  # the noise (0.32-0.41 µT), nothing more


def test_a_world_fixed_disturbance_shows_in_the_fit_residual():
    # steel under the board: the field is no longer uniform; the chips nearest it stand out
    # (or fit no ellipsoid at all: residual inf, parameters NaN), and the rest still calibrates
    env = MagneticField(FIELD, (Dipole((0.005, 0.005, -0.03), (0.0, 0.0, 0.002)),))
    _imu, c = _capture(env, seed=8)
    cal = fit_capture(c["t_s"], c["accel_mps2"], ROWS, COLS, c["gyro_rps"], c["mag_t"], field_t=FIELD.magnitude_t)
    flagged = cal.mag.residual_t > 5 * 0.6e-6
    assert flagged.sum() >= 3
    assert np.all(np.isnan(cal.mag.dip_rad[~np.isfinite(cal.mag.residual_t)]))
    assert np.all(np.isfinite(cal.mag.alignment[np.isfinite(cal.mag.residual_t)]))


def test_coplanar_rests_and_flat_rotations_are_refused():
    g = np.random.Generator(np.random.MT19937(3))
    gyro = g.normal(0, 1e-3, (6, 2, 3))
    f = np.zeros((6, 2, 3))
    f[:, :, 0] = g.normal(0, 9.8, (6, 2))
    f[:, :, 2] = 9.8  # gravity only ever in the x-z plane
    with pytest.raises(ValueError, match="coplanar"):
        fit_gyro_rest(gyro, f)
    ang = np.linspace(0, 2 * np.pi, 50)
    ring = np.stack([np.cos(ang), np.sin(ang), 0 * ang], axis=-1)[:, None, :] * 50e-6  # one axis only
    with pytest.raises(ValueError, match="ellipsoid"):
        fit_mag_ellipsoid(ring)
    with pytest.raises(ValueError, match=r"shape \(N, n_links, 3\)"):
        fit_mag_ellipsoid(ring[:, 0])


def test_segments_and_their_means():
    assert still_segments([1, 1, 0, 1, 1, 1], min_samples=3) == [(3, 6)]
    v = np.arange(12.0).reshape(4, 1, 3)
    np.testing.assert_array_equal(segment_means(v, [(0, 2), (3, 4)]), [[[1.5, 2.5, 3.5]], [[9, 10, 11]]])


def test_turns_with_a_gap_in_their_samples_are_left_out_of_the_scale_fit(captured):
    """A host that stopped sending SYNC for 300 ms in the middle of two of the eleven turns (a loaded
    machine): those turns cannot be integrated from what came, and are left out — the scale is
    recovered from the nine others as well as from all eleven. Integrated across the gaps, the
    fit would carry their lost rotation into the scale: the gyroscopes then read worse than raw
    (capsheet calibrate under load)."""
    imu, c, cal = captured
    segs = cal.segments
    cut = np.zeros(len(c["t_s"]), dtype=bool)
    for k in (3, 7):  # the middle of turns 3 and 7: 300 ms at 145 Hz
        mid = (segs[k][1] + segs[k + 1][0]) // 2
        cut[mid - 22: mid + 22] = True
    keep = ~cut
    gapped = fit_capture(c["t_s"][keep], c["accel_mps2"][keep], ROWS, COLS, c["gyro_rps"][keep], c["mag_t"][keep],
                         field_t=FIELD.magnitude_t)
    assert len(gapped.segments) == 12
    assert (gapped.gyro.turns_used, gapped.gyro.turns_dropped) == (9, 2) and (cal.gyro.turns_used, cal.gyro.turns_dropped) == (11, 0)
    truth = imu.gyro_errors.scale @ np.transpose(imu.accel_errors.misalignment, (0, 2, 1))
    E = _without_common_rotation(gapped.gyro.matrix @ truth)
    assert np.abs(np.diagonal(E, axis1=1, axis2=2) - 1).max() < 2e-4
    # integrated across the gaps (a gap bound longer than they are), the same capture's scale is off
    from host.analysis.imu_calibration import fit_gyro_turns
    segs = list(gapped.segments)
    a, g = c["accel_mps2"][keep], c["gyro_rps"][keep]
    u = gapped.accel.apply(segment_means(a, segs))
    f_chip = (a - gapped.accel.bias) / gapped.accel.scale
    rest = fit_gyro_rest(segment_means(g, segs), segment_means(f_chip, segs))
    spanned = fit_gyro_turns(g, c["t_s"][keep], segs, u / np.linalg.norm(u, axis=-1, keepdims=True), rest, f_chip,
                             max_gap_s=1.0)
    assert spanned.turns_dropped == 0
    E2 = _without_common_rotation(spanned.matrix @ truth)
    assert np.abs(np.diagonal(E2, axis1=1, axis2=2) - 1).max() > 10 * np.abs(np.diagonal(E, axis1=1, axis2=2) - 1).max()


def test_too_few_turns_without_a_gap_is_a_clear_error(captured):
    """Every turn with a gap (a bound shorter than one sample step): nothing to fit the scale
    from — an error naming the gaps, not a matrix fitted from fewer equations than unknowns."""
    from host.analysis.imu_calibration import fit_gyro_turns
    _imu, c, cal = captured
    segs = list(cal.segments)
    u = cal.accel.apply(segment_means(c["accel_mps2"], segs))
    with pytest.raises(ValueError, match=r"0 of 11 turns to fit, need 5 .*11 have a gap of more than 1 ms"):
        fit_gyro_turns(c["gyro_rps"], c["t_s"], segs, u, cal.gyro, max_gap_s=0.001)
    with pytest.raises(ValueError, match=r"4 of 4 turns to fit, need 5 \(2 equations a turn, 9 unknowns a chip\)$"):
        fit_gyro_turns(c["gyro_rps"], c["t_s"], segs[:5], u[:5], cal.gyro)


def _turn_inputs(c: dict, cal):
    """What the command hands `fit_gyro_turns` for the captured board: the held poses, each
    link's gravity direction in them (unit), the chips' specific force, the rest fit."""
    segs = list(cal.segments)
    u = cal.accel.apply(segment_means(c["accel_mps2"], segs))
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    f_chip = (c["accel_mps2"] - cal.accel.bias) / cal.accel.scale
    rest = fit_gyro_rest(segment_means(c["gyro_rps"], segs), segment_means(f_chip, segs))
    return segs, u, f_chip, rest


def _late_syncs(t_s: np.ndarray, late_s: float, seed: int) -> np.ndarray:
    """SYNC times of a host whose SYNCs leave up to ``late_s`` after the instants the chips latched
    their readings at (``t_s``): seeded, uniform. The chips' ``time_us`` is then ``t_s`` minus these."""
    g = np.random.Generator(np.random.MT19937(seed))
    return t_s + g.uniform(0.0, late_s, t_s.shape)


def test_the_turns_are_integrated_over_each_chips_sample_instants_not_the_sync_times(captured):
    """SYNCs sent up to 4 ms late (a loaded host), each chip's record saying with its ``time_us``
    when it latched the reading (docs/protocol.md §16.1): over each chip's instants (the SYNC's
    time plus ``time_us``) the fit is the one over the true instants, exactly; over the SYNC times
    alone the turns' integrals move and the scale misses the bound the true instants meet."""
    from host.analysis.imu_calibration import fit_gyro_turns
    imu, c, cal = captured
    segs, u, f_chip, rest = _turn_inputs(c, cal)
    t = c["t_s"]
    sync = _late_syncs(t, 4e-3, seed=11)
    time_us = np.repeat((t - sync)[:, None], 12, axis=1)  # every chip latched at its instant
    per_chip = fit_gyro_turns(c["gyro_rps"], sync[:, None] + time_us, segs, u, rest, f_chip)
    np.testing.assert_allclose(per_chip.matrix, cal.gyro.matrix, rtol=0, atol=1e-12)
    np.testing.assert_allclose(per_chip.turn_residual, cal.gyro.turn_residual, rtol=0, atol=1e-12)
    truth = imu.gyro_errors.scale @ np.transpose(imu.accel_errors.misalignment, (0, 2, 1))
    at_sync = fit_gyro_turns(c["gyro_rps"], sync, segs, u, rest, f_chip)

    def scale_err(m):
        return np.abs(np.diagonal(_without_common_rotation(m @ truth), axis1=1, axis2=2) - 1).max()
    assert scale_err(cal.gyro.matrix) < 2e-4 < scale_err(at_sync.matrix)


def test_each_chips_own_instants_must_not_go_back(captured):
    from host.analysis.imu_calibration import fit_gyro_turns
    _imu, c, cal = captured
    segs = list(cal.segments)
    u = cal.accel.apply(segment_means(c["accel_mps2"], segs))
    t = np.repeat(c["t_s"][:, None], 12, axis=1)
    t[100, 5] = t[98, 5]  # chip 5's instant goes back
    with pytest.raises(ValueError, match=r"not decreasing per chip"):
        fit_gyro_turns(c["gyro_rps"], t, segs, u, cal.gyro)
    t = np.repeat(c["t_s"][:, None], 12, axis=1)
    t[100, 5] = t[99, 5]  # the same instant twice (a STALE record): nothing added, accepted
    fit_gyro_turns(c["gyro_rps"], t, segs, u, cal.gyro)


def test_a_chip_whose_records_were_lost_in_a_turn_leaves_that_turn_out_alone(captured):
    """Chip 5's records lost for 300 ms in the middle of two of the eleven turns (the command's
    log repeats its last reading and that reading's instant): chip 5 fits its scale from the
    nine others, within the bound, and every other chip still uses all eleven — its fit the one
    of the whole capture, exactly — not the two turns left out for every chip."""
    from host.analysis.imu_calibration import fit_gyro_turns
    imu, c, cal = captured
    segs, u, f_chip, rest = _turn_inputs(c, cal)
    t = np.repeat(c["t_s"][:, None], 12, axis=1)
    g = c["gyro_rps"].copy()
    for k in (3, 7):  # 300 ms at 145 Hz in the middle of turns 3 and 7
        mid = (segs[k][1] + segs[k + 1][0]) // 2
        t[mid - 22: mid + 22, 5] = t[mid - 23, 5]
        g[mid - 22: mid + 22, 5] = g[mid - 23, 5]
    lost = fit_gyro_turns(g, t, segs, u, rest, f_chip)
    assert (lost.turns_used, lost.turns_dropped) == (9, 2)
    others = np.arange(12) != 5
    np.testing.assert_allclose(lost.matrix[others], cal.gyro.matrix[others], rtol=0, atol=1e-12)
    truth = imu.gyro_errors.scale @ np.transpose(imu.accel_errors.misalignment, (0, 2, 1))
    E = _without_common_rotation(lost.matrix @ truth)
    assert np.abs(np.diagonal(E, axis1=1, axis2=2) - 1).max() < 2e-4
    assert np.all(np.isfinite(lost.turn_residual)) and lost.turn_residual[5] < 10 * np.median(lost.turn_residual)


def _scale_err(imu, matrix) -> float:
    """The worst scale error of ``matrix`` against the hidden truth, the common rotation removed."""
    truth = imu.gyro_errors.scale @ np.transpose(imu.accel_errors.misalignment, (0, 2, 1))
    return float(np.abs(np.diagonal(_without_common_rotation(matrix @ truth), axis1=1, axis2=2) - 1).max())


def _read_late_in_turns(c: dict, segs, stall: int, seed: int, turns=None) -> dict:
    """The capture as a stalled sheet delivers it (measured: the 3x3 pty test at load 11-13, its
    virtual chips sampling when their thread read each SYNC, up to 100 ms after the host sent it):
    somewhere in the middle half of every turn (seeded) the chips take no reading for up to ``stall`` samples, then
    catch up at twice the rate — sample ``i`` carries the exact readings of sample ``j(i) >= i``
    but is stated at ``t[i]`` (the host's SYNC time and a ``time_us`` against the late read). No
    instant is missing, so no turn has a gap to leave it out for. ``turns``: only those (default
    every turn)."""
    rng = np.random.Generator(np.random.MT19937(seed))
    j = np.arange(len(c["t_s"]))
    for k in (range(len(segs) - 1) if turns is None else turns):
        a, b = segs[k][1], segs[k + 1][0]
        n = int(rng.integers(0, stall + 1))
        i0 = int(rng.integers(a + (b - a) // 4, b - (b - a) // 4 - 2 * n))
        j[i0: i0 + 2 * n] = i0 + n + np.arange(2 * n) // 2
    return {key: (v if key == "t_s" else v[j]) for key, v in c.items()}


def test_a_scale_fit_the_turns_do_not_vouch_for_is_not_kept(captured):
    """Readings taken up to 100 ms after the instants they are stated at, somewhere in every turn
    (a stalled sheet): the scale fit cannot carry gravity from pose to pose — its turn residual,
    the figure judged by, is above `TURN_MAX_RESIDUAL_RAD` — and is not kept: the bias and
    g-sensitivity are (the rests are whole), the matrix stays the identity, and `gyro_refused` says
    why with the figure. Kept, that scale would miss the 0.1 % target (docs/calibration.md) several
    times over. The exact capture's fit is kept.

    (What the residual cannot see: the same delay at the same place in every turn reads as a scale,
    and is fitted as one — docs/calibration.md.)"""
    from host.analysis.imu_calibration import TURN_MAX_RESIDUAL_RAD
    imu, c, cal = captured
    assert cal.gyro_refused == "" and cal.gyro_rejected is None and cal.gyro.scale_fitted
    assert cal.gyro.turn_residual.max() < TURN_MAX_RESIDUAL_RAD / 10
    late = _read_late_in_turns(c, cal.segments, stall=14, seed=1)  # up to 97 ms at 145 Hz
    judged = fit_capture(late["t_s"], late["accel_mps2"], ROWS, COLS, late["gyro_rps"], late["mag_t"],
                         field_t=FIELD.magnitude_t)
    assert judged.segments == cal.segments  # the rests are untouched: the same held poses
    np.testing.assert_array_equal(judged.gyro.matrix, np.tile(np.eye(3), (12, 1, 1)))
    assert not judged.gyro.scale_fitted and (judged.gyro.turns_used, judged.gyro.turns_dropped) == (0, 0)
    np.testing.assert_allclose(judged.gyro.bias_rps, cal.gyro.bias_rps, rtol=0, atol=1e-15)
    np.testing.assert_allclose(judged.gyro.g_sensitivity, cal.gyro.g_sensitivity, rtol=0, atol=1e-15)
    rejected = judged.gyro_rejected
    # a turn far off the others is left out for its residual, but the stalls are in every turn
    assert rejected.turns_used == 11 - rejected.turns_dropped and rejected.turns_dropped == rejected.turns_rejected
    assert rejected.turns_used >= 8 and rejected.turn_residual.max() > TURN_MAX_RESIDUAL_RAD
    worst = int(np.argmax(rejected.turn_residual))
    assert judged.gyro_refused.startswith("gyroscope scale and cross-axis not fitted (bias and g-sensitivity kept): ")
    assert (f"{np.degrees(rejected.turn_residual[worst]):.2f}° RMS" in judged.gyro_refused
            and f"(link {worst}, {rejected.turns_used} turns; limit 0.20°)" in judged.gyro_refused), judged.gyro_refused
    assert "\n" not in judged.gyro_refused
    # the judgement is right: the scale it did not keep misses the 0.1 % target; the exact one meets it
    assert _scale_err(imu, cal.gyro.matrix) < 2e-4 and _scale_err(imu, rejected.matrix) > 3e-3


def test_one_turn_read_late_is_left_out_and_the_fit_kept(captured):
    """One turn of eleven read up to 100 ms late (the pty test at load ~5 had one such turn:
    0.23° over its ten turns, the scale 0.08 % off): that turn's residual stands out from the
    others', it is left out for every chip (`turns_rejected`) and the scale is fitted from the ten
    others, within the bound of the exact capture — not refused, not spread over the scale.
    Without leaving it out (``outlier_rad`` None) its error goes into the scale."""
    from host.analysis.imu_calibration import TURN_MAX_RESIDUAL_RAD, fit_gyro_turns
    imu, c, cal = captured
    late = _read_late_in_turns(c, cal.segments, stall=14, seed=3, turns=[4])
    judged = fit_capture(late["t_s"], late["accel_mps2"], ROWS, COLS, late["gyro_rps"], late["mag_t"],
                         field_t=FIELD.magnitude_t)
    assert judged.segments == cal.segments and judged.gyro_refused == "" and judged.gyro.scale_fitted
    g = judged.gyro
    assert (g.turns_used, g.turns_dropped, g.turns_rejected) == (10, 1, 1)
    assert g.turn_residual.max() < TURN_MAX_RESIDUAL_RAD / 10 and _scale_err(imu, g.matrix) < 2e-4
    segs, u, f_chip, rest = _turn_inputs(late, judged)
    spread = fit_gyro_turns(late["gyro_rps"], late["t_s"], segs, u, rest, f_chip)
    assert spread.turns_rejected == 0 and _scale_err(imu, spread.matrix) > 5 * _scale_err(imu, g.matrix)


def test_a_gyroscope_fit_from_a_pose_that_was_not_still_is_not_kept(captured):
    """The board turned about the vertical at 0.3 °/s through one held pose (a hand that held it
    drifting): no accelerometer sees a turn about gravity, so the pose is found still as before,
    but its mean rate is not the bias. The rest residual, the figure judged by, is above
    `REST_MAX_RESIDUAL_RPS`: no gyroscope fit is kept, and `gyro_refused` says why with the
    figure. Kept, its bias would miss the fit's 0.01 °/s target several times over; the exact
    capture's is kept."""
    from host.analysis.imu_calibration import REST_MAX_RESIDUAL_RPS
    imu, c, cal = captured
    assert cal.gyro.rest_residual_rps.max() < REST_MAX_RESIDUAL_RPS / 10
    a0, b0 = cal.segments[5]
    g = c["gyro_rps"].copy()
    f = c["accel_mps2"][a0 - 100: b0 + 100]  # the pose, while the board holds it (its turns excepted)
    g[a0 - 100: b0 + 100] += np.radians(0.3) * f / np.linalg.norm(f, axis=-1, keepdims=True)
    judged = fit_capture(c["t_s"], c["accel_mps2"], ROWS, COLS, g, c["mag_t"], field_t=FIELD.magnitude_t)
    assert judged.segments == cal.segments and judged.mag is not None
    assert judged.gyro is None
    rejected = judged.gyro_rejected
    worst = int(np.argmax(rejected.rest_residual_rps))
    assert rejected.rest_residual_rps[worst] > REST_MAX_RESIDUAL_RPS
    assert judged.gyro_refused.startswith("gyroscope not fitted: the held poses' mean rates miss the fitted bias ")
    assert (f"by {np.degrees(rejected.rest_residual_rps[worst]):.3f} °/s RMS (link {worst}; limit 0.020 °/s)"
            in judged.gyro_refused), judged.gyro_refused
    # the judgement is right: that bias misses the 0.01 °/s target (the exact capture's is within 0.004)
    assert np.degrees(np.abs(rejected.bias_rps - imu.gyro_errors.bias_rps).max()) > 0.025


def test_held_poses_are_cut_to_where_the_gyroscopes_are_still(captured):
    """A stillness detector loose enough for noisy accelerometers (0.3 m/s², 3x the usual) takes
    the turns' slow ends into the held poses, where the board already turns: their rates went into
    the bias. The gyroscopes see it: every pose is cut to where the chips' rates stay within
    `REST_MAX_RATE_RPS` of its median, and the bias is the one the usual detector gives. Without
    the cut, the rest residual shows the ends and the fit is not kept."""
    imu, c, cal = captured
    args = (c["t_s"], c["accel_mps2"], ROWS, COLS, c["gyro_rps"])
    loose = fit_capture(*args, threshold_mps2=0.3)
    assert len(loose.segments) == 12 and loose.gyro_refused == "" and loose.gyro.scale_fitted
    assert np.degrees(np.abs(loose.gyro.bias_rps - imu.gyro_errors.bias_rps).max()) < 0.004
    uncut = fit_capture(*args, threshold_mps2=0.3, max_rest_rate_rps=np.inf)
    assert uncut.gyro is None and uncut.gyro_refused.startswith("gyroscope not fitted: the held poses' mean rates")
    assert np.degrees(np.abs(uncut.gyro_rejected.bias_rps - imu.gyro_errors.bias_rps).max()) > 0.01
