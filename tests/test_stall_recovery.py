"""Stall recovery: when it starts an escape or a takeover, where the escape goal lies, when
either ends."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from runtime.perception.tracking import Track
from runtime.perception.world_model import WorldState
from runtime.planning.stall_recovery import (
    RecoveryConfig,
    StallRecovery,
    obstacles_odom,
    open_heading,
    way_gap,
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


def test_a_policy_stalled_with_the_way_to_the_goal_clear_is_taken_over_by_dwa(caplog):
    caplog.set_level("INFO", logger="safemove.planner")
    """The shipped policy stood 0.4 m beside a mission's waypoint with nothing near: no escape
    (nothing to step away from), so DWA drives toward the real goal until it has travelled
    escape_distance_m or escape_timeout_s has passed."""
    cfg = RecoveryConfig(stall_s=2.0, escape_distance_m=0.4, escape_timeout_s=5.0)
    rec = StallRecovery(cfg, takeover_radius_m=0.17)
    goal = np.array([0.0, -0.4])  # beside the robot
    far_box = world(points_base=[(2.0, 0.0)])
    for t in np.arange(0.0, 2.0, 0.05):
        assert rec.planning_goal(float(t), Odometry(), far_box, goal) is goal
        assert not rec.dwa_drives
    assert rec.planning_goal(2.0, Odometry(), far_box, goal) is goal
    assert rec.dwa_drives and (rec.takeovers, rec.escapes) == (1, 0)
    assert "no progress toward the goal for 2.0 s" in caplog.text
    assert "the way to it clear: DWA drives" in caplog.text
    rec.planning_goal(2.1, Odometry(distance=0.39), far_box, goal)
    assert rec.dwa_drives
    rec.planning_goal(2.2, Odometry(distance=0.40), far_box, goal)  # travelled
    assert not rec.dwa_drives
    rec.planning_goal(4.2, Odometry(distance=0.40), far_box, goal)
    assert rec.dwa_drives and rec.takeovers == 2
    rec.planning_goal(9.25, Odometry(distance=0.40), far_box, goal)  # timed out
    assert not rec.dwa_drives


def test_a_policy_creeping_without_coming_closer_is_taken_over_too():
    """Creeping sideways at 2 cm/s travels more than stall_distance_m per stall_s, so it is
    never a stall, but it brings the goal no closer: after stall_s of that, DWA drives."""
    cfg = RecoveryConfig(stall_s=4.0, stall_distance_m=0.05)
    rec = StallRecovery(cfg, takeover_radius_m=0.17)
    goal = np.array([3.0, 0.0])
    for t in np.arange(0.0, 4.0, 0.05):
        y = 0.02 * t  # across the goal's bearing
        rec.planning_goal(float(t), Odometry(y=y, distance=y), world(), goal)
        assert not rec.dwa_drives
    rec.planning_goal(4.0, Odometry(y=0.08, distance=0.08), world(), goal)
    assert rec.dwa_drives and (rec.takeovers, rec.escapes) == (1, 0)
    closing = StallRecovery(cfg, takeover_radius_m=0.17)
    for t in np.arange(0.0, 20.0, 0.05):  # toward the goal at 2 cm/s: progress, not a stall
        closing.planning_goal(float(t), Odometry(x=0.02 * t, distance=0.02 * t), world(), goal)
    assert closing.takeovers == 0


def test_something_in_the_way_is_an_escape_and_dwa_itself_is_never_taken_over():
    """A box between the robot and its goal: the policy is not the problem, step away. DWA's
    own job (no takeover radius) and a config without takeovers never hand over."""
    box = world(points_base=[(0.5, y) for y in np.linspace(-0.5, 0.5, 11)])
    for rec in (StallRecovery(RecoveryConfig(stall_s=1.0), takeover_radius_m=0.17),
                StallRecovery(RecoveryConfig(stall_s=1.0)),
                StallRecovery(RecoveryConfig(stall_s=1.0, dwa_takeover=False), 0.17)):
        rec.planning_goal(0.0, Odometry(), box, GOAL)
        assert rec.planning_goal(1.0, Odometry(), box, GOAL) is not GOAL
        assert not rec.dwa_drives and (rec.takeovers, rec.escapes) == (0, 1)
    clear = world(points_base=[(2.0, 1.0)])
    off = StallRecovery(RecoveryConfig(stall_s=1.0, dwa_takeover=False), 0.17)
    for t in np.arange(0.0, 5.0, 0.05):
        assert off.planning_goal(float(t), Odometry(), clear, GOAL) is GOAL  # waits, as before
    assert not off.dwa_drives and off.takeovers == 0


def test_the_way_gap_measures_the_first_stretch_toward_the_goal_only():
    here, goal = np.zeros(2), np.array([5.0, 0.0])
    centres, radii = np.array([[0.5, 0.3], [3.0, 0.0]]), np.array([0.1, 0.3])
    assert way_gap(here, goal, centres, radii, 1.0) == pytest.approx(0.2)  # the far one: beyond
    assert way_gap(here, goal, centres[1:], radii[1:], 1.0) == pytest.approx(1.7)
    assert way_gap(here, goal, centres[1:], radii[1:], 10.0) == pytest.approx(-0.3)  # on the way
    assert way_gap(here, np.array([0.2, 0.0]), centres, radii, 1.0) == pytest.approx(
        math.hypot(0.3, 0.3) - 0.1)  # up to the goal, not past it
    assert way_gap(here, goal, np.zeros((0, 2)), np.zeros(0), 1.0) == math.inf


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


def test_a_policy_moving_without_progress_past_something_in_the_way_is_taken_over_when_asked():
    """takeover_when_blocked: a person stands in the way and the policy creeps and turns in front
    of them for stall_s without coming takeover_progress_m closer: DWA drives (it waits for or
    goes round people where a policy may keep facing them). Off (the default), the policy keeps
    the wheel."""
    blocked = world(tracks=[person((0.6, 0.0))])
    cfg = RecoveryConfig(stall_s=4.0, stall_distance_m=0.05, takeover_progress_m=0.5)
    asked = StallRecovery(dataclasses.replace(cfg, takeover_when_blocked=True), 0.17)
    default = StallRecovery(cfg, 0.17)
    for rec in (asked, default):
        for t in np.arange(0.0, 4.05, 0.05):  # 0.1 m/s, half of it toward the goal: 0.2 m
            rec.planning_goal(float(t), Odometry(x=0.05 * t, y=0.0866 * t, distance=0.1 * t),
                              blocked, GOAL)
    assert asked.dwa_drives and (asked.takeovers, asked.escapes) == (1, 0)
    assert not default.dwa_drives and default.takeovers == 0


def test_a_policy_standing_before_something_in_the_way_steps_away_even_when_takeovers_are_asked():
    """Standing still in front of a box is a stall, whoever drives: the escape, not DWA, which
    would stand before the box as well."""
    box = world(points_base=[(0.5, y) for y in np.linspace(-0.5, 0.5, 11)])
    rec = StallRecovery(RecoveryConfig(stall_s=1.0, takeover_when_blocked=True), 0.17)
    rec.planning_goal(0.0, Odometry(), box, GOAL)
    assert rec.planning_goal(1.0, Odometry(), box, GOAL) is not GOAL
    assert not rec.dwa_drives and (rec.takeovers, rec.escapes) == (0, 1)


def test_a_takeover_past_something_in_the_way_ends_when_dwa_stands_too():
    """DWA standing before what blocks the way gains nothing over the policy: after
    takeover_stand_s of standing the policy drives again (and a standing robot's escape is
    next). A takeover with the way clear runs its full distance or time."""
    cfg = RecoveryConfig(stall_s=4.0, takeover_progress_m=0.5, takeover_stand_s=2.0,
                         escape_timeout_s=8.0, takeover_when_blocked=True)
    for way, expected_end in ((world(tracks=[person((0.6, 0.0))]), 6.0), (world(), 12.0)):
        rec = StallRecovery(cfg, 0.17)
        for t in np.arange(0.0, 4.05, 0.05):
            rec.planning_goal(float(t), Odometry(y=0.1 * t, distance=0.1 * t), way, GOAL)
        assert rec.dwa_drives and rec.takeovers == 1
        stood = Odometry(y=0.4, distance=0.4)
        for t in np.arange(4.05, expected_end - 0.04, 0.05):
            rec.planning_goal(float(t), stood, way, GOAL)
            assert rec.dwa_drives, t
        rec.planning_goal(expected_end + 0.01, stood, way, GOAL)
        assert not rec.dwa_drives
