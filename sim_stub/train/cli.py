"""`safemove train -o RUN_DIR`: TD3 (stable-baselines3) on the lock-stepped robot, then export.

Writes into RUN_DIR: `spec.json` (the observation spec trained on), `monitor.csv` (one row per
episode: return, length, wall time, outcome; SB3's Monitor format), `learning_curve.png`
(success rate and return against env steps), `checkpoints/` (every --checkpoint-every steps,
and `bc.zip` after the bc-td3 recipe's cloning and critic warm-up), `td3.zip` (the final model),
`actor.onnx` (the final actor, exported and parity-checked by `safemove export`'s code) and
`summary.json` (the figures, every setting and the commit). Importing this module does not
import torch, gymnasium or stable-baselines3 (the robot image has none); running it does, and
says how to install them when they are missing.

Its defaults are the shipped recipe (README, Training): `safemove train -o RUN --spec VARIANT
--seed 0` trains as the shipped policies were trained. The episodes run in --envs worker
processes (`vec_env.make_vec_env`), so the simulation is shared out; the gradient steps stay in
this process, between VecEnv steps. Each VecEnv step collects one transition per env and is
followed by as many gradient steps (gradient_steps=-1): the update-to-data ratio stays one
whatever N is, which also means that past --learning-starts the gradient steps bound the rate
more than the simulation does. A run is reproducible from (--seed, --envs); the same seed with
another N gives other episodes.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from collections import Counter
from dataclasses import asdict
from pathlib import Path
from typing import Any

from runtime.cli.args import (
    add_config_args,
    finite_float,
    int_at_least,
    non_negative_float,
    positive_float,
)
from runtime.config.settings import load_config
from runtime.errors import UserError
from runtime.jobs.trained_settings import RECORD_KEY, decision_settings
from runtime.policy.obs_spec import PRESETS, load_spec
from sim_stub.progress import Progress
from sim_stub.provenance import source_commit
from sim_stub.scenario import CROWD_MODES, load_scenario
from sim_stub.train.reward import KINDS, RewardConfig

# The shipped recipe is the default: `safemove train -o RUN --spec VARIANT` trains the shipped
# policies' way (README, Training).
SHIPPED_SCENARIOS = ("paper_cal_a", "paper_cal_b", "paper_cal_c", "paper_cal_d",
                     "paper_a", "paper_b", "paper_c", "paper_d")
SHIPPED_BC_ALPHA = 2.5  # TD3+BC's α with the bc-td3 recipe (Fujimoto & Gu's value)
SHIPPED_ENVS = 2  # the episodes repeat from (--seed, --envs), so the recipe fixes both
RECIPES = ("bc-td3", "td3")
REPLAYS = ("uniform", "rmax")


def alpha_or_off(text: str) -> float | str:
    """argparse type of --bc-alpha: a weight above 0, or "off" (plain TD3)."""
    if text == "off":
        return text
    try:
        return positive_float(text)
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"{exc} (a weight above 0, or off)") from None


def bc_alpha(args: argparse.Namespace) -> float | None:
    """TD3+BC's α the command line asks for; None: plain TD3. Unset, the recipe decides:
    SHIPPED_BC_ALPHA after bc-td3's demonstrations, plain TD3 with --recipe td3."""
    if args.bc_alpha == "off":
        return None
    if args.bc_alpha is None:
        return SHIPPED_BC_ALPHA if args.recipe == "bc-td3" else None
    return float(args.bc_alpha)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_config_args(p)
    p.add_argument("-o", "--output", type=Path, required=True,
                   help="run directory (created; an existing td3.zip there is not overwritten)")
    p.add_argument("--spec", default="safemove", metavar="PRESET|FILE.json",
                   help=f"observation spec: a preset ({', '.join(PRESETS)}) or a spec JSON file"
                        " (default safemove)")
    p.add_argument("--scenarios", nargs="+", default=list(SHIPPED_SCENARIOS),
                   help="scenarios episodes are drawn from (default: the calibrated and the"
                        " dense paper ones, paper_cal_a-d and paper_a-d)")
    p.add_argument("--crowd", choices=(*CROWD_MODES, "mixed"), default="mixed",
                   help="whether the people see the robot (scenario: as the scenario says;"
                        " mixed: each episode draws reactive or oblivious; default mixed)")
    p.add_argument("--surround-people", action="store_true",
                   help="what if the robot saw every person around it: train with the people"
                        " all around as tracks from ground truth (as eval --surround-people);"
                        " such a run cannot ship, no robot has that sensor")
    p.add_argument("--steps", type=int_at_least(1), default=160_000,
                   help="TD3's environment steps (control cycles), after the demonstrations"
                        " (default 160000)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the episodes (env i: seed + i) and of TD3")
    p.add_argument("--envs", type=int_at_least(1), default=SHIPPED_ENVS,
                   help="environments, each in its own worker process; another number gives"
                        " other episodes from the same seed, and past the demonstrations the"
                        f" gradient steps bound the rate, not the workers (default {SHIPPED_ENVS})")
    p.add_argument("--net", type=int_at_least(1), nargs="+", default=[400, 300],
                   help="hidden layer sizes of actor and critics (default 400 300)")
    p.add_argument("--learning-starts", type=int_at_least(0), default=5_000,
                   help="random steps before learning (default 5000)")
    p.add_argument("--batch-size", type=int_at_least(1), default=256,
                   help="minibatch size (default 256)")
    p.add_argument("--learning-rate", type=finite_float, default=3e-4,
                   help="Adam learning rate (default 3e-4)")
    p.add_argument("--action-noise", type=non_negative_float, default=0.1,
                   help="σ of the Gaussian exploration noise on the [-1, 1] actions (default 0.1)")
    p.add_argument("--checkpoint-every", type=int_at_least(1), default=20_000,
                   help="save the model about every this many steps, a multiple of --envs"
                        " (default 20000)")
    p.add_argument("--fps", type=finite_float, default=15.0, help="rendered depth frames/s")
    p.add_argument("--no-noise", dest="noise", action="store_false",
                   help="render depth without sensor noise")
    p.add_argument("--threads", type=int_at_least(1), default=1,
                   help="torch threads for the gradient steps (default 1)")
    p.add_argument("--reward", choices=KINDS, default="project",
                   help="project: progress, time, success, collision and shield terms; paper:"
                        " the paper's R_g + R_b + R_yaw (sim_stub/train/reward.py; default"
                        " project)")
    p.add_argument("--shield-penalty", type=non_negative_float, default=None, metavar="W",
                   help="project reward: the penalty for each cycle the shield changed the"
                        f" actor's command (default {RewardConfig().shield_change})")
    p.add_argument("--replay", choices=REPLAYS, default="uniform",
                   help="uniform: drawn as SB3's replay buffer draws; rmax: the paper's"
                        " reward-ranked replay, half of each batch from the top-rewarded tenth"
                        " (default uniform)")
    p.add_argument("--recipe", choices=RECIPES, default="bc-td3",
                   help="bc-td3 (the shipped recipe): DWA demonstrations, behaviour cloning and a"
                        " critic warm-up before TD3 (sim_stub/train/recipe.py); td3: TD3 from"
                        " random actions (default bc-td3)")
    p.add_argument("--demo-steps", type=int_at_least(1), default=40_000,
                   help="bc-td3: transitions driven by DWA's choice plus noise (default 40000)")
    p.add_argument("--demo-noise", type=non_negative_float, default=0.2,
                   help="bc-td3: σ of the noise on DWA's choice, action units (default 0.2)")
    p.add_argument("--bc-epochs", type=int_at_least(0), default=30,
                   help="bc-td3: behaviour-cloning passes over the demonstrations (default 30)")
    p.add_argument("--critic-warmup", type=int_at_least(0), default=5_000,
                   help="bc-td3: critic-only gradient steps before TD3 (default 5000)")
    p.add_argument("--bc-alpha", type=alpha_or_off, default=None, metavar="ALPHA|off",
                   help="TD3+BC: keep the actor near DWA's choice during TD3, actor loss"
                        " -ALPHA*Q/mean|Q| + (action - DWA's)^2 (sim_stub/train/td3_bc.py);"
                        " smaller stays closer to DWA; off: plain TD3 (default"
                        f" {SHIPPED_BC_ALPHA} with bc-td3, as the TD3+BC paper; off with td3)")


