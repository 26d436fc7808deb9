"""The service's job: goals and missions from the control socket, driven by the configured planner.

idle (holding) → navigating ⇄ paused → reached | cancelled | preempted | failed → idle.
A goal is a mission of one waypoint. Each waypoint gets its own planner job (DWA or the TD3
actor, both through the shield) with its tolerance and speed cap; reaching it means being
within the tolerance and standing still, as for a one-shot `--goal`. A waypoint fails when its
time runs out (timeout), when the robot has not come 0.1 m closer for a while (blocked), or
when the loop has held (DEGRADED) too long: the robot then stays stopped instead of driving
off by itself minutes later. A looping mission whose whole lap was reached without driving a
cycle (every waypoint within the tolerance of the one before it) fails instead of lapping once
a cycle. Every end is an event; every command gets a reply.

Everything here runs on the control loop's thread, in the slack after a cycle's command
(`handle`, `held`) or inside `Pipeline.step` (`prepare`, `decide`): no locks.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from runtime.control.config import ControlConfig
from runtime.control.protocol import Request, Waypoint, reply
from runtime.geometry import from_frame
from runtime.perception.world_model import WorldState
from runtime.planning.planning_step import PlanningStep
from runtime.types import STOP, DecisionTrace, Odometry, Prepared, Twist

log = logging.getLogger("safemove.mission")

PROGRESS_M = 0.1  # coming this much closer to the waypoint counts as progress


@dataclass(frozen=True)
class Target:
    """A waypoint in odom with its tolerance and speed cap, resolved at acceptance."""

    x: float
    y: float
    tolerance: float
    max_speed: float | None


class PlannerJob(Protocol):
    """A goal-driven planner job (DWAJob, SafeMoveJob): runtime.pipeline.Job, and whether the
    shield changed its last command."""

    @property
    def finished(self) -> bool: ...

    def prepare(self, now: float, odom: Odometry, world: WorldState | None) -> Prepared: ...

    def decide(self, prepared: Prepared, action: np.ndarray | None = None) -> Twist: ...

    def pause(self) -> None: ...

    @property
    def shield_changed(self) -> bool:
        """The shield replaced the last decided command."""

    def summary(self) -> dict[str, Any]:
        """Its report; 'shield_interventions': counts by kind."""

    def trace(self) -> DecisionTrace:
        """Its last cycle's decision, for the recorder."""

    @property
    def planning(self) -> PlanningStep:
        """Its goal check, DWA and shield (a replay sets their budgets)."""


# (goal in odom, arrival radius, speed cap) → the planner job for one waypoint
PlannerFactory = Callable[[tuple[float, float], float, "float | None"], PlannerJob]


