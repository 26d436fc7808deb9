"""Benchmarks. Each prints figures and ends with one JSON object on its last line."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from runtime.app import run_job
from runtime.config import load_config
from runtime.drive import DriveJob, Segment
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

    from drivers.realsense_playback import PlaybackDepthSource
    from runtime.config import CameraMount, LimitsConfig
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
