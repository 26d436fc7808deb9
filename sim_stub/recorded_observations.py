"""Recorded observations for the export's parity check: what the robot's actor will really see.

Lock-stepped simulated episodes in one process, deterministic for a spec and a seed: scenario
paper_b (12 oblivious people, 4 static obstacles), depth rendered at the pixels the world model
reads (sim_stub/lockstep.py) at 10 fps, run through the runtime's `Pipeline` with the SafeMove
job of the spec: every observation the job builds is recorded. The robot follows DWA's best command (given as the actor's action, through the shield
and the limits); when an episode ends (goal, collision, time limit) the next seed starts.
Random observations fill the spec's bounds uniformly; these fill it as a run does: mostly free
scan bins, small speeds, goal far away, etc.
"""

from __future__ import annotations

import numpy as np

from runtime.config.settings import Calibration, Config
from runtime.jobs.safemove import SafeMoveJob
from runtime.pipeline import Pipeline
from runtime.policy.obs_spec import ActionSpec, ObsSpec
from sim_stub.lockstep import LockstepEpisode

FPS = 10.0
SCENARIO = "paper_b"


def _action_for(action: ActionSpec, v: float, omega: float) -> np.ndarray:
    """The action in the model's output box that the spec maps to (v, ω)."""
    lo, hi = np.asarray(action.output_low), np.asarray(action.output_high)
    return lo + 0.5 * (np.asarray(action.normalise(v, omega)) + 1.0) * (hi - lo)


def recorded_observations(spec: ObsSpec, count: int, seed: int = 0,
                          config: Config | None = None) -> np.ndarray:
    """(count, spec.size) float32 observations from simulated runs (module docs)."""
    cfg = config if config is not None else Config()
    cal = Calibration()
    out = np.empty((count, spec.size), dtype=np.float32)
    n, episode_seed = 0, seed
    while n < count:
        episode = LockstepEpisode(SCENARIO, episode_seed, cfg, cal, FPS, noise=False)
        episode_seed += 1
        job = SafeMoveJob(episode.goal_odom, cfg, None, None, spec=spec)
        pipeline = Pipeline(episode.config, cal, job)
        while n < count and (inp := episode.cycle()) is not None:
            sensed = pipeline.begin(inp)
            action = None
            if sensed.observation is not None and sensed.prepared is not None:
                out[n] = sensed.observation
                n += 1
                best = sensed.prepared.context.dwa.best
                action = _action_for(spec.action, float(best[0]), float(best[1]))
            episode.send(pipeline.finish(sensed, action).command)
    return out


def simulated_observations(spec: ObsSpec, count: int) -> tuple[np.ndarray, str]:
    """`count` recorded observations for the export's parity check, and their provenance."""
    return recorded_observations(spec, count), f"simulated run, scenario {SCENARIO}, seed 0"
