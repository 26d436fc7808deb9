"""`safemove bench cycle`: the robot's whole control cycle, recorded depth in → command out, and
how long `safemove run --planner safemove` takes to become READY.

The cycle: the SafeMove job with an ONNX actor (`--model`, or a random 61→400→300→2 one: a
cycle's cost does not depend on the weights) on the shipped config, with the DWA and shield
budgets on time.monotonic as `safemove run` has them. Depth comes from a real pyrealsense2
recording of scenario paper_d at 848×480 with sensor noise, made here with `safemove record`'s
code at the config's camera rate and played again and again, its stamps and frame numbers
moved on each pass so that both only increase; the wheel increments, one per base tick, are
synthesised from the motion the recording was made with. The recording's crowd is reactive: an
oblivious one walks into the robot within seconds, and after a collision the world stands
still. The job's goal is far away, so every cycle plans; at a pass's seam the scene jumps back
to its start while odometry goes on, which the tracker sees as people vanishing and appearing.

A cycle is `Pipeline.begin` (odometry, perception, memory, tracking, the job's plan: track
predictions, DWA, corridor, observation), one inference and `Pipeline.finish` (the action
mapped to a twist, the shield, the limits stage), as the job would run them with its own actor.
Not timed: reading the recording (the loop reads the camera's queue instead) and the floor
check, which runs in the slack after the command (reported on its own). The garbage collector
runs between cycles, as in the loop. The first WARMUP_CYCLES cycles are not counted.

Then `bench startup`'s measurement for the same actor. The targets are printed beside the
figures with whether they are met: cycle p99 ≤ 5 ms, READY ≤ 2 s and RSS at READY ≤ 200 MB,
each judged on the median start.
"""

from __future__ import annotations

import gc
import math
import tempfile
import time
from collections.abc import Iterator
from contextlib import closing
from dataclasses import replace
from itertools import count
from pathlib import Path
from typing import Any

from drivers.realsense.playback import PlaybackDepthSource
from runtime.config.settings import LoadedConfig, load_config
from runtime.jobs.safemove import SafeMoveJob
from runtime.pipeline import CycleInput, Pipeline
from runtime.policy.actor import Policy
from runtime.process.cycle_record import CycleRecord
from runtime.process.recorder import Recorder
from runtime.types import BaseStatus, CliffSensor, DepthFrame, Proximity, Twist, WheelIncrement
from sim_stub.bench import ms_stats
from sim_stub.bench_episode import quiet_logs, write_random_actor
from sim_stub.lockstep import BASE_TICK_S
from sim_stub.recording import record, simulated_frames
from sim_stub.scenario import load_scenario, with_crowd
from sim_stub.startup_bench import bench_startup

SCENARIO = "paper_d"
MOTION = Twist(0.2, 0.15)  # the robot's command while recording
GOAL_ODOM = (50.0, 0.0)  # never reached: every cycle plans
WARMUP_CYCLES = 20  # one-off allocations, the tracker's first tracks
STAGES = ("odometry", "perception", "memory", "tracking", "plan", "actor", "shield", "limits")
TARGETS = {"cycle_p99_ms": 5.0, "ready_s": 2.0, "rss_at_ready_mb": 200.0,
           "recorder_added_p99_ms": 0.3}


def _replayed(path: Path, frames: int, fps: float) -> Iterator[DepthFrame]:
    """The recording's frames pass after pass, stamps and frame numbers moved on by a pass each
    time."""
    for p in count():
        source = PlaybackDepthSource(path)
        source.start()
        played = 0
        try:
            while not source.at_end:
                frame = source.poll()
                if frame is not None:
                    played += 1
                    yield replace(frame, t=frame.t + p * frames / fps,
                                  frame_number=frame.frame_number + p * frames)
        finally:
            source.stop()
        if played == 0:
            raise RuntimeError(f"{path}: the recording played no frames")


