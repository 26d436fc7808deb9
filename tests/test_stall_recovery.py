"""Stall recovery: when it starts an escape, where the escape goal lies, when it ends."""

from __future__ import annotations

import math

import numpy as np

from runtime.perception.tracking import Track
from runtime.perception.world_model import WorldState
from runtime.planning.stall_recovery import (
    RecoveryConfig,
    StallRecovery,
    obstacles_odom,
    open_heading,
)
from runtime.types import Odometry

GOAL = np.array([5.0, 0.0])


def world(points_base=(), tracks=()) -> WorldState:
    return WorldState(0.0, np.zeros(0), np.zeros(0, bool), np.zeros(0),
                      np.asarray(points_base, float).reshape(-1, 2), list(tracks), True)


def person(pos, radius=0.3) -> Track:
    return Track(1, np.array(pos, float), np.zeros(2), radius, np.eye(4) * 0.01, 1.0, 5, True)


def test_an_escape_starts_after_the_stall_time_and_heads_the_most_open_way():
    rec = StallRecovery(RecoveryConfig(stall_s=4.0, escape_goal_m=1.0))
    odom = Odometry(x=1.0, y=2.0, theta=math.pi / 2, distance=3.0)  # facing +y in odom
    w = world(points_base=[(0.4, 0.0), (0.5, 0.3), (0.5, -0.3)])  # ahead (odom +y)
    for t in np.arange(0.0, 4.0, 0.05):
        assert rec.planning_goal(float(t), odom, w, GOAL) is GOAL
    goal = rec.planning_goal(4.0, odom, w, GOAL)
    np.testing.assert_allclose(goal, [1.0, 1.0], atol=1e-12)  # 1 m behind, away from them
    assert rec.escapes == 1


def test_travel_resets_the_stall_timer():
    rec = StallRecovery(RecoveryConfig(stall_s=4.0, stall_distance_m=0.05))
    w = world(points_base=[(0.4, 0.0)])
    for k, t in enumerate(np.arange(0.0, 20.0, 0.05)):
        odom = Odometry(x=0.01 * k, distance=0.01 * k)  # 0.2 m/s
        assert rec.planning_goal(float(t), odom, w, GOAL) is GOAL
    assert rec.escapes == 0


def test_the_escape_ends_after_its_distance_or_its_timeout_then_the_timer_starts_afresh():
    cfg = RecoveryConfig(stall_s=2.0, escape_distance_m=0.4, escape_timeout_s=5.0)
    rec = StallRecovery(cfg)
    w = world(tracks=[person((0.0, 0.5))])  # a person 0.5 m to the left (odom = base here)
    still = Odometry()
    rec.planning_goal(0.0, still, w, GOAL)
    escape = rec.planning_goal(2.0, still, w, GOAL)
    np.testing.assert_allclose(escape, [0.0, -1.0], atol=1e-12)
    assert rec.planning_goal(2.1, Odometry(distance=0.39), w, GOAL) is escape
    assert rec.planning_goal(2.2, Odometry(distance=0.40), w, GOAL) is GOAL  # travelled
    assert rec.planning_goal(4.1, Odometry(distance=0.40), w, GOAL) is GOAL  # fresh timer
    again = rec.planning_goal(4.2, Odometry(distance=0.40), w, GOAL)
    assert again is not GOAL and rec.escapes == 2
    assert rec.planning_goal(9.1, Odometry(distance=0.40), w, GOAL) is again
    assert rec.planning_goal(9.25, Odometry(distance=0.40), w, GOAL) is GOAL  # timed out


def test_no_escape_with_nothing_to_step_away_from_or_when_switched_off():
    rec = StallRecovery(RecoveryConfig(stall_s=1.0))
    for t in np.arange(0.0, 5.0, 0.05):
        assert rec.planning_goal(float(t), Odometry(), world(), GOAL) is GOAL
    off = StallRecovery(RecoveryConfig(stall_s=0.0))
    for t in np.arange(0.0, 5.0, 0.05):
        assert off.planning_goal(float(t), Odometry(), world([(0.3, 0.0)]), GOAL) is GOAL
    assert rec.escapes == off.escapes == 0


def test_the_escape_heads_the_most_open_way_not_just_away_from_the_nearest():
    """Between a person to the east and one to the south-west, away from the nearest (east)
    is west, into the other; the most open way is north-west."""
    here = np.zeros(2)
    centres = np.array([[0.49, 0.12], [-0.19, -0.46]])
    heading = open_heading(here, centres, np.array([0.3, 0.3]), 1.0)
    assert 100.0 <= math.degrees(heading) <= 160.0
    assert open_heading(here, np.array([[5.0, 5.0]]), np.array([0.3]), 1.0) is None  # far


def test_obstacles_are_points_and_confirmed_tracks_in_the_odom_frame():
    odom = Odometry(x=1.0, y=2.0, theta=math.pi / 2)
    unconfirmed = Track(2, np.array([9.0, 9.0]), np.zeros(2), 0.3, np.eye(4), 1.0, 1, False)
    centres, radii = obstacles_odom(odom, world([(0.5, 0.0)], [person((3.0, 3.0)), unconfirmed]))
    np.testing.assert_allclose(centres, [[1.0, 2.5], [3.0, 3.0]], atol=1e-12)
    np.testing.assert_allclose(radii, [0.0, 0.3])
