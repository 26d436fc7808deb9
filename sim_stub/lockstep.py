"""One seeded episode on simulated time, advanced control cycle by control cycle.

What stands in for the robot's devices, nothing more: the Spark base model (`SparkBaseSim`)
moves the robot and streams real feedback frames, which go through the real codec
(`FrameParser`, `FeedbackConverter`) into wheel increments; the renderer produces D435 frames,
only the pixels the world model reads (`perception.decimation` moves into the renderer, and the
pipeline runs with `config`, whose perception reads every pixel of them: the same rays);
the command a cycle of `Pipeline.step` passed reaches the base as a wheel-speed frame, as
`SparkBaseLink` would send it. The evaluation (`safemove eval`) and the training environment
(`sim_stub/train/env.py`) run the runtime's pipeline on what this delivers, so a policy is trained on
what it is scored on and what runs on the robot. Events fall on a common clock: base ticks every
20 ms, depth frames at `fps`, control cycles at `loop.control_hz`. The episode runs on that
clock only; `sim_s` adds up the wall time spent standing in for the world (render, crowd, base)
for the benchmarks, and changes nothing.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

from drivers.depth_source import D435_HFOV_DEG, D435_848x480, DepthIntrinsics
from drivers.spark.feedback import FeedbackConverter
from drivers.spark.protocol import (
    BASE_TO_HOST,
    FrameParser,
    decode_feedback,
    twist_to_wheel_ticks,
    wheel_speed_frame,
)
from runtime.config.settings import Calibration, Config
from runtime.perception.people_sighting import PeopleSighting
from runtime.pipeline import CycleInput
from runtime.types import DepthFrame, Twist, WheelIncrement
from sim_stub.base_sim import BasePhysics, SparkBaseSim
from sim_stub.depth_render import DepthRenderer
from sim_stub.scenario import load_scenario, with_crowd
from sim_stub.sim_server import BASE_LINK_HEIGHT_M, scene_from
from sim_stub.surround_people import surround_sighting
from sim_stub.world import World, base_to_world, goal_in_odom


def widened_d435(hfov_deg: float) -> DepthIntrinsics:
    """The D435's depth camera with a wider (or narrower) sensor: its pixels and vertical view
    kept (fx = fy, 480 rows), as many columns as the horizontal view needs. A what-if for a
    wider depth camera, or cameras side by side, at the D435's angular resolution (spreading
    848 columns over a wider view instead makes a bin a few pixels wide, and the few invalid
    pixels at an object's edge then blind whole bins)."""
    k = D435_848x480
    if hfov_deg == D435_HFOV_DEG:
        return k
    if not 0.0 < hfov_deg < 180.0:
        raise ValueError(f"a pinhole camera's horizontal view is in (0, 180) deg, got {hfov_deg}")
    half_width = round(k.fx * math.tan(math.radians(hfov_deg) / 2))
    return replace(k, width=2 * half_width, cx=float(half_width))


BASE_TICK_S = 0.02  # the Spark base's feedback period (50 Hz)


