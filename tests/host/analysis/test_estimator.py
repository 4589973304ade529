"""Shape estimator, ahrs style: simulate from known truth, state the metric and the tolerance.

Truth: exact Chebyshev nets from the virtual sheet (`virtual_sheet.shapes.make_sheet`, 14x14
joints, L = 1 cm), noise-free readings from `virtual_sheet.geometry.ideal_readings`, white noise from
`virtual_sheet.sensor.noisy_readings` (seeded MT19937). Metric: the paper's (section 3.3) — mean
per-joint distance after a least-squares rigid overlay, in % of the side length (cols-1)*L
(`host.estimator.error_percent_of_side`), averaged over a few trials.

Bounds are the measured values with margin (measured at commit time, 3 trials, seed 42):
global, 0.3 % g: gaussian 0.06, sphere 0.05, saddle 0.05, cylinder 0.03;
global, 5 % g: gaussian 0.48, sphere 0.53, saddle 0.57, cylinder 0.50.
"""

from __future__ import annotations

import numpy as np
import pytest

from host.analysis import estimator as E
from host.estimator import error_percent_of_side, estimate, overlay_error
from protocol.constants import G0
from protocol.lattice import Lattice
from virtual_sheet.geometry import ideal_readings, roll_pitch
from virtual_sheet.sensor import noisy_readings
from virtual_sheet.shapes import make_sheet

ROWS = COLS = 14
L = 0.01
TRIALS = 3


def rng(seed: int = 42) -> np.random.Generator:
    return np.random.Generator(np.random.MT19937(seed))


def mean_error(shape: str, noise_pct_g: float, method: str = "global", trials: int = TRIALS,
               seed: int = 42, valid=None) -> float:
    P = make_sheet(shape, ROWS, COLS, L)
    r0 = ideal_readings(P)
    g = rng(seed)
    errs = [error_percent_of_side(estimate(noisy_readings(r0, noise_pct_g, g), ROWS, COLS, L,
                                           valid=valid, method=method).joints, P, L).mean()
            for _ in range(trials)]
    return float(np.mean(errs))


# --- accuracy: the targets and the other shapes ----------------------------------------

@pytest.mark.parametrize("shape, noise, bound", [
    ("gaussian", 5.0, 1.0),   # issue target: <= 1 % of side at 5 % g
    ("gaussian", 0.3, 0.2),   # issue target: <= 0.2 % at 0.3 % g (a real MEMS part)
    ("sphere", 5.0, 1.0),
    ("sphere", 0.3, 0.15),
    ("saddle", 5.0, 1.0),
    ("saddle", 0.3, 0.15),
    ("cylinder", 5.0, 1.0),
    ("cylinder", 0.3, 0.15),
    ("flat", 1.0, 0.15),      # Case 1 everywhere: the prior keeps the rest layout
])
def test_global_mean_joint_error_within_bound(shape, noise, bound):
    assert mean_error(shape, noise) <= bound


def test_noise_free_exact_net_error_is_small_but_not_zero_on_curved_shapes():
    # the normal assumption (eq. 6) is only approximate on a curved net
    err = mean_error("gaussian", 0.0, trials=1)
    assert 0.0 < err <= 0.1


def test_global_beats_paper_on_the_same_data():
    P = make_sheet("gaussian", ROWS, COLS, L)
    r0 = ideal_readings(P)
    g = rng(7)
    for noise in (0.3, 1.0):
        r = noisy_readings(r0, noise, g)
        e_glob = error_percent_of_side(estimate(r, ROWS, COLS, L).joints, P, L).mean()
        e_pap = error_percent_of_side(estimate(r, ROWS, COLS, L, method="paper").joints, P, L).mean()
        assert e_glob <= e_pap


def test_paper_method_reproduces_a_noise_free_cylinder():
    # developable, every unit a parallelogram: eq. (4) and (6) hold exactly, chaining is exact
    assert mean_error("cylinder", 0.0, method="paper", trials=1) <= 0.01


# --- solvability (eq. 7) ----------------------------------------------------------------------

def test_flat_sheet_is_unsolvable_everywhere():
    est = estimate(ideal_readings(make_sheet("flat", ROWS, COLS, L)), ROWS, COLS, L)
    assert est.solvability.shape == (ROWS - 1, COLS - 1)
    assert np.all(est.solvability < 0.1)


