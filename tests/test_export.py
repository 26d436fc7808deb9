"""`safemove export` on the four checkpoint kinds (made here with torch) and its refusals."""

from __future__ import annotations

import errno
import io
import json
import os
import pickle
import subprocess
import sys
import zipfile
from collections import OrderedDict

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from export.checkpoint import save_actor_checkpoint
from export.mlp import MLPActor
from runtime.cli.main import main
from runtime.policy.actor import META_PROVENANCE, META_SPEC, Policy, PolicyConfig
from runtime.policy.obs_spec import PRESETS
from sim_stub.recorded_observations import recorded_observations

SAFEMOVE = PRESETS["safemove"]
DRL = PRESETS["drl"]


@pytest.fixture(scope="module")
def observations(tmp_path_factory) -> dict[str, str]:
    """Recorded observations once for the module (fewer than the CLI's 1,000, for time): the
    safemove preset's, and the drl preset's (its blocks are the safemove layout's first 25)."""
    obs = recorded_observations(SAFEMOVE, 300)
    d = tmp_path_factory.mktemp("obs")
    np.save(d / "safemove.npy", obs)
    np.save(d / "drl.npy", obs[:, :DRL.size])
    return {"safemove": str(d / "safemove.npy"), "drl": str(d / "drl.npy")}


def export(capsys, *args: str) -> tuple[int, dict | None, str]:
    code = main(["export", "--json", *args])
    out, err = capsys.readouterr()
    lines = [ln for ln in out.splitlines() if ln.strip()]
    return code, json.loads(lines[-1]) if code == 0 else None, err


def metadata(path) -> dict[str, str]:
    return {p.key: p.value for p in onnx.load(str(path)).metadata_props}


def td3_nav_state_dict(n_in: int, seed: int = 0, hidden: tuple[int, int] = (800, 600)
                       ) -> OrderedDict:
    """The widely used TD3 navigation actor's layout: layer_1 (S→800), layer_2, layer_3 (→2)."""
    g = torch.Generator().manual_seed(seed)
    sd = OrderedDict()
    h1, h2 = hidden
    for name, (o, i) in (("layer_1", (h1, n_in)), ("layer_2", (h2, h1)), ("layer_3", (2, h2))):
        sd[f"{name}.weight"] = torch.randn(o, i, generator=g) / i**0.5
        sd[f"{name}.bias"] = torch.randn(o, generator=g) * 0.1
    return sd


def td3_nav_reference(sd: OrderedDict, obs: np.ndarray) -> np.ndarray:
    """That actor's forward pass written out: ReLU hidden layers, tanh output."""
    x = torch.from_numpy(obs)
    x = torch.relu(x @ sd["layer_1.weight"].T + sd["layer_1.bias"])
    x = torch.relu(x @ sd["layer_2.weight"].T + sd["layer_2.bias"])
    return torch.tanh(x @ sd["layer_3.weight"].T + sd["layer_3.bias"]).numpy()


def test_a_project_checkpoint_exports_with_its_own_spec_and_provenance(tmp_path, capsys):
    torch.manual_seed(0)
    actor = MLPActor([SAFEMOVE.size, 400, 300, 2])
    ckpt = tmp_path / "actor.pt"
    save_actor_checkpoint(ckpt, actor, SAFEMOVE, "randomly initialised (untrained)")
    out = tmp_path / "actor.onnx"
    # no --spec, no --observations: the checkpoint's spec, a simulated run's observations
    code, report, err = export(capsys, str(ckpt), "-o", str(out))
    assert code == 0, err
    assert report["checkpoint_kind"] == "safemove actor checkpoint"
    assert report["parity"]["random"]["count"] == report["parity"]["recorded"]["count"] == 1000
    assert report["parity"]["random"]["max_abs"] <= 1e-5
    assert report["parity"]["recorded"]["max_abs"] <= 1e-5
    assert report["parity"]["recorded"]["from"].startswith("simulated run")
    assert 0 < report["latency_us"]["onnxruntime_fp32"]["p50"] <= (
        report["latency_us"]["onnxruntime_fp32"]["p99"])
    meta = metadata(out)
    assert json.loads(meta[META_SPEC]) == SAFEMOVE.to_dict()
    prov = json.loads(meta[META_PROVENANCE])
    import hashlib

    assert prov["source_sha256"] == hashlib.sha256(ckpt.read_bytes()).hexdigest()
    assert prov["note"] == "randomly initialised (untrained)"
    assert prov["layer_sizes"] == [61, 400, 300, 2]
    assert set(prov["tools"]) >= {"torch", "onnx", "onnxruntime", "safemove"}
    assert prov["exported_at"] and prov["parity_max_abs"]["recorded"] <= 1e-5
    # the runtime accepts it and computes what torch computes
    policy = Policy(out, PolicyConfig(warmup_runs=1))
    obs = np.random.default_rng(3).uniform(*SAFEMOVE.bounds(), (20, SAFEMOVE.size))
    obs = obs.astype(np.float32)
    with torch.no_grad():
        expected = actor(torch.from_numpy(obs)).numpy()
    np.testing.assert_allclose([policy.act(o) for o in obs], expected, atol=1e-5)


