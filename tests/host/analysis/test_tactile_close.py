"""Close contacts: two contacts 2 L apart — two balls, two punches, two fingers
side by side — are resolved as two with their forces; where the noise hides the pair, the one
contact reported says its count is uncertain (``ambiguous``), and a single finger does not."""

import numpy as np
import pytest

from host.analysis.tactile import Foam, TactileSensor, lattice_index
from virtual_sheet.foam import (CapsuleIndenter, FlatPunch, FoamBlock, FoamScene, FoamSphere,
                                Press, SphereIndenter)
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import noisy_readings

L = 0.01
FOAM = Foam()
BODIES = {"block": FoamBlock(), "sphere": FoamSphere(0.1)}


def rng(*seed):
    return np.random.Generator(np.random.MT19937(list(seed)))


_rests = {}


def learned_rest(body, noise):
    if (body, noise) not in _rests:
        r0 = ideal_readings(FoamScene(BODIES[body], [], 14, 14, L).rest_joints)
        g = rng(11, int(10 * noise), len(body))
        _rests[body, noise] = TactileSensor.learn_rest(
            [noisy_readings(r0, noise, g) for _ in range(32)], 14, 14, L)
    return _rests[body, noise]


def pair(body, kind, angle, mid, sep_l=2.0):
    """Two indenters ``sep_l`` L apart about ``mid``: round ones along ``angle``, fingers
    (along ``angle``) side by side."""
    e = np.array([np.cos(angle), np.sin(angle)])
    if kind == "finger":
        ind, force, d = CapsuleIndenter(0.01, 0.02, angle_rad=angle), 3.0, np.array([-e[1], e[0]])
    else:
        ind, force, d = ({"sphere": SphereIndenter(0.015), "punch": FlatPunch(0.0075)}[kind],
                         2.0, e)
    d = 0.5 * sep_l * L * d
    sc = FoamScene(BODIES[body], [Press(ind, tuple(mid - d), force),
                                  Press(ind, tuple(mid + d), force)], 14, 14, L)
    idx = [lattice_index(sc.rest_joints, t.position) for t in sc.contacts(0.0)]
    return ideal_readings(sc.joints(0.0)), idx, force


@pytest.mark.parametrize("body", list(BODIES))
def test_two_contacts_two_links_apart_are_resolved_with_their_forces(body):
    """The target: at 2 L at least 80 % of snapshots report two contacts, each force
    within 20 %; no wrong count unflagged (measured 100 % resolved on every body,
    benchmarks/bench_tactile.py)."""
    rest = learned_rest(body, 1.0)
    g = rng(12, len(body))
    n = resolved = silent = 0
    for k, (kind, angle) in enumerate([("sphere", 0.3), ("punch", 1.2), ("finger", -0.4),
                                       ("finger", 0.9), ("sphere", 2.0), ("punch", 0.0)]):
        r, idx, force = pair(body, kind, angle, np.array([-0.005, -0.005]) + 0.002 * (k - 2.5))
        sensor = TactileSensor(rest, FOAM)
        for s in range(3):
            fr = sensor.process(noisy_readings(r, 1.0, g), t_s=s / 145)
            cs = fr.contacts
            n += 1
            silent += len(cs) != 2 and not any(c.ambiguous for c in cs)
            if len(cs) == 2:
                near = [min(cs, key=lambda c: np.linalg.norm(c.index - i)) for i in idx]
                resolved += (near[0] is not near[1]
                             and all(abs(c.force_n / force - 1) <= 0.2 for c in near))
    assert silent == 0
    assert resolved >= 0.8 * n


@pytest.mark.parametrize("body", list(BODIES))
def test_a_pair_the_noise_hides_is_flagged_and_a_finger_is_not(body):
    """At 5 % g two balls 2 L apart read as one contact; it says its count is uncertain. A
    single finger at 1 % g (as long as the pair's dent) is one contact and says nothing — the
    flag is not simply set on every elongated contact."""
    rest5 = learned_rest(body, 5.0)
    g = rng(13, len(body))
    merged = 0
    for k, angle in enumerate((0.4, -1.0)):
        r, _, _ = pair(body, "sphere", angle, np.array([-0.005, -0.004]) + 0.003 * k)
        sensor = TactileSensor(rest5, FOAM)
        for s in range(3):
            cs = sensor.process(noisy_readings(r, 5.0, g), t_s=s / 145).contacts
            if len(cs) == 1:
                merged += 1
                assert cs[0].ambiguous
    assert merged >= 3   # the precondition: the pair does merge at this noise
    rest1 = learned_rest(body, 1.0)
    for angle in (0.4, -1.0):
        sc = FoamScene(BODIES[body], [Press(CapsuleIndenter(0.01, 0.02, angle_rad=angle),
                                            (-0.005, -0.004), 3.0)], 14, 14, L)
        r = ideal_readings(sc.joints(0.0))
        sensor = TactileSensor(rest1, FOAM)
        for s in range(3):
            cs = sensor.process(noisy_readings(r, 1.0, g), t_s=s / 145).contacts
            assert len(cs) == 1 and not cs[0].ambiguous


@pytest.mark.parametrize("body", list(BODIES))
def test_a_round_contact_has_a_round_footprint_and_no_flag(body):
    rest = learned_rest(body, 1.0)
    g = rng(14)
    for ind, pos in [(FlatPunch(0.0075), (0.002, -0.007)), (SphereIndenter(0.015), (-0.004, 0.0))]:
        sc = FoamScene(BODIES[body], [Press(ind, pos, 2.0)], 14, 14, L)
        r = ideal_readings(sc.joints(0.0))
        for _ in range(4):
            fr = TactileSensor(rest, FOAM).process(noisy_readings(r, 1.0, g))
            assert len(fr.contacts) == 1
            c = fr.contacts[0]
            assert not c.ambiguous
            # round (a punch between joints reads up to 1.3: its rim-heavy pressure is not the
            # model's uniform disc; docs/tactile.md)
            assert c.axes_m[1] > 0.7 * c.axes_m[0]
            assert 5e-3 < c.axes_m[1] and c.axes_m[0] < 1.5 * L
            assert c.angle_std_rad > 0.5                   # and it does not claim an angle
