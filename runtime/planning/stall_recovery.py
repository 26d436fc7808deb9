"""Stall recovery for the goal-driven jobs (DWA, SafeMove): when the robot has stood for a while,
step away.

DWA is a local planner with a short window: beside a person or an obstacle that blocks the way
to the goal, every sample that drives on comes closer and every turn lowers the heading term,
so the best sample is to stand and wait. When the other body waits too (a person wedged between
the robot and a box; in the simulator, an ORCA agent) nobody ever moves. A real robot's
navigation stack has recovery behaviours for this (ROS move_base, Nav2: spin, back up); this is
one of them, the same for every planner decision downstream:

  stalled  the robot's odometry travelled less than `stall_distance_m` in the last `stall_s`
           seconds, short of the goal;
  escape   DWA plans toward a temporary goal `escape_goal_m` away in the most open direction
           (of 36, the one whose straight segment keeps the most clearance from remembered
           points and tracks) instead of the real goal, until the robot has travelled
           `escape_distance_m` or `escape_timeout_s` has passed; then the real goal again, and a
           fresh stall timer.
  takeover a learned policy can freeze where its training never took it (a goal close beside
           the robot, at a large bearing: it stands or creeps, the goal unreached) while
           nothing is in its way. When a policy drives, has come no closer to the real goal
           by `stall_distance_m` in `stall_s`, and the straight way toward the goal (its first
           `escape_goal_m`) leaves room for the robot's disc, DWA's command drives instead of
           the policy's, toward the real goal, until the robot has travelled
           `escape_distance_m` or `escape_timeout_s` has passed; then the policy again. Where
           something is in the way, the policy keeps the wheel (and a stall, an escape),
           unless `takeover_when_blocked`: then a policy that moves without coming
           `takeover_progress_m` closer in `stall_s` (creeping, turning before a person) hands
           over too, and that takeover ends early once the robot has stood for
           `takeover_stand_s` (DWA waits as well; standing is the escape's business).

Every command still goes through the shield; the escape only moves the goal DWA plans for and,
in the SafeMove job, the goal in the policy's observation, and a takeover only chooses DWA's
command over the policy's. The goal-reached check always uses the real goal.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from runtime.config.schema import setting
from runtime.geometry import from_frame
from runtime.perception.world_model import WorldState
from runtime.types import Odometry

log = logging.getLogger("safemove.planner")


@dataclass(frozen=True)
class RecoveryConfig:
    stall_s: float = setting(
        8.0, "the robot counts as stalled after travelling less than stall_distance_m for this"
        " long (0 = no recovery)", "s", min=0.0, max=600.0)
    stall_distance_m: float = setting(0.05, "travel that resets the stall timer", "m",
                                      min=0.001, max=1.0)
    escape_goal_m: float = setting(
        1.0, "the escape's temporary goal lies this far from the robot, in the most open"
        " direction", "m", min=0.1, max=5.0)
    escape_distance_m: float = setting(0.4, "the escape ends after this much travel", "m",
                                       min=0.01, max=5.0)
    escape_timeout_s: float = setting(8.0, "the escape ends after this long", "s", min=0.1,
                                      max=60.0)
    dwa_takeover: bool = setting(
        True, "the SafeMove job: no progress toward the goal for stall_s with the way to it"
        " clear hands the drive to DWA, toward the real goal, for the escape's distance or"
        " time (a policy can freeze beside a goal it never met in training)")
    takeover_progress_m: float = setting(
        0.05, "the SafeMove job: the policy makes progress when it comes this much closer to"
        " the goal within stall_s; less is a takeover's first condition", "m", min=0.001,
        max=5.0)
    takeover_stand_s: float = setting(
        2.0, "a takeover with something in the way ends when the robot has stood (travelled"
        " less than stall_distance_m) this long: DWA waits too, the stall's escape is due",
        "s", min=0.1, max=60.0)
    takeover_when_blocked: bool = setting(
        False, "the SafeMove job: a policy that moves without progress hands the drive to DWA"
        " even with something in the way (DWA waits for or goes round people a policy may"
        " keep facing; measured in the README's Evaluation)")


@dataclass(frozen=True)
class _Escape:
    start_t: float
    start_distance: float
    goal: np.ndarray | None  # (2,) odom; None: a takeover, DWA drives to the real goal
    blocked: bool = False  # a takeover with something in the way: it ends when DWA stands


class StallRecovery:
    """Tracks travel and progress over time; `planning_goal` gives the goal DWA should plan for now, and
    `dwa_drives` whether DWA's command should drive instead of a policy's."""

    def __init__(self, cfg: RecoveryConfig, takeover_radius_m: float | None = None) -> None:
        """`takeover_radius_m`: when a policy drives, the robot's footprint radius (the room a
        clear way must leave); None: DWA drives itself, no takeovers."""
        self._cfg = cfg
        self._takeover_radius = takeover_radius_m if cfg.dwa_takeover else None
        self._anchor: tuple[float, float] | None = None  # (time, odometry distance)
        self._closest: tuple[float, float] | None = None  # (time, distance to the goal)
        self._escape: _Escape | None = None
        self.escapes = 0
        self.takeovers = 0

    @property
    def dwa_drives(self) -> bool:
        """A takeover is on (as of the last `planning_goal`)."""
        return self._escape is not None and self._escape.goal is None

    def planning_goal(self, now: float, odom: Odometry, world: WorldState,
                      goal: np.ndarray) -> np.ndarray:
        """The real goal, or an escape goal while the robot recovers from a stall."""
        cfg = self._cfg
        if cfg.stall_s <= 0.0:
            return goal
        here = np.array([odom.x, odom.y])
        to_goal = float(np.hypot(*(goal - here)))
        if self._escape is not None:
            e = self._escape
            assert self._anchor is not None  # set before any escape starts
            if e.blocked and odom.distance - self._anchor[1] >= cfg.stall_distance_m:
                self._anchor = (now, odom.distance)
            dwa_stands = e.blocked and now - self._anchor[0] >= cfg.takeover_stand_s
            if (odom.distance - e.start_distance < cfg.escape_distance_m
                    and now - e.start_t < cfg.escape_timeout_s and not dwa_stands):
                return goal if e.goal is None else e.goal
            self._escape = None
            self._anchor, self._closest = (now, odom.distance), (now, to_goal)
            return goal
        if self._closest is None or to_goal <= self._closest[1] - cfg.takeover_progress_m:
            self._closest = (now, to_goal)
        if self._anchor is None or odom.distance - self._anchor[1] >= cfg.stall_distance_m:
            self._anchor = (now, odom.distance)
        if self._takeover_radius is not None and now - self._closest[0] >= cfg.stall_s:
            centres, radii = obstacles_odom(odom, world)
            clear = way_gap(here, goal, centres, radii, cfg.escape_goal_m) > self._takeover_radius
            moving = now - self._anchor[0] < cfg.stall_s
            if clear or (cfg.takeover_when_blocked and moving):
                self._escape = _Escape(now, odom.distance, None, blocked=not clear)
                self.takeovers += 1
                log.info("no progress toward the goal for %.1f s (%.3f m travelled), the way to"
                         " it %s: DWA drives toward it for up to %.2f m or %.0f s",
                         now - self._closest[0], odom.distance - self._anchor[1],
                         "clear" if clear else "blocked", cfg.escape_distance_m,
                         cfg.escape_timeout_s)
                self._anchor = (now, odom.distance)
                return goal
            self._closest = (now, to_goal)  # something is in the way: look again in stall_s
        if now - self._anchor[0] < cfg.stall_s:
            return goal
        centres, radii = obstacles_odom(odom, world)
        heading = open_heading(here, centres, radii, cfg.escape_goal_m)
        if heading is None:  # nothing near to step away from: keep waiting for the goal's way
            self._anchor = (now, odom.distance)
            return goal
        away = np.array([np.cos(heading), np.sin(heading)])
        escape_goal = here + cfg.escape_goal_m * away
        self._escape = _Escape(now, odom.distance, escape_goal)
        self.escapes += 1
        log.info("stalled %.1f s (%.3f m travelled): escaping toward (%.2f, %.2f) (odom), the"
                 " most open way", now - self._anchor[0], odom.distance - self._anchor[1],
                 *escape_goal)
        return escape_goal


def obstacles_odom(odom: Odometry, world: WorldState) -> tuple[np.ndarray, np.ndarray]:
    """Remembered points and confirmed tracks in the odom frame: centres (K, 2), radii (K,)
    (0 for points)."""
    pts = np.asarray(world.points_base, dtype=float).reshape(-1, 2)
    centres = [np.stack(from_frame(odom.x, odom.y, odom.theta, pts[:, 0], pts[:, 1]), axis=1)]
    radii = [np.zeros(len(pts))]
    confirmed = [t for t in world.tracks if t.confirmed]
    if confirmed:
        centres.append(np.array([t.position for t in confirmed], dtype=float))
        radii.append(np.array([t.radius for t in confirmed], dtype=float))
    return np.concatenate(centres), np.concatenate(radii)


def way_gap(here: np.ndarray, goal: np.ndarray, centres: np.ndarray, radii: np.ndarray,
            length: float, step_m: float = 0.05) -> float:
    """The smallest gap (m) between the obstacles and the straight segment from `here` toward
    `goal`, up to `length` or the goal (inf with no obstacles)."""
    span = min(length, float(np.hypot(*(goal - here))))
    if not len(radii):
        return math.inf
    direction = (goal - here) / max(float(np.hypot(*(goal - here))), 1e-9)
    samples = here + np.linspace(0.0, span, max(2, round(span / step_m) + 1))[:, None] * direction
    gaps = np.hypot(samples[:, None, 0] - centres[None, :, 0],
                    samples[:, None, 1] - centres[None, :, 1]) - radii
    return float(gaps.min())


def open_heading(here: np.ndarray, centres: np.ndarray, radii: np.ndarray, length: float,
                 headings: int = 36, step_m: float = 0.1) -> float | None:
    """The heading (odom, rad) whose straight segment of `length` from `here` keeps the most
    clearance from the obstacles (smallest gap at samples every `step_m`); None when no
    obstacle is within `length` + 0.5 m (nothing to step away from). Away from the nearest
    obstacle alone can lead into a second one (a robot between two people)."""
    if not len(radii):
        return None
    gaps_here = np.hypot(*(centres - here).T) - radii
    near = gaps_here < length + 0.5
    if not near.any():
        return None
    centres, radii = centres[near], radii[near]
    angles = np.arange(headings) * (2.0 * np.pi / headings)
    dirs = np.stack([np.cos(angles), np.sin(angles)], axis=1)  # (H, 2)
    dists = np.arange(1, round(length / step_m) + 1) * step_m  # (S,)
    samples = here + dirs[:, None, :] * dists[None, :, None]  # (H, S, 2)
    gaps = (np.hypot(samples[:, :, None, 0] - centres[None, None, :, 0],
                     samples[:, :, None, 1] - centres[None, None, :, 1]) - radii)  # (H, S, K)
    return float(angles[int(np.argmax(gaps.min(axis=(1, 2))))])
