"""`safemove train -o RUN_DIR`: TD3 (stable-baselines3) on the lock-stepped robot, then export.

Writes into RUN_DIR: `spec.json` (the observation spec trained on), `monitor.csv` (one row per
episode: return, length, wall time, outcome; SB3's Monitor format), `checkpoints/` (every
--checkpoint-every steps), `td3.zip` (the final model) and `actor.onnx` (the final actor,
exported and parity-checked by `safemove export`'s code). Importing this module does not import
torch, gymnasium or stable-baselines3 (the robot image has none); running it does, and says how
to install them when they are missing.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path
from typing import Any

from runtime.cli.args import add_config_args, finite_float, int_at_least
from runtime.config.settings import load_config
from runtime.errors import UserError
from runtime.policy.obs_spec import PRESETS, load_spec
from sim_stub.scenario import CROWD_MODES, load_scenario

DEFAULT_SCENARIOS = ("paper_a", "paper_b", "paper_c", "paper_d")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_config_args(p)
    p.add_argument("-o", "--output", type=Path, required=True,
                   help="run directory (created; an existing td3.zip there is not overwritten)")
    p.add_argument("--spec", default="safemove", metavar="PRESET|FILE.json",
                   help=f"observation spec: a preset ({', '.join(PRESETS)}) or a spec JSON file"
                        " (default safemove)")
    p.add_argument("--scenarios", nargs="+", default=list(DEFAULT_SCENARIOS),
                   help="scenarios episodes are drawn from (default: the four paper ones)")
    p.add_argument("--crowd", choices=CROWD_MODES, default="scenario",
                   help="whether the people see the robot (default: as the scenario says)")
    p.add_argument("--steps", type=int_at_least(1), default=200_000,
                   help="environment steps (control cycles) to train (default 200000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the episodes and of TD3")
    p.add_argument("--net", type=int_at_least(1), nargs="+", default=[400, 300],
                   help="hidden layer sizes of actor and critics (default 400 300)")
    p.add_argument("--learning-starts", type=int_at_least(0), default=5_000,
                   help="random steps before learning (default 5000)")
    p.add_argument("--batch-size", type=int_at_least(1), default=256,
                   help="minibatch size (default 256)")
    p.add_argument("--learning-rate", type=finite_float, default=3e-4,
                   help="Adam learning rate (default 3e-4)")
    p.add_argument("--action-noise", type=finite_float, default=0.1,
                   help="σ of the Gaussian exploration noise on the [-1, 1] actions (default 0.1)")
    p.add_argument("--checkpoint-every", type=int_at_least(1), default=20_000,
                   help="save the model every this many steps (default 20000)")
    p.add_argument("--fps", type=finite_float, default=15.0, help="rendered depth frames/s")
    p.add_argument("--no-noise", dest="noise", action="store_false",
                   help="render depth without sensor noise")
    p.add_argument("--threads", type=int_at_least(1), default=1,
                   help="torch threads for the gradient steps (default 1)")


def run_train(args: argparse.Namespace) -> dict[str, Any]:
    """Train, save, export; returns the run's summary."""
    try:
        import gymnasium  # noqa: F401 - only checking that the train extra is installed
        import stable_baselines3  # noqa: F401
        import torch
    except ImportError as exc:
        raise UserError(f"safemove train needs the train extra ({exc.name} is missing):"
                        " pip install -e '.[train,export]'") from None
    import numpy as np
    from stable_baselines3 import TD3
    from stable_baselines3.common.callbacks import CheckpointCallback
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.noise import NormalActionNoise

    from sim_stub.train.env import SafeMoveEnv

    spec = load_spec(args.spec)
    loaded = load_config(args.config, args.overrides)
    for name in args.scenarios:
        load_scenario(name)  # a bad name fails here, once, with its message
    out: Path = args.output
    final = out / "td3.zip"
    if final.exists():
        raise UserError(f"{final}: exists; give a new --output directory")
    try:
        (out / "checkpoints").mkdir(parents=True, exist_ok=True)
        (out / "spec.json").write_text(spec.to_json(), encoding="utf-8")
    except OSError as exc:
        raise UserError(f"{out}: cannot write the run directory: {exc}") from None
    logging.getLogger("safemove").setLevel(logging.WARNING)  # per-cycle shield logs
    torch.set_num_threads(args.threads)

    env = Monitor(SafeMoveEnv(args.scenarios, spec, loaded, fps=args.fps, noise=args.noise,
                              crowd=args.crowd),
                  str(out / "monitor.csv"), info_keywords=("outcome",))
    env.reset(seed=args.seed)
    model = TD3("MlpPolicy", env, learning_rate=args.learning_rate,
                learning_starts=args.learning_starts, batch_size=args.batch_size,
                action_noise=NormalActionNoise(np.zeros(2), np.full(2, args.action_noise)),
                policy_kwargs={"net_arch": list(args.net)}, seed=args.seed, device="cpu",
                verbose=0)
    t0 = time.monotonic()
    model.learn(total_timesteps=args.steps, callback=CheckpointCallback(
        args.checkpoint_every, str(out / "checkpoints"), name_prefix="td3"))
    wall = time.monotonic() - t0
    model.save(final)
    returns = env.get_episode_rewards()  # in episode order
    export = _export(final, out / "spec.json", out / "actor.onnx")
    return {"run": str(out), "steps": args.steps, "wall_s": round(wall, 1),
            "steps_per_s": round(args.steps / wall, 1), "episodes": len(returns),
            "outcomes": _outcome_counts(out / "monitor.csv"),
            "mean_return_last_50": (round(float(np.mean(returns[-50:])), 2)
                                    if returns else None),
            "model": str(final), "actor": str(out / "actor.onnx"),
            "export_parity_max_abs": export["provenance"]["parity_max_abs"]}


def _export(model: Path, spec_path: Path, onnx_path: Path) -> dict[str, Any]:
    """The trained actor through `safemove export`'s loader, checks and writer."""
    from export.checkpoint import load_checkpoint
    from export.onnx_export import PARITY_COUNT, export_actor
    from sim_stub.recorded_observations import simulated_observations

    spec = load_spec(str(spec_path))
    actor = load_checkpoint(model, spec)
    recorded, source = simulated_observations(actor.spec, PARITY_COUNT)
    return export_actor(actor, model, onnx_path, recorded, source)


def _outcome_counts(monitor_csv: Path) -> dict[str, int]:
    """Episodes per outcome from the Monitor file (its first line is a JSON header)."""
    counts: dict[str, int] = {}
    lines = monitor_csv.read_text(encoding="utf-8").splitlines()[2:]
    for line in lines:
        outcome = line.rsplit(",", 1)[-1]
        counts[outcome] = counts.get(outcome, 0) + 1
    return counts