class MissionJob:
    """Goals and missions for the configured planner; see the module docstring."""

    name = "mission"
    finished = False  # the service's job never ends by itself

    def __init__(self, config: ControlConfig, planner: str, make_planner: PlannerFactory,
                 emit: Callable[[dict[str, Any]], None], model: str | None = None) -> None:
        """`emit(event)`: hands an event to the control server (non-blocking); `model`: the
        actor file of the safemove planner (for the report and a replay)."""
        self._cfg = config
        self.planner = planner
        self.model = model
        self._make = make_planner
        self._emit = emit
        self.state = "idle"
        self.goal_id: int | None = None
        self._next_id = 1
        self._targets: tuple[Target, ...] = ()
        self._loop = False
        self._timeout_s = config.waypoint_timeout_s
        self._index = 0
        self._lap_drove = False  # a cycle of this lap (of a looping mission) was driven
        self._job: PlannerJob | None = None
        self._active_s = 0.0  # navigating time on this waypoint (paused time excluded)
        self._last_t: float | None = None
        self._best = math.inf
        self._progress_s = 0.0  # navigating time since the last progress
        self._held_since: float | None = None
        self.distance: float | None = None
        self.last_outcome: dict[str, Any] | None = None
        self.counts = {"reached": 0, "cancelled": 0, "preempted": 0, "failed": 0}
        self.interventions = 0  # cycles whose command the shield changed
        self._shield_kinds: Counter[str] = Counter()  # by kind, of the planners done with

    # --- commands (from the control socket, applied between cycles) ---------------------------

    def handle(self, request: Request, now: float, odom: Odometry) -> dict[str, Any]:
        """Apply one validated request; the reply to send back."""
        rid = request.id
        if request.type in ("goal", "mission"):
            return self._start(request, now, odom)
        if request.type == "cancel":
            if self.state == "idle":
                return reply(rid, cancelled=None, state=self.state)
            gid = self.goal_id
            self._end("cancelled", "cancelled by request", odom)
            return reply(rid, cancelled=gid, state=self.state)
        if request.type == "pause":
            if self.state != "navigating":
                return reply(rid, False, f"nothing to pause: {self.state}")
            self.state = "paused"
            self._event("paused", odom)
            return reply(rid, goal_id=self.goal_id, state=self.state)
        if request.type == "resume":
            if self.state != "paused":
                return reply(rid, False, f"nothing to resume: {self.state}")
            self.state = "navigating"
            self._last_t = None
            self._event("resumed", odom)
            return reply(rid, goal_id=self.goal_id, state=self.state)
        return reply(rid, False, f"'{request.type}' is not a command of the control cycle")

    def _start(self, request: Request, now: float, odom: Odometry) -> dict[str, Any]:
        cfg = self._cfg
        if not all(map(math.isfinite, (odom.x, odom.y, odom.theta))):
            return reply(request.id, False, "the robot's pose is not known (non-finite odometry)")
        targets = tuple(self._resolve(w, request.frame, odom) for w in request.waypoints)
        for i, t in enumerate(targets):
            far = math.hypot(t.x - odom.x, t.y - odom.y)
            if far > cfg.max_goal_distance_m:
                which = "the goal" if request.type == "goal" else f"waypoint {i + 1}"
                return reply(request.id, False, f"{which} is {far:.1f} m from the robot, farther"
                             f" than control.max_goal_distance_m = {cfg.max_goal_distance_m:g} m")
        if self.state != "idle":
            self._end("preempted", f"pre-empted by goal {self._next_id}", odom)
        self.goal_id = self._next_id
        self._next_id += 1
        self._targets = targets
        self._loop = request.loop
        self._timeout_s = request.timeout_s or cfg.waypoint_timeout_s
        self.state = "navigating"
        self._begin_waypoint(0)
        log.info("goal %d: %s of %d waypoint(s) in odom, first (%.2f, %.2f)%s, planner %s",
                 self.goal_id, request.type, len(targets), targets[0].x, targets[0].y,
                 ", looping" if self._loop else "", self.planner)
        return reply(request.id, goal_id=self.goal_id, state=self.state,
                     waypoints=[{"x": t.x, "y": t.y} for t in targets])

    def _resolve(self, w: Waypoint, frame: str, odom: Odometry) -> Target:
        x, y = w.x, w.y
        if frame == "relative":  # base_link at acceptance: x forward, y left
            x, y = from_frame(odom.x, odom.y, odom.theta, w.x, w.y)
        return Target(x, y, w.tolerance or self._cfg.goal_tolerance_m, w.max_speed)

    def _begin_waypoint(self, index: int) -> None:
        t = self._targets[index]
        self._index = index
        if index == 0:
            self._lap_drove = False
        self._drop_planner()
        self._job = self._make((t.x, t.y), t.tolerance, t.max_speed)
        self._active_s = self._progress_s = 0.0
        self._last_t = None
        self._best = math.inf
        self._held_since = None

    # --- the cycle -------------------------------------------------------------------------

    def prepare(self, now: float, odom: Odometry, world: WorldState | None) -> Prepared:
        self._held_since = None
        job = self._job
        if self.state != "navigating" or job is None:
            self._last_t = None
            return Prepared(STOP)
        if self._last_t is not None:
            dt = max(0.0, now - self._last_t)
            self._active_s += dt
            self._progress_s += dt
        self._last_t = now
        t = self._targets[self._index]
        self.distance = math.hypot(t.x - odom.x, t.y - odom.y)
        if self.distance < self._best - PROGRESS_M or not math.isfinite(self._best):
            self._best, self._progress_s = self.distance, 0.0
        inner = job.prepare(now, odom, world)
        if job.finished:
            self._arrived(odom)
            return Prepared(STOP)
        if self._active_s > self._timeout_s:
            self._end("failed", f"timeout: waypoint {self._index + 1} not reached in"
                      f" {self._timeout_s:g} s ({self.distance:.2f} m to go)", odom)
            return Prepared(STOP)
        if self._progress_s > self._cfg.blocked_timeout_s:
            self._end("failed", f"blocked: no progress toward waypoint {self._index + 1} for"
                      f" {self._cfg.blocked_timeout_s:g} s ({self.distance:.2f} m to go)", odom)
            return Prepared(STOP)
        self._lap_drove = True
        return Prepared((job, inner))

    def decide(self, prepared: Prepared, action: np.ndarray | None = None) -> Twist:
        if not isinstance(prepared.context, tuple):
            return STOP
        job, inner = prepared.context
        command = job.decide(inner, action)
        self.interventions += job.shield_changed
        return command

    def pause(self) -> None:
        """The loop started holding: the time until it stops holding is not navigating time."""
        self._last_t = None
        if self._job is not None:
            self._job.pause()

    def held(self, now: float, reason: str, odom: Odometry) -> None:
        """A cycle the loop held (DEGRADED): a goal fails after degraded_timeout_s of them."""
        if self.state != "navigating":
            return
        if self._held_since is None:
            self._held_since = now
        elif now - self._held_since > self._cfg.degraded_timeout_s:
            self._end("failed", f"degraded too long: held {now - self._held_since:.1f} s"
                      f" ({reason})", odom)

    def shutdown(self, reason: str, odom: Odometry) -> None:
        """The service is stopping: an active goal fails with `reason`."""
        if self.state != "idle":
            self._end("failed", f"service stopping: {reason}", odom)

    # --- ends and events ---------------------------------------------------------------------

    def _arrived(self, odom: Odometry) -> None:
        self._event("arrived", odom, waypoint=self._index + 1, waypoints=len(self._targets))
        nxt = self._index + 1
        if nxt < len(self._targets):
            self._begin_waypoint(nxt)
        elif self._loop and not self._lap_drove:
            # every waypoint was reached where the robot stood (each within the tolerance of
            # the one before it): the laps would repeat without moving, an event every cycle
            self._end("failed", f"looping mission: all {len(self._targets)} waypoint(s) reached"
                      " without moving (each is within the tolerance of the one before it)", odom)
        elif self._loop:
            self._begin_waypoint(0)
        else:
            self._end("reached", f"all {len(self._targets)} waypoint(s) reached", odom)

    def _end(self, outcome: str, reason: str, odom: Odometry) -> None:
        self.counts[outcome] += 1
        level = logging.WARNING if outcome == "failed" else logging.INFO
        log.log(level, "goal %s %s: %s", self.goal_id, outcome, reason)
        self._event("finished", odom, outcome=outcome, reason=reason,
                    waypoint=self._index + 1, waypoints=len(self._targets))
        self.last_outcome = {"goal_id": self.goal_id, "outcome": outcome, "reason": reason}
        self.state = "idle"
        self._drop_planner()
        self._targets = ()
        self.distance = None

    def _event(self, name: str, odom: Odometry, **fields: Any) -> None:
        self._emit({"v": 1, "type": "event", "event": name, "goal_id": self.goal_id,
                    "pose": {"x": odom.x, "y": odom.y, "theta": odom.theta}, **fields})

    # --- reports ----------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """The mission part of a status message."""
        t = self._targets[self._index] if self._targets else None
        return {
            "state": self.state,
            "planner": self.planner,
            "goal_id": self.goal_id if self.state != "idle" else None,
            "goal": None if t is None else {"x": t.x, "y": t.y, "tolerance": t.tolerance,
                                            "max_speed": t.max_speed},
            "distance_m": self.distance,
            "waypoint": None if t is None else self._index + 1,
            "waypoints": len(self._targets),
            "loop": self._loop,
            "waypoint_elapsed_s": round(self._active_s, 2) if t is not None else None,
            "last_outcome": self.last_outcome,
        }

    def _drop_planner(self) -> None:
        """Done with the current waypoint's planner: keep its shield interventions."""
        if self._job is not None:
            self._shield_kinds.update(self._job.summary().get("shield_interventions", {}))
        self._job = None

    @property
    def planning(self) -> PlanningStep | None:
        """The current waypoint's planning step (None while idle)."""
        return None if self._job is None else self._job.planning

    def trace(self) -> DecisionTrace | None:
        """The current waypoint's planner's last decision (None while idle)."""
        job = self._job
        return None if job is None else job.trace()

    def summary(self) -> dict[str, Any]:
        """The run's report. 'shield_interventions': by kind, as every planner job reports
        them (the loop's statistics line and the tools read a dict)."""
        kinds = Counter(self._shield_kinds)
        if self._job is not None:
            kinds.update(self._job.summary().get("shield_interventions", {}))
        return {"planner": self.planner, "model": self.model, "goals": self._next_id - 1,
                "outcomes": self.counts,
                "shield_interventions": dict(kinds), "shield_changed_cycles": self.interventions,
                "last_outcome": self.last_outcome}