@pytest.mark.parametrize("fold, roll, pitch", [(0.0, 0.0, 0.0), (1.0, 0.7, np.pi / 2),
                                               (2.5, 2.0, np.pi / 2), (1.0, 0.7, 1.49)])
def test_fully_squashed_unit_is_unsolvable(fold, roll, pitch):
    # Case 2: corner angle 0 (all four links parallel), lying flat or pitched up towards vertical
    # (where the Fig. 8 grid finds it). Built by host.cli.paper's Fig. 8 unit construction;
    # readings -> estimate -> solvability.
    from host.cli.paper import unit_angles
    alpha, beta = unit_angles(0.0, fold, roll, pitch)
    reading = G0 * np.stack([-np.sin(beta), np.cos(beta) * np.sin(alpha),
                             np.cos(beta) * np.cos(alpha)], -1)
    lat = Lattice(2, 2)
    r = np.empty((lat.n_links, 3))
    r[lat.units[0, 0]] = reading
    est = estimate(r, 2, 2, L)
    assert est.solvability.shape == (1, 1)
    assert est.solvability[0, 0] < 0.1


def test_squashed_unit_tilted_is_not_flagged_by_the_eq7_ratio():
    # Finding, not a wish: at a generic tilt eq. (7)'s 4x6 matrix keeps rank 4 for a squashed unit
    # (its yaws are still underdetermined: z1 = z2 = any unit complex number solves (4) and (6)),
    # so lambda3/lambda1 misses Case 2 away from theta_p in {0, pi/2}. See host.cli.paper / README.
    from host.cli.paper import unit_angles
    alpha, beta = unit_angles(0.0, 0.0, 0.3, 0.4)
    assert E._solvability_units(alpha, beta) > 0.1


def test_curved_shapes_are_mostly_solvable():
    est = estimate(ideal_readings(make_sheet("saddle", ROWS, COLS, L)), ROWS, COLS, L)
    assert np.median(est.solvability) > 0.1


def test_solvability_equals_svd_of_the_eq7_matrix():
    g = rng(3)
    a = g.uniform(-np.pi, np.pi, (50, 4))
    b = g.uniform(-np.pi / 2, np.pi / 2, (50, 4))
    s = np.linalg.svd(E._eq7_matrices(a, b), compute_uv=False)
    np.testing.assert_allclose(E._solvability_units(a, b), s[:, 2] / s[:, 0], atol=1e-12)


# --- angles, overlay ------------------------------------------------------------------------------

def test_roll_pitch_agrees_with_virtual_sheet():
    r = noisy_readings(ideal_readings(make_sheet("sphere", ROWS, COLS, L)), 2.0, rng(1))
    for mine, theirs in zip(E.roll_pitch(r), roll_pitch(r)):
        np.testing.assert_allclose(mine, theirs, atol=1e-12)


def test_overlay_removes_rotation_and_translation():
    P = make_sheet("gaussian", ROWS, COLS, L)
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    Q = P @ R.T + np.array([0.1, -0.2, 0.3])
    assert overlay_error(Q, P).max() < 1e-12


def test_estimate_is_defined_up_to_yaw_and_anchored_at_joint_00():
    P = make_sheet("saddle", ROWS, COLS, L)
    est = estimate(ideal_readings(P), ROWS, COLS, L)
    np.testing.assert_allclose(est.joints[0, 0], 0.0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(est.directions, axis=1), 1.0, atol=1e-12)
    # link lengths of the estimate stay close to L (least squares over consistent directions)
    lengths = np.linalg.norm(Lattice(ROWS, COLS).link_vectors(est.joints), axis=1)
    assert np.max(np.abs(lengths / L - 1)) < 0.05


# --- warm start --------------------------------------------------------------------------------

def test_warm_start_keeps_accuracy_and_reuses_the_factorisation():
    P = make_sheet("gaussian", ROWS, COLS, L)
    r0 = ideal_readings(P)
    g = rng(11)
    est = estimate(noisy_readings(r0, 1.0, g), ROWS, COLS, L)
    errs, facts = [], []
    for _ in range(10):
        est = estimate(noisy_readings(r0, 1.0, g), ROWS, COLS, L, previous=est)
        errs.append(error_percent_of_side(est.joints, P, L).mean())
        facts.append(est.factorisations)
    assert np.mean(errs) <= 0.2
    assert sum(facts) <= 3  # static shape: the first snapshot's factorisation keeps serving


