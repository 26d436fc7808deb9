"""One control cycle as MCAP messages: Foxglove's well-known schemas (protobuf) for what the
Foxglove app draws without setup, and one JSON message per cycle with every decision and input.

Channels (frames follow REP 103/105; the app's 3D panel shows them in `odom`):
- `/tf` foxglove.FrameTransform odom → base_link (the fused pose), every cycle;
  `/tf_static` base_link → camera_depth_optical (the calibration), once per file.
- `/camera/depth` foxglove.RawImage 16UC1, the full frame every `full_depth_every`-th frame;
  `/camera/depth_decimated` the image the world model read (every frame it read).
- `/obstacles` foxglove.PointCloud, the remembered obstacle points in base_link.
- `/planning` foxglove.SceneUpdate: tracks in odom (discs, velocity arrows, σ rings), DWA's
  best path and the safe corridor in base_link, the goal in odom.
- `/cycle` JSON (schema `safemove.Cycle`): the cycle's number in the run, time, loop state
  and hold reason, the wheel increments and depth frames that arrived, the target and the
  limited command, the shield's decision and reason, DWA's best sample, counts and budget, the
  observation and the actor's output, stage times; the control socket's commands applied after
  the cycle (the first cycle: also its passes during start-up, `startup_control`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.ArrowPrimitive_pb2 import ArrowPrimitive
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CylinderPrimitive_pb2 import CylinderPrimitive
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.message import Message
from google.protobuf.timestamp_pb2 import Timestamp

from runtime.config.calibration import CameraMount
from runtime.process.cycle_record import CycleRecord
from runtime.types import DepthFrame, Odometry, Twist, WheelIncrement

CAMERA_FRAME = "camera_depth_optical"
CYCLE_SCHEMA = {
    "title": "safemove.Cycle",
    "description": "One SafeMove control cycle: inputs, each stage's decision, the command",
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "cycle time, host monotonic s"},
        "state": {"type": "string"}, "hold": {"type": ["string", "null"]},
        "increments": {"type": "array"}, "frames": {"type": "array"},
        "target": {"type": "object"}, "command": {"type": "object"}, "tracks": {"type": "array"},
        "shield": {"type": ["object", "null"]}, "dwa": {"type": ["object", "null"]},
        "observation": {"type": ["array", "null"]}, "action": {"type": ["array", "null"]},
        "stage_ms": {"type": "object"}, "commands": {"type": "array"},
    },
}


def _stamp(t: float) -> Timestamp:
    sec = math.floor(t)
    return Timestamp(seconds=int(sec), nanos=int((t - sec) * 1e9))


def _quat_yaw(yaw: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * yaw), w=math.cos(0.5 * yaw))


def _quat_rpy(roll: float, pitch: float, yaw: float) -> Quaternion:
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return Quaternion(w=cr * cp * cy + sr * sp * sy, x=sr * cp * cy - cr * sp * sy,
                      y=cr * sp * cy + sr * cp * sy, z=cr * cp * sy - sr * sp * cy)


def camera_transform(mount: CameraMount, t: float) -> FrameTransform:
    """base_link → the camera's optical frame (z forward, x right, y down) of the calibration."""
    roll, pitch, yaw = (math.radians(a) for a in mount.rpy_deg)
    body = _quat_rpy(roll, pitch, yaw)
    # body frame (x fwd, y left, z up) → optical: R = Rz(-90°)·Rx(-90°)
    opt = Quaternion(x=-0.5, y=0.5, z=-0.5, w=0.5)
    q = Quaternion(
        w=body.w * opt.w - body.x * opt.x - body.y * opt.y - body.z * opt.z,
        x=body.w * opt.x + body.x * opt.w + body.y * opt.z - body.z * opt.y,
        y=body.w * opt.y - body.x * opt.z + body.y * opt.w + body.z * opt.x,
        z=body.w * opt.z + body.x * opt.y - body.y * opt.x + body.z * opt.w)
    x, y, z = mount.translation_m
    return FrameTransform(timestamp=_stamp(t), parent_frame_id="base_link",
                          child_frame_id=CAMERA_FRAME, translation=Vector3(x=x, y=y, z=z),
                          rotation=q)


def _pose_tf(o: Odometry, t: float) -> FrameTransform:
    return FrameTransform(timestamp=_stamp(t), parent_frame_id="odom", child_frame_id="base_link",
                          translation=Vector3(x=o.x, y=o.y, z=0.0), rotation=_quat_yaw(o.theta))


