"""Presses in time: the tracker on a simulated clock (sans-I/O: ``now`` is
passed in), and a finger that arrives, slides, holds and leaves within a second tracked as one
contact from onset to release."""

import numpy as np
import pytest

from host.analysis.tactile import Contact, ContactTracker, Foam, TactileSensor
from virtual_sheet.foam import CapsuleIndenter, FoamBlock, FoamScene, Press
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import noisy_readings

L = 0.01


def contact(x: float, force: float = 1.0) -> Contact:
    return Contact(id=-1, index=np.zeros(2), position=np.array([x, 0.0, 0.0]),
                   normal=np.array([0, 0, 1.0]), depth_m=1e-3, force_n=force, area_m2=1e-4,
                   axes_m=np.ones(2), angle_rad=0.0, peak=(0, 0), region=np.zeros((2, 2), bool))


def test_a_sliding_contact_keeps_its_id_by_its_predicted_position():
    """A contact that speeds up from 0.75 to 3.15 cm per 10 ms snapshot (a gate is 2 cm):
    predicted from its velocity it keeps one id; without times (no prediction) it gets a new
    one at every snapshot that moves it past the gate (k = 6 to 9: 4 more) — the broken input
    that shows the prediction is what holds it."""
    x = np.cumsum([0.0] + [0.0045 + 0.003 * k for k in range(1, 10)])
    for now, expect_tracks in ((True, 1), (False, 5)):
        tr = ContactTracker(gate_m=0.02, max_missed=0)
        ids = set()
        for k in range(10):
            out = tr.update([contact(float(x[k]))], now=0.01 * k if now else None)
            ids.add(out[0].id)
        assert len(ids) == expect_tracks


def test_onset_and_release_events_on_a_simulated_clock():
    tr = ContactTracker(gate_m=0.02, max_missed=2)
    events = []
    seen = []
    for k in range(16):
        t = 0.01 * k
        present = 3 <= k <= 9 and k != 6              # one blink at k = 6 (kept: max_missed)
        out = tr.update([contact(0.001 * k)] if present else [], now=t)
        seen += [c.id for c in out]
        events += tr.pop_events()
    assert set(seen) == {0}
    assert [(e.kind, e.id) for e in events] == [("onset", 0), ("release", 0)]
    assert events[0].t_s == pytest.approx(0.03)     # the first snapshot it was seen in
    assert events[1].t_s == pytest.approx(0.10)     # the first it was no longer seen in
    assert tr.active_ids == []
    out = tr.update([contact(0.0)], now=0.2)
    assert out[0].id == 1 and out[0].onset_s == pytest.approx(0.2)   # ids are never reused
    with pytest.raises(ValueError, match="before the last snapshot"):
        tr.update([], now=0.1)


def test_a_finger_that_arrives_slides_holds_and_leaves_is_one_track():
    """40 snapshots/s on the block at 1 % g: a 3 N finger pressed from 0.1 s over 50 ms,
    sliding along itself at 5 cm/s while held, released from 0.65 s (force 0 at 0.7 s). One id
    from onset to release; the onset within two snapshots after 0.1 s, the release within two
    snapshots of 0.7 s; one contact whenever the force is above 0.3 N; every held snapshot's
    force within 15 %."""
    rate = 40.0
    g = np.random.Generator(np.random.MT19937(61))
    r0 = ideal_readings(FoamScene(FoamBlock(), [], 14, 14, L).rest_joints)
    rest = TactileSensor.learn_rest([noisy_readings(r0, 1.0, g) for _ in range(32)], 14, 14, L)
    press = Press(CapsuleIndenter(0.01, 0.02, angle_rad=0.4), (-0.015, -0.01), 3.0, t_on_s=0.1,
                  t_off_s=0.65, ramp_s=0.05, velocity_mps=(0.05 * np.cos(0.4), 0.05 * np.sin(0.4)))

    sc = FoamScene(FoamBlock(), [press], 14, 14, L)
    sensor = TactileSensor(rest, Foam())
    ids, events, held = set(), [], []
    for k in range(int(0.9 * rate) + 1):
        t = k / rate
        fr = sensor.process(noisy_readings(ideal_readings(sc.joints(t)), 1.0, g), t_s=t)
        events += fr.events
        ids |= {c.id for c in fr.contacts}
        if press.force_at(t) > 0.3:
            assert len(fr.contacts) == 1
        if 0.15 <= t <= 0.65:
            held.append(fr.contacts[0].force_n / 3.0 - 1)
    assert ids == {0}
    assert [e.kind for e in events] == ["onset", "release"]
    assert 0 <= events[0].t_s - 0.1 <= 2 / rate
    assert abs(events[1].t_s - 0.7) <= 2 / rate
    assert np.max(np.abs(held)) <= 0.15
