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
    read off the weight shapes (`export.mlp`); bare, or in an agent dict under one of
    `ACTOR_KEYS` (`{"actor": ..., "critic": ..., "actor_target": ...}`).
(d) **TorchScript module** (`torch.jit.save`): TorchScript code only, no Python pickles; probed
    with the spec's input size.
The first bytes say which container a file is (a zip archive, a legacy torch.save pickle) before
torch reads it, so text, random bytes and plain pickles are named as what they are. A file whose
loading needs pickled Python code (e.g. `torch.save(model)`) is refused unless the user passes
--trust-checkpoint: unpickling runs arbitrary code.
"""

from __future__ import annotations

import io
import json
import pickle
import re
import struct
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from export.mlp import ACTIVATIONS, MLPActor, mlp_from_state
from runtime.errors import UserError
from runtime.policy.obs_spec import ObsSpec, SpecError, with_action_box

FORMAT = "safemove-actor"
FORMAT_VERSION = 1
# how torch.load fails on a file it cannot read (with --trust-checkpoint: unpickling too)
LOAD_ERRORS = (RuntimeError, EOFError, OSError, ValueError, AttributeError, ImportError,
               pickle.UnpicklingError, zipfile.BadZipFile, struct.error)
SB3_ACTIVATIONS = {"ReLU": "relu", "LeakyReLU": "leaky_relu", "Tanh": "tanh"}
# torch.save's legacy (pre-1.6) format: a pickle whose first object is this number, as LONG1
LEGACY_MAGIC = b"\x8a\x0a" + torch.serialization.MAGIC_NUMBER.to_bytes(10, "little")
# where agent checkpoints ({"actor": ..., "critic": ..., ...}) keep the actor's state_dict
ACTOR_KEYS = ("actor", "actor_state_dict", "policy", "policy_state_dict")


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
    is_zip = _is_zip(path, src)
    if is_zip:
        with zipfile.ZipFile(path) as zf:
            names = zf.namelist()
            if "data" in names and "policy.pth" in names:
                return _load_sb3(zf, src, _need(spec, src, "a stable-baselines3 model"))
        if any("/code/" in n for n in names):
            return _load_torchscript(path, src, _need(spec, src, "a TorchScript module"))
        if not any(n == "data.pkl" or n.endswith("/data.pkl") for n in names):
            raise CheckpointError(f"{src}: a zip archive but not a stable-baselines3 model (no"
                                  " 'data' and 'policy.pth'), a TorchScript module or a"
                                  f" torch.save checkpoint; it holds {_some(names) or 'nothing'}")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except LOAD_ERRORS as exc:
        if not trust:
            raise _refused(path, src, is_zip, exc) from None
        obj = _load_trusted(path, src)
    if isinstance(obj, torch.nn.Module):  # only reachable with --trust-checkpoint
        need = _need(spec, src, "a pickled module")
        return LoadedActor(_probe(obj.eval(), src, need), "pickled torch module", need)
    if not isinstance(obj, dict):
        raise CheckpointError(f"{src}: holds a {type(obj).__name__}; expected a state_dict,"
                              " a safemove actor checkpoint, an SB3 .zip or a TorchScript module")
    if obj.get("format") == FORMAT:
        return _load_project(obj, src, spec)
    state, where, details = _actor_state(obj, src, prefix)
    actor = mlp_from_state(state, where, activation)
    need = _need(spec, src, "a state_dict")
    _check_inputs(actor.sizes[0], need, src)
    return LoadedActor(actor, "state_dict MLP", need,
                       {"layer_sizes": actor.sizes, "hidden_activation": activation,
                        "output_activation": "tanh", **details})


def _is_zip(path: Path, src: str) -> bool:
    """Whether the file is a zip archive (True) or a legacy torch.save pickle (False), told by
    its first bytes; anything else is refused here, saying what it is, because torch's
    unpickler answers a text file with an IndexError or KeyError and random bytes with advice to trust them."""
    if not path.exists():
        raise CheckpointError(f"{src}: checkpoint not found")
    if path.is_dir():
        raise CheckpointError(f"{src}: is a directory, not a checkpoint file")
    if not path.is_file():
        raise CheckpointError(f"{src}: is not a regular file (a device, pipe or socket)")
    try:
        with path.open("rb") as f:
            head = f.read(64)
    except OSError as exc:
        raise CheckpointError(f"{src}: cannot read it ({exc.strerror or exc})") from None
    if not head:
        raise CheckpointError(f"{src}: is empty (0 bytes)")
    if head.startswith(b"PK"):
        if not zipfile.is_zipfile(path):
            raise CheckpointError(f"{src}: starts like a zip archive (PK) but is truncated or"
                                  " damaged")
        return True
    if head[0] == 0x80:  # a pickle; torch.save's legacy format begins with its magic number
        if LEGACY_MAGIC not in head:
            raise CheckpointError(f"{src}: a Python pickle but not a torch checkpoint (no"
                                  " torch.save header); save the weights with torch.save")
        return False
    text = head.decode("utf-8", errors="replace")
    whole = text[:-1] if len(head) == 64 else text  # reading 64 bytes may split a character
    if all(c.isprintable() or c in "\t\r\n" for c in whole):
        if text.startswith("version https://git-lfs"):
            raise CheckpointError(f"{src}: a Git LFS pointer, not the checkpoint itself; fetch"
                                  " it with git lfs pull")
        first = text.splitlines()[0][:40] if text.strip() else ""
        raise CheckpointError(f"{src}: not a torch checkpoint but a text file (it begins"
                              f" {first!r})")
    raise CheckpointError(f"{src}: not a torch checkpoint: it begins with the bytes"
                          f" {head[:4].hex(' ')}, not a zip archive (50 4b) or a torch.save"
                          " pickle (80)")


def _refused(path: Path, src: str, is_zip: bool, exc: BaseException) -> CheckpointError:
    """Why `weights_only=True` refused a torch checkpoint: pickled code, named (the one case
    where --trust-checkpoint is the answer), or a file torch cannot read (damaged)."""
    if is_zip:
        try:
            code = sorted(torch.serialization.get_unsafe_globals_in_checkpoint(path))
        except LOAD_ERRORS:
            code = []
    else:  # the legacy format has no such scan; torch's message names the first global
        code = re.findall(r"Unsupported global: GLOBAL ([\w.]+)", str(exc))
    if code:
        return CheckpointError(
            f"{src}: loading it needs pickled Python code ({_some(code, 3)}), which can run"
            " anything; refused (pass --trust-checkpoint only for a file from a source you"
            " trust)")
    reason = re.search(r"WeightsUnpickler error:\s*(.+)", str(exc))
    return CheckpointError(f"{src}: a torch checkpoint that cannot be read"
                           f" ({reason.group(1) if reason else _first_line(exc)}): damaged,"
                           " truncated, or in a form torch's weights-only loader does not read")


def _actor_state(obj: dict[Any, Any], src: str, prefix: str
                 ) -> tuple[dict[str, Any], str, dict[str, str]]:
    """The actor's weights in a loaded dict, what to call them in messages, and what the report
    says about where they came from. A bare state_dict is the actor; an agent dict (nested
    state dicts: actor, critic, targets, optimizers) has it under one well-known key, never a
    guess between several; --prefix picks keys of either, nested ones joined with dots."""
    if prefix:
        state = {k[len(prefix):]: v for k, v in _flatten(obj).items() if k.startswith(prefix)}
        if not state:
            raise CheckpointError(f"{src}: no key starts with --prefix '{prefix}'")
        return state, src, {}
    if not any(isinstance(v, Mapping) for v in obj.values()):
        return obj, src, {}
    found = [k for k in ACTOR_KEYS if isinstance(obj.get(k), Mapping)]
    if len(found) == 1:
        return dict(obj[found[0]]), f"{src}: key '{found[0]}'", {"actor_key": found[0]}
    raise CheckpointError(f"{src}: an agent checkpoint with the keys"
                          f" {_some([repr(str(k)) for k in obj], 8)}; expected the"
                          f" actor's state_dict under {'only ' if found else ''}one of"
                          f" {', '.join(repr(k) for k in ACTOR_KEYS)} (choose with --prefix"
                          " KEY.)")


def _some(items: list[str], n: int = 5) -> str:
    """The first n items for a one-line message, and how many more there are."""
    more = f" and {len(items) - n} more" if len(items) > n else ""
    return ", ".join(items[:n]) + more


def _flatten(obj: Mapping[Any, Any], head: str = "") -> dict[str, Any]:
    """Nested dicts as one, their keys joined with dots, as a module's state_dict names them."""
    flat: dict[str, Any] = {}
    for key, value in obj.items():
        if isinstance(value, Mapping):
            flat.update(_flatten(value, f"{head}{key}."))
        else:
            flat[f"{head}{key}"] = value
    return flat


def _load_trusted(path: Path, src: str) -> Any:
    """--trust-checkpoint: unpickle everything, code included."""
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except LOAD_ERRORS as exc:
        raise CheckpointError(f"{src}: a torch checkpoint that cannot be read"
                              f" ({type(exc).__name__}: {_first_line(exc)})") from None


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
    except (json.JSONDecodeError, pickle.UnpicklingError, RuntimeError, KeyError,
            zipfile.BadZipFile) as exc:
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

