"""Benchmarks. Each prints figures and ends with one JSON object on its last line."""

from __future__ import annotations

import gc
from pathlib import Path
from typing import Any

from runtime.cli.app import run_job
from runtime.config.settings import load_config
from runtime.jobs.drive import DriveJob, Segment
from runtime.types import Twist


def bench_loop(cycles: int, config: Path | None, overrides: list[str]) -> dict[str, Any]:
    """The drive job against the emulated base (a separate process on a pty) for `cycles` cycles."""
    from sim_stub.emulator_process import EmulatorProcess

    pattern = [Segment(Twist(0.2, 0.0), 2.0), Segment(Twist(0.0, 0.8), 2.0)]
    with EmulatorProcess() as emu:
        loaded = load_config(config, [*overrides, f"base.port={emu.link}"])
        hz = loaded.config.loop.control_hz
        job = DriveJob(pattern * (int(cycles / hz / 4.0) + 2), 1.0 / hz)
        report, link = run_job(loaded, job, max_cycles=cycles)
    full = report.as_dict()
    return {
        "bench": "loop",
        "control_hz": hz,
        "cycles": report.cycles,
        "misses": report.misses,
        "period_jitter_ms": full["period_jitter_ms"],
        "cycle_ms": full["cycle_ms"],
        # same-run reference: the share of the control period one cycle uses (transfers better
        # across machines than milliseconds do)
        "cycle_p99_share_of_period": round(full["cycle_ms"]["p99"] / (1000.0 / hz), 5),
        "stage_ms": full["stage_ms"],
        "feedback_frames": link["feedback_frames"],
        "frames_sent": link["frames_sent"],
        "rejected": link["rejected"],
    }


def bench_sim(frames: int, steps: int) -> dict[str, Any]:
    """Depth render frames/s at 848×480 (scenario paper_d: 20 people + clutter), world steps/s
    with its 20-agent ORCA crowd, and playback frames/s of a recording made from those frames.
    Same-run references: the D435's 30 fps and the base's 50 Hz tick, as real-time factors."""
    import tempfile
    import time

    from drivers.realsense.playback import PlaybackDepthSource
    from runtime.config.settings import CameraMount, LimitsConfig
    from runtime.types import Twist
    from sim_stub.recording import record, simulated_frames
    from sim_stub.scenario import load_scenario
    from sim_stub.world import World

    scenario = load_scenario("paper_d")
    t0 = time.perf_counter()
    rendered = list(simulated_frames(scenario, frames, 30.0, Twist(0.2, 0.1), CameraMount(),
                                     LimitsConfig(), noise=True))
    render_s = time.perf_counter() - t0  # includes the world steps between frames (~1 %)

    world = World(scenario)
    t0 = time.perf_counter()
    for _ in range(steps):
        world.step(0.02, 0.2, 0.1)
    step_s = time.perf_counter() - t0

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.db3"
        record(path, iter(rendered), 30.0)
        source = PlaybackDepthSource(path)
        t0 = time.perf_counter()
        source.start()
        played = 0
        while not source.at_end:
            if source.poll() is not None:
                played += 1
        play_s = time.perf_counter() - t0
        source.stop()
    render_fps = frames / render_s
    steps_per_s = steps / step_s
    return {
        "bench": "sim",
        "resolution": "848x480",
        "agents": len(world.crowd),
        "render_fps": round(render_fps, 2),
        "render_realtime_factor_vs_30fps": round(render_fps / 30.0, 3),
        "world_steps_per_s": round(steps_per_s, 1),
        "world_realtime_factor_vs_50hz": round(steps_per_s / 50.0, 2),
        "playback_frames": played,
        "playback_fps": round(played / play_s, 1),
    }


