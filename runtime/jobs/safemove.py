"""The SafeMove planner mode (`safemove run --planner safemove`, with --model actor.onnx or a
shipped --variant).

Each RUNNING cycle: DWA and the track predictions as the DWA mode does them (PlanningStep),
the safe corridor along DWA's best path when the model's spec has a corridor block, the
observation by the model's own spec, one actor inference, the action mapped to a twist, and the
shield on that twist. When the robot has stood too long short of the goal, the stall recovery
(runtime.planning.stall_recovery) gives the observation an escape goal for a while, as it gives
DWA in the DWA mode: the policy drives to goals, so it steps away. With the way to the goal
clear, the policy froze, not the world: DWA's own command drives toward the goal for a while (a
takeover; only for the job's own policy: a training agent's actions are its own). Non-finite
odometry, observation or action makes the cycle a safe stop (brake at the limits'
deceleration), counted and logged with the reason: the actor never sees a non-finite
observation and its command never reaches the shield unless it is finite.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from runtime.config.settings import Config
from runtime.errors import ConfigError
from runtime.perception.world_model import WorldState
from runtime.planning.corridor import Corridor, CorridorConfig, safe_corridor
from runtime.planning.planning_step import PlanningContext, PlanningStep
from runtime.planning.stall_recovery import StallRecovery
from runtime.policy.actor import Policy
from runtime.policy.obs_spec import ObservationBuilder, ObsSpec
from runtime.policy.shipped import variant_of
from runtime.types import STOP, DecisionTrace, Odometry, Prepared, Twist

log = logging.getLogger("safemove.policy")


class SpecObserver:
    """A planning cycle's observation by a spec: the safe corridor along DWA's best path (only
    when the spec has a corridor block), then the spec's builder. The job and the recorded
    observations of `safemove export` both use it, so they see the same features."""

    def __init__(self, spec: ObsSpec) -> None:
        self.spec = spec
        cor = spec.block("corridor")
        self._corridor = (None if cor is None
                          else CorridorConfig(samples=cor.samples, max_width=cor.width_max_m))
        self._builder = ObservationBuilder(spec)
        self.last_corridor: Corridor | None = None

    def observe(self, ctx: PlanningContext, odom: Odometry, world: WorldState) -> np.ndarray:
        """The observation (the builder's vector, reused: copy it to keep it)."""
        corridor = None
        if self._corridor is not None:
            corridor = safe_corridor(ctx.dwa.best_path, world.points_base, ctx.track_pos[:, 1:],
                                     ctx.track_radii, self._corridor)
        self.last_corridor = corridor
        return self._builder.build(ctx.goal_base, odom.v, odom.omega, world, ctx.dwa, corridor)


class SafeMoveJob:
    """Drive to a goal in the odom frame with the TD3 actor, every command through the shield.
    Without a `policy` the action comes from outside each cycle (`decide(prepared, action)`:
    the training environment's agent)."""

    name = "safemove"

    def __init__(self, goal_odom: tuple[float, float], config: Config, policy: Policy | None,
                 clock: Callable[[], float] | None, spec: ObsSpec | None = None,
                 **goal: Any) -> None:
        """`goal`: PlanningStep's arrival_radius_m and speed_limit."""
        self._planning = PlanningStep(goal_odom, config, clock, "policy", **goal)
        self._recovery = StallRecovery(
            config.recovery, None if policy is None else config.robot.radius_m)
        self._policy = policy
        if spec is None:
            if policy is None:
                raise ValueError("SafeMoveJob needs a policy or a spec")
            spec = policy.spec
        self._spec = spec
        steps = max(1, round(config.dwa.horizon_s / config.dwa.dt))
        dwa_block = spec.block("dwa")
        if dwa_block is not None and dwa_block.path_points > steps:
            source = policy.path if policy is not None else "the actor"
            raise ConfigError(
                f"{source}: its spec '{spec.name}' takes {dwa_block.path_points} DWA path"
                f" points, but the DWA rolls out only {steps} steps (dwa.horizon_s / dwa.dt)")
        self._observer = SpecObserver(spec)
        self.nonfinite: Counter[str] = Counter()
        self._last_bad: str | None = None
        self._last_obs: np.ndarray | None = None  # copies, for the recorder's trace
        self._last_action: np.ndarray | None = None

    @property
    def finished(self) -> bool:
        return self._planning.finished

    @property
    def reached(self) -> bool:
        return self._planning.reached

    @property
    def shield_changed(self) -> bool:
        """The shield replaced the last decided command."""
        return self._planning.last_intervened

    def pause(self) -> None:
        """Nothing to pause: each cycle decides from the present."""

    def prepare(self, now: float, odom: Odometry, world: WorldState | None) -> Prepared:
        """DWA, the corridor and the observation; no context (hold still) when the goal is
        reached, there is no world yet, or odometry or the observation is not finite."""
        self._last_obs = self._last_action = None
        self._observer.last_corridor = None
        if not all(map(math.isfinite, (odom.x, odom.y, odom.theta, odom.v, odom.omega))):
            self._safe_stop("odometry", f"non-finite odometry {odom}")
            return Prepared()
        plan_goal = (None if world is None
                     else self._recovery.planning_goal(now, odom, world, self._planning.goal))
        ctx = self._planning.prepare(now, odom, world, plan_goal)
        if ctx is None or world is None:
            return Prepared()
        obs = self._observer.observe(ctx, odom, world)
        if not np.all(np.isfinite(obs)):
            names = self._spec.names()
            bad = [names[i] for i in np.flatnonzero(~np.isfinite(obs))[:3]]
            self._safe_stop("observation", f"non-finite features {', '.join(bad)}")
            return Prepared()
        return Prepared(ctx, obs)

    def decide(self, prepared: Prepared, action: np.ndarray | None = None) -> Twist:
        """The actor's action (this job's policy, or `action` from outside) mapped to a twist,
        through the shield; DWA's best sample instead during a stall recovery's takeover."""
        if prepared.context is None or prepared.observation is None:
            return STOP
        if self._recovery.dwa_drives:
            self._last_obs = prepared.observation.copy()
            return self._planning.certify(Twist(*map(float, prepared.context.dwa.best)),
                                          prepared.context)
        if action is None:
            if self._policy is None:
                raise ValueError("SafeMoveJob without a policy: decide() needs the action")
            action = self._policy.act(prepared.observation)
        self._last_obs = prepared.observation.copy()
        self._last_action = np.array(action, dtype=float)
        if not np.all(np.isfinite(action)):
            return self._safe_stop("action", f"non-finite action {np.asarray(action).tolist()}")
        self._last_bad = None
        return self._planning.certify(self._spec.action.to_twist(action), prepared.context)

    def step(self, now: float, odom: Odometry, world: WorldState | None) -> Twist:
        return self.decide(self.prepare(now, odom, world))

    @property
    def planning(self) -> PlanningStep:
        return self._planning

    def trace(self) -> DecisionTrace:
        return self._planning.trace(observation=self._last_obs, action=self._last_action,
                                    corridor=self._observer.last_corridor)

    def _safe_stop(self, kind: str, reason: str) -> Twist:
        """Brake this cycle; log the first cycle of a streak (the count has them all)."""
        self.nonfinite[kind] += 1
        if self._last_bad != kind:
            log.error("safe stop this cycle: %s", reason)
        self._last_bad = kind
        return STOP

    def summary(self) -> dict[str, Any]:
        policy = self._policy
        return {
            **self._planning.summary(),
            "stall_escapes": self._recovery.escapes,
            "dwa_takeovers": self._recovery.takeovers,
            "policy": None if policy is None else {
                "model": str(policy.path),
                "variant": variant_of(policy.path),
                "spec": self._spec.name,
                "features": self._spec.size,
                "threads": policy.threads,
                "provenance": policy.provenance,
                "training": policy.training,
                "evaluation": policy.evaluation,
            },
            "nonfinite_safe_stops": dict(self.nonfinite),
        }


def safemove_job(model: Path, goal_odom: tuple[float, float], config: Config,
                 clock: Callable[[], float] | None) -> SafeMoveJob:
    """The job for `safemove run --planner safemove`: the model (--model, or the shipped file
    the command line resolved) is loaded, validated and warmed up here, before the base is
    opened, so a bad model refuses to start (exit 2). `clock`: as for PlanningStep (None:
    budgets by count, for the lock-stepped evaluation)."""
    return SafeMoveJob(goal_odom, config, Policy(model, config.policy), clock)
