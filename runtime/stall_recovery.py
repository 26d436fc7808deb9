"""Stall recovery for the goal-driven DWA job: when the robot has stood for a while, step away.

DWA is a local planner with a short window: beside a person or an obstacle that blocks the way
to the goal, every sample that drives on comes closer and every turn lowers the heading term,
so the best sample is to stand and wait. When the other body waits too (a person wedged between
the robot and a box; in the simulator, an ORCA agent) nobody ever moves. A real robot's
navigation stack has recovery behaviours for this (ROS move_base, Nav2: spin, back up); this is
one of them, the same for every planner decision downstream:

  stalled  the robot's odometry travelled less than `stall_distance_m` in the last `stall_s`
           seconds, short of the goal;
  escape   DWA plans toward a temporary goal `escape_goal_m` away from the nearest obstacle
           (remembered point or track, in the odom frame) instead of the real goal, until the
           robot has travelled `escape_distance_m` or `escape_timeout_s` has passed; then the
           real goal again, and a fresh stall timer.

Every command still goes through DWA's admissibility and the shield; the escape only moves the
goal. The goal-reached check always uses the real goal.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from runtime.schema import setting
from runtime.types import Odometry

if TYPE_CHECKING:  # runtime.config holds RecoveryConfig and world_model imports runtime.config
    from runtime.world_model import WorldState

log = logging.getLogger("safemove.planner")


@dataclass(frozen=True)
class RecoveryConfig:
    stall_s: float = setting(
        4.0, "the robot counts as stalled after travelling less than stall_distance_m for this"
        " long (0 = no recovery)", "s", min=0.0, max=600.0)
    stall_distance_m: float = setting(0.05, "travel that resets the stall timer", "m",
                                      min=0.001, max=1.0)
    escape_goal_m: float = setting(
        1.0, "the escape's temporary goal lies this far from the robot, away from the nearest"
        " obstacle", "m", min=0.1, max=5.0)
    escape_distance_m: float = setting(0.4, "the escape ends after this much travel", "m",
                                       min=0.01, max=5.0)
    escape_timeout_s: float = setting(8.0, "the escape ends after this long", "s", min=0.1,
                                      max=60.0)


@dataclass(frozen=True)
class _Escape:
    start_t: float
    start_distance: float
    goal: np.ndarray  # (2,) odom


class StallRecovery:
    """Tracks travel over time; `planning_goal` gives the goal DWA should plan for now."""

    def __init__(self, cfg: RecoveryConfig) -> None:
        self._cfg = cfg
        self._anchor: tuple[float, float] | None = None  # (time, odometry distance)
        self._escape: _Escape | None = None
        self.escapes = 0

    def planning_goal(self, now: float, odom: Odometry, world: WorldState,
                      goal: np.ndarray) -> np.ndarray:
        """The real goal, or an escape goal while the robot recovers from a stall."""
        cfg = self._cfg
        if cfg.stall_s <= 0.0:
            return goal
        if self._escape is not None:
            e = self._escape
            if (odom.distance - e.start_distance < cfg.escape_distance_m
                    and now - e.start_t < cfg.escape_timeout_s):
                return e.goal
            self._escape = None
            self._anchor = (now, odom.distance)
            return goal
        if self._anchor is None or odom.distance - self._anchor[1] >= cfg.stall_distance_m:
            self._anchor = (now, odom.distance)
            return goal
        if now - self._anchor[0] < cfg.stall_s:
            return goal
        nearest = nearest_obstacle_odom(odom, world)
        if nearest is None:  # nothing to step away from: keep waiting for the goal's way
            self._anchor = (now, odom.distance)
            return goal
        here = np.array([odom.x, odom.y])
        away = here - nearest
        away /= max(float(np.hypot(*away)), 1e-9)
        self._escape = _Escape(now, odom.distance, here + cfg.escape_goal_m * away)
        self.escapes += 1
        log.info("stalled %.1f s (%.3f m travelled): escaping toward (%.2f, %.2f), away from the"
                 " obstacle at (%.2f, %.2f) (odom)", now - self._anchor[0],
                 odom.distance - self._anchor[1], *self._escape.goal, *nearest)
        return self._escape.goal


def nearest_obstacle_odom(odom: Odometry, world: WorldState) -> np.ndarray | None:
    """The nearest remembered point or confirmed track (by its edge) in the odom frame, or None
    when the world holds neither."""
    c, s = np.cos(odom.theta), np.sin(odom.theta)
    pts = np.asarray(world.points_base, dtype=float).reshape(-1, 2)
    cands = [np.stack([odom.x + c * pts[:, 0] - s * pts[:, 1],
                       odom.y + s * pts[:, 0] + c * pts[:, 1]], axis=1)]
    gaps = [np.hypot(pts[:, 0], pts[:, 1])]
    confirmed = [t for t in world.tracks if t.confirmed]
    if confirmed:
        centres = np.array([t.position for t in confirmed], dtype=float)
        cands.append(centres)
        gaps.append(np.hypot(centres[:, 0] - odom.x, centres[:, 1] - odom.y)
                    - np.array([t.radius for t in confirmed]))
    where, gap = np.concatenate(cands), np.concatenate(gaps)
    if not len(gap):
        return None
    return where[int(np.argmin(gap))]
