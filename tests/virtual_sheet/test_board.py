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
