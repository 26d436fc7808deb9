"""Pictures of an evaluation (`safemove eval --plots DIR`), drawn with matplotlib's object API
into PNG files (the Agg canvas: no display, no pyplot state).

- `<scenario>_trajectories.png`, one per scenario: the area, the static obstacles to scale (the
  footprints the world judges contacts with), the start area and the goals with their
  tolerance, and every episode's true path in the world frame coloured by its outcome (success
  green, collision red, timeout orange; the legend counts them). A collision's end is an x, with
  the robot's outline there and, for a person, that person's outline at the contact.
- `outcomes.png`: success, collision and timeout rates per scenario as grouped bars, a group per
  scenario and a bar per outcome (and per planner, for several results side by side).

Needs matplotlib (the `plots` extra, also in `train`).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle as CirclePatch
from matplotlib.patches import Patch, Rectangle
from matplotlib.patches import Polygon as PolygonPatch

from sim_stub.evaluate import Trajectory
from sim_stub.orca import Circle
from sim_stub.scenario import Scenario, load_scenario
from sim_stub.world import ROBOT_RADIUS_M, obstacle_shape

OUTCOMES = ("success", "collision", "timeout")
COLOURS = {"success": "#2ca02c", "collision": "#d62728", "timeout": "#ff7f0e"}
DPI = 120
_HATCHES = ("", "//", "..", "xx", "\\\\", "--")



def finish_map(ax: Axes, frame: str) -> None:
    """A map's axes: metres in `frame`, equal aspect, a light grid."""
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.margins(0.03)
    ax.grid(alpha=0.25)
    ax.set_xlabel(f"x (m, {frame})")
    ax.set_ylabel(f"y (m, {frame})")

def planner_label(result: dict[str, Any]) -> str:
    """The planner of an eval result in words: DWA, or the SafeMove actor (variant or file)."""
    if result.get("planner") != "safemove":
        return str(result.get("planner", "?")).upper()
    if result.get("variant"):
        return f"SafeMove ({result['variant']})"
    return f"SafeMove ({Path(str(result.get('model'))).name})"


def scenario_label(name: str) -> str:
    """A scenario as the command line named it, shortened to its file's stem for a path."""
    return Path(name).stem if "/" in name or name.endswith((".yaml", ".yml")) else name


def plot_eval(result: dict[str, Any], trajectories: Sequence[Trajectory | None],
              out_dir: Path) -> list[Path]:
    """Write the pictures of one `evaluate` result into `out_dir` (which must exist);
    `trajectories` are the episodes' in the order of `result["episodes"]` (None: left out).
    Returns the files written: a trajectories picture per scenario, then `outcomes.png`."""
    out_dir = Path(out_dir)
    episodes = result["episodes"]
    if len(trajectories) != len(episodes):
        raise ValueError(f"plot_eval: {len(trajectories)} trajectories for {len(episodes)}"
                         " episodes")
    written: list[Path] = []
    stems: set[str] = set()
    for name in result["scenarios"]:
        stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", scenario_label(name)) or "scenario"
        unique, k = stem, 2
        while unique in stems:
            unique, k = f"{stem}_{k}", k + 1
        stems.add(unique)
        mine = [(e, t) for e, t in zip(episodes, trajectories) if e["scenario"] == name]
        path = out_dir / f"{unique}_trajectories.png"
        _save(plot_trajectories(load_scenario(name), mine, result), path)
        written.append(path)
    path = out_dir / "outcomes.png"
    _save(plot_outcomes([result]), path)
    written.append(path)
    return written


def _save(fig: Figure, path: Path) -> None:
    FigureCanvasAgg(fig)  # the file-only canvas, whatever pyplot's backend is
    fig.savefig(path, dpi=DPI, bbox_inches="tight", pad_inches=0.1)


def _draw_world(ax: Axes, scenario: Scenario) -> None:
    a = scenario.area
    ax.add_patch(Rectangle((a.x_min, a.y_min), a.x_max - a.x_min, a.y_max - a.y_min,
                           fill=False, edgecolor="0.35", linewidth=1.2, zorder=1))
    for spec in scenario.obstacles:
        shape = obstacle_shape(spec)
        style: dict[str, Any] = {"facecolor": "0.6", "edgecolor": "0.25", "linewidth": 0.8,
                                 "zorder": 2}
        if isinstance(shape, Circle):
            ax.add_patch(CirclePatch(shape.center, shape.radius, **style))
        else:
            ax.add_patch(PolygonPatch(shape.vertices, closed=True, **style))
    s = scenario.robot.area
    ax.add_patch(Rectangle((s.x_min, s.y_min), s.x_max - s.x_min, s.y_max - s.y_min,
                           fill=False, edgecolor="black", linestyle=":", linewidth=0.8,
                           zorder=3))
    for gx, gy in scenario.goals:
        ax.add_patch(CirclePatch((gx, gy), scenario.goal_tolerance_m, fill=False,
                                 edgecolor=COLOURS["success"], linestyle="--", linewidth=0.8,
                                 zorder=3))
        ax.plot([gx], [gy], marker="*", markersize=12, color=COLOURS["success"],
                markeredgecolor="black", markeredgewidth=0.6, linestyle="none", zorder=6)


