"""The fused estimator beside a magnet and with links missing (host.analysis.motion): the sheet's
heading held by its links' robust mode, the groups a disturbance leaves to the loops, and links
back from a gap. Simulated from known truth as test_motion_estimator.py's; bench_motion.py has the
14x14 figures on calibrated chips."""

from __future__ import annotations

import dataclasses

import numpy as np

from host.analysis.metrics import error_percent_of_side
from host.analysis.motion import FusedConfig, MotionEstimator, fused
from host.analysis.motion._linalg import robust_mode
from virtual_sheet.magfield import MagneticField, quarter_disturbance
from virtual_sheet.motion import make_motion_scene

from .test_motion_estimator import EARTH, TOLD, L, chips, heading_error_deg, mean_error, record, run_fused


def test_the_robust_mode_is_not_pulled_by_values_a_disturbance_turns_a_little():
    # 100 links that agree (0 ± 0.1°) and 70 a disturbance turns by 0.8-3° one way: their mean
    # goes with the disturbed ones, the biweight's mode (from the weighted median, or from a start
    # near it, as the estimator's last mode) stays with the ones that agree
    g = np.random.Generator(np.random.MT19937(5))
    r = np.radians(np.concatenate([g.normal(0.0, 0.1, 100), -g.uniform(0.8, 3.0, 70)]))
    w = np.ones(r.size)
    assert np.degrees(np.mean(r)) < -0.5
    assert abs(np.degrees(robust_mode(r, w, np.radians(0.75)))) < 0.05
    assert abs(np.degrees(robust_mode(r, w, np.radians(0.75), start=np.radians(-0.4)))) < 0.05
    # weights: the ones that agree weighted out, the mode moves to the others
    assert np.degrees(robust_mode(r, np.where(np.arange(r.size) < 100, 0.0, 1.0),
                                  np.radians(0.75))) < -0.5
    assert robust_mode(r, np.zeros(r.size), np.radians(0.75)) is None
    # the check can fail: a width that takes every value in gives the mean
    assert np.degrees(robust_mode(r, w, np.radians(30.0))) < -0.5


def test_beside_a_magnet_the_heading_follows_the_links_that_agree_and_the_shape_the_loops():
    # a curved sheet carried over the bench's magnet (under a quarter: it turns the field by more
    # than 0.5° at most links, smoothly, so the field tests leave the magnetometers ~2 % of
    # their weight and the heading is held): 14x14, 3 s
    n = 14
    field = MagneticField(EARTH, (quarter_disturbance(n, n, L),))
    truth, rd = record(make_motion_scene("carry", n, n, L), chips(n, mag=True, field=field), 3.0)

    def heading_last_second(config):
        est = run_fused(n, rd, config=config)
        last = range(len(est) - 145, len(est))
        return est, float(np.mean([abs(heading_error_deg(est[k].frames, truth.frames[k]))
                                   for k in last]))

    # without the magnet's fitted field taken out (`_dipole`), the mode alone
    no_fit = dataclasses.replace(TOLD, dipole_significance=0.0)
    est, head = heading_last_second(no_fit)
    assert head <= 0.3, head
    # the shape is the loops' where the magnetometers are not trusted: no worse than without them
    e_mag = mean_error([e.joints for e in est], truth).mean()
    e_none = mean_error([e.joints for e in run_fused(n, rd, mag=False)], truth).mean()
    assert e_mag <= 1.05 * e_none + 0.005, (e_mag, e_none)
    # the check can fail: held by the gyroscopes alone the heading stays the first snapshot's
    _est, held = heading_last_second(dataclasses.replace(no_fit, heading_mode_rad=0.0))
    assert held > 0.6, held


def test_links_back_from_a_gap_take_their_tilt_from_their_accelerometers(monkeypatch):
    # half of an 8x8 waved sheet (the wave turns its links at up to 800 °/s) missing for 0.6 s:
    # carried by the sheet's mean rate they are far off when they return; their tilt variance
    # grew with the sheet's rate spread, so their accelerometers set them again within a second
    n = 8
    truth, rd = record(make_motion_scene("wave", n, n, L), chips(n), 3.0)
    n_links = 2 * n * (n - 1)

    def last_half_second():
        est = MotionEstimator(n, n, L, config=TOLD)
        errs = []
        for k in range(rd.t_s.size):
            v = np.ones(n_links, bool)
            if 1.0 <= rd.t_s[k] < 1.6:
                v[n_links // 2:] = False
            e = est.update(rd.t_s[k], rd.accel_mps2[k], rd.gyro_rps[k], valid=v)
            errs.append(error_percent_of_side(e.joints, truth.joints[k], L).mean())
        return float(np.mean(np.array(errs)[rd.t_s >= rd.t_s[-1] - 0.5]))

    assert last_half_second() <= 0.1
    # the check can fail: without the grown variance the returned links stay off
    monkeypatch.setattr(fused, "_MISSING_MAX_RAD", 0.0)
    assert last_half_second() > 1.0


def test_the_shared_gyroscope_bias_is_told_apart_from_each_chips_own():
    cfg = FusedConfig(gyro_bias_std_rps=1e-4, gyro_common_bias_std_rps=1e-3)
    est = MotionEstimator(3, 3, L, config=cfg)
    level = np.tile([0.0, 0.0, 9.80665], (12, 1))
    est.update(0.0, level, np.zeros((12, 3)))
    assert np.allclose(est.P[:, 3, 3], 1e-8)  # each chip's own
    assert np.allclose(est._common.C[2, 2], 1e-6)  # the sheet's common tilt rate
    same = MotionEstimator(3, 3, L, config=FusedConfig(gyro_bias_std_rps=1e-4))
    same.update(0.0, level, np.zeros((12, 3)))
    assert np.allclose(same._common.C[2, 2], 1e-8)  # None: the chips' own figure
    for bad in (-1e-3, float("nan")):
        try:
            FusedConfig(gyro_common_bias_std_rps=bad)
        except ValueError as exc:
            assert "gyro_common_bias_std_rps" in str(exc)
        else:
            raise AssertionError(f"accepted {bad}")
