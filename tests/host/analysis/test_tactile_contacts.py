"""Host tactile analysis on the virtual foam block (14x14, L = 1 cm, 1 % g noise): known
indentations in, the stated bounds out; no contacts on an untouched sheet; stable track ids.

Bounds: count exact; position error <= 0.5 L; force error <= 15 % of the true force
(mean over snapshots; every single snapshot within 35 %)."""

import numpy as np
import pytest

from host.cli import main as cli_main
from host.analysis.tactile import (ContactTracker, Foam, RestShape, TactileSensor, deformation,
                          find_contacts, lattice_index)
from virtual_sheet.foam import (CapsuleIndenter, FlatPunch, FoamBlock, FoamLayer, FoamScene,
                                Press, SphereIndenter)
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import noisy_readings

ROWS = COLS = 14
L = 0.01
NOISE = 1.0
FOAM = Foam()


def rng(seed):
    return np.random.Generator(np.random.MT19937(seed))


@pytest.fixture(scope="module")
def rest_scene():
    return FoamScene(FoamBlock(FoamLayer()), [], ROWS, COLS, L)


@pytest.fixture(scope="module")
def rest(rest_scene):
    g = rng(100)
    r0 = ideal_readings(rest_scene.rest_joints)
    return TactileSensor.learn_rest([noisy_readings(r0, NOISE, g) for _ in range(32)],
                                    ROWS, COLS, L)


def run_scene(rest, presses, seed, snapshots=12):
    sc = FoamScene(FoamBlock(FoamLayer()), presses, ROWS, COLS, L)
    r = ideal_readings(sc.joints(0.0))
    truth = sc.contacts(0.0)
    idx = [lattice_index(sc.rest_joints, t.position) for t in truth]
    sensor = TactileSensor(rest, FOAM)
    g = rng(seed)
    return [sensor.process(noisy_readings(r, NOISE, g)) for _ in range(snapshots)], truth, idx


def check(frames, truth, idx):
    force_err = []
    for fr in frames:
        assert len(fr.contacts) == len(truth)
        for t, ti in zip(truth, idx):
            c = min(fr.contacts, key=lambda c: np.linalg.norm(c.index - ti))
            assert np.linalg.norm(c.index - ti) <= 0.5  # link lengths
            err = abs(c.force_n - t.force_n) / t.force_n
            assert err <= 0.35
            force_err.append(err)
    assert np.mean(force_err) <= 0.15
    return float(np.mean(force_err))


@pytest.mark.parametrize("indenter", [SphereIndenter(0.015), FlatPunch(0.0075)],
                         ids=["sphere", "punch"])
def test_single_contact_count_position_force(rest, indenter):
    frames, truth, idx = run_scene(rest, [Press(indenter, (0.003, -0.008), 2.0)], seed=1)
    check(frames, truth, idx)
    depth = np.mean([fr.contacts[0].depth_m for fr in frames])
    # the joints sample the dent: a punch's flat bottom is seen, a sphere's tip falls between joints
    assert depth == pytest.approx(truth[0].max_deflection_m, rel=0.25)


@pytest.mark.parametrize("indenter", [SphereIndenter(0.015), FlatPunch(0.0075)],
                         ids=["sphere", "punch"])
def test_two_contacts_three_link_lengths_apart(rest, indenter):
    presses = [Press(indenter, (-0.015, -0.004), 2.0), Press(indenter, (0.015, -0.004), 2.0)]
    frames, truth, idx = run_scene(rest, presses, seed=2)
    check(frames, truth, idx)


def test_untouched_sheet_reports_no_contact(rest, rest_scene):
    g = rng(3)
    r0 = ideal_readings(rest_scene.rest_joints)
    sensor = TactileSensor(rest, FOAM)
    n = 400
    hits = sum(bool(sensor.process(noisy_readings(r0, NOISE, g)).contacts) for _ in range(n))
    # measured 0 / 1000 in benchmarks/bench_tactile.py; allow 1 in 400 (0.25 %)
    assert hits / n <= 0.0025


