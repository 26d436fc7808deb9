"""The replay buffers `safemove train` runs: uniform replay that also keeps each transition's
teacher label (`TeacherReplayBuffer`), and the paper's reward-ranked ("R_max") replay built on it
(`RewardRankedReplayBuffer`), both stable-baselines3 replay buffers for
`TD3(replay_buffer_class=…, replay_buffer_kwargs={...})`.

Teacher labels: the env gives, in each step's info under `TEACHER_KEY`, the action the teacher
(the DWA baseline) would take in the observation the step acted on, in the [-1, 1] box SB3's
actor and buffer work in. The buffer keeps it beside the transition (NaN where an env gives
none) and every sample carries it (`LabelledSamples.labels`), so TD3+BC (`td3_bc.py`) has a
label for every replayed transition, the actor's own included, whether or not the spec's
observation holds DWA's choice. Uniform sampling draws exactly as SB3's ReplayBuffer does.

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

from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.vec_env import VecNormalize

TEACHER_KEY = "teacher_action"


class LabelledSamples(NamedTuple):
    """SB3's ReplayBufferSamples with the teacher's labels (NaN where none was stored)."""

    observations: th.Tensor
    actions: th.Tensor
    next_observations: th.Tensor
    dones: th.Tensor
    rewards: th.Tensor
    discounts: th.Tensor | None
    labels: th.Tensor


class TeacherReplayBuffer(ReplayBuffer):
    """SB3's uniform ReplayBuffer that keeps each transition's teacher label (module doc)."""

    def __init__(self, buffer_size: int, observation_space: spaces.Space,
                 action_space: spaces.Space, device: th.device | str = "auto", n_envs: int = 1,
                 optimize_memory_usage: bool = False, handle_timeout_termination: bool = True
                 ) -> None:
        if optimize_memory_usage:  # its slot at `pos` holds no valid transition to sample
            raise ValueError(f"{type(self).__name__} does not support"
                             " optimize_memory_usage=True")
        super().__init__(buffer_size, observation_space, action_space, device, n_envs,
                         optimize_memory_usage, handle_timeout_termination)
        self.labels = np.full((self.buffer_size, self.n_envs, self.action_dim), np.nan,
                              dtype=np.float32)

    def add(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray,
            reward: np.ndarray, done: np.ndarray, infos: list[dict[str, Any]]) -> None:
        nan = np.full(self.action_dim, np.nan, dtype=np.float32)
        self.labels[self.pos] = [info.get(TEACHER_KEY, nan) for info in infos]
        super().add(obs, next_obs, action, reward, done, infos)

    def _get_samples(self, batch_inds: np.ndarray,  # type: ignore[override]
                     env: VecNormalize | None = None) -> LabelledSamples:
        # the env of each row drawn as SB3's ReplayBuffer draws it
        envs = np.random.randint(0, high=self.n_envs, size=(len(batch_inds),))
        return self._samples_at(batch_inds, envs, env)

    def _samples_at(self, rows: np.ndarray, envs: np.ndarray,
                    env: VecNormalize | None) -> LabelledSamples:
        """The transitions (and labels) at given (row, env) pairs, as SB3's `_get_samples`."""
        t = self.to_torch
        return LabelledSamples(
            observations=t(self._normalize_obs(self.observations[rows, envs, :], env)),
            actions=t(self.actions[rows, envs, :]),
            next_observations=t(self._normalize_obs(self.next_observations[rows, envs, :], env)),
            # a timeout is no terminal state: its value is bootstrapped
            dones=t((self.dones[rows, envs] * (1 - self.timeouts[rows, envs])).reshape(-1, 1)),
            rewards=t(self._normalize_reward(self.rewards[rows, envs].reshape(-1, 1), env)),
            discounts=None, labels=t(self.labels[rows, envs, :]))


class RewardRankedReplayBuffer(TeacherReplayBuffer):
    """Batches over-sampling the highest-reward transitions (the paper's R_max replay)."""

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

    def sample(self, batch_size: int,  # type: ignore[override]
               env: VecNormalize | None = None) -> LabelledSamples:
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