def test_an_sb3_td3_zip_exports_with_unscaling_equal_to_predict(tmp_path, capsys, observations):
    sb3 = pytest.importorskip("stable_baselines3")
    gym = pytest.importorskip("gymnasium")

    class Env(gym.Env):
        observation_space = gym.spaces.Box(-1.0, 1.0, (SAFEMOVE.size,), np.float32)
        action_space = gym.spaces.Box(np.array([0.0, -1.0], np.float32),
                                      np.array([0.3, 1.0], np.float32))  # physical (v, ω)

        def reset(self, seed=None, options=None):
            return np.zeros(SAFEMOVE.size, np.float32), {}

        def step(self, action):
            return np.zeros(SAFEMOVE.size, np.float32), 0.0, False, False, {}

    model = sb3.TD3("MlpPolicy", Env(), seed=1, device="cpu")  # actor [400, 300]
    model.save(tmp_path / "td3.zip")
    out = tmp_path / "td3.onnx"
    code, report, err = export(capsys, str(tmp_path / "td3.zip"), "-o", str(out), "--spec",
                               "safemove", "--observations", observations["safemove"])
    assert code == 0, err
    assert report["checkpoint_kind"] == "stable-baselines3 TD3"
    assert report["details"]["layer_sizes"] == [61, 400, 300, 2]
    policy = Policy(out, PolicyConfig(warmup_runs=1))
    assert policy.spec.action.output_low == (0.0, -1.0)  # the model's box went into its spec
    assert policy.spec.action.output_high == pytest.approx((0.3, 1.0))
    obs = np.load(observations["safemove"])[:200]
    predicted, _ = model.predict(obs, deterministic=True)
    got = np.array([policy.act(o) for o in obs])
    np.testing.assert_allclose(got, predicted, atol=1e-5)
    # and the runtime's action mapping turns that box into the same (v, ω)
    tw = policy.spec.action.to_twist(got[0])
    assert (tw.v, tw.omega) == pytest.approx(tuple(predicted[0]), abs=1e-5)


def test_a_layer_1_2_3_state_dict_exports_with_its_architecture_inferred(tmp_path, capsys,
                                                                          observations):
    sd = td3_nav_state_dict(DRL.size)
    torch.save(sd, tmp_path / "TD3_actor.pth")
    out = tmp_path / "nav.onnx"
    code, report, err = export(capsys, str(tmp_path / "TD3_actor.pth"), "-o", str(out), "--spec",
                               "drl", "--observations", observations["drl"])
    assert code == 0, err
    assert report["checkpoint_kind"] == "state_dict MLP"
    assert report["details"]["layer_sizes"] == [25, 800, 600, 2]
    assert report["parity"]["recorded"]["max_abs"] <= 1e-5
    policy = Policy(out, PolicyConfig(warmup_runs=1))
    obs = np.load(observations["drl"])[:50]
    np.testing.assert_allclose([policy.act(o) for o in obs], td3_nav_reference(sd, obs),
                               atol=1e-5)


