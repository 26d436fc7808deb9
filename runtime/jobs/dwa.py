"""The DWA planner mode (`safemove run --planner dwa`): the paper's DWA baseline, through the shield.

Each RUNNING cycle (runtime.planning.planning_step): the goal and the tracks' constant-velocity
predictions go into base_link, DWA picks the best admissible (v, ω) within its deadline, and the
shield certifies it or puts a certified DWA candidate (or a brake) in its place. Every
intervention is counted by reason. When the robot has stood too long short of the goal, the
stall recovery (runtime.planning.stall_recovery) points DWA away from what blocks it for a while.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from runtime.config.settings import Config
from runtime.perception.world_model import WorldState
from runtime.planning.planning_step import PlanningStep
from runtime.planning.stall_recovery import StallRecovery
from runtime.types import STOP, DecisionTrace, Odometry, Prepared, Twist


class DWAJob:
    """Drive to a goal in the odom frame with DWA, every command through the shield."""

    name = "dwa"

    def __init__(self, goal_odom: tuple[float, float], config: Config,
                 clock: Callable[[], float] | None, **goal: Any) -> None:
        """`goal`: PlanningStep's arrival_radius_m and speed_limit."""
        self._step = PlanningStep(goal_odom, config, clock, "DWA", **goal)
        self._recovery = StallRecovery(config.recovery)

    @property
    def finished(self) -> bool:
        return self._step.finished

    @property
    def reached(self) -> bool:
        return self._step.reached

    @property
    def shield_changed(self) -> bool:
        """The shield replaced the last decided command."""
        return self._step.last_intervened

    def pause(self) -> None:
        """Nothing to pause: each cycle plans from the present."""

    def prepare(self, now: float, odom: Odometry, world: WorldState | None) -> Prepared:
        plan_goal = (None if world is None
                     else self._recovery.planning_goal(now, odom, world, self._step.goal))
        return Prepared(self._step.prepare(now, odom, world, plan_goal))

    def decide(self, prepared: Prepared, action: object = None) -> Twist:
        """DWA's best sample through the shield (DWA is its own actor: `action` is unused)."""
        ctx = prepared.context
        if ctx is None:
            return STOP
        return self._step.certify(Twist(*map(float, ctx.dwa.best)), ctx)

    def step(self, now: float, odom: Odometry, world: WorldState | None) -> Twist:
        return self.decide(self.prepare(now, odom, world))

    def trace(self) -> DecisionTrace:
        return self._step.trace()

    @property
    def planning(self) -> PlanningStep:
        return self._step

    def summary(self) -> dict[str, Any]:
        return {**self._step.summary(), "stall_escapes": self._recovery.escapes}
