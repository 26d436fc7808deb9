"""`safemove bench episode`: how fast the lock-stepped simulation runs, and where its time goes.

Lock-stepped control cycles per second of the DWA job and of the SafeMove job (an ONNX actor),
each run as `safemove eval` runs an episode (`LockstepEpisode` feeding the runtime's
`Pipeline`): seeded episodes of one scenario, seeds seed, seed+1, … until the cycle cap, the last
one cut there. The shares split the wall time of those cycles into the pipeline's stages
(`CycleResult.stage_s`), the simulator's standing in for the world (`LockstepEpisode.sim_s`:
render, crowd, base) and "other", the rest (the episode's event loop, the depth guard, the
command back to the base). The budgets are counts and the episodes seeded, so the same seeds run
the same cycles on any machine: the seeds and cycles used are in the result, so runs on
different commits can be compared (while the robot's behaviour is unchanged, the cycles are
the same ones).

Then the training environment (`make_vec_env`, TD3 set up as `safemove train` sets it up) in
environment steps per second, with one worker and with one per core: first the random steps
before learning starts (simulation only), then steps with their gradient updates.
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np

from runtime.config.settings import LoadedConfig, load_config
from runtime.errors import UserError
from runtime.pipeline import PIPELINE_STAGES, Pipeline
from runtime.policy.actor import INPUT_NAME, META_PROVENANCE, META_SPEC, OUTPUT_NAME, Policy
from runtime.policy.obs_spec import PRESETS, load_spec
from sim_stub.evaluate import EvalSettings, make_job
from sim_stub.lockstep import LockstepEpisode
from sim_stub.scenario import load_scenario

SIM_PARTS = ("render", "crowd", "base")  # LockstepEpisode.sim_s
RANDOM_ACTOR_HIDDEN = (400, 300)  # stable-baselines3's TD3 default, as `safemove train` builds


@contextmanager
def quiet_logs() -> Iterator[None]:
    """The runtime's logs at WARNING while a benchmark runs: the shield's per-cycle
    intervention lines would bury the figures."""
    log = logging.getLogger("safemove")
    level = log.level
    log.setLevel(logging.WARNING)
    try:
        yield
    finally:
        log.setLevel(level)


def write_random_actor(path: Path, seed: int = 0) -> str:
    """A randomly initialised SafeMove-preset actor (61→400→300→2, ReLU, tanh) written as
    `safemove export` writes one (input `obs`, output `action`, the spec in the metadata), with
    onnx alone: no torch. What a cycle costs does not depend on the weights; torch's default
    initialisation (uniform ±1/√fan_in) keeps the actions spread as an untrained actor's are.
    Returns a description for the result."""
    try:
        from onnx import TensorProto, helper, numpy_helper
    except ImportError:
        raise UserError("a random actor needs onnx (pip install -e '.[export]'); or give"
                        " --model FILE.onnx") from None
    spec = PRESETS["safemove"]
    sizes = [spec.size, *RANDOM_ACTOR_HIDDEN, 2]
    rng = np.random.default_rng(seed)
    weights, nodes, x = [], [], INPUT_NAME
    for i, (n_in, n_out) in enumerate(pairwise(sizes)):
        bound = 1.0 / math.sqrt(n_in)
        weights += [
            numpy_helper.from_array(rng.uniform(-bound, bound, (n_out, n_in)).astype(np.float32),
                                    f"w{i}"),
            numpy_helper.from_array(rng.uniform(-bound, bound, n_out).astype(np.float32), f"b{i}")]
        last = i == len(sizes) - 2
        y = OUTPUT_NAME if last else f"h{i}"
        nodes += [helper.make_node("Gemm", [x, f"w{i}", f"b{i}"], [f"z{i}"], transB=1),
                  helper.make_node("Tanh" if last else "Relu", [f"z{i}"], [y])]
        x = y
    graph = helper.make_graph(
        nodes, "actor",
        [helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT, ["batch", spec.size])],
        [helper.make_tensor_value_info(OUTPUT_NAME, TensorProto.FLOAT, ["batch", 2])], weights)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    note = "randomly initialised (untrained)"
    model.metadata_props.add(key=META_SPEC, value=spec.to_json())
    model.metadata_props.add(key=META_PROVENANCE, value=json.dumps({"note": note}))
    path.write_bytes(model.SerializeToString())
    return f"{'-'.join(map(str, sizes))}, {note}"


def time_job(settings: EvalSettings, loaded: LoadedConfig, scenario: str, seed: int, cap: int
             ) -> dict[str, Any]:
    """`cap` lock-stepped cycles of one planner job over episodes seed, seed+1, …: cycles/s,
    each part's share of the cycles' wall time and its milliseconds per cycle. Setting up an
    episode (world, renderer, job, model load) is timed apart, as `setup_s`."""
    stage_s = dict.fromkeys(PIPELINE_STAGES, 0.0)
    sim_s = dict.fromkeys(SIM_PARTS, 0.0)
    wall = setup = 0.0
    episodes: list[dict[str, Any]] = []
    cycles = 0
    while cycles < cap:
        t0 = time.perf_counter()
        episode = LockstepEpisode(scenario, seed, loaded.config, loaded.calibration,
                                  settings.fps, settings.noise, settings.crowd)
        job = make_job(settings, episode.goal_odom, loaded)
        pipeline = Pipeline(episode.config, loaded.calibration, job)
        t1 = time.perf_counter()
        n = 0
        while cycles + n < cap and (inp := episode.cycle()) is not None:
            out = pipeline.step(inp)
            for stage, seconds in out.stage_s.items():
                stage_s[stage] += seconds
            episode.send(out.command)
            episode.looking = not job.finished
            n += 1
        wall += time.perf_counter() - t1
        setup += t1 - t0
        for part, seconds in episode.sim_s.items():
            sim_s[part] += seconds
        # "running": cut at the cap
        episodes.append({"seed": seed, "cycles": n, "status": episode.world.outcome.status})
        cycles += n
        seed += 1
    parts = {**stage_s, **sim_s}
    parts["other"] = wall - sum(parts.values())
    return {
        "cycles": cycles,
        "cycles_per_s": round(cycles / wall, 2),
        "wall_s": round(wall, 3),
        "setup_s": round(setup, 3),
        "episodes": episodes,
        "share": {k: round(v / wall, 4) for k, v in parts.items()},
        "ms_per_cycle": {k: round(1e3 * v / cycles, 3) for k, v in parts.items()},
    }


def time_training(scenario: str, loaded: LoadedConfig, seed: int, fps: float, noise: bool,
                  crowd: str, workers: int, learning_starts: int, updates: int
                  ) -> dict[str, Any]:
    """Environment steps per second of `workers` training envs under TD3 (hyperparameters:
    `safemove train`'s defaults, one gradient step per environment step): `learning_starts`
    random steps (simulation alone), then `updates` steps with their gradient steps. Steps are
    counted as SB3 counts them, one per env per VecEnv step."""
    import argparse

    import torch

    from sim_stub.train.cli import add_arguments, make_td3
    from sim_stub.train.vec_env import make_vec_env

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    defaults = parser.parse_args(["--output", "unused"])
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(defaults.threads)
    t0 = time.perf_counter()
    spec = load_spec(defaults.spec)
    env = make_vec_env([scenario], spec, loaded, workers, seed, fps=fps, noise=noise, crowd=crowd)
    try:
        model = make_td3(env, argparse.Namespace(**{**vars(defaults), "seed": seed,
                                                     "learning_starts": learning_starts}))
        t1 = time.perf_counter()
        model.learn(total_timesteps=learning_starts)
        t2 = time.perf_counter()
        collected = model.num_timesteps
        model.learn(total_timesteps=updates, reset_num_timesteps=False)
        t3 = time.perf_counter()
    finally:
        env.close()
        torch.set_num_threads(previous_threads)
    trained = model.num_timesteps - collected
    return {
        "workers": workers,
        "setup_s": round(t1 - t0, 2),
        "random_steps": collected,
        "random_steps_per_s": round(collected / (t2 - t1), 1),
        "learning_steps": trained,
        "learning_steps_per_s": round(trained / (t3 - t2), 1),
    }


def bench_episode(scenario: str, seed: int, cycles: int, fps: float, noise: bool, crowd: str,
                  model: Path | None, config: Path | None, overrides: list[str],
                  train_workers: list[int], learning_starts: int, updates: int
                  ) -> dict[str, Any]:
    """The whole benchmark (module docs); `train_workers` empty: no training env figures."""
    load_scenario(scenario)  # a bad name fails here, with its one line
    loaded = load_config(config, overrides)
    if train_workers:
        try:
            import stable_baselines3  # noqa: F401 - only checking the train extra is there
            import torch  # noqa: F401
        except ImportError as exc:
            raise UserError(f"bench episode: the training env needs the train extra ({exc.name}"
                            " is missing: pip install -e '.[train]'), or give --no-train"
                            ) from None
    result: dict[str, Any] = {"bench": "episode", "scenario": scenario, "crowd": crowd,
                              "fps": fps, "noise": noise, "seed": seed, "cycle_cap": cycles}
    with quiet_logs(), tempfile.TemporaryDirectory(prefix="safemove-bench-") as tmp:
        actor = str(model)
        if model is None:
            model = Path(tmp) / "actor.onnx"
            actor = write_random_actor(model)
        else:
            Policy(model, loaded.config.policy)  # a bad model refuses now, not after DWA's run
        for planner in ("dwa", "safemove"):
            settings = EvalSettings(planner, config, tuple(overrides), model, fps, noise, crowd)
            timed = time_job(settings, loaded, scenario, seed, cycles)
            result[planner] = {**timed, "actor": actor} if planner == "safemove" else timed
            print(f"{planner}: {timed['cycles_per_s']} cycles/s", file=sys.stderr)
    for workers in train_workers:
        with quiet_logs():
            result[f"train_{workers}_workers"] = time_training(
                scenario, loaded, seed, fps, noise, crowd, workers, learning_starts, updates)
        print(f"train, {workers} workers: {result[f'train_{workers}_workers']}",
              file=sys.stderr)
    result["cpu_count"] = os.cpu_count()
    return result
