"""`safemove replay LOG.mcap`: a flight recording's inputs through today's `Pipeline.step`.

No clock and no devices. The recording's metadata gives the config, the calibration and the
job (its goal, its actor file, or the service's mission job); each `/cycle` message gives the
wheel increments, the depth frames that arrived (stamps, numbers, intrinsics; the pixels of
the one the world model read come from `/camera/depth_decimated`), the feedback time, the
steps the DWA's and the shield's time budgets allowed (replayed exactly, so the anytime stages
do the same work), and the control socket's commands applied after the cycle. Each replayed
cycle's command is compared with the recorded one, bit for bit: the same code on the same
inputs reproduces every command; a change to any stage shows where the decisions first differ.
Each cycle's number in the run tells where the recorder dropped cycles (the replay stops there:
what follows cannot be compared) and whether the file begins mid-run (a rotated file: the
replay starts from a fresh pipeline, so it differs until the stages' state has caught up).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from runtime.config.calibration import Calibration
from runtime.config.schema import apply_override, build
from runtime.config.settings import Config
from runtime.control.protocol import Request, Waypoint
from runtime.errors import UserError
from runtime.pipeline import CycleInput, Pipeline
from runtime.process.flight_log import read_flight_log
from runtime.types import (
    BaseStatus,
    CliffSensor,
    DepthFrame,
    DepthIntrinsics,
    Proximity,
    WheelIncrement,
)

log = logging.getLogger("safemove.replay")


@dataclass
class Divergence:
    """Where the replay's decisions differ from the recording's."""

    cycles: int = 0
    differing: int = 0
    first: dict[str, Any] | None = None
    largest_dv: float = 0.0
    largest_domega: float = 0.0
    shield_kinds: int = 0  # cycles whose shield decision kind differs
    examples: list[dict[str, Any]] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {"cycles": self.cycles, "differing_commands": self.differing,
                "first_divergence": self.first, "largest_command_difference":
                    {"v": self.largest_dv, "omega": self.largest_domega},
                "differing_shield_decisions": self.shield_kinds, "examples": self.examples}


def _job(meta: dict[str, str], config: Config, model: Path | None, path: Path) -> Any:
    """The recorded job, rebuilt to replay: no clock (budgets come from the recording)."""
    from runtime.control.config import ControlConfig

    name = meta.get("job")
    summary = json.loads(meta.get("job_summary", "{}"))
    if name in ("dwa", "safemove"):
        goal = tuple(summary["goal_odom"])
        policy = summary.get("policy") or {}
        actor = model or (_actor(policy["model"], policy.get("variant"))
                          if name == "safemove" else None)
        return _planner(name, goal, config, actor)
    if name == "mission":
        cfg: ControlConfig = config.control
        actor = model or (_actor(summary["model"], None) if summary.get("model") else None)
        from runtime.jobs.mission import MissionJob

        return MissionJob(cfg, summary["planner"],
                          lambda g, tol, v: _planner(summary["planner"], g, config, actor,
                                                     arrival_radius_m=tol, speed_limit=v),
                          lambda _event: None, None if actor is None else str(actor))
    if name == "hold":
        from runtime.jobs.drive import HoldJob

        return HoldJob()
    raise UserError(f"{path}: a '{name}' run cannot be replayed (dwa, safemove, mission, hold)")


def _actor(model: str, variant: str | None) -> Path:
    """The recorded actor file; where it is not on this machine, the policy of the same
    variant that ships with this installation (recorded on another machine or checkout: a
    shipped file is named for its variant)."""
    from runtime.policy.shipped import VARIANTS, shipped_model

    path = Path(model)
    variant = variant or (path.stem if path.parent.name == "models" else None)
    if not path.is_file() and variant in VARIANTS:
        return shipped_model(variant, "give --model FILE.onnx")
    return path


def _planner(name: str, goal: Any, config: Config, actor: Path | None, **limits: Any) -> Any:
    if name == "dwa":
        from runtime.jobs.dwa import DWAJob

        return DWAJob(goal, config, None, **limits)
    from runtime.jobs.safemove import SafeMoveJob
    from runtime.policy.actor import Policy

    if actor is None or not actor.is_file():
        raise UserError(f"the recording's actor {actor} is not here: give --model FILE.onnx")
    return SafeMoveJob(goal, config, Policy(actor, config.policy), None, **limits)


def _increment(d: dict[str, Any]) -> WheelIncrement:
    return WheelIncrement(
        _num(d["t"]), _num(d["dt"]), _num(d["d_left"]), _num(d["d_right"]),
        None if d["gyro_z"] is None else _num(d["gyro_z"]),
        None if d["yaw"] is None else _num(d["yaw"]),
        CliffSensor(d["cliffs"]), Proximity(d["proximity"]), BaseStatus(d["status"]))


def _num(x: Any) -> float:
    """A recorded number (non-finite ones are recorded as strings: 'nan', 'inf')."""
    return float(x)


def _request(d: dict[str, Any]) -> Request:
    return Request(d["type"], d["id"], tuple(Waypoint(**w) for w in d["waypoints"]),
                   d["frame"], d["loop"], d["timeout_s"], d["rate_hz"])


def replay(path: Path, model: Path | None = None, limit: int | None = None,
           overrides: list[str] | tuple[str, ...] = ()) -> dict[str, Any]:
    """Replay the recording (its first `limit` cycles) on its config with `overrides`
    (KEY=VALUE, as --set: what-if a stage were set otherwise); the divergence report."""
    meta, messages = read_flight_log(path)
    where = f"{path}: metadata"
    data = yaml.safe_load(meta["config"]) or {}
    for assignment in overrides:
        apply_override(data, Config, assignment)
    config = build(Config, data, f"{where} config" + (
        f" (with --set {', '.join(overrides)})" if overrides else ""))
    calibration = build(Calibration, yaml.safe_load(meta["calibration"]),
                        f"{where} calibration")
    job = _job(meta, config, model, path)
    pipeline = Pipeline(config, calibration, job)
    d = config.perception.decimation
    image: np.ndarray | None = None
    report = Divergence()
    first_seq: int | None = None  # the first cycle's number in the run (None: not recorded)
    gap: dict[str, int] | None = None
    for topic, data in messages:
        if topic == "/camera/depth_decimated":
            from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

            raw = RawImage.FromString(data)
            image = np.frombuffer(raw.data, dtype="<u2").reshape(raw.height, raw.width)
            continue
        if topic != "/cycle":
            continue
        c = json.loads(data)
        seq = c.get("seq")  # (recordings before it was recorded have none)
        if seq is not None:
            if first_seq is None:
                first_seq = seq
            elif seq != first_seq + report.cycles:  # the recorder dropped cycles: what came
                # after them cannot be compared, their inputs are gone
                gap = {"after_cycle": report.cycles, "missing": seq - first_seq - report.cycles}
                break
        frames = [_frame(f, image if f["frame_number"] == c["perceived"] else None, d)
                  for f in c["frames"]]
        for earlier in c.get("startup_control", ()):  # the service's start-up, before cycle 0
            _serve(job, earlier["t"], earlier["hold"], earlier["commands"], pipeline.odom)
        planning = getattr(job, "planning", None)
        if planning is not None:
            planning.replayed_budgets = {k: (int(a), bool(b))
                                         for k, (a, b) in (c["budgets"] or {}).items()}
        out = pipeline.step(CycleInput(_num(c["t"]), [_increment(i) for i in c["increments"]],
                                       frames, None if c["feedback_t"] is None
                                       else _num(c["feedback_t"])))
        pipeline.check_floor()  # as the loop does after each command: its RANSAC draws too
        _compare(report, c, out, job)
        if c["control_t"] is not None:
            _serve(job, c["control_t"], out.hold, c["commands"], out.odom)
        report.cycles += 1
        if limit is not None and report.cycles >= limit:
            break
    if report.cycles == 0:
        raise UserError(f"{path}: no recorded cycles")
    if first_seq:
        log.warning("%s begins at cycle %d of its run (a file the recorder rotated to): the"
                    " replay starts from a fresh pipeline, so it differs until its state"
                    " (odometry, obstacle memory, tracks) has caught up", path, first_seq)
    if gap is not None:
        log.warning("%s: the recorder dropped %d cycles after cycle %d: the replay stops"
                    " there", path, gap["missing"], gap["after_cycle"])
    return {"log": str(path), "job": meta.get("job"), "first_cycle_of_run": first_seq,
            "gap": gap, **report.as_dict()}


def _serve(job: Any, t: Any, hold: str | None, commands: list[dict[str, Any]],
           odom: Any) -> None:
    """What the loop's control stage did at `t`: the hold time, then the commands applied."""
    now = _num(t)
    if hold is not None:
        job.held(now, hold, odom)
    for applied in commands:
        job.handle(_request(applied["request"]), now, odom)


