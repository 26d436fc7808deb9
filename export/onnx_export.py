"""torch actor → ONNX file the runtime accepts, verified before it is written.

Steps: the legacy TorchScript-based exporter (`dynamo=False`: offline, deterministic, and it
takes TorchScript modules; the dynamo exporter would also need onnxscript), input `obs`
(batch, N) and output `action` (batch, 2), opset 17; the spec JSON and the provenance JSON
into the metadata (`runtime.policy.actor.META_SPEC`, `META_PROVENANCE`); the full onnx checker; the
runtime's own loader (`runtime.policy.actor.Policy`: names, shapes, spec, probe); parity, i.e. max
|torch − onnxruntime| over 1,000 random observations (uniform in the spec's bounds) and 1,000
recorded ones (`sim_stub.recorded_observations` through the CLI, or the user's file), each
run batch-1 as in the loop, failing above 1e-5; latency p50/p99 of batch-1 inference on the
runtime's session settings.
Optionally an int8 copy (onnxruntime dynamic quantization of the weights) with its parity
and latency against fp32. Nothing is written to the output path unless every check passes;
the path is checked before the export and written atomically after it (`export.output`).
"""

from __future__ import annotations

import datetime
import hashlib
import io
import json
import logging
import platform
import tempfile
import time
import warnings
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
import torch

from export.checkpoint import LoadedActor
from export.output import check_output, int8_path, write_atomically
from export.ship import set_metadata
from runtime.errors import UserError
from runtime.policy.actor import (
    INPUT_NAME,
    META_PROVENANCE,
    META_SPEC,
    OUTPUT_NAME,
    Policy,
    PolicyConfig,
    session_options,
)

OPSET = 17
PARITY_TOLERANCE = 1e-5
PARITY_COUNT = 1000
LATENCY_RUNS = 2000


class ExportFailed(UserError):
    """The exported model does not do what the checkpoint does (one line, exit 1)."""

    exit_code = 1


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def tool_versions() -> dict[str, str]:
    def version(dist: str) -> str:
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return "not installed"

    return {"safemove": version("safemove-rl"), "torch": torch.__version__,
            "onnx": onnx.__version__, "onnxruntime": ort.__version__,
            "python": platform.python_version()}


def to_onnx(actor: LoadedActor) -> onnx.ModelProto:
    """The actor as an ONNX graph with named, fixed-rank input and output, its spec in the
    metadata."""
    buf = io.BytesIO()
    with warnings.catch_warnings():
        # the legacy exporter announces its deprecation; it is the one that suits (module docs)
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        torch.onnx.export(actor.module, (torch.zeros(1, actor.spec.size),), buf,
                          input_names=[INPUT_NAME], output_names=[OUTPUT_NAME],
                          dynamic_axes={INPUT_NAME: {0: "batch"}, OUTPUT_NAME: {0: "batch"}},
                          opset_version=OPSET, dynamo=False, do_constant_folding=True)
    model = onnx.load_from_string(buf.getvalue())
    for value, last in ((model.graph.input[0], actor.spec.size), (model.graph.output[0], 2)):
        dims = value.type.tensor_type.shape.dim
        del dims[:]
        dims.add().dim_param = "batch"
        dims.add().dim_value = last
    set_metadata(model, {META_SPEC: actor.spec.to_json()})
    model.producer_name = "safemove export"
    return model