def bench_perception(frames: int) -> dict[str, Any]:
    """Per-stage p50/p99 (ms) of the sensing half of `Pipeline.step` on rendered 848×480 depth
    of scenario paper_d (20 people + clutter, robot moving at 0.2 m/s, 0.15 rad/s): the
    odometry EKF for the 3 wheel increments of one cycle, perception, obstacle memory and
    tracking, at decimation 1, 2 and 4, one cycle per frame (the job holds). The floor check
    (every 10th frame) runs after the command in the loop, so it is reported on its own.
    `total_p99` is the p99 of the per-frame sum, against the 2 ms target."""
    import time
    from dataclasses import replace

    import numpy as np

    from runtime.config.settings import Calibration, CameraMount, Config, LimitsConfig
    from runtime.jobs.drive import HoldJob
    from runtime.pipeline import CycleInput, Pipeline
    from runtime.types import BaseStatus, CliffSensor, Proximity, Twist, WheelIncrement
    from sim_stub.recording import simulated_frames
    from sim_stub.scenario import load_scenario

    motion = Twist(0.2, 0.15)
    rendered = list(simulated_frames(load_scenario("paper_d"), frames, 15.0, motion,
                                     CameraMount(), LimitsConfig(), noise=True))
    cal = Calibration()
    dt = rendered[1].t - rendered[0].t if len(rendered) > 1 else 1.0 / 15.0
    half_track = 0.5 * motion.omega * cal.odometry.axle_length_m

    def increments(t: float) -> tuple[WheelIncrement, ...]:
        """The wheel travel since the previous frame, in three increments as the base sends."""
        step = dt / 3
        d_left, d_right = (motion.v - half_track) * step, (motion.v + half_track) * step
        return tuple(WheelIncrement(t - (2 - i) * step, step, d_left, d_right, motion.omega, None,
                                    CliffSensor(0), Proximity(0), BaseStatus(0)) for i in range(3))

    def pct(samples: list[float]) -> dict[str, float]:
        p50, p99 = np.percentile(np.asarray(samples) * 1000.0, [50, 99])
        return {"p50": round(float(p50), 3), "p99": round(float(p99), 3)}

    result: dict[str, Any] = {"bench": "perception", "resolution": "848x480", "frames": frames,
                              "people": 20, "target_total_p99_ms": 2.0}
    stages = ("odometry", "perception", "memory", "tracking")
    gc.collect()
    gc.disable()  # as in the control loop: collections run between cycles, never inside one
    for decimation in (1, 2, 4):
        base = Config()
        cfg = replace(base, perception=replace(base.perception, decimation=decimation))
        pipeline = Pipeline(cfg, cal, HoldJob())
        times: dict[str, list[float]] = {k: [] for k in (*stages, "total", "floor_check")}
        for k, frame in enumerate(rendered):
            out = pipeline.step(CycleInput(frame.t, increments(frame.t), (frame,), frame.t))
            t0 = time.perf_counter()
            if pipeline.check_floor() is not None:  # in the loop: after the command, in the slack
                times["floor_check"].append(time.perf_counter() - t0)
            if k == 0:
                continue  # first call pays one-off allocations
            for key in stages:
                times[key].append(out.stage_s[key])
            times["total"].append(sum(out.stage_s[key] for key in stages))
        result[f"decimation_{decimation}"] = {key: pct(v) for key, v in times.items() if v}
        gc.collect()
    gc.enable()
    return result


def _scan_of(points: Any, bin_angles: Any) -> Any:
    """Nearest point per bearing bin (10 m where a bin is empty): a stand-in scan for the
    shield's unseen-space test in random planner worlds."""
    import numpy as np

    from runtime.geometry import bin_index, bin_layout

    k = bin_index(np.arctan2(points[:, 1], points[:, 0]), *bin_layout(bin_angles),
                  len(bin_angles))
    ok = k >= 0
    scan = np.full(len(bin_angles), 10.0)
    np.minimum.at(scan, k[ok], np.hypot(points[ok, 0], points[ok, 1]))
    return scan


def ms_stats(seconds: list[float]) -> dict[str, float]:
    import numpy as np

    a = 1e3 * np.asarray(seconds)
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
            "max": float(a.max())}