class _Wheels:
    """Wheel increments, one per base tick, of the motion the recording was made with: the
    world's robot speeds up from rest to MOTION at the limits' accelerations, one world step
    per frame, and each pass starts from rest again."""

    def __init__(self, loaded: LoadedConfig, frames: int, fps: float) -> None:
        self._limits = loaded.config.limits
        self._half_track = 0.5 * loaded.calibration.odometry.axle_length_m
        self._fps = fps
        self._span = frames / fps
        self._tick = 0

    def until(self, t: float) -> tuple[WheelIncrement, ...]:
        """The increments of the ticks up to `t` not yet given (a control period spans at
        least one tick)."""
        out = []
        while (self._tick + 1) * BASE_TICK_S <= t + 1e-9:
            self._tick += 1
            tick_t = self._tick * BASE_TICK_S
            step = max(1, math.ceil((tick_t % self._span) * self._fps - 1e-9))  # world step
            v = min(MOTION.v, self._limits.accel_max * step / self._fps)
            omega = min(MOTION.omega, self._limits.alpha_max * step / self._fps)
            d_left = (v - omega * self._half_track) * BASE_TICK_S
            d_right = (v + omega * self._half_track) * BASE_TICK_S
            out.append(WheelIncrement(tick_t, BASE_TICK_S, d_left, d_right, omega, None,
                                      CliffSensor(0), Proximity(0), BaseStatus(0)))
        return tuple(out)


def time_cycles(loaded: LoadedConfig, recording: Path, frames: int, fps: float, policy: Policy,
                cycles: int, paced: bool = False, recorder: Recorder | None = None
                ) -> dict[str, Any]:
    """`cycles` timed cycles (after WARMUP_CYCLES) on the recording: per-cycle and per-stage
    times in ms, the floor check apart, and how many cycles held or decided. `paced`: each
    cycle starts a control period after the previous one, as in the loop (the slack is where
    the recorder's thread writes); `recorder`: hand it every cycle, as the loop does."""
    cfg = loaded.config
    job = SafeMoveJob(GOAL_ODOM, cfg, policy, time.monotonic)
    pipeline = Pipeline(cfg, loaded.calibration, job)
    period = 1.0 / cfg.loop.control_hz
    wheels = _Wheels(loaded, frames, fps)
    times: dict[str, list[float]] = {k: [] for k in ("cycle", *STAGES)}
    floor_checks: list[float] = []
    offers: list[float] = []
    held = decided = 0
    gc.collect()
    gc.disable()
    start = time.perf_counter()
    try:
        with closing(_replayed(recording, frames, fps)) as replay:
            pending = next(replay)
            for k in range(WARMUP_CYCLES + cycles):
                t = (k + 1) * period
                arrived = []
                while pending.t <= t + 1e-9:
                    arrived.append(pending)
                    pending = next(replay)
                increments = wheels.until(t)
                inp = CycleInput(t, increments, tuple(arrived), increments[-1].t)
                t0 = time.perf_counter()
                sensed = pipeline.begin(inp)
                t1 = time.perf_counter()
                action = None if sensed.observation is None else policy.act(sensed.observation)
                t2 = time.perf_counter()
                out = pipeline.finish(sensed, action)
                t3 = time.perf_counter()
                checked = pipeline.check_floor() is not None
                t4 = time.perf_counter()
                if recorder is not None:
                    recorder.offer(CycleRecord(t, "RUNNING", increments, tuple(arrived),
                                               pipeline.perceived_now, inp.feedback_t, out,
                                               job.trace() if out.hold is None else None))
                    offers.append(time.perf_counter() - t4)
                gc.collect(0)
                if paced:
                    time.sleep(max(0.0, start + (k + 1) * period - time.perf_counter()))
                if k < WARMUP_CYCLES:
                    continue
                held += out.hold is not None
                decided += action is not None
                stage = {**out.stage_s, "plan": sensed.stage_s["job"],
                         "shield": out.stage_s["job"] - sensed.stage_s["job"]}
                if action is not None:
                    stage["actor"] = t2 - t1
                for key in STAGES:
                    if key in stage:
                        times[key].append(stage[key])
                times["cycle"].append(t3 - t0)
                if checked:
                    floor_checks.append(t4 - t3)
    finally:
        gc.enable()
    return {
        "cycles": cycles, "warmup_cycles": WARMUP_CYCLES, "held": held, "decided": decided,
        "cycle_ms": _rounded(ms_stats(times.pop("cycle"))),
        "stage_ms": {k: _rounded(ms_stats(v)) for k, v in times.items() if v},
        "floor_check_ms": _rounded(ms_stats(floor_checks)) if floor_checks else None,
        "record_offer_ms": _rounded(ms_stats(offers[WARMUP_CYCLES:])) if offers else None,
        "control_period_ms": round(1e3 * period, 3),
    }