def _frame(f: dict[str, Any], image: np.ndarray | None, decimation: int) -> DepthFrame:
    """A recorded frame: the image the world model read, or (for a frame it did not read) a
    stand-in of the right shape, or of none where the recorded image had the wrong one, so the
    depth guard decides as it did."""
    w, h, fx, fy, cx, cy, unit = f["intrinsics"]
    k = DepthIntrinsics(int(w), int(h), _num(fx), _num(fy), _num(cx), _num(cy), _num(unit))
    frame = DepthFrame(np.zeros((0, 0), dtype=np.uint16), _num(f["t"]), int(f["frame_number"]),
                       k, decimation)
    if image is not None:
        frame.depth = image
    elif f["image_ok"]:
        frame.depth = np.broadcast_to(np.zeros((), dtype=np.uint16), frame.image_shape)
    return frame


def _compare(report: Divergence, c: dict[str, Any], out: Any, job: Any) -> None:
    rv, rw = _num(c["command"]["v"]), _num(c["command"]["omega"])
    v, w = out.command.v, out.command.omega
    same = (v == rv or (math.isnan(v) and math.isnan(rv))) and (
        w == rw or (math.isnan(w) and math.isnan(rw)))
    trace = getattr(job, "trace", None)
    t = trace() if trace is not None and out.hold is None else None
    kind = None if t is None or t.shield is None else t.shield.kind
    recorded_kind = None if c["shield"] is None else c["shield"]["kind"]
    if kind != recorded_kind:
        report.shield_kinds += 1
    if same:
        return
    report.differing += 1
    report.largest_dv = max(report.largest_dv, abs(v - rv))
    report.largest_domega = max(report.largest_domega, abs(w - rw))
    entry = {"cycle": report.cycles, "t": c["t"], "recorded": {"v": rv, "omega": rw},
             "replayed": {"v": v, "omega": w}, "recorded_shield": recorded_kind,
             "replayed_shield": kind}
    if report.first is None:
        report.first = entry
    if len(report.examples) < 5:
        report.examples.append(entry)
