"""Training: the gymnasium environment over the lock-stepped robot, and `safemove train` end to
end (train → td3.zip → exported actor.onnx → `safemove eval` runs it)."""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gymnasium")
pytest.importorskip("stable_baselines3")

from gymnasium.utils.env_checker import check_env
from rooms import write_room

from runtime.config.settings import load_config
from runtime.policy.obs_spec import PRESETS
from sim_stub.train.env import RewardConfig, SafeMoveEnv

SPEC = PRESETS["safemove"]


def _room(tmp_path, name: str, goal_x: float, crowd: str = "{count: 0}",
          time_limit_s: float = 30.0, heading_jitter_deg: float = 0.0) -> str:
    """The robot at the origin facing +x (± the jitter, drawn from the episode's seed), the
    goal goal_x ahead."""
    return write_room(tmp_path, name, goal=(goal_x, 0.0), time_limit_s=time_limit_s,
                      heading_jitter_deg=heading_jitter_deg, crowd=crowd)


def _monitor(path: Path) -> list[tuple[str, str, str]]:
    """The Monitor file's (return, length, outcome) per episode, its wall-clock column left
    out; its first line is a JSON header."""
    with path.open(encoding="utf-8") as f:
        next(f)
        return [(row["r"], row["l"], row["outcome"]) for row in csv.DictReader(f)]


def _env(scenario: str, **kw) -> SafeMoveEnv:
    return SafeMoveEnv([scenario], SPEC, load_config(None, []), noise=False, **kw)


def test_env_passes_the_gymnasium_checker_and_repeats_from_its_seed(tmp_path):
    room = _room(tmp_path, "room", 2.0)
    check_env(_env(room), skip_render_check=True)
    a, b = _env(room), _env(room)
    oa, ia = a.reset(seed=7)
    ob, ib = b.reset(seed=7)
    assert ia == ib and np.array_equal(oa, ob)
    for action in ([0.5, 0.2], [1.0, -0.3], [0.0, 0.0]):
        ra = a.step(np.array(action, dtype=np.float32))
        rb = b.step(np.array(action, dtype=np.float32))
        assert np.array_equal(ra[0], rb[0]) and ra[1:4] == rb[1:4]
    assert a.observation_space.contains(ra[0])


def test_env_with_surround_people_tracks_the_person_behind_the_robot(tmp_path):
    crowd = "{count: 1, reactive: false, speed_range: [0.5, 0.5], radius: 0.3}"
    room = _room(tmp_path, "behind", 2.5, crowd)
    for surround in (False, True):
        env = _env(room, surround_people=surround)
        env.reset(seed=0)
        world = env.world
        # 1.5 m behind the robot, walking away from it: outside the camera's view
        world.crowd.set_agent(0, (-1.5, 0.0), (-2.9, 0.0))
        world.crowd.goal_sampler = None
        for _ in range(20):  # a second: the person is up to speed
            env.step(np.array([-1.0, 0.0], dtype=np.float32))  # parked
        tracks = env._pipeline.world.tracks
        if not surround:
            assert tracks == []
            continue
        (tr,) = tracks
        assert tr.id == 0 and tr.confirmed and not tr.stationary
        # odom starts where the robot does, facing +x: the person is behind, walking away
        assert tr.position[0] < -1.5 and abs(tr.position[1]) < 0.1
        assert tr.velocity == pytest.approx([-0.5, 0.0], abs=0.05)


def test_driving_to_the_goal_earns_progress_and_the_success_bonus(tmp_path):
    env = _env(_room(tmp_path, "room", 1.0))
    cfg = RewardConfig()
    env.reset(seed=0)
    start = float(np.hypot(*env.world.goal))
    total, rewards, info, done = 0.0, [], {}, False
    while not done:
        _, r, terminated, truncated, info = env.step(np.array([1.0, 0.0], dtype=np.float32))
        rewards.append(r)
        total += r
        done = terminated or truncated
    assert terminated and info["outcome"] == "success"
    assert rewards[-1] > cfg.success  # the bonus, on top of the last cycle's progress
    robot = env.world.robot
    progress = start - float(np.hypot(*(env.world.goal - [robot.x, robot.y])))
    expected = (cfg.progress_per_m * progress - cfg.time_per_s * info["time_s"] + cfg.success)
    assert total == pytest.approx(expected, abs=0.05)  # the shield never had to step in here
    assert sum(r > 0 for r in rewards[5:]) == len(rewards) - 5  # once moving: every cycle gains


