"""Exact geometry: Chebyshev nets keep every link at L, frames follow docs/design.md, and roll/pitch
from noise-free readings equal the geometry's."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from protocol.constants import G0
from protocol.lattice import Lattice
from virtual_sheet.geometry import (chebyshev_net, ideal_readings, link_angles, link_frames,
                                    link_lengths, roll_pitch, rotation_from_angles)
from virtual_sheet.shapes import SCENES, SHAPES, make_scene, make_sheet

L = 0.01
RTOL = 1e-9


def _heightmap_file(tmp_path):
    y, x = np.mgrid[-1:1:41j, -1:1:41j]
    path = tmp_path / "bump.npy"
    np.save(path, 0.02 * np.exp(-(x ** 2 + 2 * y ** 2) * 2))
    return str(path)


def _params(shape, tmp_path):
    return {"path": _heightmap_file(tmp_path)} if shape == "heightmap" else {}


@pytest.mark.parametrize("shape", sorted(SHAPES))
@pytest.mark.parametrize("net", [{}, {"angle": 0.4, "shear": 0.3}, {"angle": -1.0, "shear": -0.5}])
@pytest.mark.parametrize("size", [(14, 14), (5, 9), (2, 2)])
def test_every_builtin_shape_has_all_links_exactly_L(shape, net, size, tmp_path):
    P = make_sheet(shape, *size, L, **net, **_params(shape, tmp_path))
    assert P.shape == (*size, 3)
    assert np.max(np.abs(link_lengths(P) / L - 1)) < RTOL


@pytest.mark.parametrize("shape", sorted(SHAPES))
def test_builtin_shapes_are_centred_on_the_origin(shape, tmp_path):
    P = make_sheet(shape, 14, 14, L, **_params(shape, tmp_path))
    assert np.all(np.abs(P[..., :2].mean(axis=(0, 1))) < 0.2 * 13 * L)


@pytest.mark.parametrize("scene", sorted(SCENES))
@pytest.mark.parametrize("t_s", [0.0, 0.3, 1.0, 2.7])
def test_every_scene_has_all_links_exactly_L_at_any_time(scene, t_s):
    P = make_scene(scene, 14, 14, L).joints(t_s)
    assert np.max(np.abs(link_lengths(P) / L - 1)) < RTOL


def test_scenes_move_and_static_wrapper_does_not():
    grow = make_scene("grow", 8, 8, L)
    assert np.ptp(grow.joints(0.0)[..., 2]) < 1e-12
    assert np.ptp(grow.joints(2.0)[..., 2]) > 0.01
    static = make_scene("gaussian", 8, 8, L)
    np.testing.assert_array_equal(static.joints(0.0), static.joints(5.0))


@settings(max_examples=25)
@given(amplitude=st.floats(-0.05, 0.05), sigma=st.floats(0.02, 0.08),
       angle=st.floats(-np.pi, np.pi), shear=st.floats(-0.6, 0.6),
       anchor=st.sampled_from(["centre", "corner"]))
def test_chebyshev_net_on_any_gaussian_has_exact_links(amplitude, sigma, angle, shear, anchor):
    h = lambda x, y: amplitude * np.exp(-(x ** 2 + y ** 2) / (2 * sigma ** 2))  # noqa: E731
    P = chebyshev_net(h, 10, 12, L, angle=angle, shear=shear, anchor=anchor)
    assert np.max(np.abs(link_lengths(P) / L - 1)) < RTOL
    np.testing.assert_allclose(P[..., 2], h(P[..., 0], P[..., 1]), atol=1e-15)


def test_chebyshev_net_fails_clearly_when_the_sheet_leaves_the_shape():
    def cap(x, y):
        d2 = 0.03 ** 2 - x * x - y * y
        return np.where(d2 >= 0, np.sqrt(np.abs(d2)), np.nan)
    with pytest.raises(ValueError, match="undefined"):
        chebyshev_net(cap, 14, 14, L)


def test_chebyshev_net_fails_clearly_on_a_rough_surface():
    rough = np.random.Generator(np.random.MT19937(0)).random((20, 20)) * 0.02
    with pytest.raises(ValueError, match="Chebyshev net"):
        make_sheet("heightmap", 14, 14, L, array=rough)


@pytest.mark.parametrize("bad", [{"shear": np.pi / 2}, {"anchor": "middle"}])
def test_chebyshev_net_rejects_invalid_options(bad):
    with pytest.raises(ValueError, match="Invalid"):
        chebyshev_net(lambda x, y: 0 * x, 4, 4, L, **bad)


def test_unknown_shape_and_parameter_are_named():
    with pytest.raises(ValueError, match="Unknown shape 'blob'"):
        make_sheet("blob", 4, 4)
    with pytest.raises(ValueError, match="wobble"):
        make_sheet("gaussian", 4, 4, wobble=1)


def test_flat_level_sheet_reads_plus_g_on_z_for_every_link():
    r = ideal_readings(make_sheet("flat", 14, 14, L))
    np.testing.assert_allclose(r, np.tile([0.0, 0.0, G0], (r.shape[0], 1)), atol=1e-12)


def test_flat_sheet_frames_are_x_along_link_and_z_up():
    P = make_sheet("flat", 3, 4, L)
    R = link_frames(P)
    lat = Lattice(3, 4)
    np.testing.assert_allclose(R[: lat.n_i_links], np.tile(np.eye(3), (lat.n_i_links, 1, 1)),
                               atol=1e-15)
    rz90 = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # j-links: x along +y
    np.testing.assert_allclose(R[lat.n_i_links:], np.tile(rz90, (lat.n_j_links, 1, 1)),
                               atol=1e-15)


@pytest.mark.parametrize("shape", ["gaussian", "sphere", "cylinder", "saddle", "tilted"])
def test_link_frames_are_right_handed_orthonormal_with_x_along_the_link(shape):
    P = make_sheet(shape, 9, 11, L, angle=0.3, shear=0.2)
    R = link_frames(P)
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), np.tile(np.eye(3), (len(R), 1, 1)),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    vec = Lattice(9, 11).link_vectors(P)
    np.testing.assert_allclose(R[:, :, 0], vec / L, atol=1e-12)
    assert np.all(R[:, 2, 2] > 0)  # these sheets face up: top face normal has +z


@pytest.mark.parametrize("shape", ["gaussian", "sphere", "cylinder", "saddle", "tilted", "flat"])
def test_roll_pitch_from_ideal_readings_equal_the_geometry(shape):
    P = make_sheet(shape, 14, 14, L, angle=0.5, shear=0.1)
    alpha, beta = roll_pitch(ideal_readings(P))
    a_true, b_true, g_true = link_angles(P)
    np.testing.assert_allclose(alpha, a_true, atol=1e-9)
    np.testing.assert_allclose(beta, b_true, atol=1e-9)
    np.testing.assert_allclose(rotation_from_angles(a_true, b_true, g_true), link_frames(P),
                               atol=1e-12)


@settings(max_examples=50)
@given(alpha=st.floats(-3.1, 3.1), beta=st.floats(-1.5, 1.5), gamma=st.floats(-3.1, 3.1),
       scale=st.floats(0.1, 10.0))
def test_roll_pitch_inverts_the_reading_of_any_rotation(alpha, beta, gamma, scale):
    R = rotation_from_angles(alpha, beta, gamma)
    reading = scale * G0 * R[:, 2, :]  # Rᵀ (0, 0, g)
    a, b = roll_pitch(reading)
    np.testing.assert_allclose([a[0], b[0]], [alpha, beta], atol=1e-9)


def test_roll_pitch_rejects_wrong_shape():
    with pytest.raises(ValueError, match=r"shape \(n_links, 3\), got \(3,\)"):
        roll_pitch(np.zeros(3))
