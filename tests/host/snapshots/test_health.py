"""Chip health (host/snapshots/health.py) on a simulated clock with exact counts, then through the Host over a
real pty: per-chip |reading| ≈ g on still snapshots, and bias shifts against the neighbours."""

from __future__ import annotations

import numpy as np
import pytest

from host.analysis.calibration import Calibration
from host.snapshots.health import HealthChecker
from host.session.core import Host, Layout
from host.transport.ports import SerialTransport
from protocol.constants import G0
from virtual_sheet.devices import PtyDevice
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import chip_error_model, noisy_readings
from virtual_sheet.shapes import GrowScene, TiltScene, make_sheet
from virtual_sheet.sheet import VirtualSheet

MG = G0 / 1000


def rng(seed):
    return np.random.Generator(np.random.MT19937(seed))


def feed(hc, frames, t0=0.0, dt=0.01):
    events = []
    for i, r in enumerate(frames):
        events += hc.update(r, None, t0 + i * dt)
    return events


def still(f, count, g, noise=0.3):
    return [noisy_readings(f, noise, g) for _ in range(count)]


def test_a_calibrated_still_sheet_raises_nothing_and_windows_are_counted():
    f = ideal_readings(make_sheet("gaussian", 6, 6, 0.01))
    hc = HealthChecker(6, 6, window=25)
    assert feed(hc, still(f, 250, rng(1))) == []
    # 24 snapshots fill the stillness window, then one averaged window per 25 still snapshots
    assert hc.windows == (250 - 24) // 25
    assert np.abs(hc.deviation).max() < 5 * MG


def test_a_chip_off_g_is_flagged_once_and_cleared_when_it_recovers():
    f = ideal_readings(make_sheet("flat", 5, 5, 0.01))
    g = rng(2)
    bad = f.copy()
    bad[7] *= 1.03  # a 3 % scale error on link 7: 30 mg
    hc = HealthChecker(5, 5, window=20)
    events = feed(hc, still(bad, 200, g))
    assert [(e.kind, e.link) for e in events] == [("health_magnitude", 7)]
    assert events[0].value == pytest.approx(0.03 * G0, abs=3 * MG)
    assert events[0].t == pytest.approx(0.01 * (19 + 20 - 1))  # the end of the first still window
    assert hc.flagged.tolist() == [k == 7 for k in range(hc.lattice.n_links)]
    events = feed(hc, still(f, 200, g), t0=10.0)
    assert ("health_magnitude_ok", 7) in [(e.kind, e.link) for e in events]
    assert not hc.flagged.any()
    # below the threshold: nothing
    hc2 = HealthChecker(5, 5, window=20)
    mild = f.copy()
    mild[7] *= 1.01
    assert feed(hc2, still(mild, 200, g)) == []


def test_a_bias_shift_is_found_against_the_neighbours():
    f = ideal_readings(make_sheet("gaussian", 6, 6, 0.01))
    g = rng(3)
    shifted = f.copy()
    shifted[40] += [0.0, 0.15, 0.0]  # 15 mg on y of link 40, in a still stretch
    hc = HealthChecker(6, 6, window=25)
    events = feed(hc, still(f, 100, g) + still(shifted, 100, g))
    shifts = [(e.kind, e.link) for e in events if e.kind == "health_bias_shift"]
    assert shifts == [("health_bias_shift", 40)]
    assert hc.shifts == 1
    # without the shift, the same stream gives no shift
    hc2 = HealthChecker(6, 6, window=25)
    assert [e for e in feed(hc2, still(f, 200, rng(3))) if e.kind == "health_bias_shift"] == []


@pytest.mark.parametrize("scene", [TiltScene(6, 6, 0.01, max_tilt=0.4), GrowScene(6, 6, 0.01)],
                         ids=["tilting", "growing bump"])
def test_a_sheet_that_moves_between_still_stretches_is_no_bias_shift(scene):
    g = rng(4)
    frames = []
    for t in (0.3, 0.8, 1.3, 1.7):  # four still poses of a moving scene, turning in between
        frames += still(ideal_readings(scene.joints(t)), 60, g)
        frames += [ideal_readings(scene.joints(t + 0.02 * k)) for k in range(1, 6)]  # moving
    hc = HealthChecker(6, 6, window=25)
    events = feed(hc, frames)
    assert hc.windows >= 4
    assert [e for e in events if e.kind == "health_bias_shift"] == []


def test_moving_snapshots_are_not_judged():
    scene = TiltScene(4, 4, 0.01, max_tilt=0.5, period_s=1.0)
    hc = HealthChecker(4, 4, window=10)
    frames = [ideal_readings(scene.joints(0.01 * k)) * 1.05 for k in range(200)]  # 5 % off, moving
    assert feed(hc, frames) == [] and hc.windows == 0
    with pytest.raises(ValueError, match=r"shape \(24, 3\)"):
        hc.update(np.zeros((23, 3)), None, 0.0)


@pytest.fixture
def realistic_rig():
    sensor = chip_error_model("realistic", noise_pct_g=0.2, chip_seed=5)
    sheet = VirtualSheet("flat", "4x4", sensor=sensor, seed=5)
    dev = PtyDevice(sheet)
    dev.start()
    host = Host([SerialTransport(dev.path)], "4x4", layout=Layout(dict(sheet.layout)), rate_hz=100,
                timeout_s=0.15, retries=5, deadline_s=0.2)
    try:
        yield sheet, host
    finally:
        host.close()
        dev.stop()


def true_calibration(sheet) -> Calibration:
    e = sheet.sensor_model.chip_errors(sheet.n_links)
    from scipy.spatial.transform import Rotation
    return Calibration(4, 4, bias=e.offset_counts * G0 / 1024, scale=e.sensitivity / 1024,
                       misalignment=Rotation.from_matrix(e.misalignment).as_rotvec())


def test_the_host_corrects_snapshots_and_reports_health_events(realistic_rig):
    sheet, host = realistic_rig
    f = ideal_readings(sheet.joints(0.0))
    e = sheet.sensor_model.chip_errors(sheet.n_links)
    raw_dev = np.linalg.norm(np.einsum("kji,kj->ki", e.misalignment, f) * e.sensitivity / 1024
                             + e.offset_counts * G0 / 1024, axis=1) - G0
    host.bring_up()
    host.health = HealthChecker(4, 4, window=20)
    raw = [s for s in host.snapshots(count=120) if s.complete]
    flagged = {ev.link for ev in host.events if ev.kind == "health_magnitude"}
    # uncalibrated: the chips the truth puts beyond 25 mg are flagged, those within 15 mg are not
    assert {k for k in range(sheet.n_links) if abs(raw_dev[k]) > 25 * MG} <= flagged
    assert not flagged & {k for k in range(sheet.n_links) if abs(raw_dev[k]) < 15 * MG}
    assert flagged  # realistic chips: some are off
    # calibrated with the truth: readings are the ideal ones to the noise; the flags clear
    host.set_calibration(true_calibration(sheet))  # corrects every snapshot emitted from now on
    host.drain()  # those emitted before
    fixed = [s for s in host.snapshots(count=120) if s.complete]
    host.stop()
    assert len(raw) > 40 and len(fixed) > 40
    mean = np.mean([s.readings for s in fixed], axis=0)
    assert np.abs(mean - f).max() < 3 * MG
    assert np.abs(np.mean([s.readings for s in raw], axis=0) - f).max() > 20 * MG
    cleared = {ev.link for ev in host.events if ev.kind == "health_magnitude_ok"}
    assert cleared == flagged
    assert not host.health.flagged.any()