def test_a_person_walking_into_the_parked_robot_ends_it_with_the_collision_penalty(tmp_path):
    crowd = "{count: 1, reactive: false, speed_range: [0.8, 0.8], radius: 0.3}"
    env = _env(_room(tmp_path, "crossing", 2.5, crowd))
    env.reset(seed=0)
    world = env.world
    world.crowd.set_agent(0, (0.0, 2.5), (0.0, -3.0))  # walks down across the robot
    world.crowd.goal_sampler = None
    stand = np.array([-1.0, 0.0], dtype=np.float32)  # v_min = 0: the robot stays parked
    for _ in range(200):
        _, r, terminated, truncated, info = env.step(stand)
        if terminated or truncated:
            break
    assert terminated and info["outcome"] == "collision" and not info["at_fault"]
    assert r < -RewardConfig().collision + 0.1


@pytest.mark.timeout(900)  # ~60 s idle: three child processes, torch and SB3 imported in each
def test_train_writes_a_model_and_an_actor_that_eval_runs(tmp_path, safemove):
    # episodes of 2.5 s (49 steps): none can end sooner (the goal is out of reach at 0.3 m/s and
    # the room is empty), so 120 steps are two whole episodes, both timeouts
    room = _room(tmp_path, "room", 1.5, time_limit_s=2.5)
    out = tmp_path / "run"
    run = safemove(["train", "-o", str(out), "--steps", "120", "--learning-starts", "60",
                    "--batch-size", "32", "--scenarios", room, "--checkpoint-every", "100",
                    "--no-noise", "--net", "64", "64", "--envs", "1", "--recipe", "td3",
                    "--set", "dwa.weight_evasion=1.5"])
    assert run.wait(timeout=300) == 0, run.stderr[-3000:]
    summary = json.loads(run.stdout.strip().splitlines()[-1])
    # the Monitor's episodes (summary) and its file (outcomes) agree, one row per episode
    assert summary["steps"] == 120 and summary["episodes"] == 2
    assert summary["outcomes"] == summary["td3_outcomes"] == {"timeout": 2}  # no demonstrations
    assert max(summary["export_parity_max_abs"].values()) < 1e-5
    for name in ("td3.zip", "actor.onnx", "spec.json", "monitor.csv",
                 "checkpoints/td3_100_steps.zip"):
        assert (out / name).is_file(), name
    evaluated = safemove(["eval", "--planner", "safemove", "--model", str(out / "actor.onnx"),
                          "--scenarios", room, "--episodes", "1", "--no-noise", "--json"])
    assert evaluated.wait(timeout=300) == 0, evaluated.stderr[-3000:]
    result = json.loads(evaluated.stdout.strip().splitlines()[-1])
    assert result["scenarios"][room]["episodes"] == 1
    # the run records the settings it trained with; eval, run without its --set, says so
    summary_record = json.loads((out / "summary.json").read_text())
    assert summary_record["settings"]["bc_alpha"] is None  # --recipe td3: plain TD3
    record = summary_record["decision_settings"]
    assert record["dwa.weight_evasion"] == 1.5 and record["loop.control_hz"] == 20.0
    assert result["trained_settings"]["differences"] == [
        {"key": "dwa.weight_evasion", "trained": 1.5, "running": 3.0}]
    assert "trained with dwa.weight_evasion=1.5, running with 3.0" in evaluated.stderr
    again = safemove(["train", "-o", str(out), "--steps", "10", "--scenarios", room])
    assert again.wait(timeout=120) == 2
    assert "td3.zip: exists" in again.stderr and "Traceback" not in again.stderr


