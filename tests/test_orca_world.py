"""ORCA crowd, simulated world and scenario files.

Overlap tolerance: agents are discs and ORCA's guarantee holds when every agent's velocity is
inside its half-planes; the 3D fallback and float rounding may break it slightly, so pairwise
gaps are allowed down to -OVERLAP_SLACK_M (5 mm). Measured (dt 0.1 s): head-on min gap +4.5 mm,
20-agent ring min gap +0.08 mm, ring complete at 20.2 s (straight-line time 16 s).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from runtime.errors import ConfigError
from sim_stub.orca import Crowd, OrcaParams, solve_velocity
from sim_stub.scenario import available_scenarios, load_scenario, parse_scenario
from sim_stub.world import Contact, RobotState, World, judge_contact

DT = 0.1
OVERLAP_SLACK_M = 0.005
OBSTACLE_SLACK_M = 0.001


def _min_pair_gap(crowd: Crowd) -> float:
    d = np.hypot(*(crowd.positions[:, None] - crowd.positions[None]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    return float((d - (crowd.radii[:, None] + crowd.radii[None])).min())


def _run_to_goals(crowd: Crowd, max_steps: int) -> tuple[int | None, float]:
    """Steps until every agent is within 5 cm of its goal (None if never), and the min gap."""
    min_gap = math.inf
    for k in range(max_steps):
        crowd.step(DT)
        min_gap = min(min_gap, _min_pair_gap(crowd))
        if np.all(np.hypot(*(crowd.goals - crowd.positions).T) < 0.05):
            return k + 1, min_gap
    return None, min_gap


# --- ORCA ----------------------------------------------------------------------------------------


def test_lp_returns_preferred_when_allowed_and_minimax_when_infeasible() -> None:
    # Allowed: vx <= 0.5 (line through (0.5, 0) pointing +y; allowed side is its left).
    assert solve_velocity([(0.5, 0.0, 0.0, 1.0)], 0, 1.0, (0.2, 0.3)) == (0.2, 0.3)
    vx, vy = solve_velocity([(0.5, 0.0, 0.0, 1.0)], 0, 1.0, (0.9, 0.0))
    assert vx == pytest.approx(0.5) and vy == pytest.approx(0.0)
    # Contradictory soft constraints vx >= 0.5 and vx <= -0.5: minimax violation puts vx at 0.
    lines = [(0.5, 0.0, 0.0, -1.0), (-0.5, 0.0, 0.0, 1.0)]
    vx, _ = solve_velocity(lines, 0, 1.0, (0.8, 0.0))
    assert vx == pytest.approx(0.0, abs=1e-9)
    # The same with the first one hard: it is kept, the soft one gives way.
    vx, _ = solve_velocity(lines, 1, 1.0, (0.8, 0.0))
    assert vx >= 0.5 - 1e-9


def test_lp_matches_brute_force_on_random_programs() -> None:
    """2D LP: feasible, and optimal to grid resolution; when infeasible, 3D LP is minimax."""
    rng = np.random.default_rng(0)
    g = np.linspace(-1.0, 1.0, 161)
    grid = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    grid = grid[np.hypot(*grid.T) <= 1.0]
    cell = g[1] - g[0]
    for _ in range(300):
        m = int(rng.integers(1, 7))
        ang = rng.uniform(0.0, 2 * np.pi, m)
        pts = rng.uniform(-1.0, 1.0, (m, 2))
        lines = [(p[0], p[1], math.cos(a), math.sin(a)) for p, a in zip(pts, ang)]
        opt = (float(rng.uniform(-1.2, 1.2)), float(rng.uniform(-1.2, 1.2)))
        arr = np.array(lines)

        def violation(v: np.ndarray, arr: np.ndarray = arr) -> np.ndarray:  # > 0: violated
            v = np.atleast_2d(v)
            return arr[:, 2] * (arr[:, 1] - v[:, 1:2]) - arr[:, 3] * (arr[:, 0] - v[:, 0:1])

        res = np.array(solve_velocity(lines, 0, 1.0, opt))
        assert np.hypot(*res) <= 1.0 + 1e-9
        grid_viol = violation(grid).max(axis=1)
        feasible = grid[grid_viol <= 0.0]
        if len(feasible):
            assert violation(res).max() <= 1e-9
            best = np.hypot(*(feasible - opt).T).min()
            assert np.hypot(*(res - opt)) <= best + cell
        else:
            assert violation(res).max() <= grid_viol.min() + 1e-9


ACCELS = [math.inf, 1.5]  # velocity changes at once, or as fast as a person's


@pytest.mark.parametrize("max_accel", ACCELS)
def test_two_agents_head_on_reach_goals_without_overlap(max_accel: float) -> None:
    crowd = Crowd([[-3.0, 0.0], [3.0, 0.0]], [[3.0, 0.0], [-3.0, 0.0]], 0.3, 1.0,
                  params=OrcaParams(max_accel=max_accel))
    steps, min_gap = _run_to_goals(crowd, 200)
    assert steps is not None, "head-on agents did not both reach their goals in 20 s"
    assert min_gap >= -OVERLAP_SLACK_M
    assert steps * DT < 12.0


@pytest.mark.parametrize("max_accel", ACCELS)
def test_ring_of_20_swaps_places_without_overlap(max_accel: float) -> None:
    n, radius_m = 20, 8.0
    a = np.arange(n) * 2 * np.pi / n
    start = np.stack([radius_m * np.cos(a), radius_m * np.sin(a)], -1)
    crowd = Crowd(start, -start, 0.3, 1.0, params=OrcaParams(max_accel=max_accel))
    steps, min_gap = _run_to_goals(crowd, 400)
    assert steps is not None, "ring did not complete within 40 s"
    assert steps * DT <= 30.0  # measured 20.2 s
    assert min_gap >= -OVERLAP_SLACK_M  # measured +0.08 mm


def test_velocity_changes_no_faster_than_a_person_can() -> None:
    """From standing, head-on: each step's velocity change is at most max_accel·dt."""
    crowd = Crowd([[-3.0, 0.1], [3.0, 0.0]], [[3.0, 0.0], [-3.0, 0.0]], 0.3, 1.0,
                  params=OrcaParams(max_accel=1.5))
    changes, speeds = [], []
    for _ in range(80):
        before = crowd.velocities.copy()
        crowd.step(DT)
        changes.append(np.hypot(*(crowd.velocities - before).T).max())
        speeds.append(np.hypot(*crowd.velocities.T).max())
    assert max(changes) <= 1.5 * DT + 1e-9
    assert speeds[5] < 1.0 and max(speeds) > 0.9  # they get going, not at once