def torch_outputs(module: torch.nn.Module, obs: np.ndarray) -> np.ndarray:
    """Batch-1 torch outputs on one intra-op thread: with torch's default of one per core, a
    busy machine leaves each call waiting milliseconds for a descheduled worker (seen: 4 ms
    instead of 0.1 ms per 800/600 layer)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with torch.no_grad():
            return np.stack([module(torch.from_numpy(o[None]))[0].numpy() for o in obs])
    finally:
        torch.set_num_threads(threads)


def ort_outputs(session: ort.InferenceSession, obs: np.ndarray) -> np.ndarray:
    return np.stack([session.run([OUTPUT_NAME], {INPUT_NAME: o[None]})[0][0] for o in obs])


def latency_us(session: ort.InferenceSession, obs: np.ndarray, runs: int) -> dict[str, float]:
    """Batch-1 inference p50/p99 (µs), cycling through `obs`, after a warm-up."""
    for o in obs[:100]:
        session.run([OUTPUT_NAME], {INPUT_NAME: o[None]})
    times = np.empty(runs)
    for k in range(runs):
        x = obs[k % len(obs)][None]
        t0 = time.perf_counter()
        session.run([OUTPUT_NAME], {INPUT_NAME: x})
        times[k] = time.perf_counter() - t0
    p50, p99 = np.percentile(times * 1e6, [50, 99])
    return {"p50": round(float(p50), 1), "p99": round(float(p99), 1)}


def _session(model_bytes: bytes) -> ort.InferenceSession:
    return ort.InferenceSession(model_bytes, session_options(1), providers=["CPUExecutionProvider"])


def _max_abs(a: np.ndarray, b: np.ndarray) -> float:
    d = np.abs(a.astype(np.float64) - b.astype(np.float64))
    return float(np.max(d)) if np.all(np.isfinite(d)) else float("inf")


def export_actor(actor: LoadedActor, source: Path, output: Path, recorded: np.ndarray,
                 recorded_from: str, int8: bool = False) -> dict[str, Any]:
    """Export, verify, write; returns the report. Raises ExportFailed or OutputError (nothing
    written)."""
    check_output(output, source, int8)
    spec = actor.spec
    model = to_onnx(actor)
    provenance = {
        "source": source.name, "source_sha256": sha256_of(source),
        "checkpoint_kind": actor.kind, **actor.details,
        "exported_at": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "tools": tool_versions(), "opset": OPSET,
    }
    onnx.checker.check_model(model, full_check=True)

    rng = np.random.default_rng(0)
    lo, hi = spec.bounds()
    random_obs = rng.uniform(lo, hi, size=(PARITY_COUNT, spec.size)).astype(np.float32)
    if recorded.ndim != 2 or recorded.shape[1] != spec.size:
        raise ExportFailed(f"{recorded_from}: recorded observations have shape"
                           f" {list(recorded.shape)}; the spec '{spec.name}' needs (n, {spec.size})")
    recorded = recorded[:PARITY_COUNT].astype(np.float32)
    session = _session(model.SerializeToString())
    parity = {}
    for name, obs in (("random", random_obs), ("recorded", recorded)):
        parity[name] = {"count": len(obs),
                        "max_abs": _max_abs(torch_outputs(actor.module, obs),
                                            ort_outputs(session, obs))}
    parity["recorded"]["from"] = recorded_from
    parity["tolerance"] = PARITY_TOLERANCE
    worst = max(parity["random"]["max_abs"], parity["recorded"]["max_abs"])
    if not worst <= PARITY_TOLERANCE:
        raise ExportFailed(f"{source}: onnxruntime differs from torch by {worst:.3g} (tolerance"
                           f" {PARITY_TOLERANCE:g}): {output} not written")
    provenance["parity_max_abs"] = {k: parity[k]["max_abs"] for k in ("random", "recorded")}
    set_metadata(model, {META_PROVENANCE: json.dumps(provenance, separators=(",", ":"))})
    data = model.SerializeToString()
    session = _session(data)
    both = np.concatenate([random_obs, recorded])
    report: dict[str, Any] = {
        "output": str(output), "spec": spec.name, "features": spec.size,
        "checkpoint_kind": actor.kind, "details": actor.details, "parity": parity,
        "latency_us": {"onnxruntime_fp32": latency_us(session, both, LATENCY_RUNS),
                       "threads": 1},
        "provenance": provenance,
    }
    with tempfile.TemporaryDirectory(prefix="safemove-export-") as tmp:
        staged = Path(tmp) / "actor.onnx"
        staged.write_bytes(data)
        Policy(staged, PolicyConfig(warmup_runs=1))  # the runtime itself accepts it
        files = {output: data}
        if int8:
            report["int8"], files[int8_path(output)] = _int8(staged, Path(tmp), actor, session,
                                                             both)
            report["int8"]["output"] = str(int8_path(output))
    write_atomically(files)
    return report


def _int8(staged: Path, tmp: Path, actor: LoadedActor, fp32: ort.InferenceSession,
          obs: np.ndarray) -> tuple[dict[str, Any], bytes]:
    """Dynamic int8 quantization (int8 weights, activations quantized at run time), with the
    fp32 file's metadata, accepted by the runtime's loader; no parity threshold (reported)."""
    from onnxruntime.quantization import QuantType, quantize_dynamic

    quantized = tmp / "actor.int8.onnx"
    logging.disable(logging.INFO)  # the quantizer logs every tensor on the root logger
    try:
        quantize_dynamic(staged, quantized, weight_type=QuantType.QInt8)
    finally:
        logging.disable(logging.NOTSET)
    model = onnx.load(quantized)
    set_metadata(model, {p.key: p.value for p in onnx.load(staged).metadata_props})
    data = model.SerializeToString()
    quantized.write_bytes(data)
    Policy(quantized, PolicyConfig(warmup_runs=1))
    session = _session(data)
    q = ort_outputs(session, obs)
    return {
        "max_abs_vs_fp32": _max_abs(q, ort_outputs(fp32, obs)),
        "max_abs_vs_torch": _max_abs(q, torch_outputs(actor.module, obs)),
        "latency_us": latency_us(session, obs, LATENCY_RUNS),
    }, data
