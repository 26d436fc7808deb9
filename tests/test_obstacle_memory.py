"""Obstacle memory: remembers what left the view, decays, ray-clears, stays bounded."""

from __future__ import annotations

import math

import numpy as np

from drivers.depth_source import D435_848x480
from runtime.config.settings import CameraMount
from runtime.perception.depth_points import Perception
from runtime.perception.obstacle_memory import ObstacleMemory, ObstacleMemoryConfig
from sim_stub.depth_render import Cylinder, DepthRenderer, Scene
from sim_stub.sim_server import BASE_LINK_HEIGHT_M

MOUNT = CameraMount()
PER = Perception(D435_848x480, MOUNT)
BINS = PER.bin_angles
NB = len(BINS)


def render(pose, scene):
    rend = DepthRenderer(D435_848x480, MOUNT, base_z=BASE_LINK_HEIGHT_M, seed=1)
    return PER.process(rend.render(pose, scene, noise=True))


def free_scan(r: float = 4.0) -> np.ndarray:
    return np.full(NB, r, dtype=np.float32)


def no_unknown() -> np.ndarray:
    return np.zeros(NB, dtype=bool)


def test_obstacle_that_left_the_view_is_remembered_for_decay_time_then_forgotten():
    mem = ObstacleMemory(ObstacleMemoryConfig(decay_s=3.0))
    post = Cylinder(1.5, 0.0, 0.15)
    out = render((0.0, 0.0, 0.0), Scene([post]))
    assert len(out.points) > 0
    mem.update_from(out, (0.0, 0.0, 0.0), t=0.0, view=PER.view)
    seen = mem.points_base((0.0, 0.0, 0.0))
    assert len(seen) > 0 and np.all(np.abs(np.hypot(seen[:, 0] - 1.5, seen[:, 1]) - 0.15) < 0.05)
    # turn 90 deg left in place: the post is now at the robot's right (-y), outside the view
    pose = (0.0, 0.0, math.pi / 2)
    for k in range(1, 30):  # 0.1 s frames until t = 2.9 s: the view sees only floor
        out = render(pose, Scene([post]))
        assert len(out.points) == 0
        mem.update_from(out, pose, t=0.1 * k, view=PER.view)
        kept = mem.points_base(pose)
        assert len(kept) == len(seen)
        np.testing.assert_allclose(kept[:, 0], seen[:, 1], atol=1e-5)
        np.testing.assert_allclose(kept[:, 1], -seen[:, 0], atol=1e-5)
    assert len(mem.points_base(pose, t=3.0)) == len(seen)  # still alive exactly at decay_s
    mem.update_from(render(pose, Scene([post])), pose, t=3.05, view=PER.view)
    assert len(mem.points_base(pose)) == 0
    assert mem.decayed_total == len(seen)


def test_an_obstacle_beside_the_robot_is_kept_while_out_of_view_and_cleared_once_seen_gone():
    """Not seeing a cell is no evidence that it is gone: a person standing beside the robot,
    out of the camera's view, is remembered past decay_s (the robot drove into one it had
    forgotten); turning to look at the place, empty now, clears it."""
    mem = ObstacleMemory(ObstacleMemoryConfig(decay_s=3.0))  # hold_out_of_view_m 1.0
    person = Cylinder(0.7, 0.0, 0.25)
    mem.update_from(render((0.0, 0.0, 0.0), Scene([person])), (0.0, 0.0, 0.0), t=0.0,
                    view=PER.view)
    seen = len(mem)
    assert seen > 0
    beside = (0.0, 0.0, math.pi / 2)  # turned left: the person is at the robot's right
    for k in range(1, 60):  # 6 s, twice decay_s
        out = render(beside, Scene([person]))
        assert len(out.points) == 0
        mem.update_from(out, beside, t=0.1 * k, view=PER.view)
        assert len(mem.points_base(beside)) == seen  # handed to the planner and the shield
    assert len(mem) == seen and mem.decayed_total == 0
    # the person has gone; the robot turns back and sees the floor where they stood
    mem.update_from(render((0.0, 0.0, 0.0), Scene([])), (0.0, 0.0, 0.0), t=6.0, view=PER.view)
    assert len(mem) == 0


def test_a_corner_beside_the_robot_at_the_view_s_edge_is_not_cleared_by_rays_that_miss_it():
    """Perception bins rays by their bearing from the camera, which sits ahead of base_link:
    a cell close beside the robot lies inside the view by its bearing from base_link but
    outside every ray the camera casts, so free space seen by those rays says nothing about it
    (a box's corner was cleared this way and driven into)."""
    corner = np.array([[0.305, -0.19]], np.float32)
    assert PER.view.bin_of(np.arctan2(corner[:, 1], corner[:, 0]))[0] >= 0  # in by base bearing
    mem = ObstacleMemory()
    mem.update(corner, (0.0, 0.0, 0.0), free_scan(0.36), no_unknown(), BINS, 0.0,
               heights=np.array([0.7], np.float32), view=PER.view)
    mem.update(np.empty((0, 2), np.float32), (0.0, 0.0, 0.0), free_scan(4.0), no_unknown(), BINS,
               0.1, view=PER.view)
    assert len(mem) == 1 and mem.cleared_total == 0
    # straight ahead, where the camera's rays do pass, the same free space clears
    ahead = ObstacleMemory()
    ahead.update(np.array([[1.0, 0.0]], np.float32), (0.0, 0.0, 0.0), free_scan(1.0),
                 no_unknown(), BINS, 0.0, heights=np.array([0.5], np.float32), view=PER.view)
    ahead.update(np.empty((0, 2), np.float32), (0.0, 0.0, 0.0), free_scan(4.0), no_unknown(),
                 BINS, 0.1, view=PER.view)
    assert len(ahead) == 0 and ahead.cleared_total == 1


