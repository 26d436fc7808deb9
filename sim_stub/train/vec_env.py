"""The training environments as one stable-baselines3 VecEnv: N `SafeMoveEnv`s, each in its own
worker process (SubprocVecEnv), so the lock-stepped simulation (rendering, world model, DWA,
shield: all Python and numpy on one core) runs on N cores while the learner waits for the batch.

Workers start with 'forkserver' (SB3's default on Linux), not 'fork': the caller has torch
loaded and may have its thread pools (or OpenCV's, or a benchmark's threads) running, and a
child forked from a multi-threaded process can inherit a lock another thread held and hang. The
fork server is a fresh single-threaded process that imports SB3 and the env once; the workers
fork from it, so starting N of them costs one import, not N (measured: 2 workers ready in
3.5 s instead of 5-9 s on a loaded 2-core machine; 'fork' takes 0.1 s, but see above).

Env i is seeded with seed + i at its first reset and draws its episodes from its own generator
after that; the VecEnv steps the envs in lock-step and in index order, so a run is reproducible
from (seed, N). As with any spawned worker, a script that calls `make_vec_env` needs the
`if __name__ == "__main__":` guard: the workers import the caller's main module.
"""

from __future__ import annotations

import functools
import multiprocessing
from pathlib import Path

from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv, VecMonitor

from runtime.config.settings import LoadedConfig
from runtime.policy.obs_spec import ObsSpec
from sim_stub.train.env import SafeMoveEnv
from sim_stub.train.reward import RewardConfig

START_METHOD = "forkserver"
PRELOAD = ["__main__", "stable_baselines3.common.vec_env.subproc_vec_env", __name__]


def make_vec_env(scenarios: list[str], spec: ObsSpec, loaded: LoadedConfig, n_envs: int,
                 seed: int, *, fps: float, noise: bool, crowd: str, surround_people: bool = False,
                 reward: RewardConfig | None = None, monitor_path: Path | None = None
                 ) -> VecEnv:
    """`n_envs` envs in worker processes (one: in this process, nothing to overlap), env i
    seeded from seed + i, under a VecMonitor that writes one row per episode (return, length,
    wall time, outcome) to `monitor_path` when given. Close it to end the workers."""
    if n_envs < 1:
        raise ValueError(f"make_vec_env: n_envs must be at least 1, got {n_envs}")
    # built in the worker from plain, picklable arguments
    factory = functools.partial(SafeMoveEnv, list(scenarios), spec, loaded, reward, fps=fps,
                                noise=noise, crowd=crowd, surround_people=surround_people)
    if n_envs == 1:
        venv: VecEnv = DummyVecEnv([factory])
    else:
        # imported once, by the fork server, instead of once per worker
        multiprocessing.get_context(START_METHOD).set_forkserver_preload(PRELOAD)
        venv = SubprocVecEnv([factory] * n_envs, start_method=START_METHOD)
    venv.seed(seed)
    return VecMonitor(venv, None if monitor_path is None else str(monitor_path),
                      info_keywords=("outcome",))