@pytest.mark.timeout(600)  # two runs at once, two workers each: 45-70 s on 2 loaded cores
def test_training_in_two_worker_envs_repeats_from_its_seed(tmp_path, safemove):
    # 100 steps per env: two 2.5 s episodes (49 steps) each, their start headings drawn from
    # the env's seed; learning starts at 100 transitions, so the second ones run the learnt
    # actor (and the noise) and the monitor's returns depend on the gradient steps too
    room = _room(tmp_path, "room", 1.5, time_limit_s=2.5, heading_jitter_deg=180.0)
    runs = {name: safemove(["train", "-o", str(tmp_path / name), "--envs", "2", "--seed", "3",
                            "--steps", "200", "--learning-starts", "100", "--batch-size", "32",
                            "--net", "16", "16", "--scenarios", room, "--no-noise", "--json",
                            "--recipe", "td3"])
            for name in ("a", "b")}
    results = {}
    for name, run in runs.items():
        assert run.wait(timeout=400) == 0, run.stderr[-3000:]
        # --json: the JSON line alone on stdout; stderr is no terminal: plain progress lines
        (line,) = run.stdout.strip().splitlines()
        summary = json.loads(line)
        assert (summary["envs"], summary["steps"], summary["episodes"]) == (2, 200, 4)
        assert "train: 200/200 steps (100 %)" in run.stderr and "\r" not in run.stderr
        with zipfile.ZipFile(tmp_path / name / "td3.zip") as model:
            results[name] = (_monitor(tmp_path / name / "monitor.csv"), model.read("policy.pth"))
    assert results["a"] == results["b"]  # episode by episode, and the weights byte for byte
    episodes = results["a"][0]
    assert len(episodes) == 4 and episodes[0][0] != episodes[1][0]  # env i seeded seed + i


@pytest.mark.timeout(600)
def test_the_bc_td3_recipe_clones_dwa_before_td3(tmp_path, safemove):
    # a goal 1.5 m ahead in an empty room: DWA reaches it in about 6 s, so the noise-free
    # demonstrations are whole successful episodes, and the clone learns DWA's choices
    room = _room(tmp_path, "room", 1.5, time_limit_s=12.0)
    out = tmp_path / "run"
    run = safemove(["train", "-o", str(out), "--envs", "1", "--scenarios", room, "--no-noise",
                    "--net", "64", "64", "--batch-size", "32", "--demo-steps", "300",
                    "--demo-noise", "0", "--bc-epochs", "40", "--critic-warmup", "20",
                    "--steps", "20", "--json"])
    assert run.wait(timeout=500) == 0, run.stderr[-3000:]
    summary = json.loads(run.stdout.strip().splitlines()[-1])
    assert summary["recipe"] == "bc-td3" and summary["demo_steps"] == 300
    assert summary["demo_episodes"] >= 2 and summary["demo_successes"] == summary["demo_episodes"]
    assert summary["bc_mse"] < 0.02  # an untrained actor is off by ~0.3 (action units)
    assert summary["critic_warmup_loss"] is not None
    assert summary["total_env_steps"] == 320
    # the 20 TD3 steps end no episode: every monitored one is a demonstration
    assert summary["episodes"] == summary["demo_episodes"] and summary["td3_episodes"] == 0
    for name in ("checkpoints/bc.zip", "learning_curve.png", "actor.onnx"):
        assert (out / name).is_file(), name
    record = json.loads((out / "summary.json").read_text())  # what a shipped model carries
    assert record["settings"]["demo_steps"] == 300 and record["settings"]["seed"] == 0
    assert record["reward"] == dataclasses.asdict(RewardConfig())  # the weights, defaults too
    assert "commit" in record and record["total_env_steps"] == 320


def test_train_refuses_a_negative_noise_in_one_line(tmp_path, safemove):
    run = safemove(["train", "-o", str(tmp_path / "run"), "--demo-noise", "-0.1"])
    assert run.wait(timeout=120) == 2
    assert "--demo-noise" in run.stderr and "Traceback" not in run.stderr


def test_train_refuses_an_unknown_scenario(tmp_path, safemove):
    run = safemove(["train", "-o", str(tmp_path / "run"), "--scenarios", "no_such_room"])
    assert run.wait(timeout=120) == 2
    assert "no_such_room" in run.stderr and "Traceback" not in run.stderr


def test_shield_penalty_reaches_the_project_reward():
    from sim_stub.train.cli import add_arguments, reward_config

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["-o", "run"])
    assert reward_config(args) == RewardConfig()
    args = parser.parse_args(["-o", "run", "--shield-penalty", "0.5"])
    assert reward_config(args) == RewardConfig(shield_change=0.5)


def test_train_refuses_a_shield_penalty_with_the_papers_reward(tmp_path, safemove):
    run = safemove(["train", "-o", str(tmp_path / "run"), "--reward", "paper",
                    "--shield-penalty", "0.5"])
    assert run.wait(timeout=120) == 2
    assert "--shield-penalty: the paper reward has no shield term" in run.stderr
    assert "Traceback" not in run.stderr and not (tmp_path / "run").exists()