def test_a_torchscript_module_exports(tmp_path, capsys, observations):
    torch.manual_seed(2)
    net = torch.nn.Sequential(torch.nn.Linear(DRL.size, 64), torch.nn.ELU(),
                              torch.nn.Linear(64, 2), torch.nn.Tanh())
    torch.jit.save(torch.jit.script(net), str(tmp_path / "actor_ts.pt"))
    out = tmp_path / "ts.onnx"
    code, report, err = export(capsys, str(tmp_path / "actor_ts.pt"), "-o", str(out), "--spec",
                               "drl", "--observations", observations["drl"])
    assert code == 0, err
    assert report["checkpoint_kind"] == "TorchScript module"
    obs = np.load(observations["drl"])[:50]
    with torch.no_grad():
        expected = net(torch.from_numpy(obs)).numpy()
    policy = Policy(out, PolicyConfig(warmup_runs=1))
    np.testing.assert_allclose([policy.act(o) for o in obs], expected, atol=1e-5)


def test_int8_reports_parity_and_latency_against_fp32(tmp_path, capsys, observations):
    sd = td3_nav_state_dict(DRL.size, seed=4, hidden=(64, 32))
    torch.save(sd, tmp_path / "a.pth")
    code, report, err = export(capsys, str(tmp_path / "a.pth"), "-o", str(tmp_path / "a.onnx"),
                               "--spec", "drl", "--observations", observations["drl"], "--int8")
    assert code == 0, err
    q = report["int8"]
    assert q["output"] == str(tmp_path / "a.int8.onnx")
    assert 0 < q["max_abs_vs_fp32"] < 0.1 and q["latency_us"]["p50"] > 0
    assert Policy(tmp_path / "a.int8.onnx", PolicyConfig(warmup_runs=1)).spec == DRL


# --- refusals ------------------------------------------------------------------------------------


def refused(capsys, *args: str) -> str:
    code, _, err = export(capsys, *args)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def test_a_state_dict_that_is_not_an_mlp_is_refused(tmp_path, capsys):
    conv = OrderedDict([("conv.weight", torch.zeros(8, 1, 3, 3)), ("conv.bias", torch.zeros(8)),
                        ("fc.weight", torch.zeros(2, 8)), ("fc.bias", torch.zeros(2))])
    torch.save(conv, tmp_path / "conv.pth")
    msg = refused(capsys, str(tmp_path / "conv.pth"), "-o", str(tmp_path / "x.onnx"),
                  "--spec", "drl")
    assert msg == (f"safemove: error: {tmp_path / 'conv.pth'}: layer 'conv' has weight"
                   " [8, 1, 3, 3], not a Linear layer's (out, in): not an MLP actor")
    broken = td3_nav_state_dict(DRL.size)
    broken["layer_2.weight"] = torch.zeros(600, 700)
    broken["norm.running_mean"] = torch.zeros(2)
    torch.save(broken, tmp_path / "broken.pth")
    msg = refused(capsys, str(tmp_path / "broken.pth"), "-o", str(tmp_path / "x.onnx"),
                  "--spec", "drl")
    assert "key 'norm.running_mean' (shape [2]) is not a Linear layer's weight or bias" in msg
    del broken["norm.running_mean"]
    torch.save(broken, tmp_path / "broken.pth")
    msg = refused(capsys, str(tmp_path / "broken.pth"), "-o", str(tmp_path / "x.onnx"),
                  "--spec", "drl")
    assert "layer 'layer_2' takes 700 inputs but the layer before outputs 800" in msg
    assert not (tmp_path / "x.onnx").exists()


