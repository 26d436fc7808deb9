"""The policies shipped with the package: resolved by variant name from the package's models
folder, a missing file refused in one line (exit 2) by run, eval and demo before anything
starts, --model and --variant exclusive, and the training/evaluation records stamped into an
actor without touching its graph."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from rooms import write_room

from runtime.cli.main import main
from runtime.config.settings import load_config
from runtime.errors import UserError
from runtime.jobs.safemove import SafeMoveJob
from runtime.jobs.trained_settings import trained_settings_report
from runtime.policy import shipped
from runtime.policy.actor import Policy, PolicyConfig
from sim_stub.bench_episode import write_random_actor

onnx = pytest.importorskip("onnx")
from export.ship import stamp  # needs onnx


@pytest.fixture
def models(tmp_path, monkeypatch) -> Path:
    """An empty models folder standing in for the package's."""
    folder = tmp_path / "models"
    folder.mkdir()
    monkeypatch.setattr(shipped, "MODELS_DIR", folder)
    return folder


@pytest.fixture
def tiny_room(tmp_path) -> str:
    """An empty room whose episode ends after one simulated second (20 cycles)."""
    return write_room(tmp_path, "tiny_room", goal=(1.25, 0.0), time_limit_s=1.0,
                      start=(-1.3, -1.2, -0.05, 0.05))


def test_variants_are_the_spec_presets():
    assert shipped.VARIANTS == ("drl", "drl_dwa", "safemove")
    assert shipped.DEFAULT_VARIANT in shipped.VARIANTS


def test_resolution_listing_and_the_missing_file(models):
    assert shipped.shipped_variants() == []
    with pytest.raises(UserError) as exc:
        shipped.shipped_model("drl")
    assert str(exc.value) == (f"no shipped 'drl' policy in this installation"
                              f" ({models / 'drl.onnx'}); give --model FILE.onnx")
    write_random_actor(models / "drl_dwa.onnx")
    assert shipped.shipped_variants() == ["drl_dwa"]
    assert shipped.shipped_model("drl_dwa") == models / "drl_dwa.onnx"
    assert shipped.variant_of(models / "drl_dwa.onnx") == "drl_dwa"
    assert shipped.variant_of(models.parent / "drl_dwa.onnx") is None
    with pytest.raises(UserError, match="unknown policy variant 'td3'"):
        shipped.shipped_model("td3")


def test_each_shipped_model_is_an_actor_of_its_own_spec():
    """Whatever the installation ships loads, and its spec is the preset of its name."""
    for variant in shipped.shipped_variants():
        policy = Policy(shipped.shipped_model(variant), PolicyConfig(warmup_runs=1))
        assert policy.spec.name == variant


def test_each_shipped_model_runs_on_the_settings_it_was_trained_with():
    """The shipped config is the one its policies learnt in: no warning on a plain run."""
    config = load_config().config
    for variant in shipped.shipped_variants():
        policy = Policy(shipped.shipped_model(variant), PolicyConfig(warmup_runs=1))
        report = trained_settings_report(policy.training, config)
        assert report.basis is not None, variant
        assert report.differences == (), (variant, report.differences)


def test_each_shipped_model_was_trained_with_the_train_commands_defaults():
    """`safemove train -o RUN --spec VARIANT` is the shipped recipe: every setting a shipped
    policy's record holds, bar where it was written and the config (checked above), is the
    command's default."""
    import argparse

    from sim_stub.train.cli import add_arguments, bc_alpha

    not_recipe = {"log_level", "command", "config", "overrides", "output", "json"}
    for variant in shipped.shipped_variants():
        trained = Policy(shipped.shipped_model(variant), PolicyConfig(warmup_runs=1)).training
        parser = argparse.ArgumentParser()
        add_arguments(parser)
        args = parser.parse_args(["-o", "run", "--spec", variant])
        defaults = {**vars(args), "bc_alpha": bc_alpha(args)}
        recipe = {k: v for k, v in trained["settings"].items() if k not in not_recipe}
        assert recipe == {k: defaults[k] for k in recipe}, variant


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["run", "--planner", "safemove", "--goal", "1", "0"],
         ["no shipped 'safemove' policy", "safemove.onnx", "give --model FILE.onnx"]),
        (["run", "--planner", "safemove", "--variant", "drl", "--goal", "1", "0"],
         ["no shipped 'drl' policy", "drl.onnx"]),
        (["eval", "--planner", "safemove"], ["no shipped 'safemove' policy", "safemove.onnx"]),
        (["demo"], ["no shipped 'safemove' policy", "safemove.onnx", "--model FILE.onnx",
                    "--planner dwa"]),
        (["run", "--variant", "drl"], ["run: --variant is for --planner safemove, not hold"]),
        (["run", "--planner", "dwa", "--model", "a.onnx"],
         ["run: --model is for --planner safemove, not dwa"]),
        (["eval", "--variant", "drl"], ["eval: --variant is for --planner safemove, not dwa"]),
        (["demo", "--planner", "dwa", "--variant", "drl"],
         ["demo: --variant is for --planner safemove, not dwa"]),
    ],
)
def test_missing_or_misplaced_policy_is_one_line_exit_2(models, args, needles, capsys):
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in err, err


