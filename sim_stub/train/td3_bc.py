"""TD3 whose actor stays near the DWA baseline's choice: TD3+BC (Fujimoto & Gu, "A Minimalist
Approach to Offline Reinforcement Learning", 2021), with DWA as the behaviour to keep close to.

Why: the bc-td3 recipe starts TD3 from a clone of DWA, and TD3 then drifts away from it; the
policies trained on the evasive DWA ended below their teacher in (b)–(d) (README, Evaluation).
TD3+BC adds a behaviour-cloning term to the actor's loss,

    actor loss = −λ · mean Q1(s, π(s)) + mean (π(s) − a_DWA(s))²,   λ = α / mean |Q1(s, π(s))|,

(the squared error averaged over the batch and both action components, as the paper's code), where
λ's normaliser is held constant in the gradient (detached), so α alone sets the balance
whatever the reward's scale: small α keeps the actor on DWA's choice, large α leaves TD3 alone
(the paper's α is 2.5). Unlike offline TD3+BC, the label is not the action stored in the buffer
(which carries exploration noise) but DWA's noise-free choice in that state, which the env gives
with every step and the replay buffer keeps beside the transition (`replay.TeacherReplayBuffer`):
so every replayed transition, the actor's own included, has a label, and all three specs can use
it, `drl` too, whose observation does not hold DWA's choice.

The critics learn as in TD3 (`critic_update`, also the recipe's critic warm-up).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
import torch.nn.functional as F
from stable_baselines3 import TD3
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.utils import polyak_update

from sim_stub.train.replay import LabelledSamples, TeacherReplayBuffer


def critic_update(model: Any, data: ReplayBufferSamples | LabelledSamples) -> float:
    """One TD3 critic step on a minibatch (clipped double Q, target policy smoothing); returns
    the loss. The target networks are not moved here."""
    discounts = data.discounts if data.discounts is not None else model.gamma
    with th.no_grad():
        noise = data.actions.clone().normal_(0, model.target_policy_noise)
        noise = noise.clamp(-model.target_noise_clip, model.target_noise_clip)
        next_actions = (model.actor_target(data.next_observations) + noise).clamp(-1, 1)
        next_q = th.cat(model.critic_target(data.next_observations, next_actions), dim=1)
        next_q, _ = th.min(next_q, dim=1, keepdim=True)
        target = data.rewards + (1 - data.dones) * discounts * next_q
    current = model.critic(data.observations, data.actions)
    loss = sum(F.mse_loss(q, target) for q in current)
    assert isinstance(loss, th.Tensor)
    model.critic.optimizer.zero_grad()
    loss.backward()
    model.critic.optimizer.step()
    return float(loss.item())


class TD3BC(TD3):
    """SB3's TD3 with the behaviour-cloning term on DWA's choice in the actor's loss.

    `bc_alpha` is α above (a default only because SB3's `load` builds the model without
    arguments and then restores the saved one). The replay buffer must keep teacher labels:
    `TeacherReplayBuffer` (the default here) or a subclass."""

    def __init__(self, *args: Any, bc_alpha: float = 2.5, **kwargs: Any) -> None:
        if not bc_alpha > 0.0:
            raise ValueError(f"bc_alpha must be > 0, got {bc_alpha}")
        self.bc_alpha = bc_alpha
        if kwargs.get("replay_buffer_class") is None:
            kwargs["replay_buffer_class"] = TeacherReplayBuffer
        elif not issubclass(kwargs["replay_buffer_class"], TeacherReplayBuffer):
            raise ValueError("TD3BC needs a replay buffer that keeps teacher labels"
                             f" (TeacherReplayBuffer), got {kwargs['replay_buffer_class']}")
        super().__init__(*args, **kwargs)

    def actor_loss(self, observations: th.Tensor, labels: th.Tensor) -> tuple[th.Tensor, float]:
        """TD3+BC's actor loss on a minibatch and its cloning part (mean squared error)."""
        if th.isnan(labels).any():
            raise RuntimeError("TD3BC: a replayed transition has no teacher label (the env"
                               " gave no info['teacher_action'])")
        action = self.actor(observations)
        q = self.critic.q1_forward(observations, action)
        lam = self.bc_alpha / q.abs().mean().detach().clamp_min(1e-6)
        bc = F.mse_loss(action, labels.clamp(-1.0, 1.0))
        return -lam * q.mean() + bc, float(bc.item())

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
        actor_losses, bc_losses, critic_losses = [], [], []
        for _ in range(gradient_steps):
            self._n_updates += 1
            data = self.replay_buffer.sample(  # type: ignore[union-attr]
                batch_size, env=self._vec_normalize_env)
            assert isinstance(data, LabelledSamples)  # __init__ made it a TeacherReplayBuffer
            critic_losses.append(critic_update(self, data))
            if self._n_updates % self.policy_delay:
                continue  # TD3's delayed policy update
            loss, bc = self.actor_loss(data.observations, data.labels)
            self.actor.optimizer.zero_grad()
            loss.backward()
            self.actor.optimizer.step()
            actor_losses.append(loss.item())
            bc_losses.append(bc)
            polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
            polyak_update(self.actor.parameters(), self.actor_target.parameters(), self.tau)
            polyak_update(self.critic_batch_norm_stats, self.critic_batch_norm_stats_target, 1.0)
            polyak_update(self.actor_batch_norm_stats, self.actor_batch_norm_stats_target, 1.0)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        if actor_losses:
            self.logger.record("train/actor_loss", np.mean(actor_losses))
            self.logger.record("train/bc_loss", np.mean(bc_losses))
        self.logger.record("train/critic_loss", np.mean(critic_losses))
