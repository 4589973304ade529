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