def test_flat_sheet_heights_hold_without_yaw_information(rest, rest_scene):
    """Case 1: the level rest sheet gives no yaw; the prior holds the layout, heights are exact."""
    P = rest_scene.rest_joints
    d, aligned = deformation(P, RestShape.from_joints(P, L))
    assert np.max(np.abs(d)) < 1e-12
    sensor = TactileSensor(rest, FOAM)
    fr = sensor.process(ideal_readings(P))
    assert np.max(np.abs(fr.displacement)) < 6e-5  # rest: mean of 32 noisy snapshots


def test_tracking_keeps_id_while_contact_moves_slowly(rest):
    # 0.25 L per snapshot; gate 2 L
    press = Press(SphereIndenter(0.015), (-0.03, -0.02), 2.0, velocity_mps=(0.0025, 0.002))
    sc = FoamScene(FoamBlock(FoamLayer()), [press], ROWS, COLS, L)
    sensor = TactileSensor(rest, FOAM)
    g = rng(4)
    ids, path = [], []
    for k in range(16):
        fr = sensor.process(noisy_readings(ideal_readings(sc.joints(float(k))), NOISE, g))
        assert len(fr.contacts) == 1
        ids.append(fr.contacts[0].id)
        path.append(fr.contacts[0].index)
    assert set(ids) == {ids[0]}
    assert np.linalg.norm(path[-1] - path[0]) > 4  # it did move (about 4.8 L)


def test_tracker_gives_new_ids_to_new_contacts_and_gates():
    from host.analysis.tactile import Contact

    def c(x):
        return Contact(id=-1, index=np.zeros(2), position=np.array([x, 0.0, 0.0]),
                       normal=np.array([0, 0, 1.0]), depth_m=1e-3, force_n=1.0, area_m2=1e-4,
                       axes_m=np.ones(2), angle_rad=0.0, peak=(0, 0), region=np.zeros((2, 2), bool))

    tr = ContactTracker(gate_m=0.02, max_missed=0)
    a = tr.update([c(0.0)])
    b = tr.update([c(0.01), c(0.1)])
    assert b[0].id == a[0].id and b[1].id != a[0].id
    d = tr.update([c(0.05)])  # too far from both: new id
    assert d[0].id not in (a[0].id, b[1].id)


def test_elongated_contact_orientation_and_axes(rest):
    ind = CapsuleIndenter(0.01, 0.02, angle_rad=0.6)
    frames, truth, idx = run_scene(rest, [Press(ind, (0.0, -0.005), 3.0)], seed=5, snapshots=6)
    for fr in frames:
        assert len(fr.contacts) == 1
        c = fr.contacts[0]
        assert c.axes_m[0] > 1.5 * c.axes_m[1]
        # lattice i along world x here, so the angle from i is the angle from +x
        diff = (c.angle_rad - 0.6 + np.pi / 2) % np.pi - np.pi / 2
        assert abs(diff) < np.radians(15)


def test_find_contacts_on_exact_displacement_conserves_total_force():
    # a 20x20 sheet: the dents' tails stay on the sheet
    presses = [Press(SphereIndenter(0.015), (-0.02, -0.005), 1.0),
               Press(FlatPunch(0.0075), (0.02, -0.005), 2.0)]
    sc = FoamScene(FoamBlock(FoamLayer()), presses, 20, 20, L)
    R = RestShape.from_joints(sc.rest_joints, L, noise_m=np.full((20, 20), 7e-5))
    P = sc.joints(0.0)
    d, _ = deformation(P, R)
    cs = find_contacts(d, R, FOAM)
    moved = np.zeros((20, 20), bool)
    for c in cs:
        moved |= c.region
    d, _ = deformation(P, R, exclude=moved)
    cs = find_contacts(d, R, FOAM)
    assert len(cs) == 2
    # what is lost: the dents' tails beyond the skirts and the sheet's edge
    assert sum(c.force_n for c in cs) == pytest.approx(3.0, rel=0.05)
    assert sorted(c.force_n for c in cs) == pytest.approx([1.0, 2.0], rel=0.08)


def test_cli_runs_and_writes_heat_map(tmp_path, capsys):
    out = tmp_path / "t.png"
    assert cli_main(["tactile", "--duration", "1", "--snapshot-rate", "4", "--out", str(out)]) == 0
    assert out.stat().st_size > 1000
    assert "contact(s)" in capsys.readouterr().out


