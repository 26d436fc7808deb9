"""People sightings from all around (runtime.perception.people_sighting): placed in odom as the
camera's points are, predicted to the world's stamp, and named when malformed. The pipeline
with the simulator's ground-truth sighting: tests/test_surround_people.py."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from runtime.perception.people_sighting import (
    PeopleSighting,
    sighting_problem,
    sighting_tracks,
)
from runtime.types import Odometry


def _sighting(position, velocity, t=1.0, radius=0.25) -> PeopleSighting:
    position, velocity = np.array(position, float), np.array(velocity, float)
    n = len(position)
    return PeopleSighting(t, position, velocity, np.full(n, radius), np.arange(n))


def test_a_sighting_is_placed_in_odom_from_the_pose_at_its_stamp_and_predicted_to_the_world():
    # the robot at (1, 2) facing +y: a person 1 m ahead walking forward at 0.5 m/s, and one
    # 2 m to its right shuffling at 1 cm/s (standing: predicted still)
    s = _sighting([[1.0, 0.0], [0.0, -2.0]], [[0.5, 0.0], [0.01, 0.0]], t=1.0)
    walker, stander = sighting_tracks(s, Odometry(t=1.0, x=1.0, y=2.0, theta=math.pi / 2), 1.2,
                                      standing_m_s=0.05)
    assert walker.position == pytest.approx([1.0, 3.1])
    assert walker.velocity == pytest.approx([0.0, 0.5], abs=1e-12)
    assert stander.position == pytest.approx([3.0, 2.0])
    assert stander.velocity.tolist() == [0.0, 0.0] and stander.stationary
    assert walker.confirmed and not walker.stationary and walker.radius == 0.25
    assert (walker.id, stander.id) == (0, 1)
    # the standing threshold is the caller's (the tracker's `stationary_speed_m_s`)
    _, shuffler = sighting_tracks(s, Odometry(t=1.0, x=1.0, y=2.0, theta=math.pi / 2), 1.2,
                                  standing_m_s=0.005)
    assert not shuffler.stationary and shuffler.velocity == pytest.approx([0.0, 0.01])


@pytest.mark.parametrize("bad, why", [
    (_sighting([[1.0, math.nan]], [[0.0, 0.0]]), "not finite"),
    (_sighting([[1.0, 0.0]], [[math.inf, 0.0]]), "not finite"),
    (_sighting([[1.0, 0.0]], [[0.0, 0.0]], t=math.nan), "not finite"),
    (replace(_sighting([[1.0, 0.0]], [[0.0, 0.0]]), radius=np.zeros(2)), "shapes"),
])
def test_a_malformed_sighting_is_named(bad, why):
    assert why in sighting_problem(bad)
    assert sighting_problem(_sighting([[1.0, 0.0]], [[0.0, 0.0]])) is None