def test_long_warm_started_run_on_a_flat_sheet_does_not_drift():
    # Case 1 everywhere: nothing in the data fixes the horizontal layout; the prior's target must
    # not be the previous estimate alone, or the layout random-walks (0.05 -> 0.22 % in 3000)
    P = make_sheet("flat", ROWS, COLS, L)
    r0 = ideal_readings(P)
    g = rng(13)
    est, errs = None, []
    for _ in range(400):
        est = estimate(noisy_readings(r0, 1.0, g), ROWS, COLS, L, previous=est)
        errs.append(error_percent_of_side(est.joints, P, L).mean())
    assert np.mean(errs[-100:]) <= 0.1  # measured 0.045, as in the first 100


# --- missing links -----------------------------------------------------------------------------

def test_missing_links_still_give_a_shape_within_bound():
    n = Lattice(ROWS, COLS).n_links
    valid = np.ones(n, bool)
    valid[rng(5).choice(n, size=n // 20, replace=False)] = False  # 5 % of the links missing
    err = mean_error("gaussian", 1.0, valid=valid)
    assert err <= 0.5  # measured 0.28 with these 18 links missing (0.11 with none), 1 % g
    est = estimate(ideal_readings(make_sheet("gaussian", ROWS, COLS, L)), ROWS, COLS, L,
                   valid=valid)
    assert np.all(np.isfinite(est.joints))
    assert np.all(np.isnan(est.normals[~valid]))
    assert np.all(np.isnan(est.solvability[np.isin(Lattice(ROWS, COLS).units, np.flatnonzero(~valid)).any(-1)]))


def test_missing_link_readings_are_ignored_even_if_garbage():
    P = make_sheet("sphere", ROWS, COLS, L)
    r = ideal_readings(P)
    valid = np.ones(len(r), bool)
    valid[[3, 200]] = False
    r_bad = r.copy()
    r_bad[~valid] = np.nan
    a = estimate(r, ROWS, COLS, L, valid=valid).joints
    b = estimate(r_bad, ROWS, COLS, L, valid=valid).joints
    np.testing.assert_array_equal(a, b)


# --- errors ------------------------------------------------------------------------------------

def test_wrong_readings_shape_names_expected_and_got():
    with pytest.raises(ValueError, match=r"\(364, 3\).*\(363, 3\)"):
        estimate(np.zeros((363, 3)), ROWS, COLS, L)


def test_wrong_valid_shape_names_expected_and_got():
    with pytest.raises(ValueError, match=r"\(364,\).*\(10,\)"):
        estimate(np.zeros((364, 3)) + [0, 0, G0], ROWS, COLS, L, valid=np.ones(10, bool))


def test_all_invalid_mask_is_a_clear_error():
    with pytest.raises(ValueError, match="No valid link"):
        estimate(np.zeros((364, 3)), ROWS, COLS, L, valid=np.zeros(364, bool))


def test_previous_of_another_lattice_is_rejected():
    prev = estimate(ideal_readings(make_sheet("flat", 4, 4, L)), 4, 4, L)
    with pytest.raises(ValueError, match=r"\(14, 14, 3\).*\(4, 4, 3\)"):
        estimate(ideal_readings(make_sheet("flat", ROWS, COLS, L)), ROWS, COLS, L, previous=prev)


def test_unknown_method_and_paper_with_mask_are_rejected():
    r = ideal_readings(make_sheet("flat", 4, 4, L))
    with pytest.raises(ValueError, match="method"):
        estimate(r, 4, 4, L, method="magic")
    valid = np.ones(len(r), bool)
    valid[0] = False
    with pytest.raises(ValueError, match="paper"):
        estimate(r, 4, 4, L, valid=valid, method="paper")


def test_overlay_shape_mismatch_is_rejected():
    with pytest.raises(ValueError, match="same shape"):
        overlay_error(np.zeros((3, 3, 3)), np.zeros((3, 4, 3)))