@pytest.mark.parametrize("command", [["run", "--planner", "safemove"],
                                     ["eval", "--planner", "safemove"], ["demo"]])
def test_model_and_variant_are_exclusive(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([*command, "--model", "a.onnx", "--variant", "drl"])
    assert exc.value.code == 2
    assert "not allowed with argument" in capsys.readouterr().err


def test_stamp_round_trip_keeps_the_graph(tmp_path):
    path = tmp_path / "actor.onnx"
    write_random_actor(path)
    before = onnx.load(path)
    plain = Policy(path, PolicyConfig(warmup_runs=1))
    assert (plain.training, plain.evaluation) == ({}, {})
    obs = np.random.default_rng(1).uniform(*plain.spec.bounds()).astype(np.float32)
    action = plain.act(obs).copy()

    stamp(path, {"steps": 10}, {"paper_a": {"success_rate": 0.1}})
    training = {"steps": 1_000_000, "seed": 1, "scenarios": ["paper_a", "paper_b"]}
    evaluation = {"paper_a": {"success_rate": 0.95, "episodes": 100}}
    stamp(path, training, evaluation)  # replaces the first stamp

    after = onnx.load(path)
    assert after.graph == before.graph
    keys = [p.key for p in after.metadata_props]
    assert len(keys) == len(set(keys)) == len(before.metadata_props) + 2
    policy = Policy(path, PolicyConfig(warmup_runs=1))
    assert (policy.training, policy.evaluation) == (training, evaluation)
    assert policy.provenance == plain.provenance and policy.spec == plain.spec
    np.testing.assert_array_equal(policy.act(obs), action)

    summary = SafeMoveJob((1.0, 0.0), load_config(None, []).config, policy, None).summary()
    assert summary["policy"]["training"] == training
    assert summary["policy"]["evaluation"] == evaluation
    assert summary["policy"]["variant"] is None


def test_stamp_refuses_what_is_not_an_actor(tmp_path):
    with pytest.raises(UserError, match="model file not found"):
        stamp(tmp_path / "none.onnx", {}, {})
    (tmp_path / "text.onnx").write_text("not a model")
    with pytest.raises(UserError, match="not an ONNX model"):
        stamp(tmp_path / "text.onnx", {}, {})
    path = tmp_path / "actor.onnx"
    write_random_actor(path)
    with pytest.raises(ValueError):
        stamp(path, {"loss": float("nan")}, {})
    bare = onnx.load(path)
    del bare.metadata_props[:]
    onnx.save(bare, tmp_path / "bare.onnx")
    with pytest.raises(UserError, match="not an actor from `safemove export`"):
        stamp(tmp_path / "bare.onnx", {}, {})


def test_eval_runs_a_shipped_variant_and_names_it(models, tiny_room, capsys):
    write_random_actor(models / "safemove.onnx")
    assert main(["eval", "--planner", "safemove", "--variant", "safemove", "--scenarios",
                 tiny_room, "--episodes", "1", "--fps", "10", "--no-noise", "--json",
                 "--set", "loop.stats_interval_s=0"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["variant"] == "safemove"
    assert result["model"] == str(models / "safemove.onnx")
    # a random actor has no training record: nothing to compare its settings with
    assert result["trained_settings"] == {"basis": None, "differences": [], "unmatched": []}
    assert result["scenarios"][tiny_room]["episodes"] == 1
    (episode,) = result["episodes"]
    assert episode["cycles"] <= 25


def _run_dir(tmp_path: Path, spec_name: str) -> Path:
    """A training run's directory as `safemove train` leaves it (a random actor)."""
    run = tmp_path / "run"
    run.mkdir()
    write_random_actor(run / "actor.onnx")
    (run / "spec.json").write_text(json.dumps({"name": spec_name}))
    (run / "summary.json").write_text(json.dumps(
        {"run": str(run), "recipe": "bc-td3", "steps": 10, "commit": "abc", "settings": {}}))
    return run


def _evaluation(tmp_path: Path, model: Path | str) -> Path:
    """A `safemove eval --planner safemove --json` result of `model` with no episodes."""
    result = tmp_path / "eval.json"
    result.write_text(json.dumps({"planner": "safemove", "model": str(model), "crowd": "scenario",
                                  "noise": True, "fps": 15.0, "scenarios": {}}))
    return result


def test_ship_installs_the_run_with_its_records(models, tiny_room, tmp_path, capsys):
    run = _run_dir(tmp_path, "safemove")
    assert main(["eval", "--planner", "safemove", "--model", str(run / "actor.onnx"),
                 "--scenarios", tiny_room, "--episodes", "1", "--fps", "10", "--no-noise",
                 "--json"]) == 0
    result = tmp_path / "eval.json"
    result.write_text(capsys.readouterr().out.strip().splitlines()[-1])
    assert main(["ship", str(run), "--eval", str(result)]) == 0
    policy = Policy(models / "safemove.onnx", PolicyConfig())
    assert policy.training["recipe"] == "bc-td3" and "run" not in policy.training
    (table,) = policy.evaluation["tables"]
    assert table["planner"] == "safemove" and table["scenarios"]["tiny_room"]["episodes"] == 1
    # which code evaluated it, with which camera
    assert table["commit"] == json.loads(result.read_text())["commit"]
    assert table["camera_hfov_deg"] == 87.0
    assert table["overrides"] == [] and table["trained_settings"]["basis"] is None
    assert shipped.shipped_variants() == ["safemove"]


def test_ship_takes_an_evaluation_of_the_run_before_it_moved(models, tmp_path, capsys):
    """The summary names the actor where training wrote it; an evaluation of that file is the
    run's, though the run directory was moved (into the repository) since."""
    run = _run_dir(tmp_path, "safemove")
    summary = json.loads((run / "summary.json").read_text())
    summary["actor"] = "/tmp/train/safemove/actor.onnx"
    (run / "summary.json").write_text(json.dumps(summary))
    assert main(["ship", str(run), "--eval", str(_evaluation(tmp_path, summary["actor"]))]) == 0
    assert shipped.shipped_variants() == ["safemove"]
    assert "actor" not in Policy(models / "safemove.onnx", PolicyConfig()).training


def test_ship_takes_an_evaluation_of_an_installed_copy_of_the_run(models, tmp_path, capsys):
    """eval --variant evaluates the installed file: the run's graph with other metadata. It
    counts for the run; an actor with other weights does not."""
    run = _run_dir(tmp_path, "safemove")
    installed = models / "safemove.onnx"
    installed.write_bytes((run / "actor.onnx").read_bytes())
    stamp(installed, {"steps": 1}, {"tables": []})
    other = tmp_path / "other.onnx"
    write_random_actor(other, seed=1)
    for model, code in ((installed, 0), (other, 2)):
        assert main(["ship", str(run), "--eval", str(_evaluation(tmp_path, model))]) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"evaluates {other}, not this run's" in err[0]
    assert Policy(installed, PolicyConfig()).training["steps"] == 10  # shipped from the run


@pytest.mark.parametrize("spec_name, eval_model, needle", [
    ("custom", None, "not a shipped variant"),
    ("drl", "other.onnx", "not this run's"),
])
def test_ship_refuses_a_foreign_spec_or_evaluation(models, tmp_path, capsys, spec_name,
                                                   eval_model, needle):
    run = _run_dir(tmp_path, spec_name)
    result = tmp_path / "eval.json"
    result.write_text(json.dumps({"planner": "safemove", "model": str(tmp_path / str(eval_model)),
                                  "scenarios": {}}))
    assert main(["ship", str(run), "--eval", str(result)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]
    assert shipped.shipped_variants() == []


def test_ship_refuses_a_run_trained_seeing_every_person_around(models, tmp_path, capsys):
    run = _run_dir(tmp_path, "safemove")
    summary = json.loads((run / "summary.json").read_text())
    summary["settings"] = {"surround_people": True}
    (run / "summary.json").write_text(json.dumps(summary))
    assert main(["ship", str(run), "--eval", str(_evaluation(tmp_path, run / "actor.onnx"))]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [(f"safemove: error: {run / 'summary.json'}: trained with --surround-people,"
                    " seeing every person around exactly; the robot has no such sensor")]
    assert shipped.shipped_variants() == []


def test_a_ship_that_fails_leaves_nothing_in_the_package(models, tmp_path, capsys):
    run = _run_dir(tmp_path, "safemove")
    (run / "actor.onnx").write_bytes(b"not a model")
    assert main(["ship", str(run), "--eval", str(_evaluation(tmp_path, run / "actor.onnx"))]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not an ONNX model" in err[0]
    assert list(models.iterdir()) == []
