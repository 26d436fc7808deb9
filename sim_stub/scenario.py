"""Simulation scenarios as data: YAML files validated with the project's typed-schema mechanism.

A scenario names the area, where the robot starts, the goal points it may be sent to, the crowd
(count, whether it sees the robot, speeds, radius, ORCA horizons) and the static obstacles. Every
mistake in a file is one line naming the file and the key (`runtime.errors.ConfigError`).

Lists (`goals`, `obstacles`) are checked here item by item with keys like `goals[2]` and
`obstacles[1].size`; everything else goes through `runtime.config.schema.build`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from runtime.config.schema import build, load_yaml_file, setting
from runtime.errors import ConfigError

SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"


@dataclass(frozen=True)
class Rect:
    x_min: float = setting(-5.0, "lower x bound", "m", min=-1000.0, max=1000.0)
    x_max: float = setting(5.0, "upper x bound", "m", min=-1000.0, max=1000.0)
    y_min: float = setting(-5.0, "lower y bound", "m", min=-1000.0, max=1000.0)
    y_max: float = setting(5.0, "upper y bound", "m", min=-1000.0, max=1000.0)

    def contains(self, x: float, y: float, margin: float = 0.0) -> bool:
        return (
            self.x_min + margin <= x <= self.x_max - margin
            and self.y_min + margin <= y <= self.y_max - margin
        )


@dataclass(frozen=True)
class RobotStart:
    area: Rect = dataclasses.field(
        default_factory=lambda: Rect(-0.5, 0.5, -0.5, 0.5),
        metadata={"doc": "the start position is drawn uniformly in this rectangle"},
    )
    heading_deg: float = setting(0.0, "start heading (0 = +x)", "deg", min=-180.0, max=180.0)
    heading_jitter_deg: float = setting(
        0.0, "start heading drawn uniformly in heading ± this", "deg", min=0.0, max=180.0
    )


@dataclass(frozen=True)
class CrowdSpec:
    count: int = setting(0, "number of ORCA agents", min=0, max=200)
    reactive: bool = setting(
        False,
        "agents see the robot (it is a non-reactive ORCA neighbour to them); false = oblivious",
    )
    speed_range: tuple[float, float] = setting(
        (0.5, 1.0), "preferred speed drawn uniformly in [lo, hi]", "m/s", min=0.05, max=3.0
    )
    radius: float = setting(0.3, "agent radius", "m", min=0.05, max=1.0)
    time_horizon_s: float = setting(5.0, "ORCA time horizon for agents", "s", min=0.1, max=30.0)
    obstacle_time_horizon_s: float = setting(
        2.0, "ORCA time horizon for static obstacles", "s", min=0.1, max=30.0
    )
    neighbour_distance_m: float = setting(
        10.0, "agents farther than this are ignored", "m", min=0.5, max=100.0
    )
    safety_margin_m: float = setting(
        0.02,
        "extra radius the agents plan with (collisions are judged with the true radius)",
        "m",
        min=0.0,
        max=0.5,
    )
    max_neighbours: int = setting(10, "at most this many nearest agents considered", min=1)
    decision_period_s: float = setting(
        0.1, "agents choose a new velocity (an ORCA step) every this many seconds and walk"
        " straight in between, as people do; 0 = at every simulation step", "s", min=0.0,
        max=1.0)
    comfort_distance_m: float = setting(
        0.25, "reactive agents keep this much space to the robot beyond contact (people keep a"
        " comfort distance from a robot); 0 = they pass as close as to each other", "m",
        min=0.0, max=2.0)
    max_accel_m_s2: float = setting(
        1.5, "agents change velocity at most this fast (people cannot turn or stop at once);"
        " 0 = unbounded", "m/s²", min=0.0, max=20.0)
    goal_min_distance_m: float = setting(
        2.0, "a re-drawn goal is at least this far from the agent (when possible)", "m", min=0.0
    )


@dataclass(frozen=True)
class BoxSpec:
    center: tuple[float, float] = setting((0.0, 0.0), "centre x, y", "m", min=-1000.0, max=1000.0)
    size: tuple[float, float] = setting(
        (1.0, 1.0), "size along its own x, y", "m", min=0.0, max=1000.0, min_exclusive=True
    )
    yaw_deg: float = setting(0.0, "rotation", "deg", min=-360.0, max=360.0)
    height: float = setting(1.0, "height", "m", min=0.0, max=10.0, min_exclusive=True)


@dataclass(frozen=True)
class CylinderSpec:
    center: tuple[float, float] = setting((0.0, 0.0), "centre x, y", "m", min=-1000.0, max=1000.0)
    radius: float = setting(0.3, "radius", "m", min=0.0, max=100.0, min_exclusive=True)
    height: float = setting(1.0, "height", "m", min=0.0, max=10.0, min_exclusive=True)


@dataclass(frozen=True)
class WallSpec:
    start: tuple[float, float] = setting((0.0, 0.0), "first end x, y", "m", min=-1000.0, max=1000.0)
    end: tuple[float, float] = setting((1.0, 0.0), "second end x, y", "m", min=-1000.0, max=1000.0)
    thickness: float = setting(0.1, "thickness", "m", min=0.0, max=10.0, min_exclusive=True)
    height: float = setting(2.0, "height", "m", min=0.0, max=10.0, min_exclusive=True)


ObstacleSpec = BoxSpec | CylinderSpec | WallSpec
OBSTACLE_TYPES: dict[str, type] = {"box": BoxSpec, "cylinder": CylinderSpec, "wall": WallSpec}


@dataclass(frozen=True)
class Scenario:
    name: str = setting("", "scenario name")
    description: str = setting("", "one line saying what the scenario is for")
    seed: int = setting(0, "default episode seed", min=0)
    time_limit_s: float = setting(60.0, "episode time limit", "s", min=0.0, min_exclusive=True)
    goal_tolerance_m: float = setting(
        0.2, "the robot succeeds within this distance of its goal", "m", min=0.01, max=5.0
    )
    area: Rect = dataclasses.field(
        default_factory=Rect, metadata={"doc": "where the crowd spawns and draws its goals"}
    )
    robot: RobotStart = dataclasses.field(
        default_factory=RobotStart, metadata={"doc": "robot start area and heading"}
    )
    crowd: CrowdSpec = dataclasses.field(
        default_factory=CrowdSpec, metadata={"doc": "the ORCA crowd"}
    )
    # Lists, validated by parse_scenario (not by runtime.config.schema.build):
    goals: tuple[tuple[float, float], ...] = ()
    obstacles: tuple[ObstacleSpec, ...] = ()
    source: str = ""


_LIST_KEYS = ("goals", "obstacles")


def _error(source: str, key: str, problem: str) -> ConfigError:
    return ConfigError(f"{source}: key '{key}': {problem}")


def _point(value: Any, source: str, key: str) -> tuple[float, float]:
    ok = isinstance(value, (list, tuple)) and len(value) == 2
    if ok:
        ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    if not ok or not all(math.isfinite(v) for v in value):
        raise _error(source, key, f"expected a list of 2 numbers, got {value!r}")
    return float(value[0]), float(value[1])


def _check_rect(rect: Rect, source: str, key: str) -> None:
    if rect.x_min >= rect.x_max:
        raise _error(source, f"{key}.x_max", f"must be greater than x_min ({rect.x_min})")
    if rect.y_min >= rect.y_max:
        raise _error(source, f"{key}.y_max", f"must be greater than y_min ({rect.y_min})")


def parse_scenario(data: Any, source: str) -> Scenario:
    """Validate parsed YAML into a Scenario; every problem is one ConfigError line."""
    if not isinstance(data, dict):
        raise ConfigError(
            f"{source}: expected a mapping of scenario keys, got {type(data).__name__}"
        )
    rest = {k: v for k, v in data.items() if k not in _LIST_KEYS and k != "source"}
    if "source" in data:
        raise ConfigError(f"{source}: unknown key 'source'")
    scenario = build(Scenario, rest, source)
    if not scenario.name:
        raise _error(source, "name", "is required (a non-empty string)")
    _check_rect(scenario.area, source, "area")
    _check_rect(scenario.robot.area, source, "robot.area")
    lo, hi = scenario.crowd.speed_range
    if lo > hi:
        raise _error(source, "crowd.speed_range", f"lower bound {lo} exceeds upper bound {hi}")

    raw_goals = data.get("goals")
    if not isinstance(raw_goals, list) or not raw_goals:
        raise _error(
            source, "goals", f"expected a non-empty list of [x, y] points, got {raw_goals!r}"
        )
    goals = tuple(_point(g, source, f"goals[{i}]") for i, g in enumerate(raw_goals))
    for i, (gx, gy) in enumerate(goals):
        if not scenario.area.contains(gx, gy):
            raise _error(source, f"goals[{i}]", f"({gx}, {gy}) lies outside the area")

    raw_obstacles = data.get("obstacles", [])
    if raw_obstacles is None:
        raw_obstacles = []
    if not isinstance(raw_obstacles, list):
        raise _error(source, "obstacles", f"expected a list, got {type(raw_obstacles).__name__}")
    obstacles: list[ObstacleSpec] = []
    for i, item in enumerate(raw_obstacles):
        key = f"obstacles[{i}]"
        if not isinstance(item, dict):
            raise _error(source, key, f"expected a mapping, got {item!r}")
        kind = item.get("type")
        if kind not in OBSTACLE_TYPES:
            allowed = ", ".join(repr(k) for k in OBSTACLE_TYPES)
            raise _error(source, f"{key}.type", f"must be one of {allowed}, got {kind!r}")
        fields_ = {k: v for k, v in item.items() if k != "type"}
        spec = build(OBSTACLE_TYPES[kind], fields_, source, f"{key}.")
        if isinstance(spec, WallSpec) and spec.start == spec.end:
            raise _error(source, f"{key}.end", "must differ from start")
        obstacles.append(spec)
    return dataclasses.replace(scenario, goals=goals, obstacles=tuple(obstacles), source=source)


def available_scenarios() -> list[str]:
    """Names of the shipped scenarios."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml"))


def load_scenario(path_or_name: str | Path) -> Scenario:
    """Load a scenario file; a bare name (no '/' and no '.yaml') means a shipped scenario."""
    text = str(path_or_name)
    if isinstance(path_or_name, Path) or "/" in text or text.endswith((".yaml", ".yml")):
        path = Path(path_or_name).expanduser()
    else:
        path = SCENARIO_DIR / f"{text}.yaml"
        if not path.is_file():
            names = ", ".join(available_scenarios())
            raise ConfigError(f"scenario '{text}': no such shipped scenario (have: {names})")
    return parse_scenario(load_yaml_file(path, "scenario file"), str(path))


CROWD_MODES = ("scenario", "reactive", "oblivious")


def with_crowd(scenario: Scenario, mode: str) -> Scenario:
    """The scenario with its crowd made to see and avoid the robot ("reactive") or not
    ("oblivious"); "scenario" keeps what the file says."""
    if mode == "scenario":
        return scenario
    if mode not in CROWD_MODES:
        raise ValueError(f"crowd mode must be one of {CROWD_MODES}, got {mode!r}")
    return dataclasses.replace(scenario, crowd=dataclasses.replace(
        scenario.crowd, reactive=mode == "reactive"))
