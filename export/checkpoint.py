"""Checkpoints `safemove export` reads, and the project's own training checkpoint format.

Four kinds, told apart by their contents (never by the file name):

(a) **safemove actor checkpoint** (what the training harness writes; `save_actor_checkpoint`):
    a dict saved with `torch.save` holding only tensors and plain values, so it loads with
    `torch.load(weights_only=True)`:
        format           "safemove-actor"
        format_version   1
        layer_sizes      [N, h1, ..., 2]        checked against the weights
        hidden_activation "relu" | "leaky_relu" | "tanh"   (the output is tanh)
        spec             the ObsSpec JSON the actor was trained with
        note             free text, e.g. "randomly initialised (untrained)"
        actor            MLPActor state_dict: layers.<i>.weight / layers.<i>.bias
(b) **stable-baselines3 TD3 `.zip`**: the actor `actor.mu.*` from `policy.pth` (weights only),
    its activation and the spaces from the JSON `data` file (never unpickled). The exported
    graph ends with SB3's action unscaling, so it equals `model.predict`.
(c) **plain state_dict of an MLP actor** (e.g. `layer_1`/`layer_2`/`layer_3`), architecture
    read off the weight shapes (`export.mlp`).
(d) **TorchScript module** (`torch.jit.save`): TorchScript code only, no Python pickles; probed
    with the spec's input size.
A file whose loading needs pickled Python code (e.g. `torch.save(model)`) is refused unless the
user passes --trust-checkpoint: unpickling runs arbitrary code.
"""

from __future__ import annotations

import io
import json
import pickle
import re
import struct
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from export.mlp import ACTIVATIONS, MLPActor, mlp_from_state
from runtime.errors import UserError
from runtime.obs_spec import ObsSpec, SpecError, with_action_box

FORMAT = "safemove-actor"
FORMAT_VERSION = 1
# how torch.load fails on a file it cannot read (with --trust-checkpoint: unpickling too)
LOAD_ERRORS = (RuntimeError, EOFError, OSError, ValueError, AttributeError, ImportError,
               pickle.UnpicklingError, zipfile.BadZipFile, struct.error)
SB3_ACTIVATIONS = {"ReLU": "relu", "LeakyReLU": "leaky_relu", "Tanh": "tanh"}


class CheckpointError(UserError):
    """A checkpoint that cannot be exported as given (one line, exit 2)."""


@dataclass
class LoadedActor:
    """A torch actor ready to export, with what the export report says about it."""

    module: torch.nn.Module
    kind: str
    spec: ObsSpec
    details: dict[str, Any] = field(default_factory=dict)


def save_actor_checkpoint(path: Path, actor: MLPActor, spec: ObsSpec, note: str) -> None:
    """Write format (a)."""
    torch.save({
        "format": FORMAT, "format_version": FORMAT_VERSION, "layer_sizes": list(actor.sizes),
        "hidden_activation": actor.activation, "spec": spec.to_json(), "note": note,
        "actor": {k: v.detach().clone() for k, v in actor.state_dict().items()},
    }, path)


def load_checkpoint(path: Path, spec: ObsSpec | None, *, trust: bool = False,
                    activation: str = "relu", prefix: str = "") -> LoadedActor:
    """Load any of the four kinds as a torch module, its input size checked against the spec.
    `spec` may be None only for format (a), which carries its own."""
    src = str(path)
    if not path.is_file():
        raise CheckpointError(f"{src}: checkpoint not found")
    if zipfile.is_zipfile(path):
        with zipfile.ZipFile(path) as zf:
            names = zf.namelist()
            if "data" in names and "policy.pth" in names:
                return _load_sb3(zf, src, _need(spec, src, "a stable-baselines3 model"))
        if any("/code/" in n for n in names):
            return _load_torchscript(path, src, _need(spec, src, "a TorchScript module"))
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        if not trust:
            found = re.search(r"Unsupported global: GLOBAL ([\w.]+)", str(exc))
            what = f" ({found.group(1)})" if found else ""
            raise CheckpointError(
                f"{src}: loading it needs pickled Python code{what}, which can run anything;"
                " refused (pass --trust-checkpoint only for a file from a source you trust)"
            ) from None
        obj = _torch_load(path, src, weights_only=False)
    except LOAD_ERRORS as exc:
        raise _unreadable(src, exc) from None
    if isinstance(obj, torch.nn.Module):  # only reachable with --trust-checkpoint
        need = _need(spec, src, "a pickled module")
        return LoadedActor(_probe(obj.eval(), src, need), "pickled torch module", need)
    if not isinstance(obj, dict):
        raise CheckpointError(f"{src}: holds a {type(obj).__name__}; expected a state_dict,"
                              " a safemove actor checkpoint, an SB3 .zip or a TorchScript module")
    if obj.get("format") == FORMAT:
        return _load_project(obj, src, spec)
    state = {k: v for k, v in obj.items() if str(k).startswith(prefix)}
    if prefix and not state:
        raise CheckpointError(f"{src}: no key starts with --prefix '{prefix}'")
    actor = mlp_from_state({k[len(prefix):]: v for k, v in state.items()}, src, activation)
    need = _need(spec, src, "a state_dict")
    _check_inputs(actor.sizes[0], need, src)
    return LoadedActor(actor, "state_dict MLP", need,
                       {"layer_sizes": actor.sizes, "hidden_activation": activation,
                        "output_activation": "tanh"})


