"""`safemove bench policy`: the actor's batch-1 latency, onnxruntime vs torch eager, one run.

Same actor, same observations, same process: an MLP actor on the SafeMove preset's
observation (61 features) in the two common sizes — 400/300 (stable-baselines3's TD3 default)
and 800/600 (the widely used layer_1/2/3 navigation actor) — randomly initialised (latency does
not depend on the weights). onnxruntime runs through the runtime's own `Policy` (the loop's
call, session settings from config defaults: 1 thread, no spinning); torch eager runs the
module under no_grad with torch's intra-op threads set to the same count. Needs the export
extra (torch). Timed in alternating blocks of BLOCK inferences per engine.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from runtime.errors import UserError
from runtime.policy.actor import Policy, PolicyConfig
from runtime.policy.obs_spec import PRESETS

SIZES = ((400, 300), (800, 600))
BLOCK = 250  # inferences per engine before switching


def _percentiles(times: np.ndarray) -> dict[str, float]:
    p50, p99 = np.percentile(times * 1e6, [50, 99])
    return {"p50": round(float(p50), 1), "p99": round(float(p99), 1)}


def bench_policy(runs: int) -> dict[str, Any]:
    try:
        import torch
    except ImportError:
        raise UserError("bench policy compares against torch: install the export extra"
                        " (pip install -e '.[export]')") from None
    from export.checkpoint import LoadedActor
    from export.mlp import MLPActor
    from export.onnx_export import to_onnx

    spec = PRESETS["safemove"]
    cfg = PolicyConfig()
    torch.manual_seed(0)
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(cfg.intra_op_threads)
    lo, hi = spec.bounds()
    obs = np.random.default_rng(0).uniform(lo, hi, (256, spec.size)).astype(np.float32)
    result: dict[str, Any] = {"bench": "policy", "spec": spec.name, "features": spec.size,
                              "runs": runs, "onnxruntime_threads": cfg.intra_op_threads,
                              "torch_threads": torch.get_num_threads(), "actors": {}}
    try:
        with tempfile.TemporaryDirectory(prefix="safemove-bench-") as tmp:
            for hidden in SIZES:
                actor = MLPActor([spec.size, *hidden, 2]).eval()
                path = Path(tmp) / "actor.onnx"
                path.write_bytes(to_onnx(LoadedActor(actor, "bench", spec)).SerializeToString())
                policy = Policy(path, cfg)
                ort_t = np.empty(runs)
                torch_t = np.empty(runs)
                inputs = [torch.from_numpy(o[None]) for o in obs]
                with torch.no_grad():
                    for k in range(200):  # warm-up, as the runtime does before READY
                        actor(inputs[k % len(inputs)])
                    # alternating blocks: both engines see the same machine load, and each
                    # runs with its weights warm in cache, as the loop's engine alone does
                    # (call by call interleaving made the 800/600 actor ~2x slower in both)
                    for start in range(0, runs, BLOCK):
                        for k in range(start, min(runs, start + BLOCK)):
                            t0 = time.perf_counter()
                            policy.act(obs[k % len(obs)])
                            ort_t[k] = time.perf_counter() - t0
                        for k in range(start, min(runs, start + BLOCK)):
                            t0 = time.perf_counter()
                            actor(inputs[k % len(inputs)])
                            torch_t[k] = time.perf_counter() - t0
                ort_s, torch_s = _percentiles(ort_t), _percentiles(torch_t)
                result["actors"][f"{spec.size}-{hidden[0]}-{hidden[1]}-2"] = {
                    "onnxruntime_us": ort_s, "torch_eager_us": torch_s,
                    "torch_over_onnxruntime_p50": round(torch_s["p50"] / ort_s["p50"], 2),
                }
    finally:
        torch.set_num_threads(previous_threads)
    return result
