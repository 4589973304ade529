"""Per-snapshot accuracy and false contacts on every body, on smaller sweeps than
benchmarks/bench_tactile.py (which measures the full ones: the table of docs/benchmarks.md).

Targets asserted here: |mean force bias| <= 5 % and the 95th percentile of the single-snapshot
force error <= 15 % for the sphere and the punch on the block, the cylinder and the sphere at 1 % g
(the fitted dent template, `DetectorSettings.force_model` "fit"); the held force (a tracked
contact's mean over 4 snapshots) within 15 % at the 95th percentile; no false contact on an untouched sheet of any body at 0.3 and
5 % g; a finger's orientation on the curved bodies."""

import numpy as np
import pytest

from host.analysis.tactile import DetectorSettings, Foam, TactileSensor, lattice_index
from virtual_sheet.foam import (CapsuleIndenter, FlatPunch, FoamBlock, FoamCylinder, FoamScene,
                                FoamSphere, Press, SphereIndenter)
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import noisy_readings

L = 0.01
BODIES = {"block": FoamBlock(), "cylinder": FoamCylinder(0.08), "sphere": FoamSphere(0.1)}
FOAM = Foam()


def rng(*seed):
    return np.random.Generator(np.random.MT19937(list(seed)))


_rests = {}


def rest_of(body, noise):
    if (body, noise) not in _rests:
        r0 = ideal_readings(FoamScene(BODIES[body], [], 14, 14, L).rest_joints)
        g = rng(41, int(noise * 100), len(body))
        _rests[body, noise] = (r0, TactileSensor.learn_rest(
            [noisy_readings(r0, noise, g) for _ in range(32)], 14, 14, L))
    return _rests[body, noise]


_runs = {}


def force_errors(body, kind, force_model="fit"):
    """Relative force errors of single snapshots and of held forces (the track's 4-snapshot
    mean), 4 placements x 8 snapshots at 1 % g; count and position checked on the way."""
    if (body, kind, force_model) in _runs:
        return _runs[body, kind, force_model]
    settings = DetectorSettings(force_model=force_model)
    _, rest = rest_of(body, 1.0)
    g = rng(42, len(body), len(kind))
    err, held = [], []
    for k in range(4):
        ind = SphereIndenter(0.015) if kind == "sphere" else FlatPunch(0.0075)
        c = np.array([-0.005, -0.005]) + g.uniform(-0.5, 0.5, 2) * L
        sc = FoamScene(BODIES[body], [Press(ind, tuple(c), 2.0)], 14, 14, L)
        r = ideal_readings(sc.joints(0.0))
        ti = lattice_index(sc.rest_joints, sc.contacts(0.0)[0].position)
        sensor = TactileSensor(rest, FOAM, settings=settings)
        for s in range(8):
            fr = sensor.process(noisy_readings(r, 1.0, g))
            assert len(fr.contacts) == 1
            assert np.linalg.norm(fr.contacts[0].index - ti) <= 0.5
            err.append(fr.contacts[0].force_n / 2.0 - 1)
            if s >= 3:  # the track has its 4 snapshots
                held.append(fr.contacts[0].force_n_held / 2.0 - 1)
    _runs[body, kind, force_model] = np.array(err), np.array(held)
    return _runs[body, kind, force_model]


@pytest.mark.parametrize("body", list(BODIES))
@pytest.mark.parametrize("kind", ["sphere", "punch"])
def test_held_force_within_15_percent_and_bias_within_8(body, kind):
    err, held = force_errors(body, kind)
    assert np.percentile(np.abs(held), 95) <= 0.15
    assert abs(np.mean(err)) <= 0.08


@pytest.mark.parametrize("body", list(BODIES))
@pytest.mark.parametrize("kind", ["sphere", "punch"])
def test_force_bias_within_5_percent(body, kind):
    err, _ = force_errors(body, kind)
    assert abs(np.mean(err)) <= 0.05


@pytest.mark.parametrize("body", list(BODIES))
@pytest.mark.parametrize("kind", ["sphere", "punch"])
def test_single_snapshot_force_p95_within_15_percent(body, kind):
    """The accuracy target: every snapshot on its own (not the held force), 32 per body and
    indenter. (The sampled Winkler sum, force_model "sum", misses it on the block and the
    cylinder: 17-19 %.)"""
    err, _ = force_errors(body, kind)
    assert np.percentile(np.abs(err), 95) <= 0.15


@pytest.mark.parametrize("body", list(BODIES))
@pytest.mark.parametrize("noise", [0.3, 5.0])
def test_untouched_sheet_reports_no_contact(body, noise):
    r0, rest = rest_of(body, noise)
    g = rng(43, int(noise * 100), len(body))
    sensor = TactileSensor(rest, FOAM)
    hits = sum(len(sensor.process(noisy_readings(r0, noise, g)).contacts) for _ in range(120))
    assert hits == 0  # the benchmark: 0 in 1000 per body and noise level


@pytest.mark.parametrize("body", ["cylinder", "sphere"])
def test_finger_orientation_on_a_curved_body(body):
    _, rest = rest_of(body, 1.0)
    g = rng(44, len(body))
    for angle in (0.6, -1.0):
        ind = CapsuleIndenter(0.01, 0.02, angle_rad=angle)
        sc = FoamScene(BODIES[body], [Press(ind, (0.0, -0.005), 3.0)], 14, 14, L)
        r = ideal_readings(sc.joints(0.0))
        for _ in range(3):
            fr = TactileSensor(rest, FOAM).process(noisy_readings(r, 1.0, g))
            assert len(fr.contacts) == 1
            c = fr.contacts[0]
            assert c.axes_m[0] > 2.0 * c.axes_m[1]
            # lattice i runs along surface u on every body, so the angle from i is the angle from u
            diff = (c.angle_rad - angle + np.pi / 2) % np.pi - np.pi / 2
            assert abs(diff) < np.radians(10)
