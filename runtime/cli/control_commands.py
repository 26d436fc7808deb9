"""The operator's commands to the running service: `goal`, `mission`, `cancel`, `pause`,
`resume`, `status`. Each speaks to the control socket (runtime.cli.control_client, whose
docstring lists the exit codes). Human-readable lines by default; with --json, the service's
own messages, one JSON object per line."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from runtime.cli.args import finite_float
from runtime.cli.control_client import (
    EXIT_OK,
    EXIT_REFUSED,
    ControlClient,
    default_socket,
)
from runtime.cli.output import print_json
from runtime.config.schema import load_yaml_file
from runtime.control.protocol import ProtocolError, parse_request
from runtime.errors import ConfigError


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--socket", type=Path, default=None,
                   help="the service's control socket (default: $SAFEMOVE_CONTROL_SOCKET or"
                        " /run/safemove/control.sock)")
    p.add_argument("--json", action="store_true", help="print the service's messages as JSON lines")


def _connect(args: argparse.Namespace) -> ControlClient:
    return ControlClient(args.socket or default_socket())


def _say(args: argparse.Namespace, message: dict[str, Any], text: str) -> None:
    if args.json:
        print_json(message)
    else:
        print(text, flush=True)


def _refused(args: argparse.Namespace, reply: dict[str, Any]) -> int:
    _say(args, reply, f"refused: {reply.get('error')}")
    return EXIT_REFUSED


def add_goal(p: argparse.ArgumentParser) -> None:
    p.add_argument("x", type=finite_float, help="metres (odom frame, or forward with --relative)")
    p.add_argument("y", type=finite_float, help="metres (odom frame, or left with --relative)")
    p.add_argument("--relative", action="store_true",
                   help="X forward and Y left of where the robot is now, not in odom")
    p.add_argument("--tolerance", type=finite_float, metavar="M",
                   help="arrival tolerance (default: the service's control.goal_tolerance_m)")
    p.add_argument("--max-speed", type=finite_float, metavar="V",
                   help="speed limit on the way, m/s (at most the service's limits.v_max)")
    p.add_argument("--timeout", type=finite_float, metavar="S",
                   help="seconds before the goal fails (default: control.waypoint_timeout_s)")
    p.add_argument("--wait", action="store_true",
                   help="wait until the goal ends; exit 0 only if it was reached")
    _common(p)
    p.set_defaults(func=goal)


def goal(args: argparse.Namespace) -> int:
    fields: dict[str, Any] = {"x": args.x, "y": args.y,
                              "frame": "relative" if args.relative else "odom"}
    for key, value in (("tolerance", args.tolerance), ("max_speed", args.max_speed),
                       ("timeout", args.timeout)):
        if value is not None:
            fields[key] = value
    return _send_goal(args, "goal", fields)


def add_mission(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", type=Path, metavar="FILE.yaml",
                   help="waypoints: {waypoints: [{x, y, tolerance?, max_speed?}, ...],"
                        " frame?: odom|relative, loop?: bool, timeout?: s per waypoint}")
    p.add_argument("--wait", action="store_true",
                   help="wait until the mission ends; exit 0 only if every waypoint was reached")
    _common(p)
    p.set_defaults(func=mission)


def load_mission(path: Path) -> dict[str, Any]:
    """A mission file as request fields, checked as the service will check it, so a mistake is
    one line naming the file and the field (exit 2) before anything is sent."""
    data = load_yaml_file(path, "mission file")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a mission file is a mapping with a 'waypoints' list")
    fields = {k: v for k, v in data.items()}
    try:
        parse_request(json.dumps({"type": "mission", **fields}, allow_nan=True).encode(),
                      math.inf)
    except ProtocolError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    except (TypeError, ValueError) as exc:  # YAML values JSON cannot carry (dates, sets)
        raise ConfigError(f"{path}: {exc}") from None
    return fields


def mission(args: argparse.Namespace) -> int:
    return _send_goal(args, "mission", load_mission(args.file))


def _send_goal(args: argparse.Namespace, kind: str, fields: dict[str, Any]) -> int:
    with _connect(args) as client:
        answer = client.request(kind, **fields)
        if not answer.get("ok"):
            return _refused(args, answer)
        gid = answer.get("goal_id")
        points = answer.get("waypoints", [])
        where = ", ".join(f"({p['x']:.2f}, {p['y']:.2f})" for p in points[:5])
        _say(args, answer, f"{kind} {gid} accepted: {where}{' ...' if len(points) > 5 else ''}"
             " in odom")
        if not args.wait:
            return EXIT_OK
        for message in client.messages():
            if message.get("type") != "event" or message.get("goal_id") != gid:
                continue
            _say(args, message, _event_text(message))
            if message.get("event") == "finished":
                return EXIT_OK if message.get("outcome") == "reached" else EXIT_REFUSED
    return EXIT_REFUSED  # not reached: messages() ends only by raising


def _event_text(e: dict[str, Any]) -> str:
    pose = e.get("pose") or {}
    at = f" at ({_f(pose, 'x'):.2f}, {_f(pose, 'y'):.2f})"
    if e.get("event") == "arrived":
        return f"goal {e.get('goal_id')}: arrived at waypoint {e.get('waypoint')} of" \
               f" {e.get('waypoints')}{at}"
    if e.get("event") == "finished":
        return f"goal {e.get('goal_id')}: {e.get('outcome')}: {e.get('reason')}{at}"
    return f"goal {e.get('goal_id')}: {e.get('event')}{at}"


def add_simple(p: argparse.ArgumentParser) -> None:
    """cancel, pause, resume: no arguments but the socket."""
    _common(p)
    p.set_defaults(func=simple)


def simple(args: argparse.Namespace) -> int:
    with _connect(args) as client:
        answer = client.request(args.command)
    if not answer.get("ok"):
        return _refused(args, answer)
    gid = answer.get("cancelled", answer.get("goal_id"))
    done = {"cancel": "cancelled", "pause": "paused", "resume": "resumed"}[args.command]
    _say(args, answer, f"goal {gid} {done}" if gid is not None else "no goal to cancel")
    return EXIT_OK


def add_status(p: argparse.ArgumentParser) -> None:
    p.add_argument("--follow", action="store_true", help="keep printing status (Ctrl-C ends)")
    p.add_argument("--rate", type=finite_float, default=2.0, metavar="HZ",
                   help="status messages per second with --follow (default 2, at most 20)")
    _common(p)
    p.set_defaults(func=status)


def status(args: argparse.Namespace) -> int:
    with _connect(args) as client:
        if not args.follow:
            answer = client.request("status")
            if not answer.get("ok"):
                return _refused(args, answer)
            _say(args, answer["status"], status_text(answer["status"]))
            return EXIT_OK
        answer = client.request("subscribe", rate_hz=args.rate)
        if not answer.get("ok"):
            return _refused(args, answer)
        try:
            for message in client.messages():
                text = status_text(message) if message.get("type") == "status" else \
                    _event_text(message)
                _say(args, message, text)
        except KeyboardInterrupt:
            return EXIT_OK
    return EXIT_OK


def _f(d: dict[str, Any], key: str) -> float:
    """A number of a message for printing; nan where the service sent null (non-finite)."""
    value = d.get(key)
    return float(value) if isinstance(value, (int, float)) else math.nan


def status_text(s: dict[str, Any]) -> str:
    """One line a person reads: loop state, mission, pose, speed, counters."""
    m = s.get("mission") or {}
    pose, vel = s.get("pose") or {}, s.get("velocity") or {}
    goal_text = "idle"
    if m.get("state") in ("navigating", "paused"):
        g = m.get("goal") or {}
        dist = m.get("distance_m")
        goal_text = (f"{m['state']} goal {m.get('goal_id')} waypoint {m.get('waypoint')}/"
                     f"{m.get('waypoints')} ({_f(g, 'x'):.2f}, {_f(g, 'y'):.2f})"
                     f"{'' if dist is None else f', {dist:.2f} m to go'}")
    hold = f" ({s['hold_reason']})" if s.get("hold_reason") else ""
    return (f"{s.get('state')}{hold}: {goal_text}; pose ({_f(pose, 'x'):.2f},"
            f" {_f(pose, 'y'):.2f}, {_f(pose, 'theta'):.2f} rad),"
            f" v {_f(vel, 'v'):.2f} m/s; planner {m.get('planner')}; shield"
            f" interventions {s.get('shield_interventions')}, missed deadlines"
            f" {s.get('missed_deadlines')}")
