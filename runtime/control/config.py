"""The `control` config section: the control socket and the goals it gives the service
(runtime.jobs.mission, runtime.process.control_server)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from runtime.config.schema import setting
from runtime.planning.planning_step import ARRIVAL_RADIUS_M


@dataclass(frozen=True)
class ControlConfig:
    socket: str = setting(
        "", "Unix socket for goals, missions and status (JSON lines, mode 0660); empty = "
        "$RUNTIME_DIRECTORY/control.sock when systemd gives the service a RuntimeDirectory "
        "(/run/safemove/control.sock), else no socket: `safemove run` without --goal holds")
    planner: str = setting(
        "safemove", "the planner that drives to the socket's goals: safemove (the shipped "
        "policy, or --model / --variant) or dwa", choices=("safemove", "dwa"))
    goal_tolerance_m: float = setting(
        ARRIVAL_RADIUS_M, "default arrival tolerance of a goal or waypoint", "m", min=0.05,
        max=2.0)
    max_goal_distance_m: float = setting(
        50.0, "goals and waypoints farther than this from the robot are refused", "m",
        min=0.5, max=1000.0)
    waypoint_timeout_s: float = setting(
        300.0, "a waypoint not reached in this long fails (timeout); a request may give its "
        "own", "s", min=1.0, max=86400.0)
    blocked_timeout_s: float = setting(
        60.0, "a waypoint fails (blocked) when the robot has not come 0.1 m closer to it in "
        "this long", "s", min=1.0, max=3600.0)
    degraded_timeout_s: float = setting(
        10.0, "a goal fails when the loop has held (DEGRADED: stale or blind sensors, a "
        "hazard) this long without a break, so the robot does not drive off by itself later",
        "s", min=0.5, max=3600.0)


def control_socket_path(cfg: ControlConfig) -> Path | None:
    """Where the control socket listens: control.socket, else the socket in the runtime
    directory systemd made for the service (RuntimeDirectory=), else nowhere."""
    if cfg.socket:
        return Path(cfg.socket).expanduser()
    runtime_dir = os.environ.get("RUNTIME_DIRECTORY", "").split(":")[0]
    return Path(runtime_dir) / "control.sock" if runtime_dir else None
