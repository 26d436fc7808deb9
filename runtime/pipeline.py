"""One control cycle, composed once: odometry → depth admission → world model (its tracks
replaced by a people sighting where one came) → health → the planner job → NaN guard → limits.

The live loop, the lock-stepped simulator, the training environment, the benchmarks and replay
all call `Pipeline.step` (or its two halves, `begin` and `finish`, where an outside agent makes
the decision between them), so what is trained, evaluated and run on the robot is the same
code. The pipeline reads no clock and touches no device: its inputs carry their times, and the
clock given to it only times the stages.

Health: the cycle HOLDS (the job is not asked; the target is a stop, which the limits stage
turns into braking at the guaranteed deceleration) while a cliff or bumper hazard is reported,
while base feedback or depth is older than its limit, or while the camera is blind. The live
loop turns a hold into its DEGRADED state; it ends by itself when the inputs are fresh again.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from runtime.config.settings import Calibration, Config
from runtime.odometry.ekf import OdometryEKF
from runtime.odometry.pose_history import PoseHistory
from runtime.perception.depth_guard import DepthGuard
from runtime.perception.depth_points import FloorVerdict
from runtime.perception.people_sighting import PeopleSighting, sighting_problem, sighting_tracks
from runtime.perception.world_model import WorldModel, WorldState
from runtime.safety.limits import apply_limits
from runtime.types import STOP, DepthFrame, Odometry, Prepared, Twist, WheelIncrement

PIPELINE_STAGES = ("odometry", "perception", "memory", "tracking", "job", "limits")


class Job(Protocol):
    """The planner a pipeline runs: prepares each cycle that does not hold, then decides."""

    name: str

    @property
    def finished(self) -> bool: ...

    def prepare(self, now: float, odom: Odometry, world: WorldState | None) -> Prepared: ...

    def decide(self, prepared: Prepared, action: np.ndarray | None = None) -> Twist:
        """The target twist; `action`: an outside actor's output in place of the job's own."""

    def pause(self) -> None:
        """The cycle started holding; time until it stops must not count as the job's time."""

    def summary(self) -> dict[str, Any]: ...


@dataclass(frozen=True)
class CycleInput:
    """What arrived since the previous cycle. `t`: the cycle's time (host monotonic seconds on
    the robot, simulated seconds in the simulator); `frames`: depth frames, oldest first;
    `feedback_t`: when the latest base feedback arrived (None: never); `people`: sightings of
    the people all around (runtime.perception.people_sighting), oldest first; none on the
    Spark today, ground truth in `safemove eval --surround-people`."""

    t: float
    increments: Sequence[WheelIncrement] = ()
    frames: Sequence[DepthFrame] = ()
    feedback_t: float | None = None
    people: Sequence[PeopleSighting] = ()


@dataclass(frozen=True)
class Sensed:
    """A cycle after sensing, before its decision (`Pipeline.begin`)."""

    t: float
    odom: Odometry
    world: WorldState | None
    hold: str | None  # why the robot holds this cycle (None: the job decides)
    prepared: Prepared | None  # the job's preparation (None while holding)
    stage_s: dict[str, float] = field(default_factory=dict)  # the stages that ran, seconds

    @property
    def observation(self) -> np.ndarray | None:
        return None if self.prepared is None else self.prepared.observation


@dataclass(frozen=True)
class CycleResult:
    """A finished cycle: the job's target (after the NaN guard) and the command the limits stage
    passed, which is what the base must be sent."""

    t: float
    odom: Odometry
    world: WorldState | None
    hold: str | None
    target: Twist
    command: Twist
    nonfinite: str | None  # the job's non-finite target, replaced by a stop
    stage_s: dict[str, float] = field(default_factory=dict)  # the stages that ran, seconds