def _torch_load(path: Path, src: str, weights_only: bool) -> Any:
    try:
        return torch.load(path, map_location="cpu", weights_only=weights_only)
    except LOAD_ERRORS as exc:
        raise _unreadable(src, exc) from None


def _unreadable(src: str, exc: BaseException) -> CheckpointError:
    return CheckpointError(f"{src}: not a torch checkpoint ({type(exc).__name__}:"
                           f" {_first_line(exc)})")


def _need(spec: ObsSpec | None, src: str, what: str) -> ObsSpec:
    if spec is None:
        raise CheckpointError(f"{src}: {what} carries no observation spec: give --spec PRESET or"
                              " --spec spec.json")
    return spec


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:200] if text else type(exc).__name__


def _check_inputs(n: int, spec: ObsSpec, src: str) -> None:
    if n != spec.size:
        raise CheckpointError(f"{src}: the actor takes {n} inputs but the spec '{spec.name}'"
                              f" builds {spec.size} features ({_layout(spec)})")


def _layout(spec: ObsSpec) -> str:
    return ", ".join(f"{kind} {b - a}" for kind, a, b in spec.layout())


def _load_project(obj: dict[str, Any], src: str, given: ObsSpec | None) -> LoadedActor:
    if obj.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{src}: safemove actor checkpoint format_version"
                              f" {obj.get('format_version')!r}; this tool reads {FORMAT_VERSION}")
    try:
        spec = ObsSpec.from_json(str(obj.get("spec")), f"{src}: key 'spec'")
    except SpecError as exc:
        raise CheckpointError(str(exc)) from None
    if given is not None and given.to_dict() != spec.to_dict():
        raise CheckpointError(f"{src}: the actor was trained with spec '{spec.name}'"
                              f" ({spec.size} features); --spec gives '{given.name}'"
                              f" ({given.size}): leave --spec out to use the checkpoint's")
    act = obj.get("hidden_activation")
    if act not in ACTIVATIONS:
        raise CheckpointError(f"{src}: key 'hidden_activation': must be one of"
                              f" {', '.join(ACTIVATIONS)}, got {act!r}")
    state = obj.get("actor")
    if not isinstance(state, dict):
        raise CheckpointError(f"{src}: key 'actor': expected the actor's state_dict")
    actor = mlp_from_state(state, f"{src}: key 'actor'", act)
    if obj.get("layer_sizes") != actor.sizes:
        raise CheckpointError(f"{src}: key 'layer_sizes' says {obj.get('layer_sizes')}, the"
                              f" weights are {actor.sizes}")
    _check_inputs(actor.sizes[0], spec, src)
    return LoadedActor(actor, "safemove actor checkpoint", spec,
                       {"layer_sizes": actor.sizes, "hidden_activation": act,
                        "output_activation": "tanh", "note": str(obj.get("note", ""))})


