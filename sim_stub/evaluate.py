"""`safemove eval`: seeded episodes per scenario, lock-stepped in one process, scored as in the
paper's table.

Each episode runs the runtime's own pipeline code on simulated time: the Spark base model
(`SparkBaseSim`) moves the robot and streams real feedback frames, which go through the real
codec (`FrameParser`, `FeedbackConverter`) into the odometry EKF; the renderer's D435 frames go
through the world model (`WorldModel`: perception → memory → tracker); the planner job (the DWA
baseline or the SafeMove policy, each through the shield) picks the command; the limits stage
rate-limits it; and it reaches the base as a wheel-speed frame, as `SparkBaseLink` would send it.
Only the serial and socket I/O and the wall clock are left out: the planner budgets (DWA
refinement, shield candidate search) are their count limits, so an episode is deterministic from
its seed and does not depend on the machine's load.

The world judges each episode from ground truth: success (within the scenario's goal tolerance),
collision, or timeout. A collision is at fault when the robot drove into the other body or the
body was not coming at it; `moving` counts every collision where the robot was moving at all
(sim_stub/world.py has the rule and why). Path length and speed come from the
true trajectory.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.depth_source import D435_848x480
from drivers.spark_feedback import FeedbackConverter
from drivers.spark_protocol import (
    BASE_TO_HOST,
    FrameParser,
    decode_feedback,
    twist_to_wheel_ticks,
    wheel_speed_frame,
)
from runtime.config import LoadedConfig, load_config
from runtime.limits import apply_limits
from runtime.odometry_ekf import OdometryEKF
from runtime.types import STOP, DepthFrame, Odometry
from runtime.world_model import WorldModel, WorldState
from sim_stub.base_sim import BasePhysics, SparkBaseSim
from sim_stub.depth_render import DepthRenderer
from sim_stub.scenario import load_scenario, with_crowd
from sim_stub.sim_server import BASE_LINK_HEIGHT_M, scene_from
from sim_stub.world import World, base_to_world, goal_in_odom

BASE_TICK_S = 0.02  # the Spark base's feedback period (50 Hz)
PLANNERS = ("dwa", "safemove")


@dataclass(frozen=True)
class EvalSettings:
    """What every episode shares (picklable: episodes may run in worker processes)."""

    planner: str
    config_path: Path | None
    overrides: tuple[str, ...]
    model: Path | None
    fps: float
    noise: bool
    crowd: str = "scenario"  # scenario | reactive | oblivious: whether agents see the robot


@dataclass(frozen=True)
class EpisodeResult:
    scenario: str
    seed: int
    status: str  # success | collision | timeout
    time_s: float
    path_length_m: float
    at_fault: bool
    moving_at_contact: bool  # strict passive safety: the robot moved at the collision
    collided_with: str | None
    contact_bearing_deg: float | None  # where the other body was: 0 ahead, + left
    min_separation_m: float
    shield_interventions: int
    cycles: int
    job_p99_ms: float


def make_job(settings: EvalSettings, goal_odom: tuple[float, float], loaded: LoadedConfig
             ) -> Any:
    """The planner job `safemove run --planner …` would run, with its budgets counted in
    refinement rounds and shield candidates instead of wall time (no clock): an episode's
    result does not depend on how busy the machine is."""
    if settings.planner == "dwa":
        from runtime.dwa_job import DWAJob

        return DWAJob(goal_odom, loaded.config, None)
    from runtime.safemove_job import safemove_job

    return safemove_job(settings.model, goal_odom, loaded.config, None)


def run_episode(scenario_name: str, seed: int, settings: EvalSettings) -> EpisodeResult:
    """One seeded episode to its judged end (see the module docs)."""
    loaded = load_config(settings.config_path, list(settings.overrides))
    cfg, cal = loaded.config, loaded.calibration
    world = World(with_crowd(load_scenario(scenario_name), settings.crowd), seed=seed,
                  limits=cfg.limits)
    start = (world.robot.x, world.robot.y, world.robot.theta)
    base = SparkBaseSim(BasePhysics(seed=seed), "stream", watchdog_s=0.0, t0=0.0)
    renderer = DepthRenderer(D435_848x480, cal.camera, base_z=BASE_LINK_HEIGHT_M, seed=seed)
    parser = FrameParser(BASE_TO_HOST)
    converter = FeedbackConverter(cal.odometry, cfg.base.glitch_ticks)
    ekf = OdometryEKF(cal.odometry.axle_length_m, cfg.odometry)
    model = WorldModel(cfg, cal.camera)
    job = make_job(settings, goal_in_odom(start, world.goal), loaded)
    max_wheel_mm_s = round(cfg.base.max_wheel_speed_m_s * 1000)

    period = 1.0 / cfg.loop.control_hz
    frame_period = 1.0 / settings.fps
    t, next_tick, next_cycle, next_frame = 0.0, BASE_TICK_S, period, 0.0
    odom, command = Odometry(), STOP
    increments: list = []
    frame: DepthFrame | None = None
    seen: DepthFrame | None = None
    state: WorldState | None = None
    frames = cycles = 0
    path = 0.0
    job_s: list[float] = []
    while not world.outcome.done:
        t_next = min(next_tick, next_cycle, next_frame)
        dt = t_next - t
        if dt > 0:
            base.step(dt)
            truth = base.truth()
            x, y, theta = base_to_world(start, truth["x"], truth["y"], truth["theta"])
            path += math.hypot(x - world.robot.x, y - world.robot.y)
            world.follow_robot(dt, x, y, theta, truth["v"], truth["omega"])
            t = t_next
            if world.outcome.done:
                break
        if t >= next_tick - 1e-9:
            next_tick += BASE_TICK_S
            for f in parser.feed(base.feedback_frame()):
                inc = converter.convert(decode_feedback(f.payload), t)
                if inc is not None:
                    increments.append(inc)
        if t >= next_frame - 1e-9:
            next_frame += frame_period
            if not job.finished:  # a finished job stands still: nobody needs to look
                snap = world.snapshot()
                depth = renderer.render(tuple(snap.robot_pose), scene_from(world, snap),
                                        noise=settings.noise)
                frame = DepthFrame(depth, t, frames, renderer.intrinsics)
                frames += 1
        if t >= next_cycle - 1e-9:
            next_cycle += period
            cycles += 1
            for inc in increments:
                odom = ekf.step(inc)
            increments.clear()
            if frame is not None and frame is not seen:
                seen = frame
                state = model.update(frame, odom)
            w0 = time.perf_counter()
            target = STOP if job.finished else job.step(t, odom, state)
            job_s.append(time.perf_counter() - w0)
            if not target.is_finite():
                target = STOP
            command = apply_limits(target, command, period, cfg.limits)
            left, right = twist_to_wheel_ticks(command.v, command.omega,
                                               cal.odometry.axle_length_m,
                                               cal.odometry.m_per_tick, max_wheel_mm_s)
            base.receive(wheel_speed_frame(left, right), t)
    out = world.outcome
    summary = job.summary()
    return EpisodeResult(
        scenario=scenario_name, seed=seed, status=out.status, time_s=out.t,
        path_length_m=path, at_fault=bool(out.at_fault),
        moving_at_contact=out.contact is not None and out.contact.moving,
        collided_with=out.collided_with,
        contact_bearing_deg=None if out.contact is None else out.contact.bearing_deg,
        min_separation_m=float(world.min_separation),
        shield_interventions=int(sum(summary.get("shield_interventions", {}).values())),
        cycles=cycles,
        job_p99_ms=float(np.percentile(1e3 * np.array(job_s), 99)) if job_s else 0.0)


def _run_one(task: tuple[str, int, EvalSettings]) -> EpisodeResult:
    logging.getLogger("safemove").setLevel(logging.WARNING)  # per-cycle shield logs are noise here
    return run_episode(*task)


def summarise(results: list[EpisodeResult]) -> dict[str, Any]:
    """The paper's columns for one scenario (path length and speed over successes), plus
    at-fault collisions and shield interventions."""
    n = len(results)
    ok = [r for r in results if r.status == "success"]
    coll = [r for r in results if r.status == "collision"]
    return {
        "episodes": n,
        "success_rate": len(ok) / n,
        "collision_rate": len(coll) / n,
        "timeout_rate": sum(r.status == "timeout" for r in results) / n,
        "at_fault_collisions": sum(r.at_fault for r in coll),
        "moving_collisions": sum(r.moving_at_contact for r in coll),
        "avg_path_length_m": float(np.mean([r.path_length_m for r in ok])) if ok else None,
        "avg_speed_m_s": (float(np.mean([r.path_length_m / r.time_s for r in ok if r.time_s > 0]))
                          if ok else None),
        "avg_time_s": float(np.mean([r.time_s for r in ok])) if ok else None,
        "shield_interventions": sum(r.shield_interventions for r in results),
        "shield_interventions_per_episode": sum(r.shield_interventions for r in results) / n,
        "min_separation_m": float(min(r.min_separation_m for r in results)),
        "job_p99_ms": float(max(r.job_p99_ms for r in results)),
    }


def evaluate(scenarios: list[str], episodes: int, seed: int, settings: EvalSettings,
             jobs: int = 1, progress: Callable[[EpisodeResult], None] | None = None
             ) -> dict[str, Any]:
    """`episodes` seeded episodes (seeds seed, seed+1, …) of each scenario; `jobs` worker
    processes. Returns the per-scenario summaries and every episode."""
    for name in scenarios:
        load_scenario(name)  # a bad name or file fails here, once, with its message
    load_config(settings.config_path, list(settings.overrides))
    tasks = [(name, seed + i, settings) for name in scenarios for i in range(episodes)]
    results: list[EpisodeResult] = []
    if jobs <= 1:
        for task in tasks:
            results.append(_run_one(task))
            if progress is not None:
                progress(results[-1])
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            for r in pool.map(_run_one, tasks):
                results.append(r)
                if progress is not None:
                    progress(r)
    return {
        "planner": settings.planner,
        "fps": settings.fps,
        "noise": settings.noise,
        "crowd": settings.crowd,
        "scenarios": {name: summarise([r for r in results if r.scenario == name])
                      for name in scenarios},
        "episodes": [asdict(r) for r in results],
    }


def table(result: dict[str, Any]) -> str:
    """The per-scenario table as text (rates in %)."""

    def cell(x: float | None, fmt: str) -> str:
        return "-" if x is None else format(x, fmt)

    rows = [(f"{'scenario':<16}{'success':>9}{'collision':>10}{'timeout':>9}{'at fault':>9}"
             f"{'moving':>7}{'path m':>8}{'speed m/s':>10}{'shield':>8}")]
    for name, s in result["scenarios"].items():
        rows.append(f"{name:<16}{100 * s['success_rate']:>8.0f}%{100 * s['collision_rate']:>9.0f}%"
                    f"{100 * s['timeout_rate']:>8.0f}%{s['at_fault_collisions']:>9d}"
                    f"{s['moving_collisions']:>7d}"
                    f"{cell(s['avg_path_length_m'], '.2f'):>8}{cell(s['avg_speed_m_s'], '.3f'):>10}"
                    f"{s['shield_interventions']:>8d}")
    return "\n".join(rows)