def _recorder_cost(loaded: LoadedConfig, recording: Path, frames: int, fps: float,
                   policy: Policy, cycles: int, directory: Path) -> dict[str, Any]:
    """Paced cycles without, then with the flight recorder; the p99 it adds and what it wrote."""
    cfg = loaded.config
    plain = time_cycles(loaded, recording, frames, fps, policy, cycles, paced=True)
    recorder = Recorder(directory, cfg.recorder, loaded.calibration.camera,
                        cfg.perception.decimation, {"bench": "cycle"})
    recorder.start()
    try:
        recorded = time_cycles(loaded, recording, frames, fps, policy, cycles, paced=True,
                               recorder=recorder)
    finally:
        recorder.stop()
    minutes = (WARMUP_CYCLES + cycles) / cfg.loop.control_hz / 60.0
    p99 = (plain["cycle_ms"]["p99"], recorded["cycle_ms"]["p99"])
    return {"cycle_ms_without": plain["cycle_ms"], "cycle_ms_with": recorded["cycle_ms"],
            "offer_ms": recorded["record_offer_ms"], "added_p99_ms": round(p99[1] - p99[0], 3),
            "written": recorder.summary(),
            "mb_per_minute": round(recorder.counts["bytes"] / 1e6 / minutes, 2)}


def _rounded(stats: dict[str, float]) -> dict[str, float]:
    return {k: round(v, 3) for k, v in stats.items()}


def _target(value: float, key: str) -> dict[str, Any]:
    return {"value": value, "target": TARGETS[key], "met": value <= TARGETS[key]}


def bench_cycle(cycles: int, frames: int, model: Path | None, startup_runs: int,
                record_too: bool = False) -> dict[str, Any]:
    """The whole benchmark (module docs); `startup_runs` 0: no start-up figures; `record_too`:
    then the recorder's cost, paced at the control rate, without and with the flight recorder
    in the same run."""
    loaded = load_config(None, [])
    cfg = loaded.config
    fps = float(cfg.depth.fps)
    result: dict[str, Any] = {"bench": "cycle", "scenario": SCENARIO, "resolution": "848x480",
                              "recorded_frames": frames, "fps": fps, "planner": "safemove"}
    with quiet_logs(), tempfile.TemporaryDirectory(prefix="safemove-bench-") as tmp:
        actor = str(model)
        if model is None:
            model = Path(tmp) / "actor.onnx"
            actor = write_random_actor(model)
        result["actor"] = actor
        policy = Policy(model, cfg.policy)  # a bad model refuses here, before the recording
        recording = Path(tmp) / f"{SCENARIO}.db3"
        scenario = with_crowd(load_scenario(SCENARIO), "reactive")
        record(recording, simulated_frames(scenario, frames, fps, MOTION,
                                           loaded.calibration.camera, cfg.limits, noise=True),
               fps)
        timed = time_cycles(loaded, recording, frames, fps, policy, cycles)
        result.update(timed)
        p99 = timed["cycle_ms"]["p99"]
        # same-run reference: the share of the control period (transfers across machines)
        result["cycle_p99_share_of_period"] = round(p99 / timed["control_period_ms"], 4)
        targets = {"cycle_p99_ms": _target(p99, "cycle_p99_ms")}
        if record_too:
            result["recorder"] = _recorder_cost(loaded, recording, frames, fps, policy, cycles,
                                                Path(tmp) / "recordings")
            targets["recorder_added_p99_ms"] = _target(
                result["recorder"]["added_p99_ms"], "recorder_added_p99_ms")
        if startup_runs:
            startup = bench_startup(startup_runs, "safemove", model)
            result["startup"] = startup
            targets["ready_s"] = _target(startup["ready_s"]["median"], "ready_s")
            targets["rss_at_ready_mb"] = _target(startup["rss_at_ready_mb"]["median"],
                                                 "rss_at_ready_mb")
    result["targets"] = targets
    return result
