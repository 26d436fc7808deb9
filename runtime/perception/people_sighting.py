"""People seen all around the robot by a sensor other than the camera, as tracks.

The D435 sees ±43.5°: a person who walks in from the side or behind is unknown to the planner
and the shield until they are close. A sensor that sees all around (a 2D lidar with a leg
tracker, side and rear cameras) would report each person's position and velocity in base_link
at its stamp. Where such a sighting arrives, its people replace the camera's tracks (they are
the people the camera sees too), placed in odom from where the robot was at the stamp, as the
camera's points are. The simulator's `safemove eval --surround-people` feeds ground truth here
to measure what all-around sensing of people would buy; nothing on the robot produces one yet.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from runtime.geometry import from_frame
from runtime.perception.tracking import Track
from runtime.types import Odometry

# How well the sighting knows each person (1 σ): a leg tracker's few centimetres and a tenth of
# a metre per second; the planner's discs grow with these as with the camera's tracks.
POSITION_SIGMA_M = 0.03
VELOCITY_SIGMA_M_S = 0.1


@dataclass(frozen=True)
class PeopleSighting:
    """The people around the robot at stamp `t` (the host clock): in base_link at that moment,
    positions (N, 2) m, velocities over the ground (N, 2) m/s in base_link's axes, radii (N,)
    m, and each person's identity (N,) as the sensor keeps it."""

    t: float
    position: np.ndarray
    velocity: np.ndarray
    radius: np.ndarray
    ids: np.ndarray


def sighting_problem(sighting: PeopleSighting) -> str | None:
    """Why a sighting cannot be used (shapes that disagree, a value that is not finite), or
    None: the pipeline then keeps the camera's tracks rather than plan around a lie."""
    n = len(sighting.ids)
    shapes = (sighting.position.shape, sighting.velocity.shape, sighting.radius.shape)
    if shapes != ((n, 2), (n, 2), (n,)):
        return f"people sighting at t={sighting.t:g}: shapes {shapes} for {n} people"
    values = (sighting.t, sighting.position, sighting.velocity, sighting.radius)
    if not all(np.isfinite(v).all() for v in values):
        return f"people sighting at t={sighting.t:g}: a value is not finite"
    return None


def sighting_tracks(sighting: PeopleSighting, seen_from: Odometry, at_t: float,
                    standing_m_s: float) -> list[Track]:
    """The sighting's people as confirmed tracks in odom at time `at_t` (the world state's
    stamp, from which the planner predicts), constant velocity from the sighting's stamp;
    `seen_from`: the robot's pose at that stamp. Slower than `standing_m_s` (the tracker's
    `stationary_speed_m_s`) a person is standing and predicted still, as the camera's tracks."""
    x, y, th = seen_from.x, seen_from.y, seen_from.theta
    vel = np.stack(from_frame(0.0, 0.0, th, sighting.velocity[:, 0], sighting.velocity[:, 1]),
                   axis=-1)
    pos = np.stack(from_frame(x, y, th, sighting.position[:, 0], sighting.position[:, 1]),
                   axis=-1)
    standing = np.hypot(vel[:, 0], vel[:, 1]) < standing_m_s
    vel[standing] = 0.0
    pos = pos + vel * (at_t - sighting.t)
    cov = np.diag([POSITION_SIGMA_M**2] * 2 + [VELOCITY_SIGMA_M_S**2] * 2)
    return [Track(id=int(i), position=p, velocity=v, radius=float(r), covariance=cov.copy(),
                  age=0.0, hits=1, confirmed=True, stationary=bool(still))
            for i, p, v, r, still in zip(sighting.ids, pos, vel, sighting.radius, standing,
                                         strict=True)]
