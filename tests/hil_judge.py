"""Shared by the planner HIL tests: the goal in the odom frame, and the contacts the sim judged.

The sim judges every contact itself from ground truth at each base tick (50 Hz) and reports it
as a `contact` event, also after its first outcome has latched (sim_stub/world.py says who is at
fault and why)."""

from __future__ import annotations

from typing import Any

from sim_stub.emulator_process import EmulatorProcess
from sim_stub.world import goal_in_odom


def odom_goal(scenario_event: dict) -> tuple[float, float]:
    """The world goal in the odom frame (the robot starts at the origin facing +x)."""
    return goal_in_odom(tuple(scenario_event["start"]), scenario_event["goal"])


def contacts(sim: EmulatorProcess) -> list[dict[str, Any]]:
    """Every contact the sim has reported so far, rounded for reading."""
    out = []
    for e in sim.history:
        if e.get("event") == "contact":
            out.append({k: round(v, 3) if isinstance(v, float) else v
                        for k, v in e.items() if k != "event"})
    return out
