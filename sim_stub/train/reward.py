"""The training rewards: the project's and the paper's, chosen by `RewardConfig.kind`, so the two
can be compared on equal budgets. Both are pure functions of one step's facts (`step_reward`).

Project (kind "project"): progress toward the goal per metre of true distance, a per-second time
cost, a bonus on success, a penalty on collision (any: the crowd may be oblivious, and a learnt
policy should keep away from people even when a contact would not be its fault), and a penalty
each cycle the shield changed the actor's command, so the actor learns to propose what the shield
passes.

Paper (kind "paper"): R = R_g + R_b + R_yaw, as we read it where the paper is ambiguous:
- R_g, the goal term: +paper_goal on the success step; on every other step a dense goal-approach
  term paper_approach_per_m · (d_prev − d_now), the paper's "approaching the goal" reward read as
  progress in true distance (the paper gives no formula for it). On the success step only the
  bonus counts, as the paper's piecewise form has it.
- R_b, the collision term: −paper_collision on the collision step, 0 otherwise.
- R_yaw, the corridor term: −paper_yaw_per_rad · |yaw error| every step, the yaw error being the
  angle from the robot's heading to the safe corridor's direction (`corridor_yaw_error`). Per
  step, as the paper has it, so its weight depends on the control rate.
The paper's reward has no time cost and no shield term: a run with it learns without being told
what the shield changed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from runtime.config.schema import setting

KINDS = ("project", "paper")


@dataclass(frozen=True)
class RewardConfig:
    kind: str = setting("project", "which reward: the project's or the paper's (R_g+R_b+R_yaw)",
                        choices=KINDS)
    progress_per_m: float = setting(10.0, "reward per metre of true progress toward the goal")
    time_per_s: float = setting(0.1, "cost per second of simulated time", min=0.0)
    success: float = setting(10.0, "bonus on reaching the goal (the world's verdict)")
    collision: float = setting(10.0, "penalty on any contact (the world's verdict)", min=0.0)
    shield_change: float = setting(
        0.05, "penalty for each cycle the shield changed the actor's command", min=0.0)
    paper_goal: float = setting(10.0, "paper R_g: bonus on reaching the goal", min=0.0)
    paper_approach_per_m: float = setting(
        10.0, "paper R_g: reward per metre of true progress toward the goal", min=0.0)
    paper_collision: float = setting(10.0, "paper R_b: penalty on any contact", min=0.0)
    paper_yaw_per_rad: float = setting(
        0.1, "paper R_yaw: penalty per step per radian of heading away from the corridor",
        min=0.0)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:  # fail at construction, not at an episode's first step
            raise ValueError(f"RewardConfig: kind must be one of {', '.join(KINDS)},"
                             f" got {self.kind!r}")


def step_reward(cfg: RewardConfig, *, progress_m: float, dt_s: float, outcome: str,
                shield_changed: bool, yaw_error_rad: float) -> float:
    """One step's reward. progress_m: true distance to the goal before minus after (> 0: nearer);
    outcome: "running", "success", "collision" or another end (no terminal term)."""
    if cfg.kind == "paper":
        r_g = cfg.paper_goal if outcome == "success" else cfg.paper_approach_per_m * progress_m
        r_b = -cfg.paper_collision if outcome == "collision" else 0.0
        return r_g + r_b - cfg.paper_yaw_per_rad * abs(yaw_error_rad)
    reward = (cfg.progress_per_m * progress_m - cfg.time_per_s * dt_s
              - (cfg.shield_change if shield_changed else 0.0))
    if outcome == "success":
        reward += cfg.success
    elif outcome == "collision":
        reward -= cfg.collision
    return reward


def corridor_yaw_error(best_path: np.ndarray) -> float:
    """The angle (rad, in [-π, π], left positive) from the robot's heading to the corridor's
    direction: the bearing in base_link of the last point of DWA's best path (steps, 3), along
    which the safe corridor runs. Its last point, not its first segment: the path is an arc from
    the robot, so its first segment's bearing is about ω·dt/2, near zero whatever the corridor
    does, while its end's is the corridor's mean direction over the horizon. A reversing path
    reads near ±π (the corridor runs behind the robot); one that does not leave the robot (DWA
    braking or turning in place) reads 0."""
    x, y = float(best_path[-1, 0]), float(best_path[-1, 1])
    if x == 0.0 and y == 0.0:  # atan2 of a signed zero would read ±π
        return 0.0
    return math.atan2(y, x)