@pytest.mark.parametrize("name", ["paper_d", "static_clutter", "corridor"])
def test_crowd_never_enters_static_obstacles(name: str) -> None:
    world = World(load_scenario(name))
    assert world.shapes
    crowd = world.crowd
    worst, worst_pair = math.inf, math.inf
    for _ in range(300):
        crowd.step(DT, world.shapes)
        gap = np.min([s.distance(crowd.positions) for s in world.shapes], axis=0) - crowd.radii
        worst = min(worst, float(gap.min()))
        if len(crowd) > 1:
            worst_pair = min(worst_pair, _min_pair_gap(crowd))
    assert worst >= -OBSTACLE_SLACK_M
    assert worst_pair >= -OVERLAP_SLACK_M
    assert crowd.goals_reached.sum() > 0  # the crowd actually walks around


def test_corridor_crowd_walks_both_ways() -> None:
    world = World(load_scenario("corridor"))
    vx = []
    for _ in range(100):
        world.crowd.step(DT, world.shapes)
        vx.append(world.crowd.velocities[:, 0].copy())
    vx_all = np.concatenate(vx)
    assert (vx_all > 0.3).any() and (vx_all < -0.3).any()
    assert np.all(np.abs(world.crowd.positions[:, 1]) <= 1.0 - 0.3 + OBSTACLE_SLACK_M)


# --- determinism ---------------------------------------------------------------------------------


def _trajectory(seed: int, steps: int = 40) -> list[np.ndarray]:
    world = World(load_scenario("paper_b"), seed=seed)
    out = []
    for _ in range(steps):
        world.step(DT, 0.0, 0.0)
        # keep the crowd going after a judged end, so the whole trajectory is compared
        if world.outcome.done:
            world.crowd.step(DT, world.shapes)
        snap = world.snapshot()
        out.append(np.concatenate([snap.agent_positions.ravel(), snap.robot_pose]))
    return out


def test_same_seed_same_trajectory_different_seed_different() -> None:
    a, b, c = _trajectory(3), _trajectory(3), _trajectory(4)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not all(np.array_equal(x, y) for x, y in zip(a, c))


# --- scenario files ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", available_scenarios())
def test_every_shipped_scenario_loads_and_builds(name: str) -> None:
    scenario = load_scenario(name)
    assert scenario.name == name
    world = World(scenario)
    assert len(world.crowd) == scenario.crowd.count
    assert world.clearance(world.crowd.positions).min() >= scenario.crowd.radius
    snap = world.snapshot()
    assert snap.agent_positions.shape == (scenario.crowd.count, 2)


