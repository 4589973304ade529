"""The magnetic field: Earth's by magnitude, dip and declination; dipoles as the gradient of their
scalar potential (an independent formula); disturbances local to the quarter they are put under."""

import numpy as np
import pytest

from virtual_sheet.magfield import (MU0, Dipole, EarthField, MagneticField, SteelPart, disturbance_angle,
                                    field_in_sensor_frames, quarter_disturbance)
from virtual_sheet.motion import make_motion_scene

L = 0.01


@pytest.mark.parametrize("F, dip, dec", [(25e-6, 0.0, 0.0), (50e-6, np.radians(60), 0.4), (65e-6, np.radians(-70), -2.0),
                                         (48e-6, np.pi / 2, 1.0)])
def test_earth_field_has_its_magnitude_dip_and_declination(F, dip, dec):
    B = EarthField(F, dip, dec).vector
    assert np.linalg.norm(B) == pytest.approx(F, rel=1e-12)
    assert np.arctan2(-B[2], np.hypot(B[0], B[1])) == pytest.approx(dip, abs=1e-12)  # below the horizon
    if abs(dip) < np.pi / 2:
        assert np.arctan2(B[1], B[0]) == pytest.approx(np.angle(np.exp(1j * dec)), abs=1e-12)


def test_a_dipole_field_is_minus_the_gradient_of_its_scalar_potential():
    d = Dipole((0.01, -0.02, -0.03), (0.002, -0.001, 0.004))
    m, p0 = np.array(d.moment_am2), np.array(d.position_m)

    def potential(p):  # B = −μ0 ∇φ_m with φ_m = m·r / (4π r³)
        r = p - p0
        return MU0 / (4 * np.pi) * (r @ m) / np.linalg.norm(r) ** 3

    g = np.random.Generator(np.random.MT19937(2))
    pts = g.uniform(-0.06, 0.06, (20, 3))
    B = d.at(pts, np.zeros(3))
    h = 1e-7
    for k, p in enumerate(pts):
        grad = [(potential(p + h * e) - potential(p - h * e)) / (2 * h) for e in np.eye(3)]
        np.testing.assert_allclose(B[k], -np.array(grad), rtol=1e-6, atol=1e-14)


def test_steel_is_magnetised_along_the_ambient_field_and_nothing_without_susceptibility():
    earth = EarthField(50e-6, np.radians(60), 0.3)
    p = np.array([[0.0, 0.0, 0.05]])
    steel = SteelPart((0.0, 0.0, 0.0), 2e-6)
    same = Dipole((0.0, 0.0, 0.0), tuple(2e-6 * earth.vector / MU0))
    np.testing.assert_allclose(MagneticField(earth, (steel,)).at(p), MagneticField(earth, (same,)).at(p), rtol=1e-12)
    np.testing.assert_array_equal(MagneticField(earth, (SteelPart((0, 0, 0), 0.0),)).at(p), MagneticField(earth).at(p))


def test_chips_feel_the_field_in_their_own_frames():
    env = MagneticField(EarthField(50e-6, np.radians(60), 0.7))
    tr = make_motion_scene("carry", 5, 5, L).sample([0.0, 2.3])
    Bs = field_in_sensor_frames(env, tr.position, tr.frames)
    np.testing.assert_allclose(np.linalg.norm(Bs, axis=-1), 50e-6, rtol=1e-12)
    back = np.einsum("tkij,tkj->tki", tr.frames, Bs)  # R (Rᵀ B) = B
    np.testing.assert_allclose(back, np.broadcast_to(env.earth.vector, back.shape), atol=1e-18)


def test_the_quarter_disturbance_turns_the_field_over_its_quarter_and_little_elsewhere():
    d = quarter_disturbance(14, 14, L)
    env = MagneticField(EarthField(50e-6, np.radians(60)), (d,))
    pos = make_motion_scene("rest", 14, 14, L, shape="flat").sample(0.0).position[0]
    ang = np.degrees(disturbance_angle(env, pos))
    q = (pos[:, 0] > 0) & (pos[:, 1] > 0)
    far = (pos[:, 0] < 0) & (pos[:, 1] < 0)
    assert np.median(ang[q]) > 10 and ang[q].min() > 4
    assert np.median(ang[~q]) < 2 and ang[far].max() < 4
    other = quarter_disturbance(14, 14, L, corner=(-1, 1))
    assert other.position_m[0] < 0 < other.position_m[1]


def test_bad_fields_are_refused():
    with pytest.raises(ValueError, match="magnitude_t"):
        EarthField(1.0)
    with pytest.raises(ValueError, match="dip_rad"):
        EarthField(50e-6, 2.0)
    with pytest.raises(ValueError, match="moment_am2"):
        Dipole((0, 0, 0), (0, 0))
    with pytest.raises(ValueError, match="disturbance"):
        MagneticField(EarthField(), ("magnet",))
    with pytest.raises(ValueError, match="corner"):
        quarter_disturbance(14, 14, L, corner=(0, 1))
    with pytest.raises(ValueError, match="on a dipole"):
        Dipole((0, 0, 0), (0, 0, 1.0)).at(np.zeros((1, 3)), np.zeros(3))
