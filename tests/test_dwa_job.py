"""The DWA planner mode's pieces that are not the DWA or shield themselves."""

from __future__ import annotations

import math

import numpy as np
import pytest

from runtime.cli.main import main
from runtime.config.settings import load_config
from runtime.perception.tracking import Track
from runtime.perception.world_model import WorldState
from runtime.planning.planning_step import ARRIVAL_RADIUS_M, PlanningStep, predict_tracks_base
from runtime.types import Odometry, Twist


def track(tid: int, pos, vel, confirmed=True, pos_var=0.01, vel_var=0.04) -> Track:
    cov = np.diag([pos_var, pos_var, vel_var, vel_var])
    return Track(tid, np.array(pos, float), np.array(vel, float), 0.3, cov, 1.0, 5, confirmed)


def test_tracks_are_predicted_at_constant_velocity_into_base_link_with_growing_sigma():
    tracks = [track(1, (2.0, 1.0), (0.0, -1.0)), track(2, (9.0, 9.0), (0.0, 0.0), confirmed=False)]
    pose = (1.0, 1.0, math.pi / 2)  # robot at (1, 1) facing +y in odom
    pos, std, radii = predict_tracks_base(tracks, pose, elapsed=0.1, dt=0.5, steps=2)
    assert pos.shape == (1, 3, 2) and std.shape == (1, 3) and radii.tolist() == [0.3]
    # odom positions at τ = 0.1, 0.6, 1.1 s: (2, 0.9), (2, 0.4), (2, -0.1); in base_link (x fwd
    # = odom +y, y left = odom −x): (−0.1, −1), (−0.6, −1), (−1.1, −1)
    np.testing.assert_allclose(pos[0], [[-0.1, -1.0], [-0.6, -1.0], [-1.1, -1.0]], atol=1e-12)
    assert np.all(np.diff(std[0]) > 0)
    assert std[0, 0] == pytest.approx(math.sqrt(0.01 + 0.04 * 0.01))


def test_dwa_planner_needs_a_goal_and_depth(capsys):
    assert main(["run", "--planner", "dwa", "--set", "depth.source=sim",
                 "--set", "depth.sim_socket=/x"]) == 2
    assert "--goal" in capsys.readouterr().err
    assert main(["run", "--planner", "dwa", "--goal", "1", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "depth.source" in err[0]


def empty_world() -> WorldState:
    angles = np.linspace(-0.75, 0.75, 90)
    return WorldState(0.0, np.full(90, np.inf), np.zeros(90, bool), angles, np.zeros((0, 2)),
                      [], True)


def test_dwa_heads_for_the_planning_goal_but_arrival_is_judged_on_the_goal():
    step = PlanningStep((3.0, 0.0), load_config(None, []).config, None, "DWA")
    here = Odometry(x=1.0, y=0.0, theta=math.pi / 2)  # facing odom +y
    ctx = step.prepare(0.0, here, empty_world(), plan_goal=np.array([1.0, -2.0]))
    np.testing.assert_allclose(ctx.goal_base, [-2.0, 0.0], atol=1e-12)  # behind it
    ctx = step.prepare(0.05, here, empty_world())
    np.testing.assert_allclose(ctx.goal_base, [0.0, -2.0], atol=1e-12)  # the goal, to its right
    near = Odometry(x=3.0 - 0.9 * ARRIVAL_RADIUS_M, v=0.0)
    assert step.prepare(0.1, near, empty_world(), plan_goal=np.array([9.0, 9.0])) is None
    assert step.reached and step.finished


def test_shield_interventions_are_counted_every_cycle_but_logged_once_per_run_of_a_kind(caplog):
    """A wall 0.35 m ahead: every forward command is braked, cycle after cycle. One log line
    for the run (the count goes into the loop's statistics line), another when it changes."""
    step = PlanningStep((5.0, 0.0), load_config(None, []).config, None, "DWA")
    ys = np.arange(-0.6, 0.61, 0.02)
    wall = np.stack([np.full_like(ys, 0.35), ys], 1)
    angles = np.linspace(-0.75, 0.75, 90)
    blocked = WorldState(0.0, np.full(90, 0.35), np.zeros(90, bool), angles, wall, [], True)
    moving = Odometry(v=0.2)
    caplog.set_level("INFO", logger="safemove.planner")
    for k in range(20):
        ctx = step.prepare(0.05 * k, moving, blocked)
        step.certify(Twist(0.3, 0.0), ctx)
    assert sum(step.interventions.values()) == 20
    assert len(caplog.records) == len(step.interventions)  # one line per kind, not per cycle
    ctx = step.prepare(1.0, Odometry(), empty_world())
    assert step.certify(Twist(0.1, 0.0), ctx) == Twist(0.1, 0.0)  # passed: a run ends
    ctx = step.prepare(1.05, moving, blocked)
    step.certify(Twist(0.3, 0.0), ctx)
    assert len(caplog.records) == len(step.interventions) + 1  # a new run: logged again


def test_the_camera_blind_zone_reaches_the_shield_so_the_strict_mode_works_on_the_robot():
    """With shield.blind_zone occupied, space nearer than the camera's minimum range counts as
    occupied: the world model's blind range must get to the shield, with the tracks' ids."""
    strict = load_config(None, ["shield.blind_zone=occupied"]).config
    angles = np.linspace(-0.75, 0.75, 90)
    world = WorldState(0.0, np.full(90, np.inf), np.zeros(90, bool), angles, np.zeros((0, 2)),
                       [track(7, (2.0, 2.0), (0.0, 0.0))], True, blind_range=np.full(90, 0.6))
    for config, passed in ((strict, False), (load_config(None, []).config, True)):
        step = PlanningStep((3.0, 0.0), config, None, "DWA")
        ctx = step.prepare(0.0, Odometry(v=0.2), world)
        assert ctx is not None and ctx.shield_world.track_ids == (7,)
        np.testing.assert_array_equal(ctx.shield_world.blind_range, world.blind_range)
        command = step.certify(Twist(0.2, 0.0), ctx)
        assert (command == Twist(0.2, 0.0)) is passed
