"""The board-pose scene (virtual_sheet/board.py): poses held, turns between them, and gravity in
the board's frame as the calibration sees it."""

import numpy as np
import pytest

from protocol.constants import G0
from virtual_sheet.board import DEFAULT_DIRECTIONS, BoardPoseScene, board_rotation
from virtual_sheet.geometry import ideal_readings, link_lengths
from virtual_sheet.shapes import make_scene
from virtual_sheet.sheet import VirtualSheet


@pytest.mark.parametrize("u", DEFAULT_DIRECTIONS + ((0.3, -0.5, 0.8), (0.0, 0.0, -2.0)))
def test_board_rotation_puts_gravity_where_asked(u):
    R = board_rotation(u)
    assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(R.T @ [0, 0, 1], np.asarray(u) / np.linalg.norm(u))


def test_held_poses_read_gravity_in_the_board_frame():
    s = BoardPoseScene(3, 4, 0.01, hold_s=2.0, move_s=1.0, jitter_rad=0.0)
    n_i = 2 * 4
    for i, u in enumerate(DEFAULT_DIRECTIONS):
        t = i * 3.0 + 0.7
        assert s.pose_at(t) == i
        r = ideal_readings(s.joints(t))
        g = G0 * np.asarray(u)
        assert np.allclose(r[:n_i], g)  # i-links: sensor axes are the board's
        assert np.allclose(r[n_i:], [g[1], -g[0], g[2]])  # j-links: x along board y, y along -x
    # the sheet stays flat and exact while turning
    for t in (2.1, 2.5, 2.9):
        assert s.pose_at(t) is None
        assert np.allclose(link_lengths(s.joints(t)), 0.01)
    assert s.pose_at(s.period_s + 0.1) == 0  # it starts again


def test_turning_changes_the_readings_and_jitter_is_seeded():
    s = BoardPoseScene(3, 3, hold_s=3.0, move_s=1.0, jitter_rad=0.03, seed=5)
    a, b = ideal_readings(s.joints(3.2)), ideal_readings(s.joints(3.8))
    assert np.abs(a - b).max() > 1.0  # m/s²: a turn is plainly not still
    same = BoardPoseScene(3, 3, jitter_rad=0.03, seed=5)
    other = BoardPoseScene(3, 3, jitter_rad=0.03, seed=6)
    assert np.array_equal(same.joints(1.0), s.joints(1.0))
    assert not np.allclose(other.joints(1.0), s.joints(1.0))
    ang = np.degrees(np.arccos(np.clip(s.gravity_in_board(0) @ [0, 0, 1] / G0, -1, 1)))
    assert 0 < ang < 10


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="hold_s"):
        BoardPoseScene(3, 3, hold_s=0)
    with pytest.raises(ValueError, match="directions"):
        BoardPoseScene(3, 3, directions=((0, 0, 1, 0),))
    with pytest.raises(ValueError, match="direction"):
        board_rotation((0, 0, 0))


def test_the_virtual_sheet_runs_the_board_scene_by_name():
    assert isinstance(make_scene("board", 3, 3, 0.01, hold_s=1.0), BoardPoseScene)
    sheet = VirtualSheet("board", "3x3", shape_params={"hold_s": 1.0, "move_s": 0.5})
    counts, _status = sheet.counts_at(1.2)  # turning from top up to top down
    assert sheet.scene.pose_at(1.2) is None and counts.shape == (12, 3)


def _rng(seed: int) -> np.random.Generator:
    return np.random.Generator(np.random.MT19937(seed))


@pytest.mark.parametrize("seed", range(3))
def test_the_scene_turns_as_scipys_slerp_did(seed):
    """The scene without scipy: the poses, the orientation through every turn and the rotation jet
    are what scipy's `Rotation` and `Slerp` made of the same poses, to 1e-12."""
    from scipy.spatial.transform import Rotation, Slerp

    s = BoardPoseScene(3, 3, 0.01, hold_s=1.5, move_s=0.8, seed=seed)
    d = np.asarray(DEFAULT_DIRECTIONS)
    jit = Rotation.from_rotvec(_rng(seed).normal(0.0, s.jitter_rad, d.shape)).as_matrix()

    def scipy_board_rotation(u):
        u = u / np.linalg.norm(u)
        axis = np.cross(u, [0.0, 0.0, 1.0])
        sn, c = np.linalg.norm(axis), float(u[2])
        if sn < 1e-12:
            return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
        return Rotation.from_rotvec(axis / sn * np.arctan2(sn, c)).as_matrix()

    R = np.array([scipy_board_rotation(u) for u in d]) @ jit
    for k, u in enumerate(d):
        np.testing.assert_allclose(board_rotation(u), scipy_board_rotation(u), rtol=0, atol=1e-12)
        np.testing.assert_allclose(s.gravity_in_board(k), R[k].T @ [0.0, 0.0, G0], rtol=0, atol=1e-12)
    t = np.linspace(0.0, s.period_s, 500, endpoint=False) + 1e-4
    jet_R, omega, _domega = s.rotation_jet(t)
    for k, tk in enumerate(t):
        i, tau = divmod(tk % s.period_s, s.hold_s + s.move_s)
        i, j = int(i), (int(i) + 1) % s.n_poses
        if tau < s.hold_s:
            want = R[i]
        else:
            w = 0.5 - 0.5 * np.cos(np.pi * (tau - s.hold_s) / s.move_s)
            want = Slerp([0.0, 1.0], Rotation.from_matrix(R[[i, j]]))([w]).as_matrix()[0]
        np.testing.assert_allclose(s.orientation(tk), want, rtol=0, atol=1e-12)
        np.testing.assert_allclose(jet_R[k], want, rtol=0, atol=1e-12)
    assert np.abs(omega).max() > 1.0  # the turns were in it