def test_an_input_size_that_disagrees_with_the_spec_is_refused(tmp_path, capsys):
    torch.save(td3_nav_state_dict(24), tmp_path / "nav24.pth")  # 20 bins + 4: the original
    msg = refused(capsys, str(tmp_path / "nav24.pth"), "-o", str(tmp_path / "x.onnx"),
                  "--spec", "drl")
    assert msg == (f"safemove: error: {tmp_path / 'nav24.pth'}: the actor takes 24 inputs but"
                   " the spec 'drl' builds 25 features (goal 3, velocity 2, scan 20)")
    torch.jit.save(torch.jit.script(torch.nn.Linear(24, 2)), str(tmp_path / "ts24.pt"))
    msg = refused(capsys, str(tmp_path / "ts24.pt"), "-o", str(tmp_path / "x.onnx"),
                  "--spec", "drl")
    assert "the module does not take the spec 'drl''s 25 features" in msg
    actor = MLPActor([SAFEMOVE.size, 8, 2])
    save_actor_checkpoint(tmp_path / "own.pt", actor, SAFEMOVE, "test")
    msg = refused(capsys, str(tmp_path / "own.pt"), "-o", str(tmp_path / "x.onnx"),
                  "--spec", "drl")
    assert "the actor was trained with spec 'safemove' (61 features); --spec gives 'drl'" in msg


def test_pickled_code_is_refused_without_the_flag(tmp_path, capsys, observations):
    net = torch.nn.Sequential(torch.nn.Linear(DRL.size, 16), torch.nn.ReLU(),
                              torch.nn.Linear(16, 2), torch.nn.Tanh())
    torch.save(net, tmp_path / "whole_model.pt")  # pickles the classes: code on load
    args = [str(tmp_path / "whole_model.pt"), "-o", str(tmp_path / "m.onnx"), "--spec", "drl",
            "--observations", observations["drl"]]
    msg = refused(capsys, *args)
    assert msg == (f"safemove: error: {tmp_path / 'whole_model.pt'}: loading it needs pickled"
                   " Python code (torch.nn.modules.activation.ReLU,"
                   " torch.nn.modules.activation.Tanh, torch.nn.modules.container.Sequential and"
                   " 1 more), which can run anything; refused (pass --trust-checkpoint only for a"
                   " file from a source you trust)")
    assert not (tmp_path / "m.onnx").exists()
    torch.save(net, tmp_path / "legacy.pt", _use_new_zipfile_serialization=False)
    msg = refused(capsys, str(tmp_path / "legacy.pt"), *args[1:])
    assert "legacy.pt: loading it needs pickled Python code (torch.nn.modules.container" in msg
    assert "--trust-checkpoint" in msg
    code, report, err = export(capsys, *args, "--trust-checkpoint")
    assert code == 0, err
    assert report["checkpoint_kind"] == "pickled torch module"


def test_other_refusals(tmp_path, capsys):
    torch.save(td3_nav_state_dict(DRL.size), tmp_path / "a.pth")
    msg = refused(capsys, str(tmp_path / "a.pth"), "-o", str(tmp_path / "x.onnx"))
    assert "a state_dict carries no observation spec: give --spec" in msg
    msg = refused(capsys, str(tmp_path / "none.pt"), "-o", str(tmp_path / "x.onnx"))
    assert msg.endswith("none.pt: checkpoint not found")
    (tmp_path / "junk.pt").write_bytes(b"junk")
    msg = refused(capsys, str(tmp_path / "junk.pt"), "-o", str(tmp_path / "x.onnx"))
    assert "junk.pt: not a torch checkpoint" in msg
    three = td3_nav_state_dict(DRL.size)
    three["layer_3.weight"], three["layer_3.bias"] = torch.zeros(3, 600), torch.zeros(3)
    torch.save(three, tmp_path / "three.pth")
    msg = refused(capsys, str(tmp_path / "three.pth"), "-o", str(tmp_path / "x.onnx"),
                  "--spec", "drl")
    assert "the last layer 'layer_3' outputs 3; an actor outputs 2 (v, ω)" in msg


def test_a_parity_failure_writes_nothing_and_exits_1(tmp_path, capsys, observations,
                                                      monkeypatch):
    import export.onnx_export as ox

    real = ox.torch_outputs
    monkeypatch.setattr(ox, "torch_outputs", lambda m, o: real(m, o) + 1e-3)
    torch.save(td3_nav_state_dict(DRL.size, hidden=(64, 32)), tmp_path / "a.pth")
    code, _, err = export(capsys, str(tmp_path / "a.pth"), "-o", str(tmp_path / "a.onnx"),
                          "--spec", "drl", "--observations", observations["drl"])
    assert code == 1 and "differs from torch by 0.001 (tolerance 1e-05)" in err
    assert not (tmp_path / "a.onnx").exists()


