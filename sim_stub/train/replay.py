"""Reward-ranked ("R_max") experience replay: a stable-baselines3 replay buffer for
`TD3(replay_buffer_class=RewardRankedReplayBuffer, replay_buffer_kwargs={...})`, to compare with
SB3's uniform ReplayBuffer.

Our reading of the paper's R_max replay: the transitions with the highest rewards are replayed
preferentially, without giving up the rest. Each batch is round(ranked_fraction · batch_size)
transitions drawn uniformly from the top `top_fraction` of the stored transitions ranked by
reward, and the rest uniformly from the whole buffer, as SB3 draws. A top transition is thus
drawn ranked_fraction / top_fraction + (1 − ranked_fraction) times as often as under uniform
replay (5.5 times with the defaults).

Ranking cost: sorting the buffer each sample would cost O(N log N) per gradient step. The top
set (flat indices row · n_envs + env) is instead recomputed with np.argpartition, O(N), at a
sample once `refresh_every` add() calls have passed since the last ranking, or once the buffer
has doubled while it holds fewer rows than that (so the set's size keeps up with a young
buffer, at O(n_envs) per add amortised). Between rankings the set is stale: a new transition
joins it at the next ranking, and a slot the ring overwrote since the last one (at most
refresh_every of buffer_size rows) stays in it until then.

Randomness: numpy's global generator, as SB3's buffers draw (the algorithm's seed seeds it), so
a seeded run is reproducible.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.vec_env import VecNormalize


class RewardRankedReplayBuffer(ReplayBuffer):
    """SB3's ReplayBuffer with batches over-sampling the highest-reward transitions."""

    def __init__(self, buffer_size: int, observation_space: spaces.Space,
                 action_space: spaces.Space, device: th.device | str = "auto", n_envs: int = 1,
                 optimize_memory_usage: bool = False, handle_timeout_termination: bool = True,
                 *, ranked_fraction: float = 0.5, top_fraction: float = 0.1,
                 refresh_every: int = 1000) -> None:
        for name, value in (("ranked_fraction", ranked_fraction),
                            ("top_fraction", top_fraction)):
            if not 0.0 < value <= 1.0:
                raise ValueError(f"RewardRankedReplayBuffer: {name} must be in (0, 1],"
                                 f" got {value}")
        if refresh_every < 1:
            raise ValueError("RewardRankedReplayBuffer: refresh_every must be at least 1,"
                             f" got {refresh_every}")
        if optimize_memory_usage:  # its slot at `pos` holds no valid transition to rank
            raise ValueError("RewardRankedReplayBuffer does not support"
                             " optimize_memory_usage=True")
        super().__init__(buffer_size, observation_space, action_space, device, n_envs,
                         optimize_memory_usage, handle_timeout_termination)
        self.ranked_fraction = ranked_fraction
        self.top_fraction = top_fraction
        self.refresh_every = refresh_every
        self._top = np.empty(0, dtype=np.int64)
        self._rows_ranked = 0
        self._adds_since_ranking = 0

    def add(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray,
            reward: np.ndarray, done: np.ndarray, infos: list[dict[str, Any]]) -> None:
        super().add(obs, next_obs, action, reward, done, infos)
        self._adds_since_ranking += 1

    def reset(self) -> None:
        super().reset()
        self._top = np.empty(0, dtype=np.int64)
        self._rows_ranked = 0
        self._adds_since_ranking = 0

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> ReplayBufferSamples:
        rows_stored = self.buffer_size if self.full else self.pos
        if (len(self._top) == 0
                or self._adds_since_ranking >= min(self.refresh_every, self._rows_ranked)):
            self._rank(rows_stored)
        n_ranked = round(self.ranked_fraction * batch_size)
        top = self._top[np.random.randint(0, len(self._top), size=n_ranked)]
        n_uniform = batch_size - n_ranked
        rows = np.concatenate([top // self.n_envs,
                               np.random.randint(0, rows_stored, size=n_uniform)])
        envs = np.concatenate([top % self.n_envs,
                               np.random.randint(0, self.n_envs, size=n_uniform)])
        return self._samples_at(rows, envs, env)

    def _rank(self, rows_stored: int) -> None:
        """The top set: flat indices of the top_fraction highest rewards stored (at least one)."""
        rewards = self.rewards[:rows_stored].reshape(-1)
        k = max(1, round(self.top_fraction * rewards.size))
        self._top = np.argpartition(rewards, -k)[-k:]
        self._rows_ranked = rows_stored
        self._adds_since_ranking = 0

    def _samples_at(self, rows: np.ndarray, envs: np.ndarray,
                    env: VecNormalize | None) -> ReplayBufferSamples:
        """SB3's `_get_samples` at given (row, env) pairs; its own draws the env of each."""
        data = (
            self._normalize_obs(self.observations[rows, envs, :], env),
            self.actions[rows, envs, :],
            self._normalize_obs(self.next_observations[rows, envs, :], env),
            # a timeout is no terminal state: its value is bootstrapped
            (self.dones[rows, envs] * (1 - self.timeouts[rows, envs])).reshape(-1, 1),
            self._normalize_reward(self.rewards[rows, envs].reshape(-1, 1), env),
        )
        return ReplayBufferSamples(*tuple(map(self.to_torch, data)))
