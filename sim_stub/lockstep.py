"""One seeded episode on simulated time, advanced control cycle by control cycle.

The evaluation (`safemove eval`) and the training environment (`train/env.py`) both drive the
runtime's pipeline code through this, so a policy is trained on what it is scored on: the Spark
base model (`SparkBaseSim`) moves the robot and streams real feedback frames, which go through
the real codec (`FrameParser`, `FeedbackConverter`) into the odometry EKF; the renderer's D435
frames go through the world model (`WorldModel`: perception → memory → tracker); the command
the caller decides goes through the limits stage and reaches the base as a wheel-speed frame, as
`SparkBaseLink` would send it. Events fall on a common clock: base ticks every 20 ms, depth
frames at `fps`, control cycles at `loop.control_hz`. No wall clock is read.
"""

from __future__ import annotations

import math

from drivers.depth_source import D435_848x480
from drivers.spark_feedback import FeedbackConverter
from drivers.spark_protocol import (
    BASE_TO_HOST,
    FrameParser,
    decode_feedback,
    twist_to_wheel_ticks,
    wheel_speed_frame,
)
from runtime.config import LoadedConfig
from runtime.limits import apply_limits
from runtime.odometry_ekf import OdometryEKF
from runtime.types import STOP, DepthFrame, Odometry, Twist
from runtime.world_model import WorldModel, WorldState
from sim_stub.base_sim import BasePhysics, SparkBaseSim
from sim_stub.depth_render import DepthRenderer
from sim_stub.scenario import load_scenario, with_crowd
from sim_stub.sim_server import BASE_LINK_HEIGHT_M, scene_from
from sim_stub.world import World, base_to_world, goal_in_odom

BASE_TICK_S = 0.02  # the Spark base's feedback period (50 Hz)


class LockstepEpisode:
    """World, base model, renderer and the runtime's world-model stages for one episode.

    Use: `cycle()` advances to the next control cycle and returns what the planner sees then
    (None once the world has judged the episode over); `command(target)` sends the cycle's
    decision. `path_length_m` is the true path so far."""

    def __init__(self, scenario: str, seed: int, loaded: LoadedConfig, fps: float, noise: bool,
                 crowd: str = "scenario") -> None:
        cfg, cal = loaded.config, loaded.calibration
        self.world = World(with_crowd(load_scenario(scenario), crowd), seed=seed,
                           limits=cfg.limits)
        w = self.world.robot
        self._start = (w.x, w.y, w.theta)
        self.goal_odom = goal_in_odom(self._start, self.world.goal)
        self._base = SparkBaseSim(BasePhysics(seed=seed), "stream", watchdog_s=0.0, t0=0.0)
        self._renderer = DepthRenderer(D435_848x480, cal.camera, base_z=BASE_LINK_HEIGHT_M,
                                       seed=seed)
        self._noise = noise
        self._parser = FrameParser(BASE_TO_HOST)
        self._converter = FeedbackConverter(cal.odometry, cfg.base)
        self._ekf = OdometryEKF(cal.odometry.axle_length_m, cfg.odometry)
        self._model = WorldModel(cfg, cal.camera)
        self._limits = cfg.limits
        self._odometry_cal = cal.odometry
        self._max_wheel_mm_s = round(cfg.base.max_wheel_speed_m_s * 1000)
        self._period = 1.0 / cfg.loop.control_hz
        self._frame_period = 1.0 / fps
        self.t = 0.0
        self._next_tick, self._next_cycle, self._next_frame = BASE_TICK_S, self._period, 0.0
        self.odom = Odometry()
        self._command = STOP
        self._increments: list = []
        self._frame: DepthFrame | None = None
        self._seen: DepthFrame | None = None
        self.state: WorldState | None = None
        self.frames = self.cycles = 0
        self.path_length_m = 0.0
        self.looking = True  # render depth frames (a finished job stands still: no need)

    @property
    def done(self) -> bool:
        return self.world.outcome.done

    def cycle(self) -> tuple[float, Odometry, WorldState | None] | None:
        """Advance to the next control cycle: (time, odometry, world state), or None when the
        world judged the episode over on the way."""
        while not self.done:
            t_next = min(self._next_tick, self._next_cycle, self._next_frame)
            if t_next > self.t:
                self._move(t_next - self.t)
                self.t = t_next
                if self.done:
                    return None
            if self.t >= self._next_tick - 1e-9:
                self._next_tick += BASE_TICK_S
                self._read_feedback()
            if self.t >= self._next_frame - 1e-9:
                self._next_frame += self._frame_period
                if self.looking:
                    self._render()
            if self.t >= self._next_cycle - 1e-9:
                self._next_cycle += self._period
                self.cycles += 1
                for inc in self._increments:
                    self.odom = self._ekf.step(inc)
                self._increments.clear()
                if self._frame is not None and self._frame is not self._seen:
                    self._seen = self._frame
                    self.state = self._model.update(self._frame, self.odom)
                return self.t, self.odom, self.state
        return None

    def command(self, target: Twist) -> Twist:
        """The cycle's decision through the limits stage to the base; returns what was sent."""
        if not target.is_finite():
            target = STOP
        self._command = apply_limits(target, self._command, self._period, self._limits)
        cal = self._odometry_cal
        left, right = twist_to_wheel_ticks(self._command.v, self._command.omega,
                                           cal.axle_length_m, cal.m_per_tick,
                                           self._max_wheel_mm_s)
        self._base.receive(wheel_speed_frame(left, right), self.t)
        return self._command

    def _move(self, dt: float) -> None:
        self._base.step(dt)
        truth = self._base.truth()
        x, y, theta = base_to_world(self._start, truth["x"], truth["y"], truth["theta"])
        r = self.world.robot
        self.path_length_m += math.hypot(x - r.x, y - r.y)
        self.world.follow_robot(dt, x, y, theta, truth["v"], truth["omega"])

    def _read_feedback(self) -> None:
        for f in self._parser.feed(self._base.feedback_frame()):
            inc = self._converter.convert(decode_feedback(f.payload), self.t)
            if inc is not None:
                self._increments.append(inc)

    def _render(self) -> None:
        snap = self.world.snapshot()
        depth = self._renderer.render(tuple(snap.robot_pose), scene_from(self.world, snap),
                                      noise=self._noise)
        self._frame = DepthFrame(depth, self.t, self.frames, self._renderer.intrinsics)
        self.frames += 1