class LockstepEpisode:
    """World, base model and renderer for one episode.

    Use: build the `Pipeline` with `config` (not `cfg`: see the module docs); `cycle()`
    advances to the next control cycle and returns what arrived for it (None once the world
    has judged the episode over); `send(command)` sends the cycle's command. `path_length_m` is
    the true path so far."""

    def __init__(self, scenario: str, seed: int, cfg: Config, cal: Calibration, fps: float,
                 noise: bool, crowd: str = "scenario", hfov_deg: float = D435_HFOV_DEG,
                 surround_people: bool = False) -> None:
        self.world = World(with_crowd(load_scenario(scenario), crowd), seed=seed,
                           limits=cfg.limits)
        w = self.world.robot
        self._start = (w.x, w.y, w.theta)
        self.goal_odom = goal_in_odom(self._start, self.world.goal)
        self._base = SparkBaseSim(BasePhysics(seed=seed), "stream", watchdog_s=0.0, t0=0.0)
        self._renderer = DepthRenderer(widened_d435(hfov_deg), cal.camera,
                                       base_z=BASE_LINK_HEIGHT_M, seed=seed,
                                       decimation=cfg.perception.decimation)
        self.config = replace(cfg, perception=replace(cfg.perception, decimation=1))
        self._noise = noise
        self._parser = FrameParser(BASE_TO_HOST)
        self._converter = FeedbackConverter(cal.odometry, cfg.base)
        self._odometry_cal = cal.odometry
        self._max_wheel_mm_s = round(cfg.base.max_wheel_speed_m_s * 1000)
        self._period = 1.0 / cfg.loop.control_hz
        self._frame_period = 1.0 / fps
        self.t = 0.0
        self._next_tick, self._next_cycle, self._next_frame = BASE_TICK_S, self._period, 0.0
        self._increments: list[WheelIncrement] = []
        self._frames: list[DepthFrame] = []
        # with each depth frame, every person around as a sighting (sim_stub.surround_people)
        self._surround_range_m = cfg.perception.range_max_m if surround_people else None
        self._people: list[PeopleSighting] = []
        self._feedback_t: float | None = None
        self.frames = self.cycles = 0
        self.path_length_m = 0.0
        self.looking = True  # render depth frames (a finished job stands still: no need)
        self.sim_s = {"render": 0.0, "crowd": 0.0, "base": 0.0}  # wall seconds, cumulative

    @property
    def done(self) -> bool:
        return self.world.outcome.done

    def cycle(self) -> CycleInput | None:
        """Advance to the next control cycle: what arrived since the previous one, or None when
        the world judged the episode over on the way."""
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
                inp = CycleInput(self.t, tuple(self._increments), tuple(self._frames),
                                 self._feedback_t, tuple(self._people))
                self._increments.clear()
                self._frames.clear()
                self._people.clear()
                return inp
        return None

    def send(self, command: Twist) -> None:
        """The cycle's command (the pipeline's, limits applied) to the base as a wheel frame."""
        cal = self._odometry_cal
        left, right = twist_to_wheel_ticks(command.v, command.omega, cal.axle_length_m,
                                           cal.m_per_tick, self._max_wheel_mm_s)
        self._base.receive(wheel_speed_frame(left, right), self.t)

    def _move(self, dt: float) -> None:
        t0 = time.perf_counter()
        self._base.step(dt)
        truth = self._base.truth()
        x, y, theta = base_to_world(self._start, truth["x"], truth["y"], truth["theta"])
        r = self.world.robot
        self.path_length_m += math.hypot(x - r.x, y - r.y)
        t1 = time.perf_counter()
        self.world.follow_robot(dt, x, y, theta, truth["v"], truth["omega"])
        self.sim_s["base"] += t1 - t0
        self.sim_s["crowd"] += time.perf_counter() - t1

    def _read_feedback(self) -> None:
        t0 = time.perf_counter()
        for f in self._parser.feed(self._base.feedback_frame()):
            inc = self._converter.convert(decode_feedback(f.payload), self.t)
            if self._converter.usable:  # as SparkBaseLink dates its feedback
                self._feedback_t = self.t
            if inc is not None:
                self._increments.append(inc)
        self.sim_s["base"] += time.perf_counter() - t0

    def _render(self) -> None:
        t0 = time.perf_counter()
        snap = self.world.snapshot()
        depth = self._renderer.render(tuple(snap.robot_pose), scene_from(self.world, snap),
                                      noise=self._noise)
        self._frames.append(DepthFrame(depth, self.t, self.frames, self._renderer.intrinsics))
        if self._surround_range_m is not None:
            self._people.append(surround_sighting(snap, self._surround_range_m))
        self.frames += 1
        self.sim_s["render"] += time.perf_counter() - t0