class Pipeline:
    """The stages of one robot, with their state (EKF, pose history, world model, the last
    command), and the job that decides. `depth`: whether depth is an input (False: a base-only
    job, e.g. `safemove drive`, whose cycles never wait for a camera)."""

    def __init__(self, config: Config, calibration: Calibration, job: Job, *, depth: bool = True,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        self._cfg = config
        self.job = job
        self._depth = depth
        self._clock = clock
        self._period = 1.0 / config.loop.control_hz
        self.depth_guard = DepthGuard(config.depth.max_future_s)
        self.latest_depth: DepthFrame | None = None
        self._perceived: DepthFrame | None = None
        self.perceived_now: DepthFrame | None = None  # the frame the last cycle's world model read
        self._world_model = WorldModel(config, calibration.camera, clock)
        self._ekf = OdometryEKF(calibration.odometry.axle_length_m, config.odometry)
        self._poses = PoseHistory()
        self.odom = Odometry()
        self.world: WorldState | None = None
        self.command = STOP
        self._hazard: str | None = None
        self._holding = False
        self.people_dropped = 0  # unusable people sightings, the last one's reason below
        self.people_dropped_why: str | None = None

    def admit(self, frames: Sequence[DepthFrame], now: float) -> None:
        """Depth frames through the guard (malformed ones are dropped and counted); the newest
        admitted one is what the world model sees next."""
        for frame in frames:
            if self.depth_guard.admit(frame, now):
                self.latest_depth = frame

    def begin(self, inp: CycleInput) -> Sensed:
        """Odometry, depth and the world model, the health check, and the job's preparation."""
        clock, stage_s = self._clock, dict[str, float]()
        t0 = clock()
        stop_on_cliff = self._cfg.loop.stop_on_cliff
        for inc in inp.increments:
            self.odom = self._ekf.step(inc)
            self._poses.add(self.odom)
            self._hazard = inc.hazard if stop_on_cliff else None  # the latest frame decides
        stage_s["odometry"] = clock() - t0
        self.admit(inp.frames, inp.t)
        frame = self.latest_depth
        self.perceived_now = None
        if frame is not None and frame is not self._perceived:
            # the newest frame only (a planner wants the present, not a backlog), placed from
            # where the robot was at its stamp
            self._perceived = self.perceived_now = frame
            self.world = self._world_model.update(frame, self.odom,
                                                  self._poses.at(frame.t, self.odom))
            stage_s.update(self._world_model.stage_s)
        if inp.people:
            self._see_people(inp.people[-1])
        t1 = clock()
        hold = self._hold_reason(inp)
        if hold is not None and not self._holding:
            self.job.pause()
        self._holding = hold is not None
        prepared = None if hold is not None else self.job.prepare(inp.t, self.odom, self.world)
        stage_s["job"] = clock() - t1
        return Sensed(inp.t, self.odom, self.world, hold, prepared, stage_s)

    def finish(self, sensed: Sensed, action: np.ndarray | None = None) -> CycleResult:
        """The job's decision (from `action` when an outside actor gave one), the NaN guard and
        the limits stage."""
        clock = self._clock
        t0 = clock()
        target = STOP if sensed.prepared is None else self.job.decide(sensed.prepared, action)
        nonfinite = None
        if not target.is_finite():
            nonfinite = f"non-finite command {target!r} from {self.job.name}"
            target = STOP
        t1 = clock()
        self.command = apply_limits(target, self.command, self._period, self._cfg.limits)
        t2 = clock()
        stage_s = {**sensed.stage_s, "limits": t2 - t1}
        stage_s["job"] = stage_s.get("job", 0.0) + (t1 - t0)
        return CycleResult(sensed.t, sensed.odom, sensed.world, sensed.hold, target,
                           self.command, nonfinite, stage_s)

    def step(self, inp: CycleInput) -> CycleResult:
        """One cycle with the job's own decision."""
        return self.finish(self.begin(inp))

    def _see_people(self, sighting: PeopleSighting) -> None:
        """The newest sighting's people replace the world's tracks; an unusable one is dropped
        (counted, with its reason) and the camera's tracks stay."""
        problem = sighting_problem(sighting)
        if problem is not None or self.world is None:
            self.people_dropped += 1
            self.people_dropped_why = problem or "people sighting before any depth frame"
            return
        tracks = sighting_tracks(sighting, self._poses.at(sighting.t, self.odom), self.world.t,
                                 self._cfg.tracking.stationary_speed_m_s)
        self.world = replace(self.world, tracks=tracks)

    def check_floor(self) -> FloorVerdict | None:
        """The camera's floor check when one is due (the loop runs it in its slack), else None."""
        return self._world_model.check_floor()

    def _hold_reason(self, inp: CycleInput) -> str | None:
        if self._hazard is not None:
            return self._hazard
        cfg = self._cfg
        age = inp.t - inp.feedback_t if inp.feedback_t is not None else math.inf
        if age > cfg.loop.feedback_max_age_s:
            return f"base feedback stale ({age * 1000:.0f} ms old)"
        if not self._depth:
            return None
        last = self.latest_depth.t if self.latest_depth is not None else -math.inf
        if inp.t - last > cfg.depth.max_age_s:
            return f"depth stale ({(inp.t - last) * 1000:.0f} ms old)"
        seen = self.world.valid_fraction if self.world is not None else 1.0
        if seen < cfg.depth.min_valid_fraction:
            return (f"depth blind ({100 * seen:.1f} % of pixels valid, fewer than"
                    f" {100 * cfg.depth.min_valid_fraction:g} %)")
        return None
