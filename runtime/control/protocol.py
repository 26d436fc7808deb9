"""The control socket's wire protocol, version 1: newline-delimited JSON objects (UTF-8).

Validation is here and only here, before anything is handed to the control cycle, so the cycle
sees typed, finite, in-range requests or nothing. Every rejection is a `ProtocolError` whose
message names the field and what is wrong; the server turns it into an error reply. The schema is
documented in the README (Reference: The control socket).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

VERSION = 1
MAX_LINE_BYTES = 65536  # a longer request line is refused and its connection closed
MAX_WAYPOINTS = 100
MAX_ID_CHARS = 128
MAX_STATUS_HZ = 20.0
MAX_DEPTH = 8  # nesting of arrays and objects; a request needs 3 (request, waypoints, waypoint)
FRAMES = ("odom", "relative")
# requests the control cycle applies (the rest the server answers itself)
CYCLE_TYPES = ("goal", "mission", "cancel", "pause", "resume")
SERVER_TYPES = ("status", "subscribe", "unsubscribe")
TOLERANCE_RANGE_M = (0.05, 2.0)
TIMEOUT_RANGE_S = (1.0, 86400.0)

RequestId = str | int | None


class ProtocolError(ValueError):
    """A request that cannot be accepted; `request_id` is echoed in the error reply."""

    def __init__(self, message: str, request_id: RequestId = None) -> None:
        super().__init__(message)
        self.request_id = request_id


@dataclass(frozen=True)
class Waypoint:
    """A place to reach: x, y in the request's frame (m), the arrival tolerance (m; None: the
    configured default) and a speed limit on the way there (m/s; None: the configured limit)."""

    x: float
    y: float
    tolerance: float | None = None
    max_speed: float | None = None


@dataclass(frozen=True)
class Request:
    """A validated request. For `goal` and `mission`: the waypoints (one for a goal), their
    frame, whether the mission repeats, and a per-waypoint time limit (None: configured)."""

    type: str
    id: RequestId = None
    waypoints: tuple[Waypoint, ...] = ()
    frame: str = "odom"
    loop: bool = False
    timeout_s: float | None = None
    rate_hz: float = 2.0


def _number(obj: dict[str, Any], key: str, where: str, rid: RequestId, *, required: bool,
            low: float | None = None, high: float | None = None,
            low_exclusive: bool = False) -> float | None:
    value = obj.get(key)
    if value is None:
        if required:
            raise ProtocolError(f"{where}'{key}' is required", rid)
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ProtocolError(f"{where}'{key}' must be a number, got {json.dumps(value)[:40]}", rid)
    try:
        value = float(value)
    except OverflowError:  # an integer literal beyond the float range (1 followed by 400 digits)
        value = math.inf
    if not math.isfinite(value):
        raise ProtocolError(f"{where}'{key}' must be finite, got {value}", rid)
    if low is not None and (value <= low if low_exclusive else value < low):
        raise ProtocolError(f"{where}'{key}' must be {'>' if low_exclusive else '≥'} {low:g},"
                            f" got {value:g}", rid)
    if high is not None and value > high:
        raise ProtocolError(f"{where}'{key}' must be ≤ {high:g}, got {value:g}", rid)
    return value


def _only(obj: dict[str, Any], allowed: set[str], where: str, rid: RequestId) -> None:
    unknown = sorted(set(obj) - allowed)
    if unknown:
        raise ProtocolError(f"{where}unknown field '{unknown[0]}'", rid)


def _waypoint(obj: Any, where: str, rid: RequestId, max_speed_limit: float) -> Waypoint:
    if not isinstance(obj, dict):
        raise ProtocolError(f"{where}must be an object with x and y", rid)
    _only(obj, {"x", "y", "tolerance", "max_speed"}, where, rid)
    x = _number(obj, "x", where, rid, required=True)
    y = _number(obj, "y", where, rid, required=True)
    tol = _number(obj, "tolerance", where, rid, required=False, low=TOLERANCE_RANGE_M[0],
                  high=TOLERANCE_RANGE_M[1])
    speed = _number(obj, "max_speed", where, rid, required=False, low=0.0, low_exclusive=True,
                    high=max_speed_limit)
    assert x is not None and y is not None
    return Waypoint(x, y, tol, speed)


def _request_id(obj: dict[str, Any]) -> RequestId:
    rid = obj.get("id")
    if rid is None:
        return None
    if isinstance(rid, bool) or not isinstance(rid, (str, int)):
        raise ProtocolError("'id' must be a string or an integer")
    if isinstance(rid, str) and len(rid) > MAX_ID_CHARS:
        raise ProtocolError(f"'id' longer than {MAX_ID_CHARS} characters")
    if isinstance(rid, int) and not -(2**53) <= rid <= 2**53:
        raise ProtocolError("'id' integer out of range (|id| ≤ 2^53)")
    return rid


def parse_request(line: bytes, max_speed_limit: float) -> Request:
    """One request line → a validated Request, or ProtocolError. `max_speed_limit`: the
    configured v_max (a waypoint may only lower it)."""
    try:
        obj = json.loads(line)
    except (UnicodeDecodeError, ValueError) as exc:  # JSONDecodeError is a ValueError
        raise ProtocolError(f"malformed JSON: {str(exc)[:80]}") from None
    except RecursionError:  # "[[[[…": deeper than the interpreter's recursion limit
        raise ProtocolError(f"JSON nested deeper than {MAX_DEPTH} levels") from None
    if not isinstance(obj, dict):
        raise ProtocolError(f"a request is a JSON object, got {type(obj).__name__}")
    rid = _request_id(obj)
    if _too_deep(obj):  # also keeps json.dumps of a value in an error message from recursing
        raise ProtocolError(f"JSON nested deeper than {MAX_DEPTH} levels", rid)
    version = obj.get("v", VERSION)
    if version != VERSION or isinstance(version, bool):
        raise ProtocolError(f"unsupported protocol version {json.dumps(version)[:20]}"
                            f" (this service speaks {VERSION})", rid)
    kind = obj.get("type")
    common = {"v", "id", "type"}
    if kind in ("cancel", "pause", "resume", "status", "unsubscribe"):
        _only(obj, common, "", rid)
        return Request(kind, rid)
    if kind == "subscribe":
        _only(obj, common | {"rate_hz"}, "", rid)
        rate = _number(obj, "rate_hz", "", rid, required=False, low=0.0, low_exclusive=True,
                       high=MAX_STATUS_HZ)
        return Request(kind, rid, rate_hz=2.0 if rate is None else rate)
    if kind not in ("goal", "mission"):
        known = ", ".join((*CYCLE_TYPES, *SERVER_TYPES))
        raise ProtocolError(f"unknown request type {json.dumps(kind)[:40]} (types: {known})", rid)
    frame = obj.get("frame", "odom")
    if frame not in FRAMES:
        raise ProtocolError(f"'frame' must be one of {', '.join(FRAMES)},"
                            f" got {json.dumps(frame)[:40]}", rid)
    timeout = _number(obj, "timeout", "", rid, required=False, low=TIMEOUT_RANGE_S[0],
                      high=TIMEOUT_RANGE_S[1])
    if kind == "goal":
        _only(obj, common | {"x", "y", "tolerance", "max_speed", "frame", "timeout"}, "", rid)
        point = {k: obj[k] for k in ("x", "y", "tolerance", "max_speed") if k in obj}
        return Request(kind, rid, (_waypoint(point, "", rid, max_speed_limit),), frame,
                       timeout_s=timeout)
    _only(obj, common | {"waypoints", "frame", "loop", "timeout"}, "", rid)
    points = obj.get("waypoints")
    if not isinstance(points, list) or not 1 <= len(points) <= MAX_WAYPOINTS:
        raise ProtocolError(f"'waypoints' must be a list of 1 to {MAX_WAYPOINTS} objects", rid)
    loop = obj.get("loop", False)
    if not isinstance(loop, bool):
        raise ProtocolError("'loop' must be true or false", rid)
    waypoints = tuple(_waypoint(p, f"waypoint {i + 1}: ", rid, max_speed_limit)
                      for i, p in enumerate(points))
    return Request(kind, rid, waypoints, frame, loop, timeout)


def _too_deep(obj: Any) -> bool:
    """Whether arrays and objects nest deeper than MAX_DEPTH (iterative: no recursion)."""
    stack = [(obj, 1)]
    while stack:
        value, depth = stack.pop()
        children = (value.values() if isinstance(value, dict)
                    else value if isinstance(value, list) else None)
        if children is None:
            continue
        if depth > MAX_DEPTH:
            return True
        stack.extend((child, depth + 1) for child in children)
    return False


def encode(message: dict[str, Any]) -> bytes:
    """One outgoing line. Non-finite floats never leave as NaN/Infinity (not JSON): null."""
    return (json.dumps(_finite(message), separators=(",", ":"), allow_nan=False) + "\n").encode()


def _finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def reply(request_id: RequestId, ok: bool = True, error: str | None = None,
          **fields: Any) -> dict[str, Any]:
    """A reply to one request: ok with its fields, or an error message."""
    message: dict[str, Any] = {"v": VERSION, "type": "reply", "id": request_id, "ok": ok}
    if error is not None:
        message["error"] = error
    message.update(fields)
    return message