def _load_sb3(zf: zipfile.ZipFile, src: str, spec: ObsSpec) -> LoadedActor:
    try:
        data = json.loads(zf.read("data"))
        policy = torch.load(io.BytesIO(zf.read("policy.pth")), map_location="cpu",
                            weights_only=True)
    except (json.JSONDecodeError, pickle.UnpicklingError, RuntimeError, KeyError) as exc:
        raise CheckpointError(f"{src}: unreadable stable-baselines3 file:"
                              f" {_first_line(exc)}") from None
    module = str(data.get("policy_class", {}).get("__module__", ""))
    if module != "stable_baselines3.td3.policies":
        raise CheckpointError(f"{src}: the policy is from '{module or 'unknown'}'; only TD3"
                              " (stable_baselines3.td3.policies) actors are supported")
    kwargs = data.get("policy_kwargs", {})
    extractor = str(kwargs.get("features_extractor_class", "FlattenExtractor"))
    if "FlattenExtractor" not in extractor:
        raise CheckpointError(f"{src}: custom features extractor {extractor}: not supported")
    act_name = str(kwargs.get("activation_fn", "ReLU")).rsplit(".", 1)[-1].strip("'>")
    if act_name not in SB3_ACTIVATIONS:
        raise CheckpointError(f"{src}: activation_fn {act_name} is not supported"
                              f" ({', '.join(SB3_ACTIVATIONS)})")
    obs_shape = _sb3_shape(data.get("observation_space", {}), src, "observation_space")
    if len(obs_shape) != 1:
        raise CheckpointError(f"{src}: observation_space has shape {obs_shape}; a flat vector"
                              " is needed")
    _check_inputs(obs_shape[0], spec, src)
    low, high = _sb3_box(data.get("action_space", {}), src)
    state = {k[len("actor.mu."):]: v for k, v in policy.items() if k.startswith("actor.mu.")}
    if not state:
        raise CheckpointError(f"{src}: policy.pth has no actor weights (actor.mu.*)")
    actor = mlp_from_state(state, f"{src}: actor.mu", SB3_ACTIVATIONS[act_name], low, high)
    _check_inputs(actor.sizes[0], spec, src)
    version = zf.read("_stable_baselines3_version").decode().strip() if (
        "_stable_baselines3_version" in zf.namelist()) else "unknown"
    return LoadedActor(actor, "stable-baselines3 TD3", with_action_box(spec, low, high),
                       {"layer_sizes": actor.sizes, "hidden_activation": SB3_ACTIVATIONS[act_name],
                        "output_activation": "tanh, then SB3 unscaling onto the action space",
                        "action_low": list(low), "action_high": list(high),
                        "stable_baselines3": version})


def _sb3_shape(space: dict[str, Any], src: str, key: str) -> list[int]:
    try:
        shape = json.loads(str(space["_shape"]).replace("(", "[").replace(")", "]")
                           .replace(",]", "]"))
        return [int(n) for n in shape]
    except (KeyError, ValueError, TypeError):
        raise CheckpointError(f"{src}: data: cannot read {key} shape") from None


def _sb3_box(space: dict[str, Any], src: str) -> tuple[tuple[float, float], tuple[float, float]]:
    """The action space's low/high from their printed arrays (the pickled space is not read)."""
    try:
        low = np.array(str(space["low"]).strip("[] ").split(), dtype=float)
        high = np.array(str(space["high"]).strip("[] ").split(), dtype=float)
    except (KeyError, ValueError):
        raise CheckpointError(f"{src}: data: cannot read the action space's low/high") from None
    if low.shape != (2,) or high.shape != (2,) or not np.all(np.isfinite(np.r_[low, high])):
        raise CheckpointError(f"{src}: the action space must be a finite box of 2 (v, ω), got"
                              f" low {low.tolist()} high {high.tolist()}")
    return (float(low[0]), float(low[1])), (float(high[0]), float(high[1]))


def _load_torchscript(path: Path, src: str, spec: ObsSpec) -> LoadedActor:
    try:
        module = torch.jit.load(str(path), map_location="cpu")
    except (RuntimeError, ValueError, OSError) as exc:
        raise CheckpointError(f"{src}: unreadable TorchScript module:"
                              f" {_first_line(exc)}") from None
    return LoadedActor(_probe(module.eval(), src, spec), "TorchScript module", spec)


def _probe(module: torch.nn.Module, src: str, spec: ObsSpec) -> torch.nn.Module:
    """An opaque module must take (1, N) and give (1, 2)."""
    try:
        with torch.no_grad():
            out = module(torch.zeros(1, spec.size))
    except (RuntimeError, TypeError, ValueError, IndexError) as exc:  # wrong input size
        raise CheckpointError(f"{src}: the module does not take the spec '{spec.name}''s"
                              f" {spec.size} features: {_first_line(exc)}") from None
    if not isinstance(out, torch.Tensor) or tuple(out.shape) != (1, 2):
        shape = list(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
        raise CheckpointError(f"{src}: the module's output for one observation is {shape};"
                              " an actor outputs (1, 2)")
    return module

