"""The DWA planner mode (`safemove run --planner dwa`): the paper's DWA baseline, through the shield.

Each RUNNING cycle: the goal and the tracks' constant-velocity predictions go into base_link,
DWA picks the best admissible (v, ω) within its deadline, and the shield certifies it or puts
a certified DWA candidate (or a brake) in its place. Every intervention is counted by reason.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np

from runtime.config import Config
from runtime.dwa import plan
from runtime.loop import WorldState
from runtime.shield import ShieldWorld, shield
from runtime.tracking import Track
from runtime.types import STOP, Odometry, Twist

log = logging.getLogger("safemove.dwa")

GOAL_TOLERANCE_M = 0.2  # the paper's success radius
STILL_V = 0.01
K_SIGMA = 2.0


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
    c, s = math.cos(th), math.sin(th)
    dx, dy = odom[..., 0] - x, odom[..., 1] - y
    base = np.stack([c * dx + s * dy, -s * dx + c * dy], axis=-1)
    pos_var = np.maximum(cov[:, 0, 0], cov[:, 1, 1])
    vel_var = np.maximum(cov[:, 2, 2], cov[:, 3, 3])
    std = np.sqrt(pos_var[:, None] + vel_var[:, None] * tau[None, :] ** 2)
    return base, std, np.array([t.radius for t in confirmed])


class DWAJob:
    """Drive to a goal in the odom frame with DWA, every command through the shield."""

    name = "dwa"

    def __init__(self, goal_odom: tuple[float, float], config: Config,
                 clock: Callable[[], float]) -> None:
        self._goal = np.asarray(goal_odom, dtype=float)
        self._cfg = config
        self._clock = clock
        self._finished = False
        self.reached = False
        self.interventions: Counter[str] = Counter()
        self.cycles = 0
        self.inadmissible = 0

    @property
    def finished(self) -> bool:
        return self._finished

    def pause(self) -> None:
        """Nothing to pause: each cycle plans from the present."""

    def step(self, now: float, odom: Odometry, world: WorldState | None) -> Twist:
        self.cycles += 1
        pose = (odom.x, odom.y, odom.theta)
        to_goal = self._goal - np.array(pose[:2])
        if float(np.hypot(*to_goal)) <= GOAL_TOLERANCE_M:
            self.reached = True
            if abs(odom.v) < STILL_V:
                self._finished = True
            return STOP
        if world is None:
            return STOP
        c, s = math.cos(odom.theta), math.sin(odom.theta)
        goal_base = np.array([c * to_goal[0] + s * to_goal[1], -s * to_goal[0] + c * to_goal[1]])
        dwa = self._cfg.dwa
        steps = max(1, round(dwa.horizon_s / dwa.dt))
        pos, std, radii = predict_tracks_base(world.tracks, pose, max(0.0, now - world.t),
                                              dwa.dt, steps)
        result = plan(dwa, self._cfg.limits, odom.v, odom.omega, goal_base, world.points_base,
                      pos[:, 1:], radii[:, None] + K_SIGMA * std[:, 1:],
                      deadline=self._clock() + dwa.budget_s, now=self._clock)
        if not result.admissible_best:
            self.inadmissible += 1
        state = Twist(odom.v, odom.omega)
        ok = result.admissible
        decision = shield(
            Twist(*map(float, result.best)), state, result.samples[ok], result.total[ok],
            ShieldWorld(points=world.points_base, track_positions=pos, track_std=std,
                        track_radii=radii, track_dt=dwa.dt, bin_angles=world.bin_angles,
                        unknown=world.unknown, scan=world.scan),
            self._cfg.limits, self._cfg.shield,
            deadline=self._clock() + self._cfg.shield.candidate_budget_s, now=self._clock,
        )
        if decision.intervened:
            kind = "replaced" if (decision.reason or "").startswith("replaced") else "braked"
            self.interventions[kind] += 1
            log.info("shield %s the DWA command: %s", kind, decision.reason)
        return decision.command

    def summary(self) -> dict[str, Any]:
        return {
            "goal_odom": self._goal.tolist(),
            "reached": self.reached,
            "cycles": self.cycles,
            "dwa_inadmissible": self.inadmissible,
            "shield_interventions": dict(self.interventions),
        }
