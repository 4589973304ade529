"""Tactile analysis on curved bodies: the overlay reads normal distances, so the sheet
sliding over the foam does not read as a shallower dent; forces on the cylinder and the sphere are
right from exact shapes and through the estimator."""

import numpy as np
import pytest

from host.analysis.metrics import rigid_fit
from host.analysis.tactile import Foam, RestShape, TactileSensor, deformation, find_contacts
from host.analysis.tactile.rest import normal_fit
from virtual_sheet.foam import FlatPunch, FoamCylinder, FoamScene, FoamSphere, Press, SphereIndenter

L = 0.01
FOAM = Foam()


def sphere_patch(R=0.1, n=9):
    """Joints of an n x n patch of a sphere of radius R (centre at -R z), their normals."""
    u = (np.arange(n) - n // 2) * L
    U, V = np.meshgrid(u, u, indexing="ij")
    th, ph = np.hypot(U, V) / R, np.arctan2(V, U)
    nrm = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    return np.array([0, 0, -R]) + R * nrm, nrm


def test_normal_fit_ignores_sliding_along_a_sphere_that_a_point_fit_turns_into_depth():
    P, n = sphere_patch()
    R = 0.1
    # the sheet slides along the sphere towards +x by up to 0.3 mm (no joint leaves the surface)
    slide = 3e-4 * np.exp(-((P[..., 0] - 0.02) ** 2 + P[..., 1] ** 2) / (2 * 0.02 ** 2))
    moved = P + slide[..., None] * np.array([1.0, 0, 0])
    c = np.array([0, 0, -R])
    moved = c + R * (moved - c) / np.linalg.norm(moved - c, axis=-1, keepdims=True)
    src, dst, nn = moved.reshape(-1, 3), P.reshape(-1, 3), n.reshape(-1, 3)
    w = np.ones(len(src))
    d_point = np.sum((dst - rigid_fit(src, dst, w)) * nn, axis=1)
    d_normal = np.sum((dst - normal_fit(src, dst, nn, w)) * nn, axis=1)
    # the point fit shifts the patch out of the foam: ~10 µm over 64 cm² is ~0.1 N at k = 1.2 MPa/m
    assert np.max(np.abs(d_point)) > 1e-5 and np.mean(d_point) < -5e-6
    assert np.max(np.abs(d_normal)) < 2e-6     # the normal fit sees the sheet on the surface


def test_normal_fit_recovers_a_rigid_motion():
    P, n = sphere_patch()
    c, s = np.cos(0.4), np.sin(0.4)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    src = P.reshape(-1, 3) @ Rz.T + [0.3, -0.1, 0.05]
    out = normal_fit(src, P.reshape(-1, 3), n.reshape(-1, 3), np.ones(len(src)))
    assert np.max(np.linalg.norm(out - P.reshape(-1, 3), axis=1)) < 1e-9


def two_pass(P, rest):
    d, _ = deformation(P, rest)
    cs = find_contacts(d, rest, FOAM)
    moved = np.zeros(d.shape, bool)
    for c in cs:
        moved |= c.region
    moved[1:] |= moved[:-1].copy()
    moved[:-1] |= moved[1:].copy()
    moved[:, 1:] |= moved[:, :-1].copy()
    moved[:, :-1] |= moved[:, 1:].copy()
    d, _ = deformation(P, rest, exclude=moved)
    return find_contacts(d, rest, FOAM)


@pytest.mark.parametrize("body", [FoamCylinder(0.08), FoamSphere(0.1)], ids=["cylinder", "sphere"])
@pytest.mark.parametrize("ind", [SphereIndenter(0.015), FlatPunch(0.0075)], ids=["sphere", "punch"])
def test_exact_shape_on_a_curved_body_reads_the_force(body, ind):
    """The issue's failure was cylinder -20 %, sphere -30 %; from exact joints a point-to-point
    overlay already loses 5-9 % here (it fails 3 of these 4 cases)."""
    sc = FoamScene(body, [Press(ind, (0.003, -0.004), 2.0)], 14, 14, L)
    rest = RestShape.from_joints(sc.rest_joints, L, noise_m=np.full((14, 14), 7e-5))
    cs = two_pass(sc.joints(0.0), rest)
    assert len(cs) == 1
    assert cs[0].force_n == pytest.approx(2.0, rel=0.05)
