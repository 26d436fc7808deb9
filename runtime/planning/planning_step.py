"""What every goal-driven planner job does around its own decision, in one place.

Each RUNNING cycle, before the decision (`PlanningStep.prepare`): the goal check (reached →
stop, finished once still), the goal and the tracks' constant-velocity predictions into
base_link, and DWA within its deadline (its candidates are what the shield substitutes). After
the decision (`PlanningStep.certify`): the shield certifies the command or puts a certified DWA
candidate (or a brake) in its place, and every intervention is counted by kind and logged with
its reason. The DWA job's decision is DWA's best sample; the SafeMove job's is the actor's.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from runtime.budget import ReplayedBudget, TimeBudget
from runtime.geometry import into_frame
from runtime.perception.tracking import Track
from runtime.perception.world_model import WorldState
from runtime.planning.dwa import DWAConfig, DWAResult, plan
from runtime.safety.certificate import ShieldConfig, ShieldWorld
from runtime.safety.limits import LimitsConfig
from runtime.safety.shield import ShieldDecision, shield
from runtime.types import STILL_M_S, DecisionTrace, Odometry, Twist

log = logging.getLogger("safemove.planner")

# The paper's success radius is 0.2 m of the TRUE position; the job knows only odometry, so it
# drives on to 0.15 m: stopping at 0.2 m of odometry left the robot 0.201 m from the goal in a
# simulated episode (1 mm of odometry error) and the episode timed out beside its goal.
ARRIVAL_RADIUS_M = 0.15


def predict_tracks_base(
    tracks: list[Track], pose: tuple[float, float, float], elapsed: float, dt: float, steps: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Confirmed tracks at times elapsed + k·dt (k = 0..steps) in base_link, constant velocity:
    positions (T, steps+1, 2), position σ growing with the velocity covariance (T, steps+1),
    radii (T,). `elapsed`: seconds from the tracks' frame to now."""
    confirmed = [t for t in tracks if t.confirmed]
    n = len(confirmed)
    tau = elapsed + dt * np.arange(steps + 1)
    if n == 0:
        return np.zeros((0, steps + 1, 2)), np.zeros((0, steps + 1)), np.zeros(0)
    p = np.array([t.position for t in confirmed])
    v = np.array([t.velocity for t in confirmed])
    cov = np.array([t.covariance for t in confirmed])
    odom = p[:, None, :] + v[:, None, :] * tau[None, :, None]
    x, y, th = pose
    base = np.stack(into_frame(odom[..., 0] - x, odom[..., 1] - y, th), axis=-1)
    pos_var = np.maximum(cov[:, 0, 0], cov[:, 1, 1])
    # a track the stationarity test holds still is predicted still: its velocity variance
    # (large while the track is young) must not grow it into a wall across the room
    moving = np.array([not t.stationary for t in confirmed])
    vel_var = np.maximum(cov[:, 2, 2], cov[:, 3, 3]) * moving
    std = np.sqrt(pos_var[:, None] + vel_var[:, None] * tau[None, :] ** 2)
    return base, std, np.array([t.radius for t in confirmed])


@dataclass(frozen=True)
class PlanningContext:
    """One cycle's world as the decision and the shield see it, all in base_link now."""

    goal_base: np.ndarray  # (2,)
    state: Twist  # odometry's (v, ω): what the base is executing
    dwa: DWAResult
    track_pos: np.ndarray  # (T, steps+1, 2) at k·dwa.dt from now
    track_std: np.ndarray  # (T, steps+1)
    track_radii: np.ndarray  # (T,)
    shield_world: ShieldWorld


class PlanningSections(Protocol):
    """The config sections a planning step reads (runtime.config.settings.Config has them)."""

    @property
    def dwa(self) -> DWAConfig: ...

    @property
    def shield(self) -> ShieldConfig: ...

    @property
    def limits(self) -> LimitsConfig: ...


