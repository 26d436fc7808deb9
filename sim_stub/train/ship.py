"""`safemove ship RUN_DIR --eval RESULT.json …`: a trained run's actor becomes the shipped policy of
its variant (`runtime/policy/models/<spec name>.onnx`), carrying how it was trained (the run's
summary.json: commit, seed, steps, wall time, the recipe's settings) and how it scored (the
`safemove eval --json` results given, one per table: per scenario, the crowd, the episodes and
the rates) in its metadata (`export.ship.stamp`). An evaluation counts for the run when it
evaluated the run's actor or a copy of it (the installed file, evaluated with --variant).

The variant is the run's spec: a run trained on a spec that is not one of the presets cannot
ship as one. The copy is written beside the target and renamed over it, so an interrupted ship
leaves the previous model whole.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

from runtime.errors import UserError
from runtime.policy import shipped

EVAL_KEYS = ("success_rate", "collision_rate", "timeout_rate", "at_fault_collisions",
             "moving_collisions", "avg_path_length_m", "avg_speed_m_s",
             "shield_interventions_per_episode")


def read_json(path: Path) -> Any:
    """A JSON file, or one line naming it when it is missing or does not parse."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: not a readable JSON file: {exc}") from None


def evaluation_record(result: dict[str, Any], source: Path) -> dict[str, Any]:
    """The figures of one `safemove eval --json` result worth carrying in the model."""
    try:
        scenarios = {Path(name).stem: {"episodes": r["episodes"],
                                       **{k: r[k] for k in EVAL_KEYS}}
                     for name, r in result["scenarios"].items()}
        record: dict[str, Any] = {"planner": result["planner"], "crowd": result["crowd"],
                                  "noise": result["noise"], "fps": result["fps"],
                                  "scenarios": scenarios}
    except (KeyError, TypeError, AttributeError) as exc:
        raise UserError(f"{source}: not a `safemove eval --json` result (missing {exc})") from None
    # what evaluated it and with which settings, where the result says (results before these
    # fields have none): figures measured with --set overrides are not the default's
    record.update({k: result[k] for k in ("commit", "camera_hfov_deg", "surround_people",
                                          "overrides", "trained_settings") if k in result})
    return record


def training_record(summary: dict[str, Any]) -> dict[str, Any]:
    """A run's summary as its actor carries it: without this machine's paths."""
    return {k: summary[k] for k in summary if k not in ("run", "model", "actor")}


def same_graph(model: Path, actor: Path) -> bool:
    """Whether `model` is a copy of `actor`: the same graph, weights included (the metadata may
    differ: an installed copy carries its records). An evaluation of the shipped file (eval
    --variant) therefore counts for the run it was shipped from."""
    import onnx
    from google.protobuf.message import DecodeError

    try:
        return bool(onnx.load(model).graph.SerializeToString()
                    == onnx.load(actor).graph.SerializeToString())
    except (OSError, DecodeError):
        return False


def ship(run_dir: Path, evaluations: list[Path]) -> Path:
    """Install the run's actor as its variant's shipped policy; returns the installed file."""
    from export.ship import stamp

    summary = read_json(run_dir / "summary.json")
    if not isinstance(summary, dict):
        raise UserError(f"{run_dir / 'summary.json'}: not a `safemove train` summary")
    settings = summary.get("settings")
    if isinstance(settings, dict) and settings.get("surround_people"):
        raise UserError(f"{run_dir / 'summary.json'}: trained with --surround-people, seeing"
                        " every person around exactly; the robot has no such sensor")
    spec = read_json(run_dir / "spec.json")
    variant = spec.get("name") if isinstance(spec, dict) else None
    if variant not in shipped.VARIANTS:
        raise UserError(f"{run_dir / 'spec.json'}: spec '{variant}' is not a shipped variant"
                        f" ({', '.join(shipped.VARIANTS)})")
    actor = run_dir / "actor.onnx"
    if not actor.is_file():
        raise UserError(f"{actor}: no exported actor in the run directory")
    # the run's actor where it is now, or where training wrote it (a run directory moved or
    # copied after its evaluation still names its actor in its summary)
    actors = {actor.resolve()} | ({Path(summary["actor"]).resolve()}
                                  if isinstance(summary.get("actor"), str) else set())
    records = []
    for path in evaluations:
        result = read_json(path)
        if not isinstance(result, dict) or result.get("planner") != "safemove":
            raise UserError(f"{path}: not a `safemove eval --planner safemove --json` result")
        model = result.get("model")
        if not isinstance(model, str) or (Path(model).resolve() not in actors
                                          and not same_graph(Path(model), actor)):
            raise UserError(f"{path}: evaluates {model}, not this run's {actor} (nor a copy"
                            " of it)")
        records.append(evaluation_record(result, path))
    target = shipped.MODELS_DIR / f"{variant}.onnx"
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.with_suffix(".onnx.partial")
    shutil.copyfile(actor, partial)
    try:
        stamp(partial, training_record(summary), {"tables": records})
        os.replace(partial, target)
    finally:
        partial.unlink(missing_ok=True)  # a stamp that failed leaves nothing in the package
    return target