def reward_config(args: argparse.Namespace) -> RewardConfig:
    """The reward the command line asks for; a shield penalty with the paper's reward, which has
    no shield term, is refused rather than dropped."""
    if args.shield_penalty is None:
        return RewardConfig(kind=args.reward)
    if args.reward != "project":
        raise UserError(f"--shield-penalty: the {args.reward} reward has no shield term"
                        " (only --reward project)")
    return RewardConfig(kind=args.reward, shield_change=args.shield_penalty)


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
    from stable_baselines3.common.callbacks import CallbackList, CheckpointCallback

    from export.ship import stamp
    from sim_stub.train.callbacks import ProgressCallback
    from sim_stub.train.curves import plot_curves, read_monitor
    from sim_stub.train.ship import training_record
    from sim_stub.train.vec_env import make_vec_env

    spec = load_spec(args.spec)
    reward = reward_config(args)
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

    commit = source_commit()  # the code that runs: taken before the hours of training
    n = args.envs
    env = make_vec_env(args.scenarios, spec, loaded, n, args.seed, fps=args.fps,
                       noise=args.noise, crowd=args.crowd, surround_people=args.surround_people,
                       reward=reward,
                       monitor_path=out / "monitor.csv")
    model = make_td3(env, args)
    t0 = time.monotonic()
    start = _start(model, args, out) if args.recipe == "bc-td3" else {}
    # SB3 stops at the first whole VecEnv step at or past --steps
    steps = math.ceil(args.steps / n) * n
    checkpoints = CheckpointCallback(max(args.checkpoint_every // n, 1),
                                     str(out / "checkpoints"), name_prefix="td3")
    with Progress(steps, "train", "step", line_every=max(steps // 10, 1)) as progress:
        model.learn(total_timesteps=args.steps,
                    callback=CallbackList([checkpoints, ProgressCallback(progress)]))
    wall = time.monotonic() - t0
    env.close()  # on an error, the workers (daemons) end with this process
    model.save(final)
    episodes = read_monitor(out / "monitor.csv")
    returns = [float(row["r"]) for row in episodes]
    td3 = episodes[start.get("demo_episodes", 0):]
    export = _export(final, out / "spec.json", out / "actor.onnx")
    plot_curves({spec.name: out / "monitor.csv"}, out / "learning_curve.png",
                td3_from=start.get("demo_steps"))
    total = model.num_timesteps + start.get("demo_steps", 0)
    summary = {"run": str(out), "recipe": args.recipe, **start, "steps": model.num_timesteps,
               "total_env_steps": total, "envs": n, "wall_s": round(wall, 1),
               "steps_per_s": round(total / wall, 1), "episodes": len(episodes),
               "outcomes": dict(Counter(row["outcome"] for row in episodes)),
               # the monitor holds the demonstrations' episodes first, then TD3's
               "td3_episodes": len(td3), "td3_outcomes": dict(Counter(r["outcome"] for r in td3)),
               "mean_return_last_50": (round(float(np.mean(returns[-50:])), 2)
                                       if returns else None),
               "model": str(final), "actor": str(out / "actor.onnx"),
               "export_parity_max_abs": export["provenance"]["parity_max_abs"]}
    # how the run was made, beside what it made: the record a shipped policy carries
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()
                if k != "func"}
    settings["bc_alpha"] = bc_alpha(args)  # as resolved: None is plain TD3, as in older records
    record = {**summary, "settings": settings, "reward": asdict(reward), "commit": commit,
              RECORD_KEY: decision_settings(loaded.config)}
    (out / "summary.json").write_text(json.dumps(record, indent=1), encoding="utf-8")
    # the actor says how it was made before it is evaluated or shipped (`safemove ship`
    # replaces the record with the same and adds the evaluations)
    stamp(out / "actor.onnx", training_record(record), {"tables": []})
    return summary


def _start(model: Any, args: argparse.Namespace, out: Path) -> dict[str, Any]:
    """The bc-td3 recipe's phases before TD3 (sim_stub/train/recipe.py); the cloned,
    warmed-up model is saved as checkpoints/bc.zip (a candidate like any checkpoint)."""
    from sim_stub.train.recipe import clone_behaviour, collect_demonstrations, warm_up_critics

    t0 = time.monotonic()
    demos = collect_demonstrations(model, args.demo_steps, args.demo_noise, args.seed)
    t1 = time.monotonic()
    bc_mse = clone_behaviour(model, demos, args.bc_epochs, args.batch_size, args.learning_rate,
                             args.seed)
    t2 = time.monotonic()
    critic_loss = warm_up_critics(model, args.critic_warmup)
    t3 = time.monotonic()
    model.save(out / "checkpoints" / "bc.zip")
    model.learning_starts = 0  # the buffer holds the demonstrations
    return {"demo_steps": len(demos.observations), "demo_episodes": demos.episodes,
            "demo_successes": demos.successes, "bc_mse": round(bc_mse, 5),
            "critic_warmup_loss": None if critic_loss is None else round(critic_loss, 4),
            "phase_wall_s": {"demonstrations": round(t1 - t0, 1), "cloning": round(t2 - t1, 1),
                             "critic_warmup": round(t3 - t2, 1)}}


def make_td3(env: Any, args: argparse.Namespace) -> Any:
    """TD3 as `safemove train` runs it on `env` (a VecEnv of SafeMoveEnv): one gradient step per
    transition collected (gradient_steps=-1), whatever the number of envs; TD3+BC on DWA's
    choice unless --bc-alpha is off (`bc_alpha`). The replay buffer keeps DWA's choice with
    every transition."""
    import numpy as np
    from stable_baselines3 import TD3
    from stable_baselines3.common.noise import NormalActionNoise

    from sim_stub.train.replay import RewardRankedReplayBuffer, TeacherReplayBuffer
    from sim_stub.train.td3_bc import TD3BC

    replay = RewardRankedReplayBuffer if args.replay == "rmax" else TeacherReplayBuffer
    settings: dict[str, Any] = {
        "learning_rate": args.learning_rate, "replay_buffer_class": replay,
        "learning_starts": args.learning_starts, "batch_size": args.batch_size,
        "gradient_steps": -1,
        "action_noise": NormalActionNoise(np.zeros(2), np.full(2, args.action_noise)),
        "policy_kwargs": {"net_arch": list(args.net)}, "seed": args.seed, "device": "cpu",
        "verbose": 0}
    alpha = bc_alpha(args)
    if alpha is None:
        return TD3("MlpPolicy", env, **settings)
    return TD3BC("MlpPolicy", env, bc_alpha=alpha, **settings)


def _export(model: Path, spec_path: Path, onnx_path: Path) -> dict[str, Any]:
    """The trained actor through `safemove export`'s loader, checks and writer."""
    from export.checkpoint import load_checkpoint
    from export.onnx_export import PARITY_COUNT, export_actor
    from sim_stub.recorded_observations import simulated_observations

    spec = load_spec(str(spec_path))
    actor = load_checkpoint(model, spec)
    recorded, source = simulated_observations(actor.spec, PARITY_COUNT)
    return export_actor(actor, model, onnx_path, recorded, source)

