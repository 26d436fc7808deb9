"""TD3+BC on DWA's choice (`safemove train --bc-alpha`): the env gives DWA's choice with every
step, the replay buffer keeps it as the label, and a small α holds the actor on it, for every
spec, `drl` (whose observation does not hold DWA's choice) included."""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

import gymnasium as gym
from stable_baselines3.common.vec_env import DummyVecEnv

from runtime.config.settings import load_config
from runtime.policy.obs_spec import PRESETS
from sim_stub.train.cli import add_arguments, make_td3
from sim_stub.train.env import SafeMoveEnv
from sim_stub.train.replay import TEACHER_KEY, RewardRankedReplayBuffer, TeacherReplayBuffer
from sim_stub.train.td3_bc import TD3BC

LABEL = np.array([0.5, -0.5], dtype=np.float32)


class LabelledEnv(gym.Env):
    """Test double: random observations; each step's info gives a fixed 'DWA choice' (none
    when `label` is None)."""

    observation_space = gym.spaces.Box(-2.0, 2.0, (4,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def __init__(self, label: np.ndarray | None = LABEL) -> None:
        self.label = label
        self.t = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self.t = 0
        return self.observation_space.sample(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self.t += 1
        reward = float(action[0])  # TD3 alone would drive a[0] to +1, away from the label
        info = {} if self.label is None else {TEACHER_KEY: self.label}
        return self.observation_space.sample(), reward, False, self.t >= 10, info


def _model(alpha: float, label: np.ndarray | None = LABEL, **kw: Any) -> TD3BC:
    return TD3BC("MlpPolicy", DummyVecEnv([lambda: LabelledEnv(label)]), bc_alpha=alpha,
                 learning_starts=100, batch_size=32, learning_rate=3e-3,
                 policy_kwargs={"net_arch": [32, 32]}, seed=0, device="cpu", **kw)


def _actions(model: TD3BC) -> np.ndarray:
    """The deterministic actions on 64 fresh observations like the env's."""
    obs = np.random.default_rng(1).uniform(-2.0, 2.0, (64, 4)).astype(np.float32)
    actions, _ = model.predict(obs, deterministic=True)
    return actions


@pytest.mark.parametrize("preset", ["safemove", "drl"])
def test_each_step_gives_dwas_choice_in_the_observation_it_acted_on(tmp_path, preset):
    from rooms import write_room

    crowd = "{count: 2, reactive: false, speed_range: [0.5, 0.8], radius: 0.3}"
    room = write_room(tmp_path, "room", goal=(3.0, 1.0), time_limit_s=10.0, crowd=crowd)
    spec = PRESETS[preset]
    env = SafeMoveEnv([room], spec, load_config(None, []), noise=False)
    env.reset(seed=3)
    dwa = next(start for kind, start, _ in PRESETS["safemove"].layout() if kind == "dwa")
    twin = SafeMoveEnv([room], PRESETS["safemove"], load_config(None, []), noise=False)
    twin_obs, _ = twin.reset(seed=3)  # the same episode, observed with the dwa block
    labels = []
    for k in range(40):
        expert = env.expert_action()
        action = np.array([0.6, 0.4 * np.sin(k / 5)], dtype=np.float32)
        _, _, terminated, truncated, info = env.step(action)
        label = info[TEACHER_KEY]
        assert label.dtype == np.float32 and label.shape == (2,)
        # the observation's own features, to the bit, and the demonstrations' expert action
        assert np.array_equal(label, twin_obs[dwa:dwa + 2])
        assert np.allclose(label, expert, atol=1e-6)
        labels.append(label)
        twin_obs, *_ = twin.step(action)
        if terminated or truncated:
            break
    assert len({tuple(x) for x in labels}) > 5  # DWA's choice changes as the robot moves


def test_a_small_alpha_holds_the_actor_on_dwas_choice():
    model = _model(alpha=1e-3)
    model.learn(total_timesteps=600)
    assert np.abs(_actions(model) - LABEL).max() < 0.1
    assert model.logger.name_to_value["train/bc_loss"] < 0.01


def test_a_large_alpha_lets_the_critic_win():
    model = _model(alpha=1e3)
    model.learn(total_timesteps=600)
    assert _actions(model)[:, 0].mean() > 0.8  # the reward's pull toward a[0] = +1


def test_labels_outside_the_box_are_clipped_to_it():
    model = _model(alpha=1e-3, label=np.array([1.8, -1.8], dtype=np.float32))
    model.learn(total_timesteps=300)
    assert model.logger.name_to_value["train/bc_loss"] < 0.05  # unreachable at ±1.8


def test_alpha_must_pull_and_every_transition_have_a_label():
    with pytest.raises(ValueError, match="bc_alpha must be > 0"):
        _model(alpha=0.0)
    from stable_baselines3.common.buffers import ReplayBuffer

    with pytest.raises(ValueError, match="keeps teacher labels"):
        _model(alpha=2.5, replay_buffer_class=ReplayBuffer)
    with pytest.raises(RuntimeError, match="has no teacher label"):
        _model(alpha=2.5, label=None).learn(total_timesteps=150)


@pytest.mark.parametrize("preset", ["safemove", "drl_dwa", "drl"])
def test_make_td3_keeps_labels_and_builds_td3_bc_unless_off(preset):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    env = DummyVecEnv([LabelledEnv])

    def model(*extra):
        return make_td3(env, parser.parse_args(["-o", "run", "--spec", preset, "--net", "8",
                                                *extra]))

    shipped = model()  # the bc-td3 recipe's default: TD3+BC at 2.5
    assert isinstance(shipped, TD3BC) and shipped.bc_alpha == 2.5
    assert isinstance(shipped.replay_buffer, TeacherReplayBuffer)
    for plain in (model("--bc-alpha", "off"), model("--recipe", "td3")):
        assert type(plain).__name__ == "TD3"
        assert isinstance(plain.replay_buffer, TeacherReplayBuffer)
    with_bc = model("--recipe", "td3", "--bc-alpha", "1", "--replay", "rmax")
    assert isinstance(with_bc, TD3BC) and with_bc.bc_alpha == 1.0
    assert isinstance(with_bc.replay_buffer, RewardRankedReplayBuffer)


@pytest.mark.parametrize("alpha", ["0", "-1", "nan", "Off"])
def test_train_refuses_an_alpha_that_does_not_pull(tmp_path, safemove, alpha):
    run = safemove(["train", "-o", str(tmp_path / "run"), "--bc-alpha", alpha])
    assert run.wait(timeout=120) == 2
    assert "--bc-alpha" in run.stderr and "Traceback" not in run.stderr


@pytest.mark.timeout(600)
def test_train_with_bc_alpha_saves_and_exports_a_td3_bc_drl_model(tmp_path, safemove):
    # drl: the label comes from the env, its observation has no dwa block
    from rooms import write_room

    room = write_room(tmp_path, "room", goal=(1.5, 0.0), time_limit_s=12.0, crowd="{count: 0}")
    out = tmp_path / "run"
    run = safemove(["train", "-o", str(out), "--spec", "drl", "--envs", "1", "--scenarios",
                    room, "--no-noise", "--net", "32", "32", "--batch-size", "32",
                    "--demo-steps", "100", "--bc-epochs", "2", "--critic-warmup", "10",
                    "--steps", "60", "--bc-alpha", "2.5", "--json"])
    assert run.wait(timeout=500) == 0, run.stderr[-3000:]
    assert (out / "actor.onnx").is_file()
    record = json.loads((out / "summary.json").read_text())
    assert record["settings"]["bc_alpha"] == 2.5 and record["settings"]["spec"] == "drl"
    model = TD3BC.load(out / "td3.zip", device="cpu")
    assert model.bc_alpha == 2.5 and model.replay_buffer_class is TeacherReplayBuffer
