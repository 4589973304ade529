"""Virtual foam: force balance, the Winkler limit, monotone depth, a conforming contact surface,
exact link lengths on the indented bodies. Tolerances are stated per test."""

import numpy as np
import pytest

from host.analysis.tactile import Foam
from virtual_sheet.foam import (CapsuleIndenter, FlatPunch, FoamBlock, FoamCylinder, FoamLayer,
                                FoamScene, FoamSphere, Press, RectPunch, SphereIndenter)
from virtual_sheet.geometry import link_lengths

L = 0.01
INDENTERS = [SphereIndenter(0.015), FlatPunch(0.0075), CapsuleIndenter(0.008, 0.012, 0.4),
             RectPunch(0.015, 0.004, -0.3)]


@pytest.mark.parametrize("ind", INDENTERS, ids=lambda i: i.kind)
def test_force_balance_winkler_integral_equals_set_force(ind):
    layer = FoamLayer()
    sc = FoamScene(FoamBlock(layer), [Press(ind, (0.004, -0.003), 1.7)], 14, 14, L)
    d = sc.deflection(0.0)
    k = layer.k_pa_per_m
    assert d.pressure.sum() * d.step_m ** 2 == pytest.approx(1.7, rel=1e-9)
    assert d.force_n(k) == pytest.approx(1.7, rel=1e-9)  # k ∫ w dA = F (shear term integrates out)
    assert d.w.min() > -1e-3 * d.w.max()  # no upward bulge beyond FFT ringing


@pytest.mark.parametrize("ind", INDENTERS, ids=lambda i: i.kind)
def test_surface_touches_the_indenter_where_pressed_and_stays_below_it(ind):
    sc = FoamScene(FoamBlock(), [Press(ind, (0.0, 0.0), 1.5)], 14, 14, L)
    d = sc.deflection(0.0)
    delta = d.depths_m[0]
    U, V = np.meshgrid(d.u, d.v, indexing="ij")
    g = ind.profile(U, V)
    touch = d.pressure > 0
    assert np.max(np.abs(d.w[touch] - (delta - g[touch]))) < 0.02 * delta
    free = np.isfinite(g) & ~touch
    assert np.all(d.w[free] >= delta - g[free] - 0.02 * delta)


@pytest.mark.parametrize("ind", INDENTERS, ids=lambda i: i.kind)
def test_without_spreading_the_solver_gives_winklers_closed_form_depth(ind):
    layer = FoamLayer(spreading=False)
    sc = FoamScene(FoamBlock(layer), [Press(ind, (0.0, 0.0), 1.0)], 6, 6, L, grid_step_m=L / 25)
    depth = sc.deflection(0.0).depths_m[0]
    # grid discretisation of the contact edge: 3 % on flat faces, 1 % on curved tips
    assert depth == pytest.approx(ind.depth_from_force(layer.k_pa_per_m, 1.0), rel=0.03)


@pytest.mark.parametrize("ind", INDENTERS[:2], ids=lambda i: i.kind)
def test_depth_grows_with_force(ind):
    presses = [Press(ind, (0.0, 0.0), 3.0, t_on_s=0.0, ramp_s=1.0)]
    sc = FoamScene(FoamBlock(), presses, 10, 10, L)
    depths = [sc.contacts(t)[0].depth_m for t in (0.2, 0.4, 0.6, 0.8, 1.0)]
    assert np.all(np.diff(depths) > 0)
    assert depths[0] > 0


def test_two_indenters_keep_their_own_forces():
    presses = [Press(SphereIndenter(0.015), (-0.02, 0.0), 1.0),
               Press(FlatPunch(0.0075), (0.02, 0.0), 2.0)]
    sc = FoamScene(FoamBlock(), presses, 14, 14, L)
    d = sc.deflection(0.0)
    U, _ = np.meshgrid(d.u, d.v, indexing="ij")
    dA = d.step_m ** 2
    assert d.pressure[U < 0].sum() * dA == pytest.approx(1.0, rel=1e-6)
    assert d.pressure[U > 0].sum() * dA == pytest.approx(2.0, rel=1e-6)


def test_press_release_schedule():
    p = Press(SphereIndenter(0.01), (0.0, 0.0), 2.0, t_on_s=1.0, t_off_s=3.0, ramp_s=0.5,
              velocity_mps=(0.01, 0.0))
    assert p.force_at(0.5) == 0.0 and p.force_at(2.0) == 2.0 and p.force_at(4.0) == 0.0
    assert 0 < p.force_at(1.25) < 2.0
    assert p.position_at(2.0)[0] == pytest.approx(0.01)


@pytest.mark.parametrize("body", [FoamBlock(), FoamCylinder(0.08), FoamSphere(0.1)],
                         ids=["block", "cylinder", "sphere"])
def test_sheet_on_indented_body_keeps_link_lengths(body):
    sc = FoamScene(body, [Press(SphereIndenter(0.015), (0.01, 0.005), 2.0)], 10, 10, L)
    P, R = sc.joints(0.0), sc.rest_joints
    assert np.max(np.abs(link_lengths(P) / L - 1)) < 1e-8
    assert np.max(np.abs(link_lengths(R) / L - 1)) < 1e-8
    dz = np.einsum("ijk,k->ij", R - P, [0, 0, 1.0])
    assert dz.max() > 0.5 * sc.contacts(0.0)[0].depth_m  # the dent shows in the sheet