def plot_trajectories(scenario: Scenario,
                      episodes: Sequence[tuple[dict[str, Any], Trajectory | None]],
                      result: dict[str, Any]) -> Figure:
    """One scenario's episodes (their JSON entries with their trajectories) over its map."""
    a = scenario.area
    w, h = a.x_max - a.x_min, a.y_max - a.y_min
    fig = Figure(figsize=(7.0, max(2.5, min(9.0, 7.0 * h / w))))
    ax = fig.add_subplot()
    _draw_world(ax, scenario)
    counts = dict.fromkeys(OUTCOMES, 0)
    people_shown = False
    on_top = {"success": 0, "timeout": 1, "collision": 2}  # collisions drawn last
    for ep, traj in sorted(episodes, key=lambda et: on_top.get(et[0]["status"], 0)):
        status = ep["status"]
        counts[status] = counts.get(status, 0) + 1
        if traj is None or len(traj.xy) == 0:
            continue
        colour = COLOURS.get(status, "0.4")
        x, y = traj.xy[:, 0], traj.xy[:, 1]
        ax.plot(x, y, color=colour, linewidth=1.0, alpha=0.75, zorder=4)
        ax.plot(x[:1], y[:1], marker="o", markersize=3, color="black", linestyle="none",
                zorder=5)
        if status != "collision":
            continue
        ax.add_patch(CirclePatch((float(x[-1]), float(y[-1])), ROBOT_RADIUS_M, fill=False,
                                 edgecolor=colour, linewidth=0.8, zorder=5))
        ax.plot(x[-1:], y[-1:], marker="x", markersize=8, markeredgewidth=2.0, color=colour,
                linestyle="none", zorder=7)
        who = str(ep.get("collided_with") or "")
        if who.startswith("agent "):
            k = int(who.split()[1])
            if 0 <= k < len(traj.people_xy):
                ax.add_patch(CirclePatch(tuple(traj.people_xy[k]), traj.people_radius,
                                         fill=False, edgecolor=colour, linestyle="--",
                                         linewidth=1.0, zorder=5))
                people_shown = True
    finish_map(ax, "world")
    n = len(episodes)
    seeds = sorted(int(ep["seed"]) for ep, _ in episodes)
    seed_text = "" if not seeds else (f", seed {seeds[0]}" if len(seeds) == 1
                                      else f", seeds {seeds[0]}–{seeds[-1]}")
    ax.set_title(f"{planner_label(result)} — {scenario.name}\n{n} episode{'s' * (n != 1)}"
                 f"{seed_text}, crowd: {result.get('crowd', 'scenario')}", fontsize=10)
    handles: list[Any] = [Line2D([], [], color=COLOURS[o], linewidth=2, label=f"{o} ({counts[o]})")
                          for o in OUTCOMES]
    handles += [
        Line2D([], [], marker="o", markersize=4, color="black", linestyle="none", label="start"),
        Line2D([], [], marker="*", markersize=10, color=COLOURS["success"],
               markeredgecolor="black", linestyle="none", label="goal (tolerance)"),
        Line2D([], [], marker="x", markersize=8, markeredgewidth=2, color=COLOURS["collision"],
               linestyle="none", label="contact (robot outline)"),
        Patch(facecolor="0.6", edgecolor="0.25", label="obstacle"),
    ]
    if people_shown:
        handles.append(Line2D([], [], color=COLOURS["collision"], linestyle="--",
                              label="person at contact"))
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8,
              frameon=False)
    return fig


def plot_outcomes(results: Sequence[dict[str, Any]]) -> Figure:
    """Success, collision and timeout rates per scenario: a group of bars per scenario, a bar
    per outcome; several results (planners) side by side in each group, told apart by hatching."""
    scenarios: list[str] = []
    for r in results:
        scenarios += [s for s in r["scenarios"] if s not in scenarios]
    n_bars = len(OUTCOMES) * len(results)
    width = 0.8 / n_bars
    fig = Figure(figsize=(max(4.0, 1.5 + (0.3 * n_bars + 0.4) * len(scenarios)), 4.0))
    ax = fig.add_subplot()
    for i, r in enumerate(results):
        for j, outcome in enumerate(OUTCOMES):
            offset = -0.4 + (i * len(OUTCOMES) + j + 0.5) * width
            xs, heights = [], []
            for k, name in enumerate(scenarios):
                if name in r["scenarios"]:
                    xs.append(k + offset)
                    heights.append(100.0 * r["scenarios"][name][f"{outcome}_rate"])
            bars = ax.bar(xs, heights, width, color=COLOURS[outcome], edgecolor="black",
                          linewidth=0.5, hatch=_HATCHES[i % len(_HATCHES)])
            ax.bar_label(bars, fmt="%.0f", fontsize=7, padding=1)
    ax.set_xticks(range(len(scenarios)), [scenario_label(s) for s in scenarios],
                  rotation=20 if len(scenarios) > 4 else 0)
    ax.set_ylim(0, 110)
    ax.set_ylabel("episodes, %")
    ax.grid(axis="y", alpha=0.25)
    handles: list[Any] = [Patch(facecolor=COLOURS[o], edgecolor="black", label=o)
                          for o in OUTCOMES]
    if len(results) > 1:
        handles += [Patch(facecolor="white", edgecolor="black", hatch=_HATCHES[i % len(_HATCHES)],
                          label=planner_label(r)) for i, r in enumerate(results)]
        title = "outcomes per scenario"
    else:
        r = results[0]
        counts = sorted({s["episodes"] for s in r["scenarios"].values()})
        each = f"{counts[0]} episodes" if len(counts) == 1 else f"{counts[0]}–{counts[-1]} episodes"
        title = (f"{planner_label(r)}: outcomes per scenario\n({each} each,"
                 f" crowd: {r.get('crowd', 'scenario')})")
    ax.set_title(title, fontsize=10)
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8,
              frameon=False)
    return fig
