"""The spring-mass drape (paper section 3.1) reaches its target: links at L and joints on the
surface, within the tolerance it states, also for surfaces that are not height fields."""

import numpy as np
import pytest

from protocol.lattice import Lattice
from virtual_sheet.drape import Cylinder, DrapeInfo, HeightField, Sphere, drape
from virtual_sheet.geometry import link_frames, link_lengths

L = 0.01
TOL = 1e-9


def _check(surface, P, info: DrapeInfo):
    assert info.converged
    assert info.max_length_error <= TOL
    assert info.max_surface_distance <= 1e-12
    # The stated figures are the true ones.
    assert np.max(np.abs(link_lengths(P) / L - 1)) == pytest.approx(info.max_length_error, abs=1e-15)
    assert np.max(np.linalg.norm(P - surface.project(P), axis=-1)) <= 1e-12


@pytest.mark.parametrize("surface", [Cylinder(0.03), Cylinder(0.05, axis=(1.0, 1.0, 0.3)),
                                     Sphere(0.06), Sphere(0.13),
                                     HeightField(lambda x, y: 0.03 * np.exp(-(x * x + y * y) / 0.002))],
                         ids=["cylinder-wrapped", "cylinder-skew", "sphere", "sphere-large",
                              "heightfield"])
def test_drape_reaches_the_surface_within_the_stated_tolerance(surface):
    P, info = drape(surface, 14, 14, L, tol=TOL)
    _check(surface, P, info)


def test_sheet_wrapped_round_a_thin_cylinder_is_not_a_height_field():
    surface = Cylinder(0.03)
    P, info = drape(surface, 14, 14, L)
    _check(surface, P, info)
    assert P[..., 2].min() < -0.015  # beyond the equator: joints below the axis
    # The top face (sensor z) points away from the axis on every link, even on the underside.
    ends = Lattice(14, 14).endpoints
    mid = 0.5 * (P.reshape(-1, 3)[ends[:, 0]] + P.reshape(-1, 3)[ends[:, 1]])
    radial = mid[:, [0, 2]] / np.linalg.norm(mid[:, [0, 2]], axis=1, keepdims=True)
    z_axis = link_frames(P)[:, [0, 2], 2]
    # (edge j-links have one adjacent cell only: tilted by half its bend, asin(L/2R) = 0.17 rad)
    assert np.all(np.einsum("ij,ij->i", z_axis, radial) > np.cos(np.arcsin(L / 0.06)) - 1e-9)


@pytest.mark.parametrize("surface", [Cylinder(0.03), Sphere(0.06)])
@pytest.mark.parametrize("max_newton", [0, 20], ids=["sweeps-only", "with-newton"])
def test_relaxation_repairs_a_perturbed_sheet(surface, max_newton):
    P0, _ = drape(surface, 14, 14, L)
    noise = np.random.Generator(np.random.MT19937(7)).normal(0.0, 1e-3, P0.shape)
    P, info = drape(surface, 14, 14, L, init=P0 + noise, tol=TOL, max_newton=max_newton)
    _check(surface, P, info)
    assert info.iterations > 0
    assert np.max(np.abs(P - P0)) < 0.005


@pytest.mark.parametrize("surface", [Sphere(0.2), Cylinder(0.1)])
def test_flat_sheet_laid_over_a_gentle_shape_relaxes_onto_it(surface):
    P, info = drape(surface, 14, 14, L, init="flat", tol=TOL)
    _check(surface, P, info)


def test_drape_of_14x14_is_fast():
    import time
    t0 = time.perf_counter()
    drape(Sphere(0.06), 14, 14, L)
    assert time.perf_counter() - t0 < 2.0


def test_drape_states_failure_when_out_of_iterations():
    P, info = drape(Sphere(0.2), 14, 14, L, init="flat", iterations=10, max_newton=0)
    assert not info.converged and info.iterations == 10
    assert info.max_length_error > TOL


@pytest.mark.parametrize("bad", [{"init": "crumpled"}, {"init": np.zeros((3, 3, 3))},
                                 {"shear": 2.0}, {"direction": (0.0, 0.0, 1.0)}])
def test_drape_rejects_invalid_options(bad):
    with pytest.raises(ValueError):
        drape(Sphere(0.1), 4, 4, L, **bad)


@pytest.mark.parametrize("make", [lambda: Sphere(-1.0), lambda: Cylinder(0.1, axis=(0, 0, 0))])
def test_surfaces_validate_themselves(make):
    with pytest.raises(ValueError, match="Invalid"):
        make()


# --- sensor axes from the target (surface_frames) ----------------------------------------------

def test_surface_normals_are_the_surfaces():
    p = np.array([[0.3, -0.2, 0.5], [0.0, 0.1, -0.4]])
    np.testing.assert_allclose(Sphere(0.2).normal(p), p / np.linalg.norm(p, axis=1, keepdims=True))
    n = Cylinder(0.1, axis=(0.0, 1.0, 0.0)).normal(p)
    radial = p * [1, 0, 1]
    np.testing.assert_allclose(n, radial / np.linalg.norm(radial, axis=1, keepdims=True))
    plane = HeightField(lambda x, y: 0.2 * x - 0.5 * y)
    np.testing.assert_allclose(plane.normal(p), np.tile([-0.2, 0.5, 1.0] / np.sqrt(1.29), (2, 1)),
                               atol=1e-9)


def test_surface_frames_agree_with_the_sheets_normal_where_the_cells_are_exact():
    from virtual_sheet.drape import surface_frames, surface_readings
    from virtual_sheet.geometry import ideal_readings

    plane = HeightField(lambda x, y: 0.2 * x - 0.5 * y)
    P, _ = drape(plane, 6, 6, L, init="flat")
    np.testing.assert_allclose(surface_readings(P, plane), ideal_readings(P), atol=1e-6)
    # round a cylinder the cells' mean normal is the surface's inside the sheet; on its edge a
    # link has one cell and leans by half its bend (L / 2r = 7.2°): the two models differ there
    c = Cylinder(0.04)
    P, _ = drape(c, 8, 8, L)
    F, G = surface_frames(P, c), link_frames(P)
    np.testing.assert_allclose(F[:, :, 0], G[:, :, 0])  # x: the link
    np.testing.assert_allclose(np.einsum("nij,nik->njk", F, F), np.tile(np.eye(3), (len(F), 1, 1)),
                               atol=1e-12)
    ang = np.degrees(np.arccos(np.clip(np.sum(F[:, :, 2] * G[:, :, 2], axis=1), -1, 1)))
    e = Lattice(8, 8).endpoints
    edge = np.all((e // 8 == 0) | (e // 8 == 7) | (e % 8 == 0) | (e % 8 == 7), axis=1)
    assert ang[~edge].max() < 1e-5 and ang[edge].max() == pytest.approx(np.degrees(L / 0.04 / 2), rel=0.01)


def test_surface_frames_need_a_surface_with_normals():
    from virtual_sheet.drape import surface_frames

    P, _ = drape(Sphere(0.1), 4, 4, L)
    with pytest.raises(ValueError, match="normal"):
        surface_frames(P, object())