def bench_planner(worlds: int = 20, calls: int = 10_000, p99_calls: int = 500,
                  seed: int = 0) -> dict[str, Any]:
    """(a) vectorised DWA vs the per-sample reference, coarse 400 samples × 30 steps with 15
    obstacles (10 static blobs of points, 5 tracks): time ratio (per call, the median of three
    passes over `worlds` worlds each) and identical choices; (b) 800 samples × 30 steps, 20 tracks, 500 points: DWA, safe
    corridor along its best path and the shield on its best command, per call and summed;
    (c) `calls` budgeted DWA calls (default config, 20 tracks, 500 points) with the deadline
    on time.monotonic: how far past its deadline a call returns. The garbage collector is off
    while timing, as it is in the control loop's cycles."""
    import math
    import time
    from dataclasses import replace

    import numpy as np

    from runtime.planning.corridor import CorridorConfig, safe_corridor
    from runtime.planning.dwa import DWAConfig, plan, plan_coarse
    from runtime.safety.certificate import ShieldConfig, ShieldWorld
    from runtime.safety.limits import LimitsConfig
    from runtime.safety.shield import shield
    from sim_stub.dwa_reference import plan_reference, random_world

    lim, cfg, ccfg, scfg = LimitsConfig(), DWAConfig(), CorridorConfig(), ShieldConfig()
    rng = np.random.default_rng(seed)
    gc.collect()
    gc.disable()
    try:
        same, max_term_err = 0, 0.0
        w = random_world(np.random.default_rng(seed + 1), 30, 100, 5, n_blobs=10)
        plan_coarse(cfg, lim, w["v0"], w["w0"], w["goal"], w["points"], w["obs_pos"],
                    w["obs_radius"])  # one-off set-up (imports, OpenCV) outside the timing
        problems = [random_world(rng, 30, 100, 5, n_blobs=10) for _ in range(worlds)]
        args = [(w["v0"], w["w0"], w["goal"], w["points"], w["obs_pos"], w["obs_radius"])
                for w in problems]
        # each implementation in its own loop over the same worlds (interleaving them would
        # time the vectorised one with the reference's cache footprint), three passes each,
        # the median pass counts (the same noise filter for both)
        def median_pass(fn: Any) -> tuple[float, list]:
            passes = []
            for _ in range(3):
                t0 = time.perf_counter()
                out = [fn(cfg, lim, *a) for a in args]
                passes.append(time.perf_counter() - t0)
            return float(np.median(passes)), out

        t_vec, mine = median_pass(plan_coarse)
        t_ref, refs = median_pass(plan_reference)
        for a, b in zip(mine, refs):
            same += int(a.best_index == b.best_index or (b.best_index < 0 and a.best == b.best))
            for k in ("heading", "clearance", "velocity", "density"):
                max_term_err = max(max_term_err,
                                   float(np.abs(getattr(a, k)[:400] - b.terms[k]).max()))
        out: dict[str, Any] = {
            "a_worlds": worlds, "a_identical_choices": same,
            "a_vectorised_ms": 1e3 * t_vec / worlds, "a_reference_ms": 1e3 * t_ref / worlds,
            "a_speedup": t_ref / t_vec, "a_max_term_err": max_term_err}

        cfg800 = replace(cfg, n_v=40, n_omega=20, refine_max_rounds=0, block_samples=800)
        half_fov = math.radians(43.5)
        bins = np.linspace(-half_fov, half_fov, 64, endpoint=False) + half_fov / 64
        lat: dict[str, list[float]] = {"dwa": [], "corridor": [], "shield": [], "total": []}
        interventions = 0
        for _ in range(p99_calls):
            w = random_world(rng, 30, 500, 20, n_blobs=40)
            sworld = ShieldWorld(
                points=w["points"], track_positions=w["obs_pos"],
                track_std=np.zeros(w["obs_pos"].shape[:2]), track_radii=w["obs_radius"][:, 0],
                track_dt=0.1, bin_angles=bins, unknown=np.zeros(len(bins), bool),
                scan=_scan_of(w["points"], bins))
            t0 = time.perf_counter()
            r = plan(cfg800, lim, w["v0"], w["w0"], w["goal"], w["points"], w["obs_pos"],
                     w["obs_radius"])
            t1 = time.perf_counter()
            safe_corridor(r.best_path, w["points"], w["obs_pos"], w["obs_radius"][:, 0], ccfg)
            t2 = time.perf_counter()
            ok = r.admissible
            d = shield(Twist(*r.best), Twist(w["v0"], w["w0"]), r.samples[ok], r.total[ok],
                       sworld, lim, scfg, deadline=t2 + scfg.candidate_budget_s,
                       now=time.perf_counter)
            t3 = time.perf_counter()
            interventions += int(d.intervened)
            for key, dt in (("dwa", t1 - t0), ("corridor", t2 - t1), ("shield", t3 - t2),
                            ("total", t3 - t0)):
                lat[key].append(dt)
        out.update({"b_samples": r.evaluated, "b_calls": p99_calls,
                    "b_shield_interventions": interventions,
                    **{f"b_{key}_ms": ms_stats(v) for key, v in lat.items()}})

        pool = [random_world(rng, 30, 500, 20, n_blobs=40) for _ in range(50)]
        over, rounds, cuts = [], 0, 0
        for i in range(calls):
            w = pool[i % len(pool)]
            t0 = time.monotonic()
            r = plan(cfg, lim, w["v0"], w["w0"], w["goal"], w["points"], w["obs_pos"],
                     w["obs_radius"], deadline=t0 + cfg.budget_s, now=time.monotonic)
            over.append(time.monotonic() - (t0 + cfg.budget_s))
            rounds += r.refine_rounds
            cuts += int(r.budget_cut)
    finally:
        gc.enable()
    over_ms = 1e3 * np.array(over)
    out.update({"c_calls": calls, "c_budget_ms": 1e3 * cfg.budget_s,
                "c_max_overshoot_ms": float(over_ms.max()),
                "c_p99_end_minus_deadline_ms": float(np.percentile(over_ms, 99)),
                "c_mean_rounds": rounds / calls, "c_budget_cut_share": cuts / calls})
    return out
