"""The actor in the loop: model validation at load (each refusal one line, exit 2), the
SafeMove job's NaN/inf guard, and the job's command going through the shield."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from runtime.config.settings import Config
from runtime.errors import ConfigError
from runtime.jobs.safemove import SafeMoveJob
from runtime.perception.world_model import WorldState
from runtime.policy.actor import META_PROVENANCE, META_SPEC, Policy, PolicyConfig
from runtime.policy.obs_spec import PRESETS
from runtime.types import STOP, Odometry

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper, numpy_helper

SPEC = PRESETS["safemove"]


def mlp_model(n_in: int, *, spec_json: str | None = SPEC.to_json(), input_name: str = "obs",
              output: str = "tanh", bias: float = 0.0, seed: int = 0) -> onnx.ModelProto:
    """obs (batch, n_in) → Linear(32) → ReLU → Linear(2) → tanh (or a NaN/inf-making op)."""
    rng = np.random.default_rng(seed)
    w1 = numpy_helper.from_array(rng.normal(0, 0.3, (n_in, 32)).astype(np.float32), "w1")
    w2 = numpy_helper.from_array(rng.normal(0, 0.3, (32, 2)).astype(np.float32), "w2")
    b2 = numpy_helper.from_array(np.full(2, bias, np.float32), "b2")
    nodes = [helper.make_node("MatMul", [input_name, "w1"], ["h"]),
             helper.make_node("Relu", ["h"], ["r"]),
             helper.make_node("MatMul", ["r", "w2"], ["z0"]),
             helper.make_node("Add", ["z0", "b2"], ["z"])]
    if output == "tanh":
        nodes.append(helper.make_node("Tanh", ["z"], ["action"]))
    else:  # log(-1) = NaN: a model that goes bad
        nodes.append(helper.make_node("Log", ["z"], ["action"]))
    graph = helper.make_graph(
        nodes, "actor",
        [helper.make_tensor_value_info(input_name, TensorProto.FLOAT, ["batch", n_in])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", 2])],
        [w1, w2, b2])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    if spec_json is not None:
        model.metadata_props.add(key=META_SPEC, value=spec_json)
    model.metadata_props.add(key=META_PROVENANCE,
                             value=json.dumps({"note": "randomly initialised (untrained)"}))
    return model


def save(model: onnx.ModelProto, path) -> str:
    path.write_bytes(model.SerializeToString())
    return str(path)


def test_a_valid_actor_loads_warm_with_explicit_threads(tmp_path):
    path = tmp_path / "actor.onnx"
    save(mlp_model(SPEC.size), path)
    policy = Policy(path, PolicyConfig(intra_op_threads=1, warmup_runs=3))
    assert policy.spec == SPEC and policy.threads == 1
    assert policy.provenance["note"] == "randomly initialised (untrained)"
    out = policy.act(np.zeros(SPEC.size, np.float32))
    assert out.shape == (2,) and np.all(np.abs(out) <= 1)


@pytest.mark.parametrize(("make", "message"), [
    (lambda: mlp_model(25), "the model takes 25 features but its spec 'safemove' builds 61"),
    (lambda: mlp_model(61, spec_json=None), "no observation spec in its metadata"),
    (lambda: mlp_model(61, spec_json='{"spec_version": 1, "blocks": [{"type": "scan",'
                                     ' "bins": -1}]}'),
     "metadata 'safemove.obs_spec': key 'blocks[0].bins': must be at least 1, got -1"),
    (lambda: mlp_model(61, spec_json="not json"), "metadata 'safemove.obs_spec': not valid JSON"),
    (lambda: mlp_model(61, input_name="input"), "expected one input 'obs' and one output"),
    (lambda: mlp_model(61, output="log", bias=-5.0),
     "the model's output on a probe observation is not two finite numbers"),
])
def test_bad_models_are_refused_with_one_line_naming_the_file(tmp_path, make, message):
    path = tmp_path / "actor.onnx"
    save(make(), path)
    with pytest.raises(ConfigError) as err:
        Policy(path, PolicyConfig(warmup_runs=1))
    text = str(err.value)
    assert text.startswith(str(path) + ": ") and message in text and "\n" not in text


def test_missing_and_non_onnx_files_are_refused(tmp_path):
    with pytest.raises(ConfigError, match="model file not found"):
        Policy(tmp_path / "none.onnx", PolicyConfig())
    (tmp_path / "junk.onnx").write_bytes(b"\x00not a model")
    with pytest.raises(ConfigError, match="junk.onnx: not a loadable ONNX model"):
        Policy(tmp_path / "junk.onnx", PolicyConfig())


def test_run_refuses_a_model_whose_spec_mismatches_with_exit_2(tmp_path, safemove):
    path = save(mlp_model(25), tmp_path / "drl_sized.onnx")
    run = safemove(["run", "--planner", "safemove", "--model", path, "--goal", "2", "0",
                    "--set", "depth.source=sim", "--set", f"depth.sim_socket={tmp_path}/d.sock",
                    "--set", f"base.port={tmp_path}/nobase"])
    assert run.wait(timeout=60) == 2
    err = run.stderr.strip().splitlines()
    assert err[-1] == (f"safemove: error: {path}: the model takes 25 features but its spec"
                       " 'safemove' builds 61")
    assert "Traceback" not in run.stderr and run.stdout == ""  # refused before the base opened


def test_model_needs_safemove(capsys):
    """(Without --model, the shipped policy: tests/test_shipped_policy.py.)"""
    from runtime.cli.main import main

    common = ["--goal", "1", "0", "--set", "depth.source=sim", "--set", "depth.sim_socket=/x"]
    assert main(["run", "--planner", "dwa", "--model", "a.onnx", *common]) == 2
    assert "--model is for --planner safemove" in capsys.readouterr().err


# --- the job -------------------------------------------------------------------------------------


def wall_world(distance: float) -> WorldState:
    """A wall across the path `distance` ahead, seen in every bin."""
    angles = np.linspace(-0.75, 0.75, 90).astype(np.float32)
    ys = np.linspace(-1.5, 1.5, 61)
    points = np.stack([np.full_like(ys, distance), ys], axis=1)
    scan = (distance / np.cos(angles)).astype(np.float32)
    return WorldState(0.0, scan, np.zeros(90, bool), angles, points, [], True)


class FixedPolicy:
    """Stands in for Policy: a fixed raw output, with the real safemove spec."""

    def __init__(self, output) -> None:
        self.spec = SPEC
        self.path = Path("fixed.onnx")
        self.threads = 1
        self.provenance = self.training = self.evaluation = {}
        self.output = np.asarray(output, dtype=np.float32)
        self.seen: list[np.ndarray] = []

    def act(self, obs: np.ndarray) -> np.ndarray:
        self.seen.append(obs.copy())
        return self.output


def job_with(output) -> tuple[SafeMoveJob, FixedPolicy]:
    policy = FixedPolicy(output)
    return SafeMoveJob((3.0, 0.0), Config(), policy, lambda: 0.0), policy  # type: ignore[arg-type]


def test_free_space_command_passes_the_shield_unchanged_and_obs_follows_the_spec():
    job, policy = job_with([0.0, 0.0])  # a = 0 → v = 0.15, ω = 0
    cmd = job.step(0.0, Odometry(v=0.15), wall_world(10.0))
    assert (cmd.v, cmd.omega) == pytest.approx((0.15, 0.0))
    obs = policy.seen[-1]
    assert obs.shape == (SPEC.size,)
    np.testing.assert_allclose(obs[:5], [0.3, 0.0, 1.0, 0.0, 0.0], atol=1e-6)  # goal 3 m ahead
    assert job.summary()["shield_interventions"] == {}


def test_the_shield_overrules_the_actor_and_counts_it():
    job, _ = job_with([1.0, 0.0])  # full speed into a wall 0.25 m ahead (braking needs more)
    cmd = job.step(0.0, Odometry(v=0.3), wall_world(0.25))
    assert cmd.v < 0.3
    assert sum(job.summary()["shield_interventions"].values()) == 1


@pytest.mark.parametrize("bad", [[math.nan, 0.0], [0.0, math.inf]])
def test_non_finite_actions_are_a_safe_stop_with_the_reason(bad, caplog):
    job, _ = job_with(bad)
    for _ in range(3):
        assert job.step(0.0, Odometry(v=0.2), wall_world(5.0)) == STOP
    assert job.summary()["nonfinite_safe_stops"] == {"action": 3}
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and "non-finite action" in errors[0]  # once per streak


def test_non_finite_odometry_or_observation_never_reaches_the_actor(monkeypatch):
    job, policy = job_with([0.0, 0.0])
    assert job.step(0.0, Odometry(v=math.nan), wall_world(5.0)) == STOP
    bad = np.full(SPEC.size, np.inf, dtype=np.float32)
    monkeypatch.setattr(job._observer, "observe", lambda *_: bad)
    assert job.step(0.0, Odometry(v=0.1), wall_world(5.0)) == STOP
    assert policy.seen == []
    assert job.summary()["nonfinite_safe_stops"] == {"odometry": 1, "observation": 1}


def test_a_stalled_policy_is_given_an_escape_goal_away_from_what_blocks_it():
    """The DWA job's stall recovery serves the policy too: after recovery.stall_s standing
    short of the goal, the observation's goal is an escape goal the most open way."""
    job, policy = job_with([-1.0, 0.0])  # a = -1 → v = 0: the policy stands
    blocked = wall_world(0.5)
    stall_s = Config().recovery.stall_s
    for t in np.arange(0.0, stall_s, 0.05):
        job.step(float(t), Odometry(t=float(t)), blocked)
    # goal block: distance / 10 m, sin and cos of its bearing
    np.testing.assert_allclose(policy.seen[-1][:3], [0.3, 0.0, 1.0], atol=1e-6)  # 3 m ahead
    job.step(stall_s, Odometry(t=stall_s), blocked)
    np.testing.assert_allclose(policy.seen[-1][:3], [0.1, 0.0, -1.0], atol=1e-6)  # 1 m behind
    assert job.summary()["stall_escapes"] == 1