def depth_image(frame: DepthFrame, step: int = 1) -> RawImage:
    """The frame's depth (every `step`-th pixel each way) as 16UC1 in the camera's frame."""
    img = frame.depth[::step, ::step] if step > 1 else frame.depth
    img = np.ascontiguousarray(img, dtype="<u2")
    return RawImage(timestamp=_stamp(frame.t), frame_id=CAMERA_FRAME, width=img.shape[1],
                    height=img.shape[0], encoding="16UC1", step=2 * img.shape[1],
                    data=img.tobytes())


_XYZ = [PackedElementField(name=n, offset=4 * i, type=PackedElementField.FLOAT32)
        for i, n in enumerate("xyz")]


def _cloud(points: np.ndarray, t: float) -> PointCloud:
    pts = np.zeros((len(points), 3), dtype="<f4")
    pts[:, :2] = points
    return PointCloud(timestamp=_stamp(t), frame_id="base_link", pose=Pose(
        position=Vector3(), orientation=Quaternion(w=1.0)), point_stride=12, fields=_XYZ,
        data=pts.tobytes())


_RED, _GREEN, _BLUE, _GREY = (Color(r=0.9, g=0.2, b=0.2, a=0.8), Color(r=0.2, g=0.8, b=0.3, a=1.0),
                              Color(r=0.2, g=0.4, b=0.9, a=1.0), Color(r=0.6, g=0.6, b=0.6, a=0.5))


def _line(points: np.ndarray, kind: LinePrimitive.Type.ValueType, color: Color,
          width: float = 0.02) -> LinePrimitive:
    return LinePrimitive(type=kind, pose=Pose(position=Vector3(), orientation=Quaternion(w=1.0)),
                         thickness=width, points=[Point3(x=float(x), y=float(y), z=0.05)
                                                  for x, y in points[:, :2]], color=color)


def _scene(rec: CycleRecord) -> SceneUpdate:
    stamp = _stamp(rec.t)
    entities = []
    world = rec.result.world
    if world is not None:
        tracks = SceneEntity(timestamp=stamp, frame_id="odom", id="tracks")
        for tr in world.tracks:
            x, y = float(tr.position[0]), float(tr.position[1])
            d = 2.0 * tr.radius
            tracks.cylinders.append(CylinderPrimitive(
                pose=Pose(position=Vector3(x=x, y=y, z=0.5), orientation=Quaternion(w=1.0)),
                size=Vector3(x=d, y=d, z=1.0), bottom_scale=1.0, top_scale=1.0,
                color=_RED if tr.confirmed else _GREY))
            vx, vy = float(tr.velocity[0]), float(tr.velocity[1])
            speed = math.hypot(vx, vy)
            if speed > 0.05:
                tracks.arrows.append(ArrowPrimitive(
                    pose=Pose(position=Vector3(x=x, y=y, z=1.05),
                              orientation=_quat_yaw(math.atan2(vy, vx))),
                    shaft_length=speed, shaft_diameter=0.03, head_length=0.1,
                    head_diameter=0.08, color=_RED))
        entities.append(tracks)
    trace = rec.trace
    if trace is not None and trace.context is not None:
        plan = SceneEntity(timestamp=stamp, frame_id="base_link", id="plan")
        plan.lines.append(_line(trace.context.dwa.best_path, LinePrimitive.LINE_STRIP, _GREEN))
        if trace.corridor is not None and len(trace.corridor.polygon):
            plan.lines.append(_line(np.asarray(trace.corridor.polygon), LinePrimitive.LINE_LOOP,
                                    _BLUE))
        entities.append(plan)
    if trace is not None and trace.goal_odom is not None:
        goal = SceneEntity(timestamp=stamp, frame_id="odom", id="goal")
        gx, gy = trace.goal_odom
        goal.cylinders.append(CylinderPrimitive(
            pose=Pose(position=Vector3(x=gx, y=gy, z=0.01), orientation=Quaternion(w=1.0)),
            size=Vector3(x=0.3, y=0.3, z=0.02), bottom_scale=1.0, top_scale=1.0, color=_GREEN))
        entities.append(goal)
    return SceneUpdate(entities=entities)


def _twist(t: Twist) -> dict[str, float]:
    return {"v": t.v, "omega": t.omega}


def _increment(i: WheelIncrement) -> dict[str, Any]:
    return {"t": i.t, "dt": i.dt, "d_left": i.d_left, "d_right": i.d_right, "gyro_z": i.gyro_z,
            "yaw": i.yaw, "cliffs": int(i.cliffs), "proximity": int(i.proximity),
            "status": int(i.status)}


