"""The world model end to end on rendered depth in scenario (d): D435-like depth of 20 people →
perception → memory (one point per cell) → tracker, scored against the simulator's ground truth."""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import linear_sum_assignment

from drivers.depth_source import D435_848x480
from runtime.config.settings import CameraMount, Config
from runtime.perception.depth_points import Perception
from runtime.perception.obstacle_memory import ObstacleMemory
from runtime.perception.tracking import Tracker
from sim_stub.depth_render import DepthRenderer
from sim_stub.scenario import CylinderSpec, load_scenario
from sim_stub.sim_server import BASE_LINK_HEIGHT_M, scene_from
from sim_stub.world import World

FPS = 15.0
SECONDS = 24.0
IN_VIEW_RANGE_M = 3.8
IN_VIEW_HALF_ANGLE = math.radians(40.0)  # inside the 87° view with a margin at its edges


def test_tracks_of_people_in_view_match_ground_truth_and_static_ones_stay_still():
    cfg = Config()
    world = World(load_scenario("paper_d"), seed=3)
    renderer = DepthRenderer(D435_848x480, CameraMount(), base_z=BASE_LINK_HEIGHT_M, seed=3)
    perception = Perception(D435_848x480, CameraMount(), cfg.perception)
    tracker = Tracker(cfg.tracking)
    memory = ObstacleMemory(cfg.memory)
    statics = np.array([o.center for o in world.obstacles if isinstance(o, CylinderSpec)])
    pos_err, speed_err, static_speed = [], [], []
    owner: dict[int, int] = {}
    switches = 0
    dt = 1.0 / FPS
    for k in range(int(SECONDS * FPS)):
        world.step(dt, 0.0, 0.1 if (k // 120) % 2 else 0.0)  # stand, then turn slowly, ...
        snap = world.snapshot()
        pose = tuple(snap.robot_pose)
        out = perception.process(renderer.render(pose, scene_from(world, snap), noise=True))
        memory.update_from(out, pose, world.t, view=perception.view)
        tracks = [t for t in tracker.update(memory.frame_points, world.t, sensor_pose=np.array(pose))
                  if t.confirmed]
        if not tracks:
            continue
        where = np.array([t.position for t in tracks])
        rel = snap.agent_positions - snap.robot_pose[:2]
        bearing = (np.arctan2(rel[:, 1], rel[:, 0]) - pose[2] + np.pi) % (2 * np.pi) - np.pi
        in_view = np.flatnonzero((np.hypot(*rel.T) < IN_VIEW_RANGE_M)
                                 & (np.abs(bearing) < IN_VIEW_HALF_ANGLE))
        if len(in_view):
            cost = np.linalg.norm(where[:, None] - snap.agent_positions[in_view][None], axis=2)
            for ti, ai in zip(*linear_sum_assignment(cost)):
                if cost[ti, ai] > 0.5:
                    continue
                agent = int(in_view[ai])
                pos_err.append(cost[ti, ai])
                speed_err.append(abs(np.linalg.norm(tracks[ti].velocity)
                                     - np.linalg.norm(snap.agent_velocities[agent])))
                switches += owner.get(agent, tracks[ti].id) != tracks[ti].id
                owner[agent] = tracks[ti].id
        if len(statics):
            near = np.linalg.norm(where[:, None] - statics[None], axis=2).min(axis=1) < 0.3
            static_speed += [float(np.linalg.norm(t.velocity)) for t, n in zip(tracks, near) if n]
    print(f"paper_d rendered: {len(pos_err)} matches; median position error "
          f"{100 * np.median(pos_err):.1f} cm, median speed error {np.median(speed_err):.3f} m/s;"
          f" ID switches {switches / (SECONDS / 60):.1f}/min; static tracks: {len(static_speed)}"
          f" frames, max speed {max(static_speed, default=0.0):.3f} m/s")
    assert len(pos_err) > 300
    assert np.median(pos_err) <= 0.10
    assert np.median(speed_err) <= 0.15
    assert max(static_speed, default=0.0) <= 0.05