def test_remembered_point_seen_through_is_cleared():
    mem = ObstacleMemory()
    pts = np.array([[2.0, 0.0], [2.0, 0.03]], dtype=np.float32)
    hts = np.array([0.5, 0.5], dtype=np.float32)
    mem.update(pts, (0.0, 0.0, 0.0), free_scan(2.0), no_unknown(), BINS, 0.0, heights=hts,
               view=PER.view)
    assert len(mem) == 1 or len(mem) == 2
    # the bin now sees free space up to 4 m: the remembered point is gone
    mem.update(np.empty((0, 2), np.float32), (0.0, 0.0, 0.0), free_scan(4.0), no_unknown(), BINS,
               0.1, view=PER.view)
    assert len(mem) == 0 and mem.cleared_total >= 1


def test_unknown_bins_and_short_free_range_do_not_clear():
    hts = np.array([0.5], dtype=np.float32)
    for scan, unknown in ((free_scan(4.0), np.ones(NB, dtype=bool)),  # blind / no return
                          (free_scan(2.05), no_unknown())):  # seen free only up to the point
        mem = ObstacleMemory()
        mem.update(np.array([[2.0, 0.0]], np.float32), (0.0, 0.0, 0.0), free_scan(2.0),
                   no_unknown(), BINS, 0.0, heights=hts, view=PER.view)
        mem.update(np.empty((0, 2), np.float32), (0.0, 0.0, 0.0), scan, unknown, BINS, 0.1,
                   view=PER.view)
        assert len(mem) == 1


def test_point_below_the_view_is_not_cleared_by_the_wall_behind_it():
    # a 10 cm high box seen at 1.5 m; at 0.5 m it is under the camera's lowest ray
    mem = ObstacleMemory()
    hts = np.array([0.1], dtype=np.float32)
    mem.update(np.array([[1.5, 0.0]], np.float32), (0.0, 0.0, 0.0), free_scan(1.5), no_unknown(),
               BINS, 0.0, heights=hts, view=PER.view)
    pose = (1.0, 0.0, 0.0)  # drove 1 m: the box is 0.5 m ahead, the floor/wall seen far
    mem.update(np.empty((0, 2), np.float32), pose, free_scan(4.0), no_unknown(), BINS, 0.1,
               view=PER.view)
    assert len(mem) == 1
    np.testing.assert_allclose(mem.points_base(pose), [[0.5, 0.0]], atol=1e-6)
    # a post seen from 0.3 to 1.2 m high at the same place is in view (0.42 ... 0.87 m) and
    # clears; a point seen only at 1.2 m is above the view there and is kept
    mem2 = ObstacleMemory()
    mem2.update(np.array([[1.5, 0.0], [1.5, 0.0]], np.float32), (0.0, 0.0, 0.0), free_scan(1.5),
                no_unknown(), BINS, 0.0, heights=np.array([0.3, 1.2], np.float32), view=PER.view)
    mem2.update(np.empty((0, 2), np.float32), pose, free_scan(4.0), no_unknown(), BINS, 0.1,
                view=PER.view)
    assert len(mem2) == 0
    mem3 = ObstacleMemory()
    mem3.update(np.array([[1.5, 0.0]], np.float32), (0.0, 0.0, 0.0), free_scan(1.5),
                no_unknown(), BINS, 0.0, heights=np.array([1.2], np.float32), view=PER.view)
    mem3.update(np.empty((0, 2), np.float32), pose, free_scan(4.0), no_unknown(), BINS, 0.1,
                view=PER.view)
    assert len(mem3) == 1


def test_moving_obstacle_leaves_no_ghost_with_real_frames():
    mem = ObstacleMemory()
    pose = (0.0, 0.0, 0.0)
    mem.update_from(render(pose, Scene([Cylinder(2.0, 0.3, 0.2)])), pose, 0.0, PER.view)
    assert len(mem) > 0
    mem.update_from(render(pose, Scene([Cylinder(2.0, -0.6, 0.2)])), pose, 0.1, PER.view)
    left = mem.points_base(pose)
    assert len(left) > 0
    # nothing remains where the post was (bearing ~ +8.5 deg); its new place is remembered
    assert not np.any(np.hypot(left[:, 0] - 2.0, left[:, 1] - 0.3) < 0.3)
    assert np.all(np.hypot(left[:, 0] - 2.0, left[:, 1] + 0.6) < 0.3)


def test_memory_stays_bounded():
    cfg = ObstacleMemoryConfig(max_points=500, decay_s=100.0)
    mem = ObstacleMemory(cfg)
    rng = np.random.default_rng(0)
    for k in range(200):
        pose = (float(rng.uniform(-3, 3)), float(rng.uniform(-3, 3)), float(rng.uniform(-3, 3)))
        pts = rng.uniform(-4, 4, size=(300, 2)).astype(np.float32)
        mem.update(pts, pose, np.zeros(NB, np.float32), np.ones(NB, bool), BINS, 0.1 * k)
        assert len(mem) <= 500
    assert len(mem) == 500 and mem.dropped_total > 0
    # the newest frame's cells are the ones kept
    assert len(mem.points_base((0.0, 0.0, 0.0))) == 500
