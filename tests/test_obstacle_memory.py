"""Obstacle memory: remembers what left the view, decays, ray-clears, stays bounded."""

from __future__ import annotations

import math

import numpy as np

from drivers.depth_source import D435_848x480
from runtime.config.settings import CameraMount, Config
from runtime.perception.depth_points import Perception
from runtime.perception.obstacle_memory import ObstacleMemory, ObstacleMemoryConfig
from runtime.perception.world_model import WorldModel
from runtime.types import DepthFrame, Odometry
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


def _world_after(poses, scenes) -> np.ndarray:
    """The world model run on rendered frames at 15 fps (poses in odom); the remembered points
    in odom at the end."""
    model = WorldModel(Config(), MOUNT)
    rend = DepthRenderer(D435_848x480, MOUNT, base_z=BASE_LINK_HEIGHT_M, seed=2)
    pts = np.empty((0, 2))
    for k, (pose, scene) in enumerate(zip(poses, scenes)):
        t = k / 15.0
        world = model.update(DepthFrame(rend.render(pose, scene, noise=True), t, k, D435_848x480),
                             Odometry(t=t, x=pose[0], y=pose[1], theta=pose[2]))
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pb = world.points_base
        pts = np.column_stack([pose[0] + c * pb[:, 0] - s * pb[:, 1],
                               pose[1] + s * pb[:, 0] + c * pb[:, 1]])
    return pts


def test_a_passer_by_s_trail_beside_the_robot_decays():
    """Nothing static stands where a person walks: cells inside a moving track's disc are the
    person's trail and decay. Held beside the robot, out of view, such a trail stood a robot
    still among people who had walked on (29 cells here before)."""
    ts = np.arange(int(14.0 * 15)) / 15.0
    # a walker crosses 1 m ahead at 0.6 m/s; the robot drives 0.8 m as they pass
    xs = 0.25 * np.clip(ts - 5.0, 0.0, 3.2)
    pts = _world_after([(x, 0.0, 0.0) for x in xs],
                       [Scene([Cylinder(1.0, 3.8 - 0.6 * t, 0.2)]) for t in ts])
    near = np.hypot(pts[:, 0] - xs[-1], pts[:, 1]) < 1.0
    assert np.count_nonzero(near) <= 2


def test_a_person_standing_beside_the_robot_out_of_view_is_kept():
    """A standing person (a stationary track) is no trail: seen, then left out of view by the
    robot's turn, they are kept past decay_s."""
    ts = np.arange(int(9.0 * 15)) / 15.0
    theta = math.radians(90.0) * np.clip(ts - 2.0, 0.0, 1.0)  # face them 2 s, turn away
    person = Scene([Cylinder(0.8, 0.0, 0.2)])
    pts = _world_after([(0.0, 0.0, th) for th in theta], [person] * len(ts))
    assert np.count_nonzero(np.hypot(pts[:, 0] - 0.8, pts[:, 1]) < 0.3) >= 3


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


def test_a_cell_inside_the_minimum_range_is_cleared_by_the_floor_seen_behind_it():
    """The camera measures nothing closer than its minimum range, but a body there blanks the
    floor behind it and perception marks the bin blind. A passer-by's cells left in front of
    the robot, closer than that range, are cleared once the bins see their floor (they held a
    robot still among people who had walked on); a body that is really there is kept."""
    person = Cylinder(0.7, 0.0, 0.25)  # its front 0.45 m ahead of base_link
    here, closer = (0.0, 0.0, 0.0), (0.2, 0.0, 0.0)  # 0.2 m on, the front is 0.25 m away
    assert 0.25 < float(PER.view.near_range.min())  # inside the minimum range there
    for there, kept in ((Scene([person]), True), (Scene([]), False)):
        mem = ObstacleMemory(ObstacleMemoryConfig(decay_s=3.0))
        mem.update_from(render(here, Scene([person])), here, t=0.0, view=PER.view)
        front = mem.points_base(closer)
        front = front[np.hypot(*front.T) < PER.view.near_range[0]]
        assert len(front) > 0
        for k in range(1, 60):  # 6 s, twice decay_s
            out = render(closer, there)
            mem.update_from(out, closer, t=0.1 * k, view=PER.view)
        ahead = mem.points_base(closer)
        ahead = ahead[(np.hypot(*ahead.T) < PER.view.near_range[0]) & (ahead[:, 0] > 0.1)]
        if kept:
            assert out.blind[NB // 2] and len(ahead) >= len(front) // 2
        else:
            assert not out.unknown[NB // 2] and len(ahead) == 0


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