def _track(tr: Any) -> dict[str, Any]:
    """A track in odom: position, velocity, radius, its 4×4 covariance (x, y, vx, vy)."""
    return {"id": tr.id, "x": float(tr.position[0]), "y": float(tr.position[1]),
            "vx": float(tr.velocity[0]), "vy": float(tr.velocity[1]), "radius": tr.radius,
            "confirmed": tr.confirmed, "stationary": tr.stationary,
            "covariance": np.round(np.asarray(tr.covariance, dtype=float), 6).tolist()}


def _frame(f: DepthFrame) -> dict[str, Any]:
    """A frame that arrived: its stamp and number, the camera's intrinsics, and whether its
    image had the shape and type the depth guard checks (its pixels are recorded only when the
    world model read it)."""
    k = f.intrinsics
    ok = isinstance(f.depth, np.ndarray) and f.depth.dtype == np.uint16 and (
        f.depth.shape == f.image_shape)
    return {"t": f.t, "frame_number": f.frame_number, "image_ok": bool(ok),
            "intrinsics": [k.width, k.height, k.fx, k.fy, k.cx, k.cy, k.depth_unit_m]}


def _finite(x: Any) -> Any:
    """JSON has no NaN or infinity: such a number is recorded as its string ('nan', 'inf')."""
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def cycle_json(rec: CycleRecord, seq: int) -> bytes:
    """`seq`: the cycle's number in the run (a gap: cycles the recorder dropped)."""
    r = rec.result
    out: dict[str, Any] = {
        "seq": seq, "t": rec.t, "state": rec.state, "hold": r.hold, "feedback_t": rec.feedback_t,
        "increments": [_increment(i) for i in rec.increments],
        "frames": [_frame(f) for f in rec.frames],
        "perceived": None if rec.perceived is None else rec.perceived.frame_number,
        "odometry": {"x": r.odom.x, "y": r.odom.y, "theta": r.odom.theta, "v": r.odom.v,
                     "omega": r.odom.omega},
        "target": _twist(r.target), "command": _twist(r.command), "nonfinite": r.nonfinite,
        "stage_ms": {k: 1e3 * v for k, v in r.stage_s.items()},
        "tracks": [] if r.world is None else [_track(tr) for tr in r.world.tracks],
        "shield": None, "dwa": None, "observation": None, "action": None,
        "commands": list(rec.commands), "control_t": rec.control_t, "budgets": None,
        "startup_control": list(rec.startup_control),
    }
    tr = rec.trace
    if tr is not None:
        if tr.shield is not None:
            out["shield"] = {"kind": tr.shield.kind, "reason": tr.shield.reason,
                             "command": _twist(tr.shield.command)}
        if tr.context is not None:
            dwa = tr.context.dwa
            out["dwa"] = {"best": list(dwa.best), "best_index": int(dwa.best_index),
                          "best_total": float(dwa.total[dwa.best_index]),
                          "evaluated": int(dwa.evaluated), "refine_rounds": int(dwa.refine_rounds),
                          "budget_cut": bool(dwa.budget_cut),
                          "admissible": int(np.count_nonzero(dwa.admissible)),
                          "goal_base": [float(g) for g in tr.context.goal_base],
                          # every candidate: (v, ω), its total cost and admissibility (rounded:
                          # for reading; the replay recomputes them)
                          "candidates": {
                              "v": np.round(dwa.samples[:, 0], 4).tolist(),
                              "omega": np.round(dwa.samples[:, 1], 4).tolist(),
                              "total": np.round(np.nan_to_num(dwa.total, nan=-1e9,
                                                              neginf=-1e9), 4).tolist(),
                              "admissible": dwa.admissible.astype(int).tolist()}}
        if tr.budgets is not None:
            out["budgets"] = {k: list(v) for k, v in tr.budgets.items()}
        if tr.observation is not None:
            out["observation"] = [float(v) for v in tr.observation]
        if tr.action is not None:
            out["action"] = [float(v) for v in np.ravel(tr.action)]
    return json.dumps(_finite(out), separators=(",", ":")).encode()


def cycle_messages(rec: CycleRecord, seq: int, full_depth: bool, decimation: int
                   ) -> Iterator[tuple[str, Message | bytes]]:
    """(topic, message) for one cycle; bytes are the JSON channel's."""
    r = rec.result
    yield "/tf", _pose_tf(r.odom, rec.t)
    if rec.perceived is not None:
        yield "/camera/depth_decimated", depth_image(rec.perceived, decimation)
        if full_depth:
            yield "/camera/depth", depth_image(rec.perceived)
    if r.world is not None and rec.perceived is not None:
        yield "/obstacles", _cloud(r.world.points_base, rec.t)
    yield "/planning", _scene(rec)
    yield "/cycle", cycle_json(rec, seq)
