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
