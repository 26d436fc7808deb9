"""The start of the shipped training recipe, before TD3 runs on its own: demonstrations by the
DWA baseline, behaviour cloning of the actor on them, and a warm-up of the critics.

Why: TD3 from random actions on this simulator spent its whole budget (90,000 steps, 53 min)
without reaching a goal: an episode is hundreds of cycles, and a random actor almost never
finds the goal bonus. The DWA baseline reaches most goals, and every observation comes with
DWA's choice (the planning step runs DWA each cycle whatever the spec), so:
1. Demonstrations: the envs are driven by DWA's choice plus Gaussian noise (σ in action units;
   the noise makes the demonstrations visit the states just off DWA's path that the cloned
   actor will reach, as in DART, Laskey et al. 2017). Every transition goes into TD3's replay
   buffer with the action executed, and DWA's noise-free choice is kept as the clone's label.
2. Behaviour cloning: the actor (and its target) regress DWA's choice on the demonstrations'
   observations (mean squared error, Adam, minibatches).
3. Critic warm-up: the critics learn the cloned actor's values from the demonstrations by TD3's
   own target (clipped double Q, target policy smoothing) with the actor frozen, so that the
   first actor updates follow a critic that knows the task instead of a random one.
The TD3 run that follows starts from this actor, these critics and this buffer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from sim_stub.progress import Progress


@dataclass(frozen=True)
class Demonstrations:
    observations: np.ndarray  # (M, obs) float32
    expert_actions: np.ndarray  # (M, 2) DWA's choice, noise-free
    episodes: int
    successes: int


def collect_demonstrations(model: Any, steps: int, noise_sigma: float, seed: int
                           ) -> Demonstrations:
    """Drive `model.env` (a VecEnv of SafeMoveEnv) with DWA's choice plus noise for at least
    `steps` transitions, each added to `model.replay_buffer` as TD3 would add its own."""
    venv = model.get_env()
    n = venv.num_envs
    rng = np.random.default_rng(seed)
    low, high = venv.action_space.low, venv.action_space.high
    obs = venv.reset()
    observations, labels = [], []
    episodes = successes = 0
    with Progress(steps, "demonstrations", "step", line_every=max(steps // 5, 1)) as progress:
        while len(observations) * n < steps:
            expert = np.stack(venv.env_method("expert_action"))
            action = np.clip(expert + rng.normal(0.0, noise_sigma, expert.shape), low, high)
            new_obs, rewards, dones, infos = venv.step(action.astype(np.float32))
            next_obs = new_obs.copy()
            for i, done in enumerate(dones):
                if done:  # the VecEnv has reset it: the transition ends in the terminal one
                    next_obs[i] = infos[i]["terminal_observation"]
                    episodes += 1
                    successes += infos[i].get("outcome") == "success"
            # the buffer and the actor work in the policy's [-1, 1] box, as TD3 stores them
            model.replay_buffer.add(obs, next_obs, model.policy.scale_action(action), rewards,
                                    dones, infos)
            observations.append(obs)
            labels.append(model.policy.scale_action(expert))
            obs = new_obs
            progress.advance(n, episodes=episodes)
    return Demonstrations(np.concatenate(observations).astype(np.float32),
                          np.concatenate(labels).astype(np.float32), episodes, successes)


def clone_behaviour(model: Any, demos: Demonstrations, epochs: int, batch_size: int,
                    learning_rate: float, seed: int) -> float:
    """Regress the actor on DWA's choices; the target actor is set to the result. Returns the
    last epoch's mean squared error (action units)."""
    import torch

    actor = model.actor
    optimiser = torch.optim.Adam(actor.parameters(), lr=learning_rate)
    x = torch.as_tensor(demos.observations)
    y = torch.as_tensor(demos.expert_actions)
    gen = torch.Generator().manual_seed(seed)
    loss_sum = 0.0
    actor.set_training_mode(True)
    for _ in range(epochs):
        order = torch.randperm(len(x), generator=gen)
        loss_sum, batches = 0.0, 0
        for start in range(0, len(x), batch_size):
            idx = order[start:start + batch_size]
            loss = torch.nn.functional.mse_loss(actor(x[idx]), y[idx])
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            loss_sum += loss.item()
            batches += 1
        loss_sum /= max(batches, 1)
    actor.set_training_mode(False)
    model.actor_target.load_state_dict(actor.state_dict())
    return loss_sum


def warm_up_critics(model: Any, gradient_steps: int) -> float | None:
    """TD3's critic update (clipped double Q with target policy smoothing, Polyak-averaged
    targets) with the actor frozen; returns the mean critic loss of the last 100 steps (None
    without steps)."""
    from stable_baselines3.common.utils import polyak_update

    from sim_stub.train.td3_bc import critic_update

    model.critic.set_training_mode(True)
    losses: list[float] = []
    for _ in range(gradient_steps):
        data = model.replay_buffer.sample(model.batch_size, env=model._vec_normalize_env)
        losses.append(critic_update(model, data))
        polyak_update(model.critic.parameters(), model.critic_target.parameters(), model.tau)
        polyak_update(model.critic_batch_norm_stats, model.critic_batch_norm_stats_target, 1.0)
    model.critic.set_training_mode(False)
    return float(np.mean(losses[-100:])) if losses else None