def test_a_policy_stalled_with_the_way_clear_hands_the_drive_to_dwa():
    """The policy stands with its goal 0.4 m away, 45° to the side, nothing near: after
    recovery.stall_s the command is DWA's best sample through the shield, the actor unasked;
    once the takeover has run its time, the policy drives again."""
    job = SafeMoveJob((0.28, -0.28), Config(), FixedPolicy([-1.0, 0.0]),
                      lambda: 0.0)  # type: ignore[arg-type]
    policy = job._policy
    open_room = wall_world(10.0)
    cfg = Config().recovery
    for t in np.arange(0.0, cfg.stall_s, 0.05):
        assert job.step(float(t), Odometry(t=float(t)), open_room).v == pytest.approx(0.0)
    asked = len(policy.seen)
    cmd = job.step(cfg.stall_s, Odometry(t=cfg.stall_s), open_room)
    best = job.planning.last_context.dwa.best
    assert (cmd.v, cmd.omega) == pytest.approx(best) and best[0] > 0.0
    assert len(policy.seen) == asked  # the actor was not asked
    trace = job.trace()
    assert trace.observation is not None and trace.action is None
    assert job.summary()["dwa_takeovers"] == 1 and job.summary()["stall_escapes"] == 0
    job.step(cfg.stall_s + cfg.escape_timeout_s, Odometry(t=cfg.stall_s), open_room)
    assert len(policy.seen) == asked + 1  # the policy again


def test_goal_reached_stops_and_finishes():
    job, _ = job_with([1.0, 0.0])
    assert job.step(0.0, Odometry(x=2.9, v=0.0), wall_world(5.0)) == STOP
    assert job.finished and job.summary()["reached"]


def test_a_spec_wanting_more_path_points_than_the_dwa_has_is_refused():
    from dataclasses import replace

    from runtime.policy.obs_spec import DWABlock

    policy = FixedPolicy([0, 0])
    policy.spec = replace(SPEC, blocks=(*SPEC.blocks[:3], DWABlock(path_points=50),
                                        SPEC.blocks[4]))
    with pytest.raises(ConfigError, match="takes 50 DWA path points, but the DWA rolls out"
                                          " only 30 steps"):
        SafeMoveJob((1.0, 0.0), Config(), policy, lambda: 0.0)  # type: ignore[arg-type]


def test_the_probe_observation_builds_for_every_preset_inside_its_bounds():
    from runtime.policy.actor import probe_observation

    for spec in PRESETS.values():
        obs = probe_observation(spec)
        lo, hi = spec.bounds()
        assert obs.shape == (spec.size,) and np.all((obs >= lo) & (obs <= hi))
