"""Flight-recorder test input: real cycles of the DWA job, lock-stepped, handed over as the
control loop hands them to the recorder (tests/test_recorder.py, tests/test_log_plot.py)."""

from __future__ import annotations

import time

from runtime.config.settings import load_config
from runtime.jobs.dwa import DWAJob
from runtime.pipeline import Pipeline
from runtime.process.cycle_record import CycleRecord
from runtime.process.recorder import Recorder
from sim_stub.lockstep import LockstepEpisode


def episode_records(n: int) -> list[CycleRecord]:
    """`n` real cycles of the DWA job in paper_a (seed 3, reactive crowd, noisy depth)."""
    loaded = load_config(None, [])
    ep = LockstepEpisode("paper_a", 3, loaded.config, loaded.calibration, 15.0, True,
                         "reactive")
    job = DWAJob(ep.goal_odom, loaded.config, None)
    pipeline = Pipeline(ep.config, loaded.calibration, job)
    out: list[CycleRecord] = []
    while len(out) < n and (inp := ep.cycle()) is not None:
        cycle = pipeline.step(inp)
        ep.send(cycle.command)
        out.append(CycleRecord(inp.t, "RUNNING", tuple(inp.increments), tuple(inp.frames),
                               pipeline.perceived_now, inp.feedback_t, cycle,
                               job.trace() if cycle.hold is None else None))
    return out


def wait_written(rec: Recorder, n: int, limit_s: float = 60.0) -> None:
    """Until the writer has taken `n` cycles (written or dropped), as a 20 Hz loop lets it."""
    deadline = time.monotonic() + limit_s
    while rec.counts["cycles"] + rec.counts["dropped"] < n and rec.stopped_reason is None:
        assert time.monotonic() < deadline, rec.counts
        time.sleep(0.01)
