"""The layout-poses scene (virtual_sheet/layout_poses.py) and shuffled uids (virtual_sheet/sheet.py)."""

from __future__ import annotations

import numpy as np
import pytest

from virtual_sheet.geometry import ideal_readings
from virtual_sheet.layout_poses import POSES, LayoutPoseScene, PosesThenScene
from virtual_sheet.shapes import make_scene
from virtual_sheet.sheet import VirtualSheet, make_uids

G = 9.80665


def test_every_instant_is_an_exact_net():
    s = LayoutPoseScene(5, 7, link_length=0.02, hold_s=1.0, move_s=1.0)
    for t in np.arange(0.0, s.period_s, 0.13):
        P = s.joints(t)
        li = np.linalg.norm(np.diff(P, axis=0), axis=2)
        lj = np.linalg.norm(np.diff(P, axis=1), axis=2)
        assert np.allclose(li, 0.02, atol=1e-12) and np.allclose(lj, 0.02, atol=1e-12), t


def test_the_poses_read_as_designed():
    """Flat: +g on z; ramp: i-links pitch up by tilt_rad, j-links roll; humps: the i-links' (j-links')
    slope falls from +hump_rad at row (column) 0 to -hump_rad."""
    s = LayoutPoseScene(4, 5, hold_s=2.0, move_s=1.0, tilt_rad=0.5, hump_rad=1.0, jitter_rad=0.0)
    at = {name: k * 3.0 + 1.0 for k, name in enumerate(POSES)}
    n_i = 3 * 5
    r = {name: ideal_readings(s.joints(t)) / G for name, t in at.items()}
    assert np.allclose(r["flat"], [0, 0, 1], atol=1e-12)
    assert np.allclose(r["tilt"][:n_i], [np.sin(0.5), 0, np.cos(0.5)], atol=1e-12)
    assert np.allclose(r["tilt"][n_i:], [0, -np.sin(0.5), np.cos(0.5)], atol=1e-12)
    slope_i = r["hump_i"][:n_i, 0].reshape(3, 5)  # rows of i-links
    assert np.allclose(slope_i, np.sin(1.0 * (1 - 2 * (np.arange(3) + 0.5) / 3))[:, None], atol=1e-12)
    slope_j = r["hump_j"][n_i:, 0].reshape(4, 4)  # j-links: columns
    assert np.allclose(slope_j, np.sin(1.0 * (1 - 2 * (np.arange(4) + 0.5) / 4))[None, :], atol=1e-12)


def test_pose_at_follows_the_timer():
    s = LayoutPoseScene(3, 3, hold_s=2.0, move_s=0.5)
    assert [s.pose_at(t) for t in (0.1, 2.1, 2.6, 5.1, 7.6, 9.9, 10.1)] == \
        ["flat", None, "tilt", "hump_i", "hump_j", None, "flat"]


@pytest.mark.parametrize("kw", [{"hold_s": 0}, {"move_s": -1}, {"tilt_rad": 2.0}, {"hump_rad": 0}, {"jitter_rad": 1}])
def test_bad_parameters_are_named(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        LayoutPoseScene(3, 3, **kw)


def test_shuffled_ids_are_the_same_uids_on_other_links():
    plain = VirtualSheet("flat", "6x6", seed=4)
    shuffled = VirtualSheet("flat", "6x6", seed=4, shuffle_ids=True)
    assert plain.uids == make_uids(plain.n_links, 4)
    assert sorted(shuffled.uids) == sorted(plain.uids)
    moved = sum(1 for u in plain.uids if plain.layout[u] != shuffled.layout[u])
    assert moved > 0.9 * plain.n_links
    assert VirtualSheet("flat", "6x6", seed=4, shuffle_ids=True).uids == shuffled.uids  # seeded


def test_poses_then_another_scene_switches_once_at_a_step():
    poses = LayoutPoseScene(4, 4, hold_s=1.0, move_s=1.0)
    grow = make_scene("grow", 4, 4, 0.01)
    s = PosesThenScene(poses, grow)
    assert s.precompute(10.0) == 80 + 40
    assert np.array_equal(s.joints(3.0), poses.joints(3.0))
    s.switch(5.0)
    assert np.array_equal(s.joints(4.9), poses.joints(4.9))
    assert np.allclose(s.joints(5.2), grow.joints(5.2), atol=1e-12)
    assert np.allclose(s.joints(5.25), grow.joints(5.25), atol=1e-12)  # off the step grid: solved
    with pytest.raises(ValueError, match="already switched"):
        s.switch(6.0)