def test_shipped_set_and_paper_counts() -> None:
    names = set(available_scenarios())
    assert {"paper_a", "paper_b", "paper_c", "paper_d", "static_clutter", "corridor"} <= names
    counts = [load_scenario(f"paper_{k}").crowd.count for k in "abcd"]
    assert counts == [8, 12, 16, 20]
    for k in "abcd":
        sc = load_scenario(f"paper_{k}")
        assert len(sc.goals) == 4
        for g in sc.goals:
            assert math.hypot(*g) == pytest.approx(7.0, abs=0.1)


def test_calibrated_set_keeps_the_paper_counts_and_an_oblivious_crowd() -> None:
    for k, count in zip("abcd", (8, 12, 16, 20)):
        cal, dense = load_scenario(f"paper_cal_{k}"), load_scenario(f"paper_{k}")
        assert cal.crowd.count == count and not cal.crowd.reactive
        assert cal.crowd.speed_range == (0.5, 1.0)
        assert (cal.goals, cal.obstacles, cal.robot) == (dense.goals, dense.obstacles, dense.robot)


def test_unknown_shipped_name_is_one_line() -> None:
    with pytest.raises(ConfigError) as err:
        load_scenario("paper_z")
    assert "paper_z" in str(err.value) and "paper_a" in str(err.value)


def _good() -> dict[str, Any]:
    return {
        "name": "t",
        "seed": 1,
        "time_limit_s": 10.0,
        "goals": [[1.0, 1.0]],
        "crowd": {"count": 2},
        "obstacles": [{"type": "box", "center": [2.0, 2.0], "size": [0.5, 0.5]}],
    }


def _set(data: dict[str, Any], dotted: str, value: Any) -> dict[str, Any]:
    node: Any = data
    *path, last = dotted.split(".")
    for part in path:
        node = node[int(part)] if isinstance(node, list) else node.setdefault(part, {})
    node[last] = value
    return data


@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [
        # unknown keys
        ("crowd.cuont", 3, "unknown key 'crowd.cuont' (did you mean 'crowd.count'?)"),
        ("time_limit", 3, "unknown key 'time_limit'"),
        ("obstacles.0.colour", "red", "unknown key 'obstacles[0].colour'"),
        # wrong types
        ("time_limit_s", "soon", "key 'time_limit_s': expected a number"),
        ("crowd.reactive", "yes", "key 'crowd.reactive': expected true or false"),
        ("goals", [[1.0, "a"]], "key 'goals[0]': expected a list of 2 numbers"),
        ("obstacles.0.center", 2.0, "key 'obstacles[0].center': expected a list of 2 numbers"),
        ("obstacles.0.type", "pyramid", "key 'obstacles[0].type': must be one of"),
        ("crowd", [1, 2], "key 'crowd': expected a mapping"),
        # bad ranges
        ("crowd.radius", -0.1, "key 'crowd.radius': must be at least 0.05 m"),
        ("crowd.speed_range", [1.0, 0.5], "key 'crowd.speed_range': lower bound 1.0 exceeds"),
        ("obstacles.0.size", [0.0, 1.0], "key 'obstacles[0].size': must be greater than 0.0"),
        ("area.x_max", -6.0, "key 'area.x_max': must be greater than x_min"),
        ("goals", [[9.0, 0.0]], "key 'goals[0]': (9.0, 0.0) lies outside the area"),
        ("goals", [], "key 'goals': expected a non-empty list"),
    ],
)
def test_scenario_file_mistakes_are_one_line_errors(
    tmp_path: Path, key: str, value: Any, expected: str
) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(_set(_good(), key, value)), encoding="utf-8")
    with pytest.raises(ConfigError) as err:
        load_scenario(path)
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(str(path) + ": ")
    assert expected in message


def test_invalid_yaml_and_missing_file_are_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "broken.yaml"
    bad.write_text("name: [unclosed\n", encoding="utf-8")
    for path in (bad, tmp_path / "missing.yaml"):
        with pytest.raises(ConfigError) as err:
            load_scenario(path)
        assert "\n" not in str(err.value) and str(path) in str(err.value)


# --- world judging -------------------------------------------------------------------------------


def _scene(**over: Any) -> dict[str, Any]:
    data: dict[str, Any] = {
        "name": "judge",
        "seed": 0,
        "time_limit_s": 30.0,
        "robot": {"area": {"x_min": -0.01, "x_max": 0.01, "y_min": -0.01, "y_max": 0.01}},
        "goals": [[4.0, 4.0]],
        "crowd": {"count": 0},
    }
    data.update(over)
    return data


