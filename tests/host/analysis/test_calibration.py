"""The per-chip calibration fit (host/analysis/calibration.py), checked against the virtual sheet's
truth: readings come from the board-pose scene through the sensor model's ADC, exactly as a
capsheet calibrate run sees them."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from host.analysis.calibration import (BOARD_POSES, G0, MIN_POSES, NOMINAL_SENSITIVITY, Calibration,
                                       StaticDetector, fit_board_poses)
from protocol.constants import G0 as PROTOCOL_G0
from protocol.constants import counts_to_si, nominal_sensitivity
from virtual_sheet.board import BoardPoseScene
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import chip_error_model

MG = G0 / 1000.0
ROWS = COLS = 6


def rng(seed):
    return np.random.Generator(np.random.MT19937(seed))


def pose_readings(model, scene, samples, seed, poses=None):
    """Each pose's readings averaged over ``samples`` ADC samples, converted with the nominal
    calibration (what the host sees from uncalibrated chips)."""
    g = rng(seed)
    out = []
    for i in (range(scene.n_poses) if poses is None else poses):
        f = ideal_readings(scene.joints(i * (scene.hold_s + scene.move_s)))
        acc = np.zeros_like(f)
        for _ in range(samples):
            counts, _status = model.sample(f, g if model.noise_pct_g > 0 else None)
            acc += counts_to_si(counts.astype(float))
        out.append(acc / samples)
    return np.array(out)


def truth(model, n):
    """Bias (m/s²), scale, and misalignment rotation vectors minus their common part (in the
    board's frame), computed here from the sensor model's errors, independently of the fit."""
    e = model.chip_errors(n)
    bias = e.offset_counts * G0 / NOMINAL_SENSITIVITY
    scale = e.sensitivity / NOMINAL_SENSITIVITY
    n_i = (ROWS - 1) * COLS
    R0 = np.tile(np.eye(3), (n, 1, 1))
    R0[n_i:] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    B = R0 @ e.misalignment @ np.transpose(R0, (0, 2, 1))
    U, _s, Vt = np.linalg.svd(B.mean(axis=0))
    Q = U @ Vt
    mis = Rotation.from_matrix(np.transpose(R0, (0, 2, 1)) @ Q.T @ B @ R0).as_rotvec()
    return bias, scale, mis


@pytest.fixture(scope="module")
def realistic():
    model = chip_error_model("realistic", noise_pct_g=0.3, chip_seed=11)
    scene = BoardPoseScene(ROWS, COLS, jitter_rad=0.03, seed=4)
    r = pose_readings(model, scene, 200, seed=5)
    return model, scene, r, fit_board_poses(r, ROWS, COLS)


def test_constants_agree_with_the_protocol():
    assert G0 == PROTOCOL_G0
    assert NOMINAL_SENSITIVITY == nominal_sensitivity()


def test_host_calibration_re_exports_the_public_names():
    import host.analysis.calibration as real
    import host.calibration as alias
    assert alias.__all__ == real.__all__ and all(getattr(alias, n) is getattr(real, n) for n in real.__all__)
    from host.calibration import Calibration as C, fit_board_poses as f
    assert C is Calibration and f is fit_board_poses


def test_recovers_realistic_chip_errors_within_the_stated_accuracy(realistic):
    model, _scene, _r, cal = realistic
    n = cal.n_links
    bias, scale, mis = truth(model, n)
    assert np.abs(cal.bias - bias).max() < 2 * MG
    assert np.abs(cal.scale - scale).max() < 1e-3
    assert np.abs(cal.misalignment - mis).max() < np.radians(0.1)
    # the errors were there to find: an identity calibration misses every bound
    assert np.abs(bias).max() > 2 * MG and np.abs(scale - 1).max() > 1e-3
    assert np.abs(mis).max() > np.radians(0.1)
    assert cal.outliers == ()
    # residual: the averaged noise (0.3 % g / sqrt(200)) and the ADC's quantisation, no model error
    assert cal.residual_rms < 0.3e-2 * G0 / np.sqrt(200) * 1.5


def test_noise_free_readings_are_fitted_exactly():
    model = chip_error_model("realistic", noise_pct_g=0.0, chip_seed=3)
    scene = BoardPoseScene(ROWS, COLS, jitter_rad=0.05, seed=9)
    n = (ROWS - 1) * COLS + ROWS * (COLS - 1)
    e = model.chip_errors(n)
    g = np.array([scene.gravity_in_board(i) for i in range(scene.n_poses)])
    # the model without the ADC: s ⊙ Mᵀ R0ᵀ g + b, built from the geometry's own frames
    f = np.array([ideal_readings(scene.joints(i * (scene.hold_s + scene.move_s))) for i in range(scene.n_poses)])
    r = (np.einsum("kji,pkj->pki", e.misalignment, f) * e.sensitivity / NOMINAL_SENSITIVITY
         + e.offset_counts * G0 / NOMINAL_SENSITIVITY)
    cal = fit_board_poses(r, ROWS, COLS)
    bias, scale, mis = truth(model, n)
    assert np.abs(cal.bias - bias).max() < 1e-8
    assert np.abs(cal.scale - scale).max() < 1e-9
    assert np.abs(cal.misalignment - mis).max() < 1e-9
    assert cal.residual_rms < 1e-9
    # the pose directions are the truth turned by the common rotation: their mutual angles agree
    assert np.allclose(cal.pose_directions @ cal.pose_directions.T, (g @ g.T) / G0 ** 2, atol=1e-9)


def test_a_common_rotation_of_every_chip_is_not_identified():
    # the same chips, all turned by one extra rotation: the fit gives the same misalignments
    base = chip_error_model("realistic", noise_pct_g=0.0, chip_seed=3)
    scene = BoardPoseScene(ROWS, COLS, jitter_rad=0.0)
    n = (ROWS - 1) * COLS + ROWS * (COLS - 1)
    f = np.array([ideal_readings(scene.joints(i * (scene.hold_s + scene.move_s))) for i in range(scene.n_poses)])
    e = base.chip_errors(n)
    extra = Rotation.from_rotvec([0.02, -0.01, 0.015]).as_matrix()  # board frame
    n_i = (ROWS - 1) * COLS
    R0 = np.tile(np.eye(3), (n, 1, 1))
    R0[n_i:] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    turned = np.transpose(R0, (0, 2, 1)) @ extra @ R0 @ e.misalignment
    fits = [fit_board_poses(np.einsum("kji,pkj->pki", M, f), ROWS, COLS) for M in (e.misalignment, turned)]
    assert np.abs(fits[0].misalignment - fits[1].misalignment).max() < 1e-9
    # and the gauge chosen is "mean board-frame misalignment = identity"
    B = R0 @ fits[0].rotations @ np.transpose(R0, (0, 2, 1))
    U, _s, Vt = np.linalg.svd(B.mean(axis=0))
    assert np.abs(Rotation.from_matrix(U @ Vt).as_rotvec()).max() < 1e-9


def test_apply_corrects_a_pose_the_fit_never_saw(realistic):
    model, scene, _r, cal = realistic
    other = BoardPoseScene(ROWS, COLS, directions=((0.3, -0.5, 0.8),), jitter_rad=0.0)
    f_true = ideal_readings(other.joints(0.0))
    raw = pose_readings(model, other, 200, seed=8)[0]
    fixed = cal.apply(raw)
    n = cal.n_links
    # only the common rotation (unidentifiable, < 0.2° here) and the averaged noise remain;
    # compare directions after removing one rotation common to the whole board
    err_raw = np.linalg.norm(raw - f_true, axis=1)
    err_fixed = np.linalg.norm(fixed - f_true, axis=1)
    assert np.median(err_fixed) < 0.1 * np.median(err_raw)
    assert np.abs(np.linalg.norm(fixed, axis=1) - G0).max() < 2 * MG
    # shapes: a batch (..., n, 3) keeps its shape; a wrong one is refused
    assert cal.apply(np.stack([raw, raw])).shape == (2, n, 3)
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 60, 3\)"):
        cal.apply(raw[:-1])


def test_chip_calibration_and_rebase(realistic):
    model, _scene, _r, cal = realistic
    e = model.chip_errors(cal.n_links)
    off, sens = cal.chip_calibration()
    assert np.abs(off - e.offset_counts).max() < 2 * MG / G0 * NOMINAL_SENSITIVITY  # 2 mg in counts
    assert np.abs(sens / e.sensitivity - 1).max() < 1e-3
    # the chips now report (off, sens): rebased, only the misalignment is left
    written = cal.rebased(off, sens)
    assert np.abs(written.bias).max() < 1e-12 and np.abs(written.scale - 1).max() < 1e-12
    assert np.array_equal(written.misalignment, cal.misalignment)
    raw = np.random.default_rng(0).normal(0, 5, (cal.n_links, 3))
    counts = raw / G0 * NOMINAL_SENSITIVITY  # readings converted with the nominal calibration ...
    as_written = (counts - off) / sens * G0  # ... and the same counts with the written one
    assert np.allclose(written.apply(as_written), cal.apply(raw), atol=1e-9)


def test_too_few_poses_wrong_shapes_and_nan_are_named(realistic):
    _m, _s, r, _cal = realistic
    with pytest.raises(ValueError, match=f"Too few poses: {MIN_POSES - 1}"):
        fit_board_poses(r[:MIN_POSES - 1], ROWS, COLS)
    with pytest.raises(ValueError, match=r"shape \(n_poses, 60, 3\) for a 6x6 lattice, got \(12, 59, 3\)"):
        fit_board_poses(r[:, :-1], ROWS, COLS)
    with pytest.raises(ValueError, match="shape"):
        fit_board_poses(r, 5, 6)
    bad = r.copy()
    bad[3, 17, 1] = np.nan
    with pytest.raises(ValueError, match="NaN or inf .*pose 3, link 17"):
        fit_board_poses(bad, ROWS, COLS)


def test_poses_too_alike_are_refused():
    model = chip_error_model("realistic", noise_pct_g=0.0, chip_seed=1)
    # eight tilts within 25° of top up: z never sees -g, bias and scale of z cannot separate
    dirs = [(np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), np.cos(a))
            for a in (0.2, 0.4) for b in (0, 1.6, 3.2, 4.8)]
    scene = BoardPoseScene(ROWS, COLS, directions=tuple(dirs), jitter_rad=0.0)
    with pytest.raises(ValueError, match="Poses too alike .* z axis"):
        fit_board_poses(pose_readings(model, scene, 1, 0), ROWS, COLS)
    # the six faces, each twice: every axis spans 2 g, accepted
    faces = BoardPoseScene(ROWS, COLS, directions=tuple(p[2] for p in BOARD_POSES[:6]) * 2, jitter_rad=0.0)
    fit_board_poses(pose_readings(model, faces, 1, 0), ROWS, COLS)


def test_a_chip_that_moved_during_a_pose_is_an_outlier(realistic):
    _m, _s, r, cal = realistic
    assert cal.outliers == ()
    bad = r.copy()
    bad[4, 23] += [0.15, -0.1, 0.05]  # link 23 slipped in pose 4 (about 19 mg)
    out = fit_board_poses(bad, ROWS, COLS)
    assert out.outliers == (23,)
    assert out.chip_rms[23] > 4 * np.median(out.chip_rms)


def test_save_and_load_round_trip(tmp_path, realistic):
    cal = realistic[3]
    path = cal.save(tmp_path / "cal.json")
    back = Calibration.load(path)
    for name in ("bias", "scale", "misalignment", "chip_rms", "reference_offset_counts",
                 "reference_sensitivity", "pose_directions"):
        assert np.array_equal(getattr(back, name), getattr(cal, name)), name
    assert back.outliers == cal.outliers and back.residual_rms == cal.residual_rms
    doc = json.loads(path.read_text())
    assert doc["format"] == "capsheet-calibration" and len(doc["chips"]) == cal.n_links
    doc["chips"][5]["scale"] = [1.0, -0.2, 1.0]
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"bad.json: chip 5: scale -0.2 is outside \[0.5, 2\]"):
        Calibration.load(tmp_path / "bad.json")
    del doc["chips"][5]
    (tmp_path / "short.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="links 0..59 once each"):
        Calibration.load(tmp_path / "short.json")
    (tmp_path / "other.json").write_text('{"format": "capsheet-layout"}')
    with pytest.raises(ValueError, match="not a capsheet calibration"):
        Calibration.load(tmp_path / "other.json")


def test_static_detector_on_a_simulated_stream():
    det = StaticDetector(4, window=5, threshold_mps2=0.1)
    g = rng(1)
    still = [np.full((4, 3), 5.0) + g.normal(0, 0.03, (4, 3)) for _ in range(12)]
    turning = [np.full((4, 3), 5.0 + 0.5 * (k + 1)) for k in range(6)]
    states = [det.update(r) for r in still + turning + still]
    # 4 snapshots to fill the window, still after; the turn breaks it until 5 still ones again
    assert states == [False] * 4 + [True] * 8 + [False] * 6 + [False] * 4 + [True] * 8
    # a missing chip is not judged; the others decide
    det2 = StaticDetector(4, window=3, threshold_mps2=0.1)
    valid = np.array([True, True, True, False])
    assert [det2.update(r, valid) for r in still[:4]] == [False, False, True, True]
    with pytest.raises(ValueError, match=r"shape \(4, 3\)"):
        det2.update(np.zeros((3, 3)))


def test_non_orthogonal_axes_are_fitted_when_asked():
    from host.analysis.calibration import _lower  # the model's own T; the data below builds it by hand
    model = chip_error_model("realistic", noise_pct_g=0.0, chip_seed=6)
    scene = BoardPoseScene(ROWS, COLS, jitter_rad=0.03, seed=2)
    n = (ROWS - 1) * COLS + ROWS * (COLS - 1)
    e = model.chip_errors(n)
    t = rng(9).normal(0, np.radians(0.5), (n, 3))  # y towards x, z towards x, z towards y
    T = np.zeros((n, 3, 3))
    T[:, 0, 0] = T[:, 1, 1] = T[:, 2, 2] = 1
    T[:, 1, 0], T[:, 2, 0], T[:, 2, 1] = t[:, 0], t[:, 1], t[:, 2]
    assert np.array_equal(T, _lower(t))
    f = np.array([ideal_readings(scene.joints(i * (scene.hold_s + scene.move_s))) for i in range(scene.n_poses)])
    chip = np.einsum("kij,pkj->pki", T, np.einsum("kji,pkj->pki", e.misalignment, f))  # T Mᵀ f
    r = chip * e.sensitivity / NOMINAL_SENSITIVITY + e.offset_counts * G0 / NOMINAL_SENSITIVITY
    cal = fit_board_poses(r, ROWS, COLS, non_orthogonality=True)
    bias, scale, mis = truth(model, n)
    assert np.abs(cal.non_orthogonality - t).max() < 1e-8
    assert np.abs(cal.misalignment - mis).max() < 1e-8
    assert np.abs(cal.bias - bias).max() < 1e-8 and np.abs(cal.scale - scale).max() < 1e-9
    # corrected readings are the true ones turned by the common rotation Q (the gauge): R0ᵀ Qᵀ R0 f
    n_i = (ROWS - 1) * COLS
    R0 = np.tile(np.eye(3), (n, 1, 1))
    R0[n_i:] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    U, _s, Vt = np.linalg.svd((R0 @ e.misalignment @ np.transpose(R0, (0, 2, 1))).mean(axis=0))
    turn = np.transpose(R0, (0, 2, 1)) @ (U @ Vt).T @ R0
    assert np.abs(cal.apply(r) - np.einsum("kij,pkj->pki", turn, f)).max() < 1e-7
    # the same data without the terms: the skew the misalignment cannot absorb stays in the
    # residuals (3.4 mg here, against 0.18 mg of averaged noise in a real capture)
    plain = fit_board_poses(r, ROWS, COLS)
    assert plain.residual_rms > 2 * MG and cal.residual_rms < 1e-9
    assert not plain.non_orthogonality.any()
    # and the terms survive the file
    import tempfile, os
    with tempfile.TemporaryDirectory() as d:
        back = Calibration.load(cal.save(os.path.join(d, "c.json")))
    assert np.array_equal(back.non_orthogonality, cal.non_orthogonality)
