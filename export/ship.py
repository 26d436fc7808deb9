"""A trained actor made ready to ship: how it was trained and how it scored, in its own metadata.

`stamp` writes `safemove.training` and `safemove.evaluation` (JSON objects) into an exported
actor, replacing earlier ones, and leaves the graph and every other entry as they are, so the
file the runtime loads (`runtime.policy.actor.Policy.training`, `.evaluation`, the job's
summary) says what it is. Needs onnx but no torch: the training tooling calls it after
`safemove eval`; `safemove export` writes its own entries with `set_metadata`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import onnx
from google.protobuf.message import DecodeError

from export.output import write_atomically
from runtime.errors import UserError
from runtime.policy.actor import META_EVALUATION, META_SPEC, META_TRAINING


def set_metadata(model: onnx.ModelProto, entries: dict[str, str]) -> None:
    """Add or replace metadata entries (one entry per key)."""
    for key, value in entries.items():
        for prop in model.metadata_props:
            if prop.key == key:
                prop.value = value
                break
        else:
            model.metadata_props.add(key=key, value=value)


def stamp(onnx_path: Path, training: dict[str, Any], evaluation: dict[str, Any]) -> None:
    """Write the training and evaluation records into the actor at `onnx_path`, in place and
    atomically. Strict JSON (no NaN), so any reader can parse them."""
    onnx_path = Path(onnx_path)
    for name, record in (("training", training), ("evaluation", evaluation)):
        if not isinstance(record, dict):
            raise TypeError(f"stamp: {name} must be a dict, got {type(record).__name__}")
    try:
        model = onnx.load(onnx_path)
    except FileNotFoundError:
        raise UserError(f"{onnx_path}: model file not found") from None
    except DecodeError:
        raise UserError(f"{onnx_path}: not an ONNX model") from None
    if not any(p.key == META_SPEC for p in model.metadata_props):
        raise UserError(f"{onnx_path}: not an actor from `safemove export` (no '{META_SPEC}' in"
                        " its metadata)")
    set_metadata(model, {
        META_TRAINING: json.dumps(training, separators=(",", ":"), allow_nan=False),
        META_EVALUATION: json.dumps(evaluation, separators=(",", ":"), allow_nan=False),
    })
    write_atomically({onnx_path: model.SerializeToString()})
