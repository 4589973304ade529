"""The paper's estimator (host/analysis/paper_method.py): eq. (8) per unit by steepest descent from
several starts, the units combined into the sheet, every open choice an option.

Truth: exact Chebyshev nets (`virtual_sheet.shapes`) and single units built by Fig. 8's
construction (`host.cli.paper.unit_state`); metric: the paper's, % of the side after the overlay.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from host.analysis import paper_method as pm
from host.analysis.estimator import error_percent_of_side, estimate, roll_pitch
from protocol.lattice import Lattice
from virtual_sheet.geometry import ideal_readings, link_angles
from virtual_sheet.shapes import make_sheet

N, L = 8, 0.01


def _wrap(x):
    return (np.asarray(x) + np.pi) % (2 * np.pi) - np.pi


@pytest.mark.parametrize("combine", pm.COMBINE)
@pytest.mark.parametrize("joints", pm.JOINTS)
@pytest.mark.parametrize("shape, kw", [("cylinder", {}),
                                       ("tilted", {"shear": 0.3})])
def test_every_reading_recovers_a_sheet_whose_units_are_planar(combine, joints, shape, kw):
    # every unit a planar parallelogram (a cylinder's cells along its rulings; a tilted, sheared
    # flat sheet): eq. (4) and (6) hold exactly, so every way of solving and combining the units
    # must give the net back, rhombi as well as squares
    P = make_sheet(shape, N, N, L, **kw)
    est = estimate(ideal_readings(P), N, N, L, method="paper",
                   paper_options=pm.PaperOptions(combine=combine, joints=joints))
    assert error_percent_of_side(est.joints, P, L).max() < 1e-5
    assert est.method == "paper" and np.isfinite(est.residual)


def test_a_unit_solved_from_the_square_start_has_the_true_relative_yaws():
    from host.cli.paper import unit_state

    # generic units near the square (Fig. 8's construction): corner, fold, roll, pitch
    states = np.array([[1.2, 0.4, 0.3, 0.5], [1.8, 0.3, 0.2, 0.3], [1.5, 0.6, 0.1, 0.8]])
    a, b, g = unit_state(*states.T)
    # one 2x2-joint lattice per unit: its links are the unit's (Lattice.units numbering)
    lat = Lattice(2, 2)
    order = lat.units[0, 0]  # link index of slots 0..3
    for k in range(len(states)):
        alpha, beta = np.empty(4), np.empty(4)
        alpha[order], beta[order] = a[k], b[k]
        delta, P, steps = pm.unit_yaws(alpha, beta, 2, 2, pm.PaperOptions(n_starts=1))
        np.testing.assert_allclose(_wrap(delta[0, 0] - (g[k] - g[k, 0])), 0.0, atol=1e-5)
        assert P[0, 0] < 1e-12  # a planar-normal unit of Fig. 8: eq. (6) holds exactly


def test_the_start_kept_is_the_first_acceptable_or_the_smallest():
    P = np.array([[0.5, 0.05, 0.01, 0.2],   # first <= 0.1 is start 1, though 2 is smaller
                  [0.3, 0.2, 0.4, 0.15],    # none acceptable: the smallest, start 3
                  [0.02, 0.0, 0.0, 0.0]])   # the square (start 0) is acceptable: kept
    first = pm._select(P, pm.PaperOptions(select="first", accept=0.1))
    assert first.tolist() == [1, 3, 0]
    assert pm._select(P, pm.PaperOptions(select="min")).tolist() == [2, 3, 1]
    assert pm._select(P, pm.PaperOptions(select="first", accept=0.0)).tolist() == [2, 3, 1]


@pytest.mark.parametrize("combine", ["sync", "tree"])
def test_combining_rotated_unit_solutions_gives_the_yaws_back(combine):
    # each unit's relative yaws as a unit solve returns them (link 0 at 0): the combination must
    # undo every unit's unknown rotation and give the sheet's yaws up to one gauge
    P = make_sheet("gaussian", N, N, L, shear=0.1)
    gamma = link_angles(P)[2]
    units = Lattice(N, N).units
    delta = _wrap(gamma[units] - gamma[units][..., :1])
    got = (pm._combine_sync if combine == "sync" else pm._combine_tree)(delta, N, N)
    gauge = _wrap(got[units[0, 0, 0]] - gamma[units[0, 0, 0]])
    np.testing.assert_allclose(_wrap(got - gamma - gauge), 0.0, atol=1e-12)


def test_sync_spreads_one_wrong_unit_where_the_tree_carries_it_on():
    P = make_sheet("gaussian", N, N, L)
    gamma = link_angles(P)[2]
    units = Lattice(N, N).units
    delta = _wrap(gamma[units] - gamma[units][..., :1])
    bad = delta.copy()
    bad[0, 1, 1] += 0.5  # one unit of the first row wrong on the link it shares with (0, 2)
    err = {}
    for name, fn in (("sync", pm._combine_sync), ("tree", pm._combine_tree)):
        got = fn(bad, N, N)
        d, _ = pm.directions_normals(*roll_pitch(ideal_readings(P)), got)
        err[name] = error_percent_of_side(pm.place_joints(L * d, N, N), P, L).mean()
    assert err["sync"] < err["tree"] / 2


def test_estimate_dispatches_the_options_and_rejects_them_for_the_global_method():
    P = make_sheet("gaussian", N, N, L)
    r = ideal_readings(P) + np.random.Generator(np.random.MT19937(3)).normal(0, 0.3, (Lattice(N, N).n_links, 3))
    sync = estimate(r, N, N, L, method="paper")
    chain = estimate(r, N, N, L, method="paper", paper_options=pm.PaperOptions(combine="chain"))
    assert np.abs(sync.joints - chain.joints).max() > 1e-6  # the option reached the solver
    again = estimate(r, N, N, L, method="paper", paper_options=pm.PaperOptions())
    np.testing.assert_array_equal(sync.joints, again.joints)  # the defaults are the defaults
    with pytest.raises(ValueError, match="paper_options"):
        estimate(r, N, N, L, paper_options=pm.PaperOptions())
    with pytest.raises(ValueError, match="paper_options"):
        estimate(r, N, N, L, method="paper", paper_options={"combine": "chain"})


@pytest.mark.parametrize("field, value", [("combine", "stitch"), ("starts", "grid"),
                                          ("select", "best"), ("joints", "spline"),
                                          ("n_starts", 0), ("max_iter", 0), ("n_starts", 2.5),
                                          ("accept", -1.0), ("accept", float("nan")),
                                          ("seed", -1), ("n_starts", True)])
def test_options_validate_themselves(field, value):
    with pytest.raises(ValueError, match=field):
        pm.PaperOptions(**{field: value})


def test_the_defaults_are_the_ones_docs_estimator_md_names():
    # docs/estimator.md section 7 measures every alternative against exactly these
    assert dataclasses.asdict(pm.PaperOptions()) == {
        "combine": "sync", "starts": "parallelogram", "n_starts": 6, "select": "first",
        "accept": 0.1, "max_iter": 300, "joints": "lsq", "seed": 2008}
