"""A picture of one flight recording (`safemove plot LOG.mcap -o run.png`), drawn with
matplotlib's object API into a PNG file (the Agg canvas: no display, no pyplot state).

Left, the odom frame (equal aspect): the robot's path (fused pose, `/tf`) from its start (o) to
its end (square); the obstacle points it remembered (`/obstacles`, each cloud moved into odom
with its cycle's pose, on a 5 cm grid, at most `MAX_POINTS` of them); the people it tracked
(`/planning` "tracks", a dot per track per cycle, darker later; tentative ones grey); DWA's best
path every `PLAN_EVERY`-th planning cycle and the last one (green); the goals (stars).
Right, against seconds from the first cycle (`/cycle`): the commanded and the measured speed;
a mark per cycle the shield intervened (by kind) or the loop held; each stage's time and the
cycle's sum of them, against the control period.

Needs matplotlib (the `plots` extra, also in `train`).
"""

from __future__ import annotations

import json
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from runtime.errors import UserError
from runtime.process.flight_log import read_flight_log
from sim_stub.plots import finish_map

DPI = 120
MAX_POINTS = 50_000  # obstacle points drawn at most
GRID_M = 0.05  # obstacle points are merged on this grid before drawing
PLAN_EVERY = 20  # DWA's best path drawn every this many planning cycles (and the last)
STAGES = ("odometry", "perception", "memory", "tracking", "job")
KINDS = ("replaced", "turned", "braked")  # the shield's interventions, in this order
KIND_COLOURS = {"replaced": "#ff7f0e", "turned": "#9467bd", "braked": "#d62728",
                "held": "0.45"}
_MERGE_AT = 2_000_000  # grid keys collected before they are merged (bounds the memory)


@dataclass
class FlightLog:
    """What the picture shows, read from one recording."""

    metadata: dict[str, str]
    t: list[float] = field(default_factory=list)  # cycle times, s (host monotonic)
    pose: list[tuple[float, float, float]] = field(default_factory=list)  # /tf x, y, yaw
    v_cmd: list[float] = field(default_factory=list)
    v_odom: list[float] = field(default_factory=list)
    shield: list[str | None] = field(default_factory=list)  # the kind, None: no decision
    held: list[bool] = field(default_factory=list)
    stage_ms: list[dict[str, float]] = field(default_factory=list)
    obstacles: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # odom, m
    clouds: int = 0
    tracks: list[tuple[float, float, float, bool]] = field(default_factory=list)  # t, x, y, conf
    plans: list[np.ndarray] = field(default_factory=list)  # odom, drawn thin
    last_plan: np.ndarray | None = None
    goals: list[tuple[float, float]] = field(default_factory=list)


