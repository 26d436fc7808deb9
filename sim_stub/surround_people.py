"""Ground truth as a sensor that sees every person around the robot (`eval --surround-people`).

A what-if: the robot's one camera sees ±43.5°, and most collisions in the dense scenarios are
people who walk in from outside it. Handing the pipeline every person within the perception's
range, all around and through occlusion, exactly (`runtime.perception.people_sighting`),
bounds what the best all-around people sensing (a 2D lidar's leg tracker, more cameras) could
buy the planner and the shield. Static obstacles still come from the camera alone.
"""

from __future__ import annotations

import numpy as np

from runtime.geometry import into_frame
from runtime.perception.people_sighting import PeopleSighting
from sim_stub.world import Snapshot


def surround_sighting(snap: Snapshot, range_m: float) -> PeopleSighting:
    """Every person whose disc comes within `range_m` of the robot's centre, in base_link at
    the snapshot's time (velocities over the ground, in base_link's axes)."""
    x, y, th = (float(a) for a in snap.robot_pose)
    dx, dy = into_frame(snap.agent_positions[:, 0] - x, snap.agent_positions[:, 1] - y, th)
    vx, vy = into_frame(snap.agent_velocities[:, 0], snap.agent_velocities[:, 1], th)
    near = np.hypot(dx, dy) - snap.agent_radii <= range_m
    return PeopleSighting(t=snap.t, position=np.stack([dx, dy], axis=-1)[near],
                          velocity=np.stack([vx, vy], axis=-1)[near],
                          radius=snap.agent_radii[near].astype(float),
                          ids=np.flatnonzero(near))