def test_host_and_virtual_foam_agree_on_the_model():
    layer, foam = FoamLayer(0.025, 15e3, 0.3), Foam(0.025, 15e3, 0.3)
    assert foam.k_pa_per_m == pytest.approx(layer.k_pa_per_m, rel=1e-12)
    assert foam.shear_length_m == pytest.approx(layer.shear_length_m, rel=1e-12)
    assert FoamLayer(poisson=0.0).k_pa_per_m == pytest.approx(20e3 / 0.02)  # E_oed = E at ν = 0


def test_curved_layer_is_softer_by_the_columns_taper():
    """A foam column on a curved core narrows towards it: k = E_oed / ∫ ds / ((1-κ1 s)(1-κ2 s)),
    closed forms R h / (R - h) (sphere) and R ln(R / (R - h)) (cylinder)."""
    from virtual_sheet.foam import column_compliance, oedometric_modulus
    h, R = 0.02, 0.08
    assert column_compliance(h) == pytest.approx(h, rel=1e-14)
    assert column_compliance(h, 1 / R, 1 / R) == pytest.approx(R * h / (R - h), rel=1e-12)
    assert column_compliance(h, 1 / R, 0.0) == pytest.approx(R * np.log(R / (R - h)), rel=1e-12)
    e_oed = oedometric_modulus(20e3, 0.25)
    assert FoamSphere(R).contact_layer.k_pa_per_m == pytest.approx(e_oed * (R - h) / (R * h))
    assert FoamBlock().contact_layer.k_pa_per_m == pytest.approx(e_oed / h)
    with pytest.raises(ValueError, match="curvature"):
        FoamLayer(curvature_m_inv=(60.0, 0.0))  # 1/κ = 1.7 cm < h
    with pytest.raises(ValueError, match="radius_m"):
        FoamSphere(0.015)


@pytest.mark.parametrize("body", [FoamCylinder(0.08), FoamSphere(0.1)], ids=["cylinder", "sphere"])
def test_force_balance_on_a_curved_body_uses_its_softer_layer(body):
    sc = FoamScene(body, [Press(SphereIndenter(0.015), (0.0, 0.0), 2.0)], 10, 10, L)
    d = sc.deflection(0.0)
    assert d.force_n(sc.layer.k_pa_per_m) == pytest.approx(2.0, rel=1e-9)
    assert d.force_n(body.layer.k_pa_per_m) > 2.2  # the flat layer's k would read 14-25 % high


def test_host_reads_the_curvature_the_virtual_body_has():
    from host.analysis.tactile import RestShape
    for body, want in [(FoamBlock(), (0.0, 0.0)), (FoamCylinder(0.08), (12.5, 0.0)),
                       (FoamSphere(0.1), (10.0, 10.0))]:
        rest = RestShape.from_joints(FoamScene(body, [], 12, 12, L).rest_joints, L)
        got = np.median(rest.curvatures.reshape(-1, 2), axis=0)
        assert got == pytest.approx(want, abs=0.03 * max(want[0], 1.0))
        k_host = np.median(Foam().k_at(rest.curvatures))
        assert k_host == pytest.approx(body.contact_layer.k_pa_per_m, rel=0.01)


def test_true_footprints_of_round_and_elongated_presses():
    """`FoamScene.footprints`: every press's contact patch (pressure moments) and its own dent's
    half-depth footprint: round for a ball and a punch (a punch's pressure is rim-heavy: its
    patch's 2 sqrt(moment) exceeds its radius), a finger's long along its angle; each centred on
    its press."""
    from virtual_sheet.foam import TrueFootprint
    presses = [Press(SphereIndenter(0.015), (0.03, 0.03), 2.0),
               Press(FlatPunch(0.0075), (-0.03, 0.03), 2.0),
               Press(CapsuleIndenter(0.01, 0.02, angle_rad=0.5), (0.0, -0.02), 3.0)]
    sc = FoamScene(FoamBlock(), presses, 14, 14, L)
    fps = sc.footprints(0.0)
    assert [f.index for f in fps] == [0, 1, 2] and all(isinstance(f, TrueFootprint) for f in fps)
    step = sc.deflection(0.0).step_m
    for f, p in zip(fps, presses):
        assert np.linalg.norm(f.pressure_centre_m - np.asarray(p.position_m)) < step
    ball, punch, finger = fps
    for f in (ball, punch):
        assert f.pressure_axes_m[1] > 0.95 * f.pressure_axes_m[0]
        assert f.dent_axes_m[1] > 0.95 * f.dent_axes_m[0]
        assert f.dent_axes_m[0] > f.pressure_axes_m[1] * 0.9   # the dent spreads beyond it
    assert 0.0075 < punch.pressure_axes_m[0] < 1.4 * 0.0075
    assert finger.pressure_axes_m[0] > 4 * finger.pressure_axes_m[1]
    assert abs(finger.pressure_angle_rad - 0.5) < 0.02 and abs(finger.dent_angle_rad - 0.5) < 0.02
    assert finger.dent_area_m2 > 3 * ball.dent_area_m2
    untouched = FoamScene(FoamBlock(), [Press(SphereIndenter(0.015), (0.0, 0.0), 2.0,
                                              t_on_s=1.0)], 14, 14, L)
    assert untouched.footprints(0.5) == []