def test_recorded_observations_are_deterministic_and_inside_the_bounds():
    a = recorded_observations(SAFEMOVE, 60, seed=5)
    assert np.array_equal(a, recorded_observations(SAFEMOVE, 60, seed=5))
    lo, hi = SAFEMOVE.bounds()
    assert np.all((a >= lo) & (a <= hi))
    assert a[:, 3].max() > -1.0  # the robot moved (velocity feature left its floor)


def test_bench_policy_reports_onnxruntime_and_torch_in_one_run(capsys):
    assert main(["bench", "policy", "--runs", "100", "--json"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["bench"] == "policy" and result["onnxruntime_threads"] == 1
    assert set(result["actors"]) == {"61-400-300-2", "61-800-600-2"}
    for figures in result["actors"].values():
        for engine in ("onnxruntime_us", "torch_eager_us"):
            assert 0 < figures[engine]["p50"] <= figures[engine]["p99"]


# --- files that are not checkpoints, agent checkpoints, output paths (issue 12, item 10) ---------


def legacy_state_dict_bytes() -> bytes:
    """A state_dict in torch.save's legacy (pre-1.6) format: a pickle stream, no zip."""
    buf = io.BytesIO()
    torch.save(td3_nav_state_dict(DRL.size, hidden=(8, 4)), buf,
               _use_new_zipfile_serialization=False)
    return buf.getvalue()


def zip_bytes(**entries: str) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, text in entries.items():
            zf.writestr(name, text)
    return buf.getvalue()


def torch_zip_bytes() -> bytes:
    buf = io.BytesIO()
    torch.save(td3_nav_state_dict(DRL.size, hidden=(8, 4)), buf)
    return buf.getvalue()


NOT_CHECKPOINTS = {  # file contents -> what the one line must say after the file's name
    "text": (b"hello world\nthis is a text file\n",
             ": not a torch checkpoint but a text file (it begins 'hello world')"),
    "random bytes": (b"\x17" + np.random.default_rng(0).bytes(4095),
                     ": not a torch checkpoint: it begins with the bytes 17 "),
    "empty": (b"", ": is empty (0 bytes)"),
    "plain pickle": (pickle.dumps({"layer_1.weight": [[0.0]]}, protocol=2),
                     ": a Python pickle but not a torch checkpoint (no torch.save header)"),
    "git lfs pointer": (b"version https://git-lfs.github.com/spec/v1\noid sha256:00\nsize 9\n",
                        ": a Git LFS pointer, not the checkpoint itself"),
    "other zip": (zip_bytes(**{"data": "{}", "readme.txt": "x"}),
                  (": a zip archive but not a stable-baselines3 model (no 'data' and"
                   " 'policy.pth'), a TorchScript module or a torch.save checkpoint; it holds"
                   " data, readme.txt")),
    "truncated zip": (torch_zip_bytes()[:600],
                      ": starts like a zip archive (PK) but is truncated or damaged"),
    "truncated legacy": (legacy_state_dict_bytes()[:-40],
                         ": a torch checkpoint that cannot be read (unexpected EOF"),
}


@pytest.mark.parametrize("kind", NOT_CHECKPOINTS)
def test_a_file_that_is_not_a_checkpoint_is_named_as_what_it_is(kind, tmp_path, capsys):
    """One line naming the file and what it is; never advice to trust it (it holds no code)."""
    content, says = NOT_CHECKPOINTS[kind]
    ckpt = tmp_path / "actor.pt"
    ckpt.write_bytes(content)
    msg = refused(capsys, str(ckpt), "-o", str(tmp_path / "x.onnx"), "--spec", "drl")
    assert msg.startswith(f"safemove: error: {ckpt}{says}"), msg
    assert "trust" not in msg
    assert sorted(p.name for p in tmp_path.iterdir()) == ["actor.pt"]


def test_a_directory_as_the_checkpoint_is_refused(tmp_path, capsys):
    msg = refused(capsys, str(tmp_path), "-o", str(tmp_path / "x.onnx"), "--spec", "drl")
    assert msg == f"safemove: error: {tmp_path}: is a directory, not a checkpoint file"


def test_the_real_process_answers_bad_files_with_one_line(tmp_path, observations):
    """`safemove export` as a user runs it: a text file as the checkpoint, /dev/full as the
    output; exit 2, one stderr line, no traceback, nothing written."""
    text = tmp_path / "notes.pt"
    text.write_text("these are not weights\n")
    torch.save(td3_nav_state_dict(DRL.size, hidden=(8, 4)), tmp_path / "a.pth")
    cases = [([str(text), "-o", str(tmp_path / "x.onnx")],
              f"{text}: not a torch checkpoint but a text file"),
             ([str(tmp_path / "a.pth"), "-o", "/dev/full", "--observations",
               observations["drl"]], "/dev/full: exists and is not a regular file")]
    for args, says in cases:
        proc = subprocess.run([sys.executable, "-m", "runtime.cli.main", "export", *args, "--spec",
                               "drl"], capture_output=True, text=True, timeout=120, check=False)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr
        assert lines[0].startswith(f"safemove: error: {says}"), lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.pth", "notes.pt"]


AGENT_LAYOUTS = {  # how training scripts save a TD3 agent: the actor's key, the rest
    "actor": ("actor_target", "critic", "critic_target"),
    "actor_state_dict": ("critic_state_dict", "actor_optimizer_state_dict"),
    "policy": ("value_net",),
}


@pytest.mark.parametrize("key", AGENT_LAYOUTS)
def test_an_agent_checkpoint_exports_its_actor(key, tmp_path, capsys, observations):
    sd = td3_nav_state_dict(DRL.size, seed=5, hidden=(64, 32))
    agent: dict = {key: sd, "total_it": 1200}
    for k, other in enumerate(AGENT_LAYOUTS[key]):
        if other.endswith("optimizer_state_dict"):
            params = [torch.nn.Parameter(v.clone()) for v in sd.values()]
            agent[other] = torch.optim.Adam(params).state_dict()
        else:  # a critic takes state and action; a target is another actor
            agent[other] = td3_nav_state_dict(DRL.size + 2 * ("critic" in other), seed=k)
    torch.save(agent, tmp_path / "agent.pth")
    out = tmp_path / "agent.onnx"
    code, report, err = export(capsys, str(tmp_path / "agent.pth"), "-o", str(out), "--spec",
                               "drl", "--observations", observations["drl"])
    assert code == 0, err
    assert report["details"]["actor_key"] == key
    assert report["details"]["layer_sizes"] == [25, 64, 32, 2]
    assert max(report["parity"][k]["max_abs"] for k in ("random", "recorded")) <= 1e-5
    obs = np.load(observations["drl"])[:50]
    policy = Policy(out, PolicyConfig(warmup_runs=1))
    np.testing.assert_allclose([policy.act(o) for o in obs], td3_nav_reference(sd, obs),
                               atol=1e-5)


def test_an_agent_checkpoint_without_one_actor_key_is_refused_naming_its_keys(tmp_path, capsys,
                                                                              observations):
    sd = td3_nav_state_dict(DRL.size, hidden=(16, 8))
    torch.save({"net": sd, "critic": td3_nav_state_dict(27)}, tmp_path / "unknown.pth")
    msg = refused(capsys, str(tmp_path / "unknown.pth"), "-o", str(tmp_path / "x.onnx"),
                  "--spec", "drl")
    assert msg == (f"safemove: error: {tmp_path / 'unknown.pth'}: an agent checkpoint with the"
                   " keys 'net', 'critic'; expected the actor's state_dict under one of 'actor',"
                   " 'actor_state_dict', 'policy', 'policy_state_dict' (choose with --prefix"
                   " KEY.)")
    torch.save({"actor": sd, "policy": sd}, tmp_path / "both.pth")
    msg = refused(capsys, str(tmp_path / "both.pth"), "-o", str(tmp_path / "x.onnx"),
                  "--spec", "drl")
    assert "with the keys 'actor', 'policy'; expected the actor's state_dict under only one" in msg
    assert not (tmp_path / "x.onnx").exists()
    code, report, err = export(capsys, str(tmp_path / "unknown.pth"), "-o",
                               str(tmp_path / "x.onnx"), "--spec", "drl", "--prefix", "net.",
                               "--observations", observations["drl"])
    assert code == 0, err
    assert report["details"]["layer_sizes"] == [25, 16, 8, 2]


@pytest.fixture
def no_export(monkeypatch):
    """Fails the test if the export itself starts: a bad output must be refused before it."""
    import export.onnx_export as ox

    def ran(*_: object) -> None:
        raise AssertionError("the export ran before the output path was checked")

    monkeypatch.setattr(ox, "to_onnx", ran)


def test_an_output_path_that_cannot_be_written_is_refused_before_the_export(tmp_path, capsys,
                                                                            no_export):
    ckpt = tmp_path / "a.pth"
    torch.save(td3_nav_state_dict(DRL.size, hidden=(8, 4)), ckpt)
    (tmp_path / "dir.onnx").mkdir()
    (tmp_path / "file").write_text("")
    (tmp_path / "b.int8.onnx").mkdir()
    cases = {
        str(tmp_path / "dir.onnx"): "is a directory, not a file name for the ONNX model",
        str(tmp_path / "missing" / "a.onnx"): f"the directory {tmp_path / 'missing'} does not"
                                              " exist",
        str(tmp_path / "file" / "a.onnx"): f"the directory {tmp_path / 'file'} is not a"
                                           " directory",
        str(ckpt): "is the checkpoint itself; writing would destroy it",
        "/dev/full": "exists and is not a regular file (a device, pipe or socket)",
    }
    for output, says in cases.items():
        msg = refused(capsys, str(ckpt), "-o", output, "--spec", "drl")
        assert msg.startswith(f"safemove: error: {output}: {says}"), msg
    msg = refused(capsys, str(ckpt), "-o", str(tmp_path / "b.onnx"), "--spec", "drl", "--int8")
    assert msg.startswith(f"safemove: error: {tmp_path / 'b.int8.onnx'}: is a directory"), msg
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.pth", "b.int8.onnx", "dir.onnx",
                                                          "file"]


def test_a_read_only_directory_is_refused_before_the_export(tmp_path, capsys, no_export):
    ckpt = tmp_path / "a.pth"
    torch.save(td3_nav_state_dict(DRL.size, hidden=(8, 4)), ckpt)
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        if os.access(ro, os.W_OK):
            pytest.skip("running as root: a read-only mode does not stop writes")
        msg = refused(capsys, str(ckpt), "-o", str(ro / "a.onnx"), "--spec", "drl")
        assert msg == f"safemove: error: {ro / 'a.onnx'}: the directory {ro} is not writable"
    finally:
        ro.chmod(0o755)


def test_a_full_disk_at_the_end_writes_nothing_and_keeps_the_old_model(tmp_path, capsys,
                                                                       observations,
                                                                       monkeypatch):
    """The disk fills while the int8 copy is written (the second file; an 8 KiB tmpfs gives the
    same line): one line, exit 2, the previous model untouched, no temporary file left."""
    torch.save(td3_nav_state_dict(DRL.size, hidden=(16, 8)), tmp_path / "a.pth")
    (tmp_path / "a.onnx").write_bytes(b"the previous model")
    real_fsync, calls = os.fsync, []

    def fsync(fd: int) -> None:
        calls.append(fd)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    msg = refused(capsys, str(tmp_path / "a.pth"), "-o", str(tmp_path / "a.onnx"), "--spec",
                  "drl", "--observations", observations["drl"], "--int8")
    assert msg == (f"safemove: error: {tmp_path / 'a.int8.onnx'}: writing it failed (No space"
                   " left on device); nothing was written")
    assert (tmp_path / "a.onnx").read_bytes() == b"the previous model"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.onnx", "a.pth"]