class PlanningStep:
    """Goal check, DWA and the shield for a job driving to a goal in the odom frame."""

    def __init__(self, goal_odom: tuple[float, float], config: PlanningSections,
                 clock: Callable[[], float] | None, decision: str, *,
                 arrival_radius_m: float = ARRIVAL_RADIUS_M,
                 speed_limit: float | None = None) -> None:
        """`clock` times the DWA and shield budgets (time.monotonic on the robot); None runs
        both to their count limits (refinement rounds, candidates): deterministic, as the
        lock-stepped evaluation wants. `speed_limit` (m/s): a goal's own cap below
        limits.v_max (the control socket's max_speed)."""
        self.goal = np.asarray(goal_odom, dtype=float)
        self.arrival_radius_m = arrival_radius_m
        self._cfg = config
        self._clock = clock
        self._decision = decision  # who proposes the command, for the log ("DWA", "policy")
        # the shield never certifies reversing into space the camera cannot see (unless told
        # to trust obstacle memory there): candidates it would refuse are not worth planning
        lim = config.limits
        v_max = lim.v_max if speed_limit is None else min(lim.v_max, speed_limit)
        self._v_cap = v_max if v_max < lim.v_max else None
        self._plan_limits = replace(lim, v_max=v_max, v_min=(
            lim.v_min if config.shield.reverse_into_unseen else max(lim.v_min, 0.0)))
        self.finished = False
        self.reached = False
        self.cycles = 0
        self.inadmissible = 0
        self.interventions: Counter[str] = Counter()
        self._last_kind = "passed"
        self.last_intervened = False
        self.last_context: PlanningContext | None = None  # this cycle's (for the recorder)
        self.last_decision: ShieldDecision | None = None
        self.budgets: dict[str, TimeBudget] = {}  # this cycle's, by stage
        # a replay sets each cycle's recorded (allowed, cut) per stage before the cycle
        self.replayed_budgets: dict[str, tuple[int, bool]] | None = None

    def prepare(self, now: float, odom: Odometry, world: WorldState | None,
                plan_goal: np.ndarray | None = None) -> PlanningContext | None:
        """The cycle's context, or None when the job must stop (goal reached, no world yet).
        `plan_goal` (odom): where DWA heads instead of the goal (a stall recovery's escape);
        reaching is always judged on the goal."""
        self.cycles += 1
        self.last_context = self.last_decision = None
        self.budgets = {}
        here = np.array((odom.x, odom.y))
        if float(np.hypot(*(self.goal - here))) <= self.arrival_radius_m:
            self.reached = True
            if abs(odom.v) < STILL_M_S:
                self.finished = True
            return None
        if world is None:
            return None
        to_goal = (self.goal if plan_goal is None else plan_goal) - here
        goal_base = np.array(into_frame(float(to_goal[0]), float(to_goal[1]), odom.theta))
        dwa = self._cfg.dwa
        steps = max(1, round(dwa.horizon_s / dwa.dt))
        pos, std, radii = predict_tracks_base(world.tracks, (odom.x, odom.y, odom.theta),
                                              max(0.0, now - world.t), dwa.dt, steps)
        result = plan(dwa, self._plan_limits, odom.v, odom.omega, goal_base, world.points_base,
                      pos[:, 1:], radii[:, None] + np.minimum(dwa.track_k_sigma * std[:, 1:],
                                                              dwa.track_inflation_cap_m),
                      budget=self._budget("dwa", dwa.budget_s))
        if not result.admissible_best:
            self.inadmissible += 1
        sw = ShieldWorld(points=world.points_base, track_positions=pos, track_std=std,
                         track_radii=radii, track_dt=dwa.dt, bin_angles=world.bin_angles,
                         unknown=world.unknown, scan=world.scan, blind_range=world.blind_range,
                         track_ids=tuple(t.id for t in world.tracks if t.confirmed),
                         points_age=max(0.0, now - world.t))
        self.last_context = PlanningContext(goal_base, Twist(odom.v, odom.omega), result, pos, std,
                                            radii, sw)
        return self.last_context

    def certify(self, command: Twist, ctx: PlanningContext) -> Twist:
        """The shield's decision on `command` (first slowed to the goal's speed cap along the
        same arc); interventions counted and logged."""
        if self._v_cap is not None and command.v > self._v_cap:
            command = Twist(self._v_cap, command.omega * self._v_cap / command.v)
        ok = ctx.dwa.admissible
        decision = shield(command, ctx.state, ctx.dwa.samples[ok], ctx.dwa.total[ok],
                          ctx.shield_world, self._cfg.limits, self._cfg.shield,
                          budget=self._budget("shield", self._cfg.shield.candidate_budget_s))
        self.last_decision = decision
        self.last_intervened = decision.intervened
        if decision.intervened:
            self.interventions[decision.kind] += 1
            if decision.kind != self._last_kind:  # the count is in the loop's statistics line
                log.info("shield %s the %s command: %s", decision.kind, self._decision,
                         decision.reason)
        self._last_kind = decision.kind
        return decision.command

    def trace(self, **decision: Any) -> DecisionTrace:
        """The last cycle's context and shield decision, with the job's own `decision` parts."""
        return DecisionTrace(context=self.last_context, shield=self.last_decision,
                             goal_odom=(float(self.goal[0]), float(self.goal[1])),
                             budgets={k: (b.allowed, b.cut) for k, b in self.budgets.items()},
                             **decision)

    def _budget(self, stage: str, budget_s: float) -> TimeBudget:
        """This cycle's budget of `stage` (dwa, shield): on the clock, or the next one a replay
        recorded; kept in `budgets` for the recorder."""
        if self.replayed_budgets is not None:
            # a stage the recording did not run this cycle: the replay has diverged already
            allowed, cut = self.replayed_budgets.pop(stage, (0, False))
            budget: TimeBudget = ReplayedBudget(allowed, cut)
        else:
            deadline = math.inf if self._clock is None else self._clock() + budget_s
            budget = TimeBudget(deadline, self._clock)
        self.budgets[stage] = budget
        return budget

    def summary(self) -> dict[str, Any]:
        return {
            "goal_odom": self.goal.tolist(),
            "reached": self.reached,
            "cycles": self.cycles,
            "dwa_inadmissible": self.inadmissible,
            "shield_interventions": dict(self.interventions),
        }
