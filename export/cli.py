"""`safemove export CHECKPOINT -o actor.onnx --spec PRESET|spec.json`: arguments and the run.

Importing this module does not import torch (the robot image has none); running it does, and
says how to install it when it is missing.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from runtime.errors import UserError
from runtime.policy.obs_spec import PRESETS, ObsSpec, load_spec


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checkpoint", type=Path,
                   help="a safemove actor checkpoint, a stable-baselines3 TD3 .zip, a state_dict"
                        " of an MLP actor (bare or in an agent dict under 'actor',"
                        " 'actor_state_dict', 'policy' or 'policy_state_dict'), or a TorchScript"
                        " module")
    p.add_argument("-o", "--output", type=Path, required=True, help="the ONNX file to write")
    p.add_argument("--spec", metavar="PRESET|FILE.json",
                   help=f"observation spec: a preset ({', '.join(PRESETS)}) or a spec JSON file;"
                        " a safemove actor checkpoint carries its own")
    p.add_argument("--trust-checkpoint", action="store_true",
                   help="allow a checkpoint whose loading runs pickled Python code (only for"
                        " files from a source you trust)")
    p.add_argument("--activation", choices=("relu", "leaky_relu", "tanh"), default="relu",
                   help="hidden activation of a plain state_dict's MLP (default relu; the output"
                        " is tanh)")
    p.add_argument("--prefix", default="",
                   help="use only the state_dict keys starting with this (e.g. actor.mu.);"
                        " keys of nested dicts are joined with dots (e.g. actor.)")
    p.add_argument("--observations", type=Path, metavar="FILE.npy",
                   help="recorded observations (n, N) float32 for the parity check (default:"
                        " 1,000 from a lock-stepped simulated run in scenario paper_b)")
    p.add_argument("--int8", action="store_true",
                   help="also write OUTPUT.int8.onnx (dynamic quantization) with its parity and"
                        " latency against fp32")


SimulatedObservations = Callable[[ObsSpec, int], tuple[np.ndarray, str]]


def _recorded(path: Path | None, spec: ObsSpec, simulated: SimulatedObservations
              ) -> tuple[np.ndarray, str]:
    if path is None:
        from export.onnx_export import PARITY_COUNT

        return simulated(spec, PARITY_COUNT)
    try:
        obs = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise UserError(f"{path}: observations file not found") from None
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: not a .npy array of observations: {exc}") from None
    if obs.ndim != 2 or obs.shape[1] != spec.size or len(obs) == 0:
        raise UserError(f"{path}: observations have shape {list(obs.shape)}; the spec"
                        f" '{spec.name}' needs (n ≥ 1, {spec.size})")
    if not np.all(np.isfinite(obs)):
        raise UserError(f"{path}: observations contain NaN or inf")
    return obs.astype(np.float32), str(path)


def run_export(args: argparse.Namespace, simulated: SimulatedObservations) -> dict[str, Any]:
    """Load, export, verify, write; returns the report. `simulated(spec, n)`: n observations
    (and where they came from) when the user gives no --observations file; the caller (the
    CLI, the composition root) supplies the simulator's, so export/ needs no sim_stub."""
    try:
        import onnx  # noqa: F401 - only checking that the export extra is installed
        import torch  # noqa: F401
    except ImportError as exc:
        raise UserError(f"safemove export needs the export extra ({exc.name} is missing):"
                        " pip install -e '.[export]'") from None
    from export.checkpoint import load_checkpoint
    from export.onnx_export import export_actor
    from export.output import check_output

    check_output(args.output, args.checkpoint, args.int8)  # before the work, not after it
    spec = load_spec(args.spec) if args.spec else None
    actor = load_checkpoint(args.checkpoint, spec, trust=args.trust_checkpoint,
                            activation=args.activation, prefix=args.prefix)
    recorded, recorded_from = _recorded(args.observations, actor.spec, simulated)
    return export_actor(actor, args.checkpoint, args.output, recorded, recorded_from,
                        int8=args.int8)