def _num(x: Any) -> float:
    """A recorded number (non-finite ones are recorded as strings: 'nan', 'inf')."""
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def _yaw(q: Any) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _to_odom(xy: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return np.column_stack((x + c * xy[:, 0] - s * xy[:, 1], y + s * xy[:, 0] + c * xy[:, 1]))


def _cloud_xy(cloud: PointCloud) -> np.ndarray:
    offsets = {f.name: f.offset for f in cloud.fields}
    stride = cloud.point_stride
    if stride <= 0 or "x" not in offsets or "y" not in offsets:
        return np.zeros((0, 2))
    n = len(cloud.data) // stride
    raw = np.frombuffer(cloud.data, dtype=np.uint8, count=n * stride).reshape(n, stride)
    xy = np.empty((n, 2))
    for k, name in enumerate("xy"):
        o = offsets[name]
        xy[:, k] = raw[:, o:o + 4].copy().view("<f4").ravel()
    return xy[np.isfinite(xy).all(axis=1)]


def _grid_keys(xy: np.ndarray) -> np.ndarray:
    cells = np.floor(xy / GRID_M).astype(np.int64)
    return (cells[:, 0] << 32) ^ (cells[:, 1] & 0xFFFFFFFF)


def _grid_points(keys: np.ndarray) -> np.ndarray:
    ix = keys >> 32
    iy = (keys & 0xFFFFFFFF).astype(np.int64)
    iy = np.where(iy >= 2**31, iy - 2**32, iy)
    return (np.column_stack((ix, iy)).astype(float) + 0.5) * GRID_M


def read_log(path: Path) -> FlightLog:
    """The recording's cycles, poses, remembered obstacles, tracks, plans and goals."""
    metadata, messages = read_flight_log(path)
    log = FlightLog(metadata)
    pose: tuple[float, float, float] | None = None
    keys: list[np.ndarray] = []
    held_keys, planning_cycles = 0, 0
    goals: dict[tuple[float, float], None] = {}
    for topic, data in messages:
        if topic == "/tf":
            tf = FrameTransform.FromString(data)
            if tf.parent_frame_id == "odom" and tf.child_frame_id == "base_link":
                pose = (tf.translation.x, tf.translation.y, _yaw(tf.rotation))
        elif topic == "/obstacles" and pose is not None:
            xy = _cloud_xy(PointCloud.FromString(data))
            log.clouds += 1
            if len(xy):
                keys.append(np.unique(_grid_keys(_to_odom(xy, pose))))
                held_keys += len(keys[-1])
                if held_keys > _MERGE_AT:
                    keys = [np.unique(np.concatenate(keys))]
                    held_keys = len(keys[0])
        elif topic == "/planning":
            for e in SceneUpdate.FromString(data).entities:
                t = e.timestamp.seconds + 1e-9 * e.timestamp.nanos  # the cycle's time
                if e.id == "tracks":
                    for c in e.cylinders:
                        confirmed = c.color.r > 0.8 and c.color.g < 0.5
                        log.tracks.append((t, c.pose.position.x, c.pose.position.y, confirmed))
                elif e.id == "plan" and e.lines and pose is not None:
                    pts = np.array([(p.x, p.y) for p in e.lines[0].points], dtype=float)
                    if len(pts):
                        path_odom = _to_odom(pts, pose)
                        if planning_cycles % PLAN_EVERY == 0:
                            log.plans.append(path_odom)
                        log.last_plan = path_odom
                        planning_cycles += 1
                elif e.id == "goal":
                    for c in e.cylinders:
                        goals[(round(c.pose.position.x, 3), round(c.pose.position.y, 3))] = None
        elif topic == "/cycle":
            c = json.loads(data)
            odom = c.get("odometry") or {}
            log.t.append(_num(c.get("t")))
            log.pose.append(pose if pose is not None else (
                _num(odom.get("x")), _num(odom.get("y")), _num(odom.get("theta"))))
            log.v_cmd.append(_num((c.get("command") or {}).get("v")))
            log.v_odom.append(_num(odom.get("v")))
            shield = c.get("shield")
            log.shield.append(None if not shield else str(shield.get("kind")))
            log.held.append(c.get("hold") is not None)
            log.stage_ms.append({k: _num(v) for k, v in (c.get("stage_ms") or {}).items()})
    if keys:
        log.obstacles = _grid_points(np.unique(np.concatenate(keys)))
    if len(log.obstacles) > MAX_POINTS:
        pick = np.random.default_rng(0).choice(len(log.obstacles), MAX_POINTS, replace=False)
        log.obstacles = log.obstacles[np.sort(pick)]
    log.goals = list(goals)
    return log


def _control_period_ms(metadata: dict[str, str]) -> float | None:
    try:
        hz = float(yaml.safe_load(metadata.get("config", ""))["loop"]["control_hz"])
    except (yaml.YAMLError, KeyError, TypeError, ValueError):
        return None
    return 1e3 / hz if hz > 0 else None


def summary(log: FlightLog) -> dict[str, Any]:
    """Cycles, duration, distance travelled (the fused pose), interventions by kind."""
    t = np.asarray(log.t, dtype=float)
    xy = np.asarray([p[:2] for p in log.pose], dtype=float).reshape(-1, 2)
    steps = np.hypot(*np.diff(xy, axis=0).T) if len(xy) > 1 else np.zeros(0)
    kinds = Counter(k for k in log.shield if k is not None and k != "passed")
    return {"job": log.metadata.get("job"), "cycles": len(log.t),
            "duration_s": round(float(t[-1] - t[0]), 3) if len(t) else 0.0,
            "distance_m": round(float(np.nansum(steps)), 3),
            "interventions": dict(sorted(kinds.items())), "held_cycles": sum(log.held),
            "obstacle_points": len(log.obstacles), "track_observations": len(log.tracks),
            "goals": [list(g) for g in log.goals]}


def _draw_map(ax: Axes, log: FlightLog) -> None:
    handles: list[Any] = []
    if len(log.obstacles):
        ax.scatter(log.obstacles[:, 0], log.obstacles[:, 1], s=2.0, c="0.45", marker=".",
                   linewidths=0, zorder=1, rasterized=True)
        handles.append(Line2D([], [], marker=".", color="0.45", linestyle="none",
                              label=f"remembered obstacles ({len(log.obstacles)} pts)"))
    if log.tracks:
        tr = np.asarray([(t, x, y) for t, x, y, ok in log.tracks if ok], dtype=float)
        tentative = np.asarray([(x, y) for _t, x, y, ok in log.tracks if not ok], dtype=float)
        if len(tentative):
            ax.scatter(tentative[:, 0], tentative[:, 1], s=4, c="0.7", linewidths=0,
                       alpha=0.5, zorder=2)
        if len(tr):
            ax.scatter(tr[:, 1], tr[:, 2], s=5, c=tr[:, 0], cmap="Reds", linewidths=0,
                       alpha=0.6, vmin=float(tr[0, 0]) - 0.3 * max(1e-9, np.ptp(tr[:, 0])),
                       vmax=float(tr[-1, 0]), zorder=3)
        handles.append(Line2D([], [], marker="o", markersize=4, color="#d62728", alpha=0.6,
                              linestyle="none", label="people tracked (darker: later)"))
    for plan in log.plans:
        ax.plot(plan[:, 0], plan[:, 1], color="#2ca02c", linewidth=0.6, alpha=0.55, zorder=4)
    if log.last_plan is not None:
        ax.plot(log.last_plan[:, 0], log.last_plan[:, 1], color="#2ca02c", linewidth=1.4,
                zorder=4)
        handles.append(Line2D([], [], color="#2ca02c", linewidth=1.0,
                              label=f"DWA best path (every {PLAN_EVERY}th, last)"))
    xy = np.asarray([p[:2] for p in log.pose], dtype=float).reshape(-1, 2)
    if len(xy):
        ax.plot(xy[:, 0], xy[:, 1], color="#1f77b4", linewidth=1.6, zorder=5)
        ax.plot(xy[:1, 0], xy[:1, 1], marker="o", markersize=7, color="black",
                linestyle="none", zorder=7)
        ax.plot(xy[-1:, 0], xy[-1:, 1], marker="s", markersize=6, color="#1f77b4",
                markeredgecolor="black", linestyle="none", zorder=7)
        yaw = log.pose[-1][2]
        if math.isfinite(yaw):
            ax.annotate("", xy=(xy[-1, 0] + 0.3 * math.cos(yaw), xy[-1, 1] + 0.3 * math.sin(yaw)),
                        xytext=(xy[-1, 0], xy[-1, 1]),
                        arrowprops={"arrowstyle": "->", "color": "black", "lw": 1.0}, zorder=7)
        handles += [Line2D([], [], color="#1f77b4", linewidth=1.6, label="robot path (odom)"),
                    Line2D([], [], marker="o", color="black", linestyle="none", label="start"),
                    Line2D([], [], marker="s", color="#1f77b4", markeredgecolor="black",
                           linestyle="none", label="end (heading)")]
    if log.goals:
        g = np.asarray(log.goals, dtype=float)
        ax.plot(g[:, 0], g[:, 1], marker="*", markersize=14, color="#2ca02c",
                markeredgecolor="black", markeredgewidth=0.6, linestyle="none", zorder=8)
        handles.append(Line2D([], [], marker="*", markersize=10, color="#2ca02c",
                              markeredgecolor="black", linestyle="none", label="goal"))
    finish_map(ax, "odom")
    ax.legend(handles=handles, loc="best", fontsize=7, framealpha=0.8)


def _draw_speed(ax: Axes, t: np.ndarray, log: FlightLog) -> None:
    ax.plot(t, log.v_cmd, drawstyle="steps-post", color="#ff7f0e", linewidth=1.0,
            label="commanded v")
    ax.plot(t, log.v_odom, color="#1f77b4", linewidth=1.0, label="measured v (odometry)")
    ax.axhline(0.0, color="0.5", linewidth=0.6)
    ax.set_ylabel("speed (m/s)")
    ax.legend(loc="best", fontsize=7, framealpha=0.8)
    ax.grid(alpha=0.25)


def _draw_shield(ax: Axes, t: np.ndarray, log: FlightLog) -> None:
    seen = {k for k in log.shield if k is not None and k != "passed"}
    rows = [k for k in KINDS if k in seen] + sorted(seen - set(KINDS))
    if any(log.held):
        rows.append("held")
    labels = []
    for y, row in enumerate(rows):
        mask = (np.asarray(log.held) if row == "held"
                else np.asarray([k == row for k in log.shield], dtype=bool))
        ax.scatter(t[mask], np.full(int(mask.sum()), y), marker="|", s=60,
                   color=KIND_COLOURS.get(row, "C0"), linewidths=1.2)
        labels.append(f"{row} ({int(mask.sum())})")
    if rows:
        ax.set_yticks(range(len(rows)), labels, fontsize=8)
        ax.set_ylim(-0.6, len(rows) - 0.4)
    else:
        ax.set_yticks([])
        ax.text(0.5, 0.5, "no interventions, no holds", transform=ax.transAxes,
                ha="center", va="center", fontsize=9, color="0.4")
    ax.set_ylabel("shield")
    ax.grid(axis="x", alpha=0.25)


def _draw_stages(ax: Axes, t: np.ndarray, log: FlightLog) -> None:
    present = [s for s in STAGES if any(s in d for d in log.stage_ms)]
    for k, stage in enumerate(present):
        ms = np.asarray([d.get(stage, math.nan) for d in log.stage_ms], dtype=float)
        ax.plot(t, np.where(ms > 0, ms, np.nan), linewidth=0.7, color=f"C{k}", label=stage)
    total = np.asarray([sum(v for v in d.values() if math.isfinite(v)) for d in log.stage_ms],
                       dtype=float)
    ax.plot(t, np.where(total > 0, total, np.nan), linewidth=1.1, color="black",
            label="sum of stages")
    period = _control_period_ms(log.metadata)
    if period is not None:
        ax.axhline(period, color="#d62728", linestyle="--", linewidth=0.8,
                   label=f"control period ({period:.0f} ms)")
    if np.any(total > 0):
        ax.set_yscale("log")
        top = max(period or 0.0, float(np.nanmax(np.where(total > 0, total, np.nan))))
        ax.set_ylim(top=40.0 * top)  # room for the legend above the lines
    ax.set_ylabel("stage time (ms)")
    ax.set_xlabel("time since the first cycle (s)")
    ax.legend(loc="upper right", fontsize=7, ncol=2, framealpha=0.8)
    ax.grid(alpha=0.25, which="both")


def draw(log: FlightLog, name: str) -> Figure:
    """The picture of a read recording; `name` heads it (the file's name)."""
    fig = Figure(figsize=(15.0, 8.0), layout="constrained")
    grid = fig.add_gridspec(3, 2, width_ratios=(1.25, 1.0))
    _draw_map(fig.add_subplot(grid[:, 0]), log)
    speed = fig.add_subplot(grid[0, 1])
    shield = fig.add_subplot(grid[1, 1], sharex=speed)
    stages = fig.add_subplot(grid[2, 1], sharex=speed)
    t = np.asarray(log.t, dtype=float) - log.t[0]
    _draw_speed(speed, t, log)
    _draw_shield(shield, t, log)
    _draw_stages(stages, t, log)
    for ax in (speed, shield):
        ax.tick_params(labelbottom=False)
    s = summary(log)
    kinds = ", ".join(f"{n} {k}" for k, n in s["interventions"].items()) or "none"
    fig.suptitle(f"{name} — job {s['job'] or '?'}, {s['duration_s']:.1f} s, {s['cycles']}"
                 f" cycles, {s['distance_m']:.2f} m travelled; shield interventions: {kinds}",
                 fontsize=11)
    return fig


def plot_log(path: Path, out_png: Path) -> dict[str, Any]:
    """Draw the recording at `path` into `out_png`; a small summary of the run. A file that is
    not a readable SafeMove recording, one with no cycles, or an output that cannot be written
    is a UserError."""
    path, out_png = Path(path), Path(out_png)
    log = read_log(path)
    if not log.t:
        raise UserError(f"{path}: no recorded cycles")
    fig = draw(log, path.name)
    FigureCanvasAgg(fig)  # the file-only canvas, whatever pyplot's backend is
    try:
        fig.savefig(out_png, dpi=DPI, format="png")
    except OSError as exc:
        raise UserError(f"{out_png}: cannot write: {exc.strerror or exc}") from None
    return {"log": str(path), "plot": str(out_png), **summary(log)}
