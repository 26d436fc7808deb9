"""The TD3 actor in the loop: an onnxruntime session checked at load, sized for a small CPU.

An actor file is usable only if it is what `safemove export` writes: one float32 input `obs`
of shape (batch, N) and one output `action` of shape (batch, 2), and the observation spec JSON
in the metadata under `safemove.obs_spec`, a spec this runtime can build whose size is N. Every
refusal is a ConfigError naming the file (one line, exit 2). A probe observation built by the
spec's own builder must give finite outputs before the loop may start.

Session: explicit thread counts, sequential execution, and no spinning worker threads (they ate
whole cores in a comparable robot runtime: field notes, onnxruntime); warmed up at load, because
the first inferences are slow.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from runtime.config.schema import setting
from runtime.errors import ConfigError
from runtime.policy.obs_spec import ObservationBuilder, ObsSpec, SpecError

if TYPE_CHECKING:
    import onnxruntime as ort

INPUT_NAME = "obs"
OUTPUT_NAME = "action"
META_SPEC = "safemove.obs_spec"
META_PROVENANCE = "safemove.provenance"
# how a shipped actor was trained and how it scored (`export.ship.stamp`): reported, not used
META_TRAINING = "safemove.training"
META_EVALUATION = "safemove.evaluation"


@dataclass(frozen=True)
class PolicyConfig:
    intra_op_threads: int = setting(1, "onnxruntime threads for one inference (a batch-1 MLP"
                                    " gains nothing from more)", min=1, max=16)
    warmup_runs: int = setting(50, "inferences run at load, before the loop starts", min=1,
                               max=10000)


def session_options(threads: int) -> ort.SessionOptions:
    """Options for a small CPU: fixed threads, sequential, no spinning."""
    import onnxruntime as ort  # here, not at the top: the config imports PolicyConfig

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.add_session_config_entry("session.inter_op.allow_spinning", "0")
    so.log_severity_level = 3
    return so


def probe_observation(spec: ObsSpec) -> np.ndarray:
    """An observation the spec's builder makes from a plain synthetic scene: goal 2 m ahead,
    a wall 1.5 m ahead, a straight DWA path, a 0.5 m corridor. Proves the spec builds."""
    from types import SimpleNamespace

    bins = 90
    angles = np.linspace(-0.75, 0.75, bins)
    world = SimpleNamespace(scan=np.full(bins, 1.5, dtype=np.float32),
                            unknown=np.zeros(bins, dtype=bool), bin_angles=angles)
    dwa_block = spec.block("dwa")
    steps = max(30, dwa_block.path_points if dwa_block is not None else 0)
    t = np.arange(1, steps + 1) * 0.1
    path = np.stack([0.2 * t, np.zeros(steps), np.zeros(steps)], axis=1)
    one = np.array([0.5])
    dwa = SimpleNamespace(best=(0.2, 0.0), best_path=path, best_index=0, heading=one,
                          clearance=one, velocity=one, density=one)
    cor_block = spec.block("corridor")
    k = cor_block.samples if cor_block is not None else 1
    corridor = SimpleNamespace(left=np.full(k, 0.5), right=np.full(k, 0.5))
    return ObservationBuilder(spec).build(np.array([2.0, 0.0]), 0.1, 0.0, world, dwa,
                                          corridor).copy()


class Policy:
    """A validated actor: `act(obs)` → the model's raw output (2,), float32."""

    def __init__(self, path: Path, cfg: PolicyConfig) -> None:
        import onnxruntime as ort

        self.path = path
        where = str(path)
        if not path.is_file():
            raise ConfigError(f"{where}: model file not found")
        try:
            self._session = ort.InferenceSession(str(path), session_options(cfg.intra_op_threads),
                                                 providers=["CPUExecutionProvider"])
        except Exception as exc:  # noqa: BLE001 - onnxruntime's error types derive from Exception
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise ConfigError(f"{where}: not a loadable ONNX model: {first}") from None
        meta = self._session.get_modelmeta().custom_metadata_map
        self.spec = self._check_io_and_spec(where, meta)
        self.provenance = _json_object(meta, META_PROVENANCE)
        self.training = _json_object(meta, META_TRAINING)
        self.evaluation = _json_object(meta, META_EVALUATION)
        self._input = np.zeros((1, self.spec.size), dtype=np.float32)
        self._feed = {INPUT_NAME: self._input}
        self._outputs = [OUTPUT_NAME]
        try:
            probe = probe_observation(self.spec)
        except ValueError as exc:
            raise ConfigError(f"{where}: metadata '{META_SPEC}': the spec cannot be built:"
                              f" {exc}") from None
        for _ in range(cfg.warmup_runs):
            out = self.act(probe)
        if out.shape != (2,) or not np.all(np.isfinite(out)):
            raise ConfigError(f"{where}: the model's output on a probe observation is not two"
                              f" finite numbers: {out.tolist()}")

    def _check_io_and_spec(self, where: str, meta: dict[str, str]) -> ObsSpec:
        inputs, outputs = self._session.get_inputs(), self._session.get_outputs()
        if [i.name for i in inputs] != [INPUT_NAME] or [o.name for o in outputs] != [OUTPUT_NAME]:
            raise ConfigError(
                f"{where}: expected one input '{INPUT_NAME}' and one output '{OUTPUT_NAME}', got"
                f" inputs {[i.name for i in inputs]} and outputs {[o.name for o in outputs]}"
                " (export it with `safemove export`)")
        inp, outp = inputs[0], outputs[0]
        if inp.type != "tensor(float)":
            raise ConfigError(f"{where}: input '{INPUT_NAME}' must be float32, got {inp.type}")
        n = inp.shape[-1] if len(inp.shape) == 2 else None
        if not isinstance(n, int) or not _batch_ok(inp.shape[0]):
            raise ConfigError(f"{where}: input '{INPUT_NAME}' must have shape (batch, N), got"
                              f" {inp.shape}")
        if len(outp.shape) != 2 or outp.shape[-1] != 2 or not _batch_ok(outp.shape[0]):
            raise ConfigError(f"{where}: output '{OUTPUT_NAME}' must have shape (batch, 2), got"
                              f" {outp.shape}")
        if META_SPEC not in meta:
            raise ConfigError(f"{where}: no observation spec in its metadata ('{META_SPEC}'):"
                              " export it with `safemove export ... --spec PRESET|spec.json`")
        try:
            spec = ObsSpec.from_json(meta[META_SPEC], f"{where}: metadata '{META_SPEC}'")
        except SpecError as exc:
            raise ConfigError(str(exc)) from None
        if spec.size != n:
            raise ConfigError(f"{where}: the model takes {n} features but its spec"
                              f" '{spec.name}' builds {spec.size}")
        return spec

    def act(self, obs: np.ndarray) -> np.ndarray:
        """One batch-1 inference (the input buffer is reused)."""
        self._input[0] = obs
        return self._session.run(self._outputs, self._feed)[0][0]

    @property
    def threads(self) -> int:
        return int(self._session.get_session_options().intra_op_num_threads)


def _json_object(meta: dict[str, str], key: str) -> dict[str, Any]:
    """A JSON object from the metadata, {} when absent or unreadable: these entries only
    describe the model, so they never stop it from running."""
    try:
        value = json.loads(meta.get(key, "{}"))
    except json.JSONDecodeError:
        return {}
    return value if isinstance(value, dict) else {}


def _batch_ok(dim: Any) -> bool:
    """A batch dimension: symbolic (dynamic) or 1."""
    return isinstance(dim, str) or dim is None or dim == 1