def test_cli_presses_fingers(tmp_path, capsys):
    """``--indenter finger``: a finger presses, a second joins beside it; the status lines give
    every contact's force with its standard deviation, its footprint and orientation, and the
    onsets and releases."""
    out = tmp_path / "f.png"
    assert cli_main(["tactile", "--indenter", "finger", "--duration", "2", "--snapshot-rate", "8",
                     "--out", str(out)]) == 0
    assert out.stat().st_size > 1000
    text = capsys.readouterr().out
    assert "2 contact(s)" in text and "[onset #1" in text and "[release #0" in text
    assert "±" in text and "deg" in text
    with pytest.raises(SystemExit) as exc:
        cli_main(["tactile", "--indenter", "thumb"])
    assert exc.value.code == 2
    assert "invalid choice: 'thumb'" in capsys.readouterr().err


def test_tracker_holds_the_mean_force_and_restarts_it_on_a_jump():
    from host.analysis.tactile import Contact

    def c(f):
        return Contact(id=-1, index=np.zeros(2), position=np.zeros(3), normal=np.array([0, 0, 1.0]),
                       depth_m=1e-3, force_n=f, area_m2=1e-4, axes_m=np.ones(2), angle_rad=0.0,
                       peak=(0, 0), region=np.zeros((2, 2), bool))

    tr = ContactTracker(gate_m=0.02, force_window=3)
    held = [tr.update([c(f)])[0].force_n_held for f in (1.0, 1.2, 0.8, 1.25, 2.0, 2.1)]
    assert held == pytest.approx([1.0, 1.1, 1.0, 3.25 / 3, 2.0, 2.05])  # window 3; 2.0 is a jump
    assert ContactTracker(0.02).update([c(1.5)])[0].force_n_held == 1.5
    with pytest.raises(ValueError, match="force_window"):
        ContactTracker(0.02, force_window=0)


def test_a_finger_is_one_contact_whose_force_is_fitted_not_summed():
    """A finger is one contact (the old watershed cut it in two 5-15 % of the time,
    and its force fell back to the sampled sum); its force is the fitted model's."""
    from host.analysis.tactile import DetectorSettings
    sc = FoamScene(FoamBlock(FoamLayer()), [Press(CapsuleIndenter(0.01, 0.02, angle_rad=0.6),
                                                  (-0.005, -0.004), 3.0)], ROWS, COLS, L)
    R = RestShape.from_joints(sc.rest_joints, L, noise_m=np.full((ROWS, COLS), 7e-5))
    d, al = deformation(sc.joints(0.0), R)
    fit = find_contacts(d, R, FOAM, DetectorSettings(force_model="fit"), aligned=al)
    summed = find_contacts(d, R, FOAM, DetectorSettings(force_model="sum"), aligned=al)
    assert len(fit) == 1 and not fit[0].ambiguous
    assert fit[0].force_n != summed[0].force_n
    assert fit[0].force_n == pytest.approx(3.0, rel=0.05)


def test_fitted_force_of_a_round_contact_differs_from_the_sum():
    """The fit is really used for a round contact (a check on the test above)."""
    from host.analysis.tactile import DetectorSettings
    sc = FoamScene(FoamBlock(FoamLayer()), [Press(FlatPunch(0.0075), (-0.005, -0.004), 2.0)],
                   ROWS, COLS, L)
    R = RestShape.from_joints(sc.rest_joints, L, noise_m=np.full((ROWS, COLS), 7e-5))
    d, al = deformation(sc.joints(0.0), R)
    fit = find_contacts(d, R, FOAM, DetectorSettings(force_model="fit"), aligned=al)
    summed = find_contacts(d, R, FOAM, DetectorSettings(force_model="sum"), aligned=al)
    assert not fit[0].ambiguous
    assert fit[0].force_n != summed[0].force_n
    assert fit[0].force_n == pytest.approx(2.0, rel=0.05)
    with pytest.raises(ValueError, match="force_model"):
        DetectorSettings(force_model="template")
