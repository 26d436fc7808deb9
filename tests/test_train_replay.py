"""The replay buffers: teacher labels kept beside each transition (uniform replay drawing as
SB3's does), and reward-ranked ("R_max") replay: batch proportions, the (row, env) bookkeeping
with several envs, timeouts, lazy ranking, reproducibility, and TD3 training with it."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gymnasium")
pytest.importorskip("stable_baselines3")

import gymnasium as gym
from stable_baselines3 import TD3
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.vec_env import DummyVecEnv

from sim_stub.train.replay import TEACHER_KEY, RewardRankedReplayBuffer, TeacherReplayBuffer

OBS = gym.spaces.Box(-1e6, 1e6, (1,), np.float32)
ACT = gym.spaces.Box(-1e6, 1e6, (1,), np.float32)


def _buffer(rows: int, n_envs: int, **kwargs) -> RewardRankedReplayBuffer:
    return RewardRankedReplayBuffer(rows * n_envs, OBS, ACT, device="cpu", n_envs=n_envs,
                                    **kwargs)


def _add(buf: RewardRankedReplayBuffer, rewards: np.ndarray, done: bool = False,
         timeout: bool = False) -> None:
    """One add() of one transition per env whose obs, next obs and action encode its reward."""
    r = np.asarray(rewards, dtype=np.float32)
    col = r.reshape(-1, 1)
    buf.add(col, col + 0.5, col - 0.5, r, np.full(len(r), done),
            [{"TimeLimit.truncated": timeout} for _ in r])


def _rewards(buf: RewardRankedReplayBuffer, batches: int, size: int) -> np.ndarray:
    return np.concatenate([buf.sample(size).rewards.numpy().ravel() for _ in range(batches)])


def test_top_transitions_are_over_represented_by_the_expected_proportion():
    # 1000 rows × 2 envs, rewards a permutation of 0..1999: the top 10 % are those >= 1800
    buf = _buffer(1000, 2)
    rewards = np.random.default_rng(0).permutation(2000).reshape(1000, 2)
    for row in rewards:
        _add(buf, row)
    np.random.seed(0)
    drawn = _rewards(buf, 100, 1000)
    # half the batch from the top set, the other half uniform (10 % of it top): 55 % top,
    # binomial std of the uniform half's share 0.0013: the margins are > 10 σ
    top = drawn >= 1800
    assert 0.535 < top.mean() < 0.565
    # within the top set, uniform: each of its 200 transitions drawn ~275 times
    counts = np.bincount(drawn[top].astype(int) - 1800, minlength=200)
    assert counts.min() > 150 and counts.max() < 400
    # the rest is uniform over the others: each decile of 0..1799 holds about a ninth of it
    deciles = np.bincount(drawn[~top].astype(int) // 200, minlength=9)
    assert np.all(np.abs(deciles / (~top).sum() - 1 / 9) < 0.02)


def _labelled(buf: ReplayBuffer, i: int, n_envs: int) -> None:
    """One add() whose transitions encode (row i, env e) as i + e / 10, labelled −that."""
    x = np.array([i + e / 10 for e in range(n_envs)], dtype=np.float32)
    buf.add(x.reshape(-1, 1), x.reshape(-1, 1), x.reshape(-1, 1), x, np.zeros(n_envs),
            [{TEACHER_KEY: np.array([-v], dtype=np.float32)} for v in x])


def test_uniform_replay_keeps_each_transitions_label_and_draws_as_sb3_does():
    ours = TeacherReplayBuffer(60, OBS, ACT, device="cpu", n_envs=3)
    sb3 = ReplayBuffer(60, OBS, ACT, device="cpu", n_envs=3)
    for i in range(20):
        _labelled(ours, i, 3)
        _labelled(sb3, i, 3)
    np.random.seed(5)
    s = ours.sample(256)
    np.random.seed(5)
    reference = sb3.sample(256)  # a plain run's batches are unchanged by the labels
    for name in ("observations", "actions", "next_observations", "dones", "rewards"):
        assert np.array_equal(getattr(s, name).numpy(), getattr(reference, name).numpy()), name
    x = s.observations.numpy().ravel()
    assert np.array_equal(s.labels.numpy().ravel(), -x)
    assert len(set(np.round(x % 1, 1))) == 3  # all three envs drawn


def test_a_transition_without_a_label_is_kept_with_nan():
    buf = TeacherReplayBuffer(4, OBS, ACT, device="cpu", n_envs=1)
    buf.add(np.zeros((1, 1)), np.zeros((1, 1)), np.zeros((1, 1)), np.zeros(1), np.zeros(1),
            [{}])
    assert np.isnan(buf.sample(8).labels.numpy()).all()


def test_ranked_samples_carry_their_transitions_labels():
    buf = _buffer(30, 2, top_fraction=0.2)
    for i in range(30):
        _labelled(buf, i, 2)
    np.random.seed(6)
    s = buf.sample(256)
    x = s.rewards.numpy().ravel()
    assert np.array_equal(s.labels.numpy().ravel(), -x)


def test_each_sample_is_one_stored_transition_across_envs():
    buf = _buffer(50, 3, top_fraction=0.2)
    for i in range(50):
        _add(buf, [3 * i, 3 * i + 1, 3 * i + 2])
    np.random.seed(1)
    s = buf.sample(512)
    r = s.rewards.numpy().ravel()
    assert np.array_equal(s.observations.numpy().ravel(), r)
    assert np.array_equal(s.next_observations.numpy().ravel(), r + 0.5)
    assert np.array_equal(s.actions.numpy().ravel(), r - 0.5)
    assert set(r.astype(int)) <= set(range(150)) and len(set(r.astype(int))) > 100


def test_timeouts_are_not_terminal_and_terminations_are():
    buf = _buffer(4, 2, top_fraction=1.0)
    _add(buf, [1.0, 2.0], done=True, timeout=True)
    _add(buf, [3.0, 4.0], done=True)
    np.random.seed(2)
    s = buf.sample(256)
    r, done = s.rewards.numpy().ravel(), s.dones.numpy().ravel()
    assert np.all(done[r <= 2.0] == 0.0) and np.all(done[r >= 3.0] == 1.0)


def test_ranking_is_lazy_and_catches_up_after_refresh_every_adds():
    buf = _buffer(2000, 1, refresh_every=100)
    for i in range(1000):
        _add(buf, [float(i)])
    np.random.seed(3)
    buf.sample(10)  # ranks: the top 100 are 900..999
    for _ in range(99):
        _add(buf, [5000.0])
    # not ranked yet: the new ones come only through the uniform half (99 of 1099 rows)
    assert (_rewards(buf, 20, 1000) == 5000.0).mean() < 0.1
    _add(buf, [5000.0])
    # ranked again: 100 of the top 110, plus the uniform half's 100 of 1100, about 50 %
    assert (_rewards(buf, 20, 1000) == 5000.0).mean() > 0.4


def test_same_numpy_seed_same_batches():
    a, b = _buffer(100, 2), _buffer(100, 2)
    for i in range(100):
        _add(a, [i, -i])
        _add(b, [i, -i])
    np.random.seed(4)
    first = _rewards(a, 5, 64)
    np.random.seed(4)
    assert np.array_equal(first, _rewards(b, 5, 64))


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"ranked_fraction": 0.0}, "ranked_fraction must be in"),
    ({"ranked_fraction": 1.5}, "ranked_fraction must be in"),
    ({"ranked_fraction": float("nan")}, "ranked_fraction must be in"),
    ({"top_fraction": -0.1}, "top_fraction must be in"),
    ({"top_fraction": 1.01}, "top_fraction must be in"),
    ({"refresh_every": 0}, "refresh_every must be at least 1"),
    ({"optimize_memory_usage": True, "handle_timeout_termination": False},
     "optimize_memory_usage"),
])
def test_invalid_parameters_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        _buffer(10, 1, **kwargs)


@pytest.mark.parametrize("n_envs", [1, 2])
def test_td3_trains_with_it(n_envs):
    # 300 steps in all, Pendulum's episodes cut at 50 steps: the buffer stores timeouts
    env = DummyVecEnv([lambda: gym.make("Pendulum-v1", max_episode_steps=50)] * n_envs)
    model = TD3("MlpPolicy", env, replay_buffer_class=RewardRankedReplayBuffer,
                replay_buffer_kwargs={"ranked_fraction": 0.5, "top_fraction": 0.2,
                                      "refresh_every": 50},
                learning_starts=100, batch_size=32, policy_kwargs={"net_arch": [16, 16]},
                seed=0, device="cpu")
    model.learn(total_timesteps=300)
    buf = model.replay_buffer
    assert isinstance(buf, RewardRankedReplayBuffer)
    assert buf.pos * n_envs == model.num_timesteps == 300
    assert len(buf._top) > 0  # it was sampled, so ranked
    assert buf.timeouts[:buf.pos].sum() == 300 // 50
