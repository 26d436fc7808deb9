"""TD3+BC on DWA's choice (`safemove train --bc-alpha`): the label is read from the
observation's dwa block, and a small α holds the actor on it."""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

import gymnasium as gym
from stable_baselines3.common.vec_env import DummyVecEnv

from runtime.errors import UserError
from runtime.policy.obs_spec import PRESETS
from sim_stub.train.cli import add_arguments, make_td3, teacher_columns
from sim_stub.train.td3_bc import TD3BC

LABEL = np.array([0.5, -0.5], dtype=np.float32)


class LabelledEnv(gym.Env):
    """Test double: random observations whose columns 2:4 hold a fixed 'DWA choice'."""

    observation_space = gym.spaces.Box(-2.0, 2.0, (4,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def __init__(self, label: np.ndarray = LABEL) -> None:
        self.label = label
        self.t = 0

    def _obs(self) -> np.ndarray:
        obs = self.np_random.uniform(-1.0, 1.0, 4).astype(np.float32)
        obs[2:4] = self.label
        return obs

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self.t += 1
        reward = float(action[0])  # TD3 alone would drive a[0] to +1, away from the label
        return self._obs(), reward, False, self.t >= 10, {}


def _model(alpha: float, label: np.ndarray = LABEL) -> TD3BC:
    return TD3BC("MlpPolicy", DummyVecEnv([lambda: LabelledEnv(label)]), bc_alpha=alpha,
                 teacher=(2, 4), learning_starts=100, batch_size=32, learning_rate=3e-3,
                 policy_kwargs={"net_arch": [32, 32]}, seed=0, device="cpu")


def _actions(model: TD3BC) -> np.ndarray:
    """The deterministic actions on 64 fresh observations like the env's."""
    obs = np.random.default_rng(1).uniform(-1.0, 1.0, (64, 4)).astype(np.float32)
    obs[:, 2:4] = LABEL
    actions, _ = model.predict(obs, deterministic=True)
    return actions


def test_teacher_columns_are_the_dwa_blocks_first_two():
    spec = PRESETS["safemove"]
    start = next(s for kind, s, _ in spec.layout() if kind == "dwa")
    assert teacher_columns(spec) == (start, start + 2)
    assert spec.names()[start:start + 2] == ["dwa.best_v", "dwa.best_omega"]
    assert teacher_columns(PRESETS["drl"]) is None


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


def test_alpha_must_pull_and_the_teacher_be_known():
    with pytest.raises(ValueError, match="bc_alpha must be > 0"):
        _model(alpha=0.0)
    model = TD3BC("MlpPolicy", DummyVecEnv([LabelledEnv]), learning_starts=10, batch_size=8,
                  policy_kwargs={"net_arch": [8]}, seed=0, device="cpu")
    with pytest.raises(RuntimeError, match="columns of DWA's choice"):
        model.learn(total_timesteps=20)


def test_make_td3_builds_td3_bc_only_when_asked():
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    env = DummyVecEnv([LabelledEnv])
    plain = make_td3(env, parser.parse_args(["-o", "run", "--net", "8"]), PRESETS["safemove"])
    assert type(plain).__name__ == "TD3"
    with_bc = make_td3(env, parser.parse_args(["-o", "run", "--net", "8", "--bc-alpha", "2.5"]),
                       PRESETS["safemove"])
    assert isinstance(with_bc, TD3BC) and with_bc.bc_alpha == 2.5
    assert with_bc.teacher == teacher_columns(PRESETS["safemove"])
    with pytest.raises(UserError, match="the spec 'drl' has no dwa block"):
        make_td3(env, parser.parse_args(["-o", "run", "--net", "8", "--bc-alpha", "2.5"]),
                 PRESETS["drl"])


def test_train_refuses_bc_alpha_without_a_dwa_block(tmp_path, safemove):
    run = safemove(["train", "-o", str(tmp_path / "run"), "--spec", "drl", "--bc-alpha", "2.5"])
    assert run.wait(timeout=120) == 2
    assert "--bc-alpha: the spec 'drl' has no dwa block" in run.stderr
    assert "Traceback" not in run.stderr and not (tmp_path / "run").exists()


@pytest.mark.parametrize("alpha", ["0", "-1", "nan"])
def test_train_refuses_an_alpha_that_does_not_pull(tmp_path, safemove, alpha):
    run = safemove(["train", "-o", str(tmp_path / "run"), "--bc-alpha", alpha])
    assert run.wait(timeout=120) == 2
    assert "--bc-alpha" in run.stderr and "Traceback" not in run.stderr


@pytest.mark.timeout(600)
def test_train_with_bc_alpha_saves_and_exports_a_td3_bc_model(tmp_path, safemove):
    from rooms import write_room

    room = write_room(tmp_path, "room", goal=(1.5, 0.0), time_limit_s=12.0, crowd="{count: 0}")
    out = tmp_path / "run"
    run = safemove(["train", "-o", str(out), "--envs", "1", "--scenarios", room, "--no-noise",
                    "--net", "32", "32", "--batch-size", "32", "--demo-steps", "100",
                    "--bc-epochs", "2", "--critic-warmup", "10", "--steps", "60",
                    "--bc-alpha", "2.5", "--json"])
    assert run.wait(timeout=500) == 0, run.stderr[-3000:]
    assert (out / "actor.onnx").is_file()
    record = json.loads((out / "summary.json").read_text())
    assert record["settings"]["bc_alpha"] == 2.5
    model = TD3BC.load(out / "td3.zip", device="cpu")
    assert model.bc_alpha == 2.5  # the teacher columns come back as a list
    assert tuple(model.teacher) == teacher_columns(PRESETS["safemove"])
