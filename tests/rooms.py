"""Small scenario files for tests: an empty 6 m room (or one with a few obstacles) whose robot
start, goal, crowd and time limit a test chooses, so an episode's length and outcome are known."""

from __future__ import annotations

from pathlib import Path


def write_room(directory: Path, name: str, *, goal: tuple[float, float],
               time_limit_s: float = 30.0,
               start: tuple[float, float, float, float] = (-0.01, 0.01, -0.01, 0.01),
               heading_jitter_deg: float = 0.0, crowd: str = "{count: 0}",
               obstacles: str = " []") -> str:
    """Write `name`.yaml into `directory`: the robot drawn in `start` (x_min, x_max, y_min,
    y_max) facing +x (± the jitter), one goal; returns its path. `obstacles` is the YAML after
    the key (a flow list, or block lines starting with a newline)."""
    x0, x1, y0, y1 = start
    path = Path(directory) / f"{name}.yaml"
    path.write_text(
        f"name: {name}\n"
        "description: a test room\n"
        "seed: 3\n"
        f"time_limit_s: {time_limit_s}\n"
        "area: {x_min: -3.0, x_max: 3.0, y_min: -3.0, y_max: 3.0}\n"
        "robot:\n"
        f"  area: {{x_min: {x0}, x_max: {x1}, y_min: {y0}, y_max: {y1}}}\n"
        "  heading_deg: 0.0\n"
        f"  heading_jitter_deg: {heading_jitter_deg}\n"
        f"goals: [[{goal[0]}, {goal[1]}]]\n"
        f"crowd: {crowd}\n"
        f"obstacles:{obstacles}\n")
    return str(path)
