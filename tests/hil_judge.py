"""Shared by the planner HIL tests: the goal in the odom frame, and a judge of every contact
from the sim's polled ground truth (the sim itself latches only its first outcome)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sim_stub.emulator_process import EmulatorProcess
from sim_stub.scenario import load_scenario
from sim_stub.world import MOVING_SPEED_M_S, ROBOT_RADIUS_M, goal_in_odom, obstacle_shape


def odom_goal(scenario_event: dict) -> tuple[float, float]:
    """The world goal in the odom frame (the robot starts at the origin facing +x)."""
    return goal_in_odom(tuple(scenario_event["start"]), scenario_event["goal"])


class ContactJudge:
    """Every robot–agent and robot–obstacle contact from polled ground truth."""

    def __init__(self, scenario_path: Path) -> None:
        scenario = load_scenario(str(scenario_path))
        self.agent_reach = scenario.crowd.radius + ROBOT_RADIUS_M
        self.shapes = [obstacle_shape(o) for o in scenario.obstacles]
        self.touching: set[str] = set()
        self.contacts: list[dict] = []
        self.polls = 0
        self.min_gap = math.inf
        self._last: tuple[float, np.ndarray] | None = None

    def poll(self, sim: EmulatorProcess, t: float) -> None:
        """One look at ground truth, `t` seconds into the run."""
        world = sim.request("world", "world")
        v = float(sim.truth()["v"])
        speed = abs(v)
        x, y, th = world["robot_pose"]
        p = np.array([x, y])
        now: set[str] = set()
        agents = np.asarray(world["agents"]).reshape(-1, 2)
        if len(agents):
            gaps = np.hypot(*(agents - p).T) - self.agent_reach
            self.min_gap = min(self.min_gap, float(gaps.min()))
            now |= {f"agent {k}" for k in np.flatnonzero(gaps < 0)}
        now |= {f"obstacle {o}" for o, s in enumerate(self.shapes)
                if s.distance(p[None])[0] < ROBOT_RADIUS_M}
        for who in sorted(now - self.touching):
            contact = {"t": round(t, 1), "with": who, "robot_speed": round(speed, 3),
                       "at_fault": speed > MOVING_SPEED_M_S}
            if who.startswith("agent"):  # where it was (0° ahead, ±43.5° the camera's edges)
                k = int(who.split()[1])
                rel = agents[k] - p
                bearing = math.atan2(rel[1], rel[0]) - th
                contact["bearing_deg"] = round(math.degrees(math.atan2(math.sin(bearing),
                                                                      math.cos(bearing))))
                # the robot's own speed toward the person (≤ 0: it was moving away)
                contact["robot_closing_speed"] = round(v * math.cos(bearing), 3)
                if self._last is not None and len(self._last[1]) == len(agents):
                    vel = (agents[k] - self._last[1][k]) / max(t - self._last[0], 1e-3)
                    contact["agent_speed"] = round(float(np.hypot(*vel)), 2)
            self.contacts.append(contact)
        self.touching = now
        self._last = (t, agents)
        self.polls += 1