def _run(world: World, v: float, omega: float, max_steps: int = 400) -> None:
    for _ in range(max_steps):
        if world.step(DT, v, omega).done:
            return


def test_robot_driven_into_box_collides_at_fault() -> None:
    box = {"type": "box", "center": [1.0, 0.0], "size": [0.4, 1.0]}
    world = World(parse_scenario(_scene(obstacles=[box]), "test"))
    _run(world, 0.3, 0.0)
    out = world.outcome
    assert (out.status, out.collided_with, out.at_fault) == ("collision", "obstacle 0", True)
    assert world.robot.x == pytest.approx(1.0 - 0.2 - 0.17, abs=0.04)  # contact, not beyond


def _crossing_world(reactive: bool) -> World:
    crowd = {"count": 1, "reactive": reactive, "speed_range": [0.8, 0.8]}
    world = World(parse_scenario(_scene(crowd=crowd), "test"))
    world.crowd.set_agent(0, (-3.0, 0.0), (3.0, 0.0))
    world.crowd.goal_sampler = None
    return world


def test_parked_robot_hit_by_oblivious_agent_is_not_at_fault() -> None:
    world = _crossing_world(reactive=False)
    _run(world, 0.0, 0.0, 100)
    out = world.outcome
    assert (out.status, out.collided_with, out.at_fault) == ("collision", "agent 0", False)


def test_reactive_agent_walks_around_parked_robot() -> None:
    world = _crossing_world(reactive=True)
    _run(world, 0.0, 0.0, 100)
    assert world.outcome.status == "running"
    assert world.crowd.positions[0, 0] > 2.5  # it went past
    assert world.min_separation >= -OVERLAP_SLACK_M


def test_reactive_people_keep_their_comfort_distance_from_the_robot() -> None:
    """Walking straight at a parked robot, a reactive person passes it with at least about the
    comfort distance between them; with none they pass as close as to each other."""
    gaps = {}
    for comfort in (0.0, 0.25):
        crowd = {"count": 1, "reactive": True, "speed_range": [0.8, 0.8],
                 "comfort_distance_m": comfort}
        world = World(parse_scenario(_scene(crowd=crowd), "test"))
        world.crowd.set_agent(0, (-3.0, 0.0), (3.0, 0.0))
        world.crowd.goal_sampler = None
        _run(world, 0.0, 0.0, 100)
        assert world.crowd.positions[0, 0] > 2.5  # it went past
        gaps[comfort] = world.min_separation
    assert gaps[0.0] < 0.1
    assert gaps[0.25] >= 0.2


def test_people_decide_every_period_and_walk_straight_in_between() -> None:
    """Driven at the base's irregular event times, velocities change only at multiples of
    crowd.decision_period_s; with a period of 0 every step is a decision, as ORCA's own step."""
    data = _scene(crowd={"count": 6, "speed_range": [0.5, 1.0]}, area={
        "x_min": -5.0, "x_max": 5.0, "y_min": -5.0, "y_max": 5.0})
    world = World(parse_scenario(data, "test"))
    t, changes, last = 0.0, [], world.crowd.velocities.copy()
    for dt in [0.02, 0.013, 0.017, 0.05] * 30:
        world.follow_robot(dt, 0.0, 0.0, 0.0, 0.0, 0.0)
        t += dt
        if not np.array_equal(world.crowd.velocities, last):
            changes.append(t)
            last = world.crowd.velocities.copy()
    assert len(changes) >= 20
    # each change shows up at the end of the step in which a decision time k·0.1 s fell
    assert all(math.floor((c + 1e-9) / 0.1) > math.floor((c - 0.05 - 1e-9) / 0.1)
               for c in changes)
    data["crowd"]["decision_period_s"] = 0.0
    a, b = World(parse_scenario(data, "test")), World(parse_scenario(data, "test"))
    for dt in [0.02, 0.013, 0.05] * 10:
        a.follow_robot(dt, 0.0, 0.0, 0.0, 0.0, 0.0)
        b.crowd.step(dt, b.shapes)
    assert np.array_equal(a.crowd.positions, b.crowd.positions)


def test_reaching_goal_is_success() -> None:
    world = World(parse_scenario(_scene(goals=[[1.5, 0.0]]), "test"))
    _run(world, 0.3, 0.0)
    assert world.outcome.status == "success"
    assert math.hypot(world.robot.x - 1.5, world.robot.y) <= 0.2
    assert world.outcome.t == pytest.approx(1.3 / 0.3 + 0.3, abs=0.3)  # accel 0.5 m/s^2


