"""`safemove bench episode`: the seeds and cycles it ran, shares that add up, the training env
figures, and the random actor it makes without torch. Behaviour only, never timing values."""

from __future__ import annotations

import json

import numpy as np
import pytest

from runtime.cli.main import main
from runtime.pipeline import PIPELINE_STAGES
from runtime.policy.actor import Policy, PolicyConfig
from runtime.policy.obs_spec import PRESETS
from sim_stub.bench_episode import SIM_PARTS, write_random_actor
from sim_stub.scenario import SCENARIO_DIR

pytestmark = pytest.mark.sim  # lock-stepped episodes


def run_bench(capsys, *args: str) -> dict:
    assert main(["bench", "episode", "--json", *args]) == 0
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def short_paper_b(tmp_path) -> str:
    """paper_b with a 1 s time limit: an episode is about 20 cycles."""
    path = tmp_path / "paper_b_1s.yaml"
    text = (SCENARIO_DIR / "paper_b.yaml").read_text()
    path.write_text(text.replace("time_limit_s: 60.0", "time_limit_s: 1.0"))
    return str(path)


def test_each_job_runs_the_cap_over_successive_seeds_and_its_shares_add_up(tmp_path, capsys):
    args = ("--scenario", short_paper_b(tmp_path), "--cycles", "50", "--seed", "7", "--no-train")
    result, again = run_bench(capsys, *args), run_bench(capsys, *args)
    assert result["bench"] == "episode" and result["cycle_cap"] == 50 and result["seed"] == 7
    assert (result["crowd"], result["fps"], result["noise"]) == ("reactive", 15.0, True)
    assert not any(key.startswith("train_") for key in result)
    assert "randomly initialised" in result["safemove"]["actor"]
    for job in ("dwa", "safemove"):
        r = result[job]
        episodes = r["episodes"]
        assert [e["seed"] for e in episodes] == list(range(7, 7 + len(episodes)))
        assert len(episodes) >= 3  # 1 s episodes under a 50-cycle cap
        assert again[job]["episodes"] == episodes  # the same seeds run the same cycles
        assert sum(e["cycles"] for e in episodes) == r["cycles"] == 50
        # every episode but the last ran to the world's verdict; the last was cut at the cap
        assert all(e["status"] in ("success", "collision", "timeout") for e in episodes[:-1])
        parts = [*PIPELINE_STAGES, *SIM_PARTS, "other"]
        assert list(r["share"]) == list(r["ms_per_cycle"]) == parts
        assert all(v >= 0.0 for v in r["share"].values())
        assert sum(r["share"].values()) == pytest.approx(1.0, abs=2e-3)
        assert r["cycles_per_s"] == pytest.approx(r["cycles"] / r["wall_s"], rel=0.01)
        assert sum(r["ms_per_cycle"].values()) == pytest.approx(
            1e3 * r["wall_s"] / r["cycles"], rel=0.01)


def test_the_training_env_reports_steps_with_one_and_n_workers(capsys):
    pytest.importorskip("stable_baselines3")
    result = run_bench(capsys, "--cycles", "5", "--workers", "2", "--learning-starts", "4",
                       "--updates", "4")
    for workers in (1, 2):
        r = result[f"train_{workers}_workers"]
        assert r["workers"] == workers
        # SB3 counts one step per env per VecEnv step
        assert r["random_steps"] == r["learning_steps"] == 4
        assert r["random_steps_per_s"] > 0 and r["learning_steps_per_s"] > 0


def test_a_bad_scenario_or_model_is_one_line(tmp_path, capsys):
    assert main(["bench", "episode", "--scenario", "nowhere", "--no-train"]) == 2
    assert "nowhere" in capsys.readouterr().err.strip().splitlines()[-1]
    missing = tmp_path / "actor.onnx"
    assert main(["bench", "episode", "--model", str(missing), "--no-train"]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].endswith(
        f"{missing}: model file not found")


def test_the_random_actor_loads_as_an_exported_one_and_its_actions_vary(tmp_path):
    pytest.importorskip("onnx")
    path = tmp_path / "actor.onnx"
    assert write_random_actor(path).startswith("61-400-300-2")
    policy = Policy(path, PolicyConfig(warmup_runs=1))
    spec = PRESETS["safemove"]
    assert policy.spec == spec
    obs = np.random.default_rng(0).uniform(*spec.bounds(), (20, spec.size)).astype(np.float32)
    actions = np.array([policy.act(o).copy() for o in obs])
    assert np.all(np.abs(actions) <= 1.0) and np.ptp(actions, axis=0).min() > 0.01