def test_time_limit_is_timeout_and_world_then_stays_put() -> None:
    world = World(parse_scenario(_scene(time_limit_s=2.0), "test"))
    _run(world, 0.0, 0.0)
    assert world.outcome.status == "timeout"
    assert world.outcome.t == pytest.approx(2.0)
    assert world.step(DT, 0.3, 0.0) == world.outcome  # no longer advances


def test_robot_respects_acceleration_limits() -> None:
    world = World(parse_scenario(_scene(), "test"))
    world.step(DT, 0.3, 1.0)
    assert world.robot.v == pytest.approx(0.5 * DT)  # accel_max 0.5 m/s^2
    assert world.robot.omega == pytest.approx(2.0 * DT)  # alpha_max 2 rad/s^2


def _contact(robot_v: float, bearing_deg: float, person_velocity: tuple[float, float]) -> Contact:
    """A contact with a robot at the origin facing +x and a person in direction `bearing_deg`."""
    b = math.radians(bearing_deg)
    return judge_contact(1.0, "agent 0", RobotState(0.0, 0.0, 0.0, robot_v),
                         np.array([math.cos(b), math.sin(b)]), np.array(person_velocity))


@pytest.mark.parametrize(("robot_v", "bearing", "person", "moving", "at_fault"), [
    (0.2, 0.0, (0.0, 0.0), True, True),  # drove into a person standing ahead
    (0.2, 10.0, (-0.5, 0.0), True, True),  # head-on: both closing, the robot looked that way
    (0.2, 60.0, (0.0, 0.0), True, True),  # swept its side into a person standing there
    (0.2, 60.0, (0.3, 0.2), True, True),  # the person was walking away: the robot caught them
    (0.12, 77.0, (0.0, -0.8), True, False),  # walked into the side of a creeping robot
    (0.12, 180.0, (0.8, 0.0), True, False),  # walked into its back
    (-0.1, 180.0, (0.0, 0.0), True, True),  # reversed into a person standing behind
    (0.0, 0.0, (-0.8, 0.0), False, False),  # walked into a robot standing still
    (0.005, 0.0, (-0.8, 0.0), False, False),  # ... or creeping below the 0.01 m/s threshold
])
def test_contact_fault(robot_v, bearing, person, moving, at_fault) -> None:
    c = _contact(robot_v, bearing, person)
    assert (c.moving, c.at_fault) == (moving, at_fault)
    assert abs(c.bearing_deg) == pytest.approx(bearing)


def test_contact_records_its_geometry() -> None:
    c = _contact(0.2, 45.0, (0.0, -0.6))
    assert c.robot_speed == pytest.approx(0.2)
    assert c.robot_closing == pytest.approx(0.2 * math.cos(math.radians(45)))
    assert c.other_closing == pytest.approx(0.6 * math.sin(math.radians(45)))
    assert c.at_fault  # within ±45° and closing: the robot drove into them


def test_static_obstacle_contact_is_at_fault_exactly_when_moving() -> None:
    for v, fault in ((0.2, True), (0.0, False)):
        c = judge_contact(0.0, "obstacle 0", RobotState(0.0, 0.0, 0.0, v), None, np.zeros(2))
        assert (c.moving, c.at_fault, c.bearing_deg) == (fault, fault, None)


def test_world_records_each_contact_once_and_after_the_outcome_latched() -> None:
    world = _crossing_world(reactive=False)
    for _ in range(100):  # 8 s: the oblivious agent walks through the parked robot
        world.follow_robot(DT, 0.0, 0.0, 0.0, 0.0, 0.0)
    assert world.outcome.status == "collision" and world.outcome.contact == world.contacts[0]
    assert len(world.contacts) == 1  # one contact, not one per step while touching
    c = world.contacts[0]
    assert (c.with_, c.moving, c.at_fault) == ("agent 0", False, False)
    assert abs(c.bearing_deg) > 135.0  # it came from behind (x = -3)
    assert c.other_closing == pytest.approx(0.8, abs=0.05)
    world.crowd.set_agent(0, (3.0, 0.0), (-3.0, 0.0))  # and back again, into the robot's face
    for _ in range(100):
        world.follow_robot(DT, 0.0, 0.0, 0.0, 0.0, 0.0)
    assert len(world.contacts) == 2 and abs(world.contacts[1].bearing_deg) < 45.0
    assert world.outcome.contact == world.contacts[0]  # the outcome stays latched
